#!/usr/bin/env python3
"""Generate the secured zenohd configuration (TLS or user/password + access control) for rlutf.

Zenoh's access control has no templating, so the per-robot rules are generated here:

    python3 deploy/gen-acl.py -o deploy/zenoh/router-secure.json5 r1 r2 r3

Identities (TLS certificate common names, or usernames with ``--auth usrpwd``):

    rlutf-service   service instances: everything under {prefix}/**
    zenoh-router    other routers of the fleet (router-to-router links): same as the service
    rlutf-operator  writes (puts and deletes) maps, initial poses and relocalize requests;
                    reads everything under {prefix}/**
    robot-ID        puts its own scan and odom (no DELETE); reads maps, its own pose
                    (subscribe and get) and its own events

Anything else is denied (``default_permission: deny``), including the admin space. What this
does not enforce: what a permitted put holds (a robot may still send any stamp or number on its
own keys; the service checks those), nor how often (no rate limit: zenoh's ACL has none). The
storage section matches deploy/zenoh/router.json5 (without the REST plugin, which would
bypass access control). Uses only the standard library; the output is JSON, which is JSON5.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

ROBOT_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
PREFIX = re.compile(r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")

#: Each link queues 16 batches of data (zenoh's maximum; its default is 2): a router drops a
#: robot's scan once the link to a subscriber has been full for 1 ms (as deploy/zenoh/router.json5).
LINK_TX = {"queue": {"size": {"data": 16, "data_high": 16}}}
SERVICE = "rlutf-service"
OPERATOR = "rlutf-operator"
ROUTER = "zenoh-router"

ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]


def robot_name(robot_id: str) -> str:
    return f"robot-{robot_id}"


def storage_manager(prefix: str) -> dict[str, Any]:
    """The storage manager section; must stay equal to the one in deploy/zenoh/router.json5."""
    return {
        "__required__": True,
        "backend_search_dirs": ["/zenoh/backends"],
        "volumes": {"fs": {"backend": "fs"}},
        "storages": {
            "rlutf_maps": {
                "key_expr": f"{prefix}/maps/**",
                "strip_prefix": f"{prefix}/maps",
                "complete": True,
                "volume": {"id": "fs", "dir": "rlutf-maps"},
            },
            "rlutf_poses": {
                "key_expr": f"{prefix}/robots/*/pose",
                "volume": "memory",
            },
        },
    }


def rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": [flow],
        "messages": messages,
        "key_exprs": key_exprs,
    }


def subjects_for(subject_id: str, name: str, auth: str) -> list[dict[str, Any]]:
    if auth == "tls":
        return [{"id": subject_id, "cert_common_names": [name]}]
    return [{"id": subject_id, "usernames": [name]}]


def access_control(prefix: str, robots: list[str], auth: str) -> dict[str, Any]:
    everything = [f"{prefix}/**"]
    rules: list[dict[str, Any]] = [
        {
            "id": "all_of_prefix",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": ALL_MESSAGES,
            "key_exprs": everything,
        },
        rule(
            "operator_write",
            "ingress",
            ["put", "delete"],
            [
                f"{prefix}/maps/**",
                f"{prefix}/robots/*/initialpose",
                f"{prefix}/robots/*/relocalize",
            ],
        ),
        rule(
            "operator_ask",
            "ingress",
            ["declare_subscriber", "query", "liveliness_query", "declare_liveliness_subscriber"],
            everything,
        ),
        rule(
            "operator_receive", "egress", ["put", "delete", "reply", "liveliness_token"], everything
        ),
    ]
    subjects = subjects_for("service", SERVICE, auth)
    subjects += subjects_for("router", ROUTER, auth)
    subjects += subjects_for("operator", OPERATOR, auth)
    policies: list[dict[str, Any]] = [
        {
            "id": "service_and_routers",
            "rules": ["all_of_prefix"],
            "subjects": ["service", "router"],
        },
        {
            "id": "operators",
            "rules": ["operator_write", "operator_ask", "operator_receive"],
            "subjects": ["operator"],
        },
    ]
    for rid in robots:
        own = f"{prefix}/robots/{rid}"
        readable = [f"{prefix}/maps/**", f"{own}/pose", f"{own}/events"]
        rules += [
            rule(f"robot_{rid}_write", "ingress", ["put"], [f"{own}/scan", f"{own}/odom"]),
            rule(f"robot_{rid}_ask", "ingress", ["declare_subscriber", "query"], readable),
            rule(f"robot_{rid}_receive", "egress", ["put", "delete", "reply"], readable),
        ]
        subjects += subjects_for(f"robot_{rid}", robot_name(rid), auth)
        policies.append(
            {
                "id": f"robot_{rid}",
                "rules": [f"robot_{rid}_write", f"robot_{rid}_ask", f"robot_{rid}_receive"],
                "subjects": [f"robot_{rid}"],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def router_config(
    robots: list[str],
    *,
    prefix: str = "rlutf",
    auth: str = "tls",
    listen: list[str] | None = None,
    certs_dir: str = "/etc/zenoh/certs",
    users_file: str = "/etc/zenoh/secrets/users.txt",
) -> dict[str, Any]:
    if listen is None:
        listen = ["tls/[::]:7447"] if auth == "tls" else ["tcp/[::]:7447"]
    transport: dict[str, Any]
    if auth == "tls":
        certs = certs_dir.rstrip("/")
        transport = {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": f"{certs}/ca.pem",
                    "listen_certificate": f"{certs}/router.pem",
                    "listen_private_key": f"{certs}/router.key",
                    "connect_certificate": f"{certs}/router.pem",
                    "connect_private_key": f"{certs}/router.key",
                    "enable_mtls": True,
                },
                "tx": LINK_TX,
            }
        }
    else:
        transport = {
            "auth": {"usrpwd": {"dictionary_file": users_file}},
            "link": {"tx": LINK_TX},
        }
    return {
        "mode": "router",
        "listen": {"endpoints": listen},
        "scouting": {"multicast": {"enabled": False}},
        "transport": transport,
        "access_control": access_control(prefix, robots, auth),
        "plugins": {"storage_manager": storage_manager(prefix)},
    }


def render(config: dict[str, Any], options: list[str]) -> str:
    command = " ".join(["python3 deploy/gen-acl.py", *options, "-o", "<this file>"])
    header = [
        "// GENERATED by deploy/gen-acl.py; do not edit by hand. Regenerate with:",
        f"//   {command}",
        "// Secured zenohd for rlutf: access control by "
        + (
            "TLS certificate common name (mTLS)."
            if config["transport"].get("link")
            else "user/password (transport/auth/usrpwd)."
        ),
        "// Subjects: rlutf-service and zenoh-router (all of the prefix), rlutf-operator (writes",
        "// maps, initial poses and relocalize requests, reads all), robot-ID (puts its own scan",
        "// and odom, no DELETE; reads maps and its own pose and events). Everything else is",
        "// denied.",
    ]
    return "\n".join(header) + "\n" + json.dumps(config, indent=2) + "\n"


def canonical_options(args: argparse.Namespace) -> list[str]:
    """The command line that regenerates the output, independent of where it is written."""
    opts: list[str] = []
    if args.prefix != "rlutf":
        opts += ["--prefix", args.prefix]
    if args.auth != "tls":
        opts += ["--auth", args.auth]
    for endpoint in args.listen or []:
        opts += ["--listen", endpoint]
    if args.auth == "tls" and args.certs_dir != "/etc/zenoh/certs":
        opts += ["--certs-dir", args.certs_dir]
    if args.auth == "usrpwd" and args.users_file != "/etc/zenoh/secrets/users.txt":
        opts += ["--users-file", args.users_file]
    return [*opts, *args.robots]


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="gen-acl.py",
        description="Write the secured zenohd configuration with per-robot access control.",
    )
    p.add_argument("robots", nargs="+", metavar="ROBOT_ID", help="robot ids ([A-Za-z0-9_-]{1,64})")
    p.add_argument("-o", "--output", help="output file (default: standard output)")
    p.add_argument("--prefix", default="rlutf", help="key prefix of the service (default: rlutf)")
    p.add_argument(
        "--auth",
        choices=["tls", "usrpwd"],
        default="tls",
        help="identify subjects by TLS certificate common name with mTLS (default) or by "
        "usrpwd username",
    )
    p.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="listen endpoint, repeatable (default: tls/[::]:7447, or tcp/[::]:7447 for usrpwd)",
    )
    p.add_argument(
        "--certs-dir",
        default="/etc/zenoh/certs",
        help="directory holding ca.pem, router.pem and router.key as the router sees it "
        "(default: /etc/zenoh/certs)",
    )
    p.add_argument(
        "--users-file",
        default="/etc/zenoh/secrets/users.txt",
        help="usrpwd dictionary file, one user:password per line "
        "(default: /etc/zenoh/secrets/users.txt)",
    )
    args = p.parse_args(argv)
    bad = [r for r in args.robots if not ROBOT_ID.match(r)]
    if bad:
        p.error(f"invalid robot id(s): {', '.join(bad)} (allowed: [A-Za-z0-9_-]{{1,64}})")
    if not PREFIX.match(args.prefix):
        p.error(f"invalid prefix: {args.prefix}")
    args.robots = list(dict.fromkeys(args.robots))
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    config = router_config(
        args.robots,
        prefix=args.prefix,
        auth=args.auth,
        listen=args.listen,
        certs_dir=args.certs_dir,
        users_file=args.users_file,
    )
    text = render(config, canonical_options(args))
    if args.output:
        Path(args.output).write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
