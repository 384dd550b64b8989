"""Checks of the container image and deployment files (docker/, deploy/, .dockerignore).

Static checks parse the Dockerfile, the compose and Kubernetes YAML and every Zenoh JSON5
configuration. Integration tests load the generated access-control configuration into an
in-process Zenoh router on a free loopback port and check who may write and read what.

Helpers meant for reuse (e.g. to run the image's command outside a container):
``dockerfile_command()`` (ENTRYPOINT + CMD of the final stage), ``dockerfile_env()``,
``dockerfile_healthcheck()``. Load them with ``importlib`` from this file's path, or call them
from a test in this folder.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
import yaml

from service.live.sessions import free_port

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
DOCKERFILE = REPO / "docker" / "Dockerfile"
ZENOH_DIR = DEPLOY / "zenoh"
K8S = DEPLOY / "k8s"
COMPOSE_FILES = sorted(DEPLOY.glob("compose*.yaml"))
JSON5_FILES = sorted(DEPLOY.rglob("*.json5"))
# Paths that compose files may mount although they are not in the repository: produced by a
# script of deploy/ (and gitignored).
GENERATED = {DEPLOY / "certs": DEPLOY / "gen-certs.sh"}
ZENOH_IMAGE = re.compile(r"^eclipse/zenoh:(\d+)\.(\d+)\.(\d+)$")
WAIT = 5.0  # seconds, upper bound of every wait for a sample that must arrive


# --------------------------------------------------------------------------- Dockerfile helpers


def dockerfile_instructions(path: Path = DOCKERFILE) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, with continuation lines joined and comments dropped."""
    out: list[tuple[str, str]] = []
    pending = ""
    for raw in path.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if pending and line.startswith("#"):
            continue  # comment lines inside a continued instruction are ignored by Docker
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        line = pending + line
        pending = ""
        word, _, rest = line.partition(" ")
        out.append((word.upper(), rest.strip()))
    if pending:
        word, _, rest = pending.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
    return out


def _final_stage(path: Path) -> list[tuple[str, str]]:
    instructions = dockerfile_instructions(path)
    starts = [i for i, (word, _) in enumerate(instructions) if word == "FROM"]
    assert starts, f"{path}: no FROM"
    return instructions[starts[-1] :]


def _exec_form(args: str) -> list[str]:
    """A JSON array (exec form) as a list; shell form becomes ["/bin/sh", "-c", text]."""
    if args.startswith("["):
        value = json.loads(args)
        assert isinstance(value, list) and all(isinstance(v, str) for v in value), args
        return value
    return ["/bin/sh", "-c", args]


def dockerfile_command(path: Path = DOCKERFILE, args: list[str] | None = None) -> list[str]:
    """The argv a container of the image runs: ENTRYPOINT + CMD (or ENTRYPOINT + ``args``)."""
    entrypoint: list[str] = []
    cmd: list[str] = []
    for word, rest in _final_stage(path):
        if word == "ENTRYPOINT":
            entrypoint = _exec_form(rest)
            cmd = []  # ENTRYPOINT resets an inherited CMD
        elif word == "CMD":
            cmd = _exec_form(rest)
    return entrypoint + (cmd if args is None else list(args))


def dockerfile_env(path: Path = DOCKERFILE) -> dict[str, str]:
    """ENV of the final stage (``KEY=value`` pairs, shell-style quoting; $VAR not expanded)."""
    env: dict[str, str] = {}
    for word, rest in _final_stage(path):
        if word != "ENV":
            continue
        for token in shlex.split(rest):
            key, sep, value = token.partition("=")
            assert sep, f"ENV {rest!r}: use KEY=value"
            env[key] = value
    return env


def dockerfile_healthcheck(path: Path = DOCKERFILE) -> tuple[dict[str, str], list[str]]:
    """(options, argv) of the final stage's HEALTHCHECK CMD."""
    checks = [rest for word, rest in _final_stage(path) if word == "HEALTHCHECK"]
    assert len(checks) == 1, "exactly one HEALTHCHECK"
    text = checks[0]
    options: dict[str, str] = {}
    while text.startswith("--"):
        opt, _, text = text.partition(" ")
        key, _, value = opt[2:].partition("=")
        options[key] = value
        text = text.strip()
    word, _, rest = text.partition(" ")
    assert word.upper() == "CMD", f"HEALTHCHECK {checks[0]!r}"
    return options, _exec_form(rest.strip())


def healthcheck_rlutf_args(argv: list[str]) -> list[str]:
    """The words from ``rlutf`` on in a health check command (shell wrappers unwrapped)."""
    words = argv
    if len(argv) >= 3 and argv[0] in {"/bin/sh", "sh", "/bin/bash", "bash"} and argv[1] == "-c":
        words = shlex.split(argv[2])
    for i, word in enumerate(words):
        if Path(word).name == "rlutf":
            return words[i:]
    return []


# ------------------------------------------------------------------- .dockerignore and context


def _dockerignore_regex(pattern: str) -> re.Pattern[str]:
    """Docker's pattern syntax (moby/patternmatcher): * ? [..] within a segment, ** across."""
    out = "^"
    i = 0
    while i < len(pattern):
        ch = pattern[i]
        if ch == "*":
            if i + 1 < len(pattern) and pattern[i + 1] == "*":
                i += 2
                if i < len(pattern) and pattern[i] == "/":
                    i += 1
                out += ".*" if i >= len(pattern) else "(.*/)?"
                continue
            out += "[^/]*"
        elif ch == "?":
            out += "[^/]"
        elif ch == "[":
            end = pattern.find("]", i)
            assert end > i, f"unbalanced [ in {pattern!r}"
            out += pattern[i : end + 1]
            i = end
        elif ch == "\\" and i + 1 < len(pattern):
            i += 1
            out += re.escape(pattern[i])
        else:
            out += re.escape(ch)
        i += 1
    return re.compile(out + "$")


def dockerignore_rules(path: Path = REPO / ".dockerignore") -> list[tuple[bool, re.Pattern[str]]]:
    rules: list[tuple[bool, re.Pattern[str]]] = []
    for raw in path.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        if negate:
            line = line[1:].strip()
        line = os.path.normpath(line).lstrip("/")
        rules.append((negate, _dockerignore_regex(line)))
    return rules


def in_build_context(relpath: str, rules: list[tuple[bool, re.Pattern[str]]]) -> bool:
    """Whether a file (path relative to the context) is sent to the builder."""
    parts = relpath.split("/")
    candidates = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    excluded = False
    for negate, regex in rules:
        if any(regex.match(c) for c in candidates):
            excluded = not negate
    return not excluded


def build_context_files(root: Path = REPO) -> list[str]:
    rules = dockerignore_rules(root / ".dockerignore")
    files = []
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = Path(dirpath).relative_to(root)
        if rel_dir.parts[:1] in {(".git",), (".venv",)}:
            dirnames.clear()
            continue
        for name in filenames:
            rel = (rel_dir / name).as_posix()
            if in_build_context(rel, rules):
                files.append(rel)
    return sorted(files)


# ------------------------------------------------------------------------------- misc helpers


def load_yaml_docs(path: Path) -> list[dict[str, Any]]:
    return [d for d in yaml.safe_load_all(path.read_text(encoding="utf-8")) if d is not None]


def load_gen_acl() -> Any:
    spec = importlib.util.spec_from_file_location("gen_acl", DEPLOY / "gen-acl.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def zenoh_json(path: Path, key: str) -> Any:
    import zenoh

    return json.loads(zenoh.Config.from_file(str(path)).get_json(key))


def wait_until(predicate: Callable[[], bool], timeout: float = WAIT) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


# ============================================================================ Dockerfile tests


def test_dockerfile_entrypoint_and_cmd() -> None:
    assert dockerfile_command() == ["rlutf", "serve"]
    assert dockerfile_command(args=["health"]) == ["rlutf", "health"]


def test_dockerfile_healthcheck_names_an_rlutf_subcommand() -> None:
    options, argv = dockerfile_healthcheck()
    words = healthcheck_rlutf_args(argv)
    assert words[:2] == ["rlutf", "health"], argv
    assert "--timeout" in words
    for key in ("interval", "timeout", "start-period", "retries"):
        assert key in options, f"HEALTHCHECK --{key}"
    # The health probe must end before Docker gives up on it.
    probe_timeout = float(words[words.index("--timeout") + 1])
    assert probe_timeout < float(options["timeout"].rstrip("s"))


def test_dockerfile_runtime_settings() -> None:
    stage = _final_stage(DOCKERFILE)
    users = [rest for w, rest in stage if w == "USER"]
    assert users, "the image must not run as root"
    uid = users[-1].split(":")[0]
    assert uid.isdigit() and int(uid) != 0, "numeric non-root USER (Kubernetes runAsNonRoot)"
    expose = " ".join(rest for w, rest in stage if w == "EXPOSE")
    assert "7447" in expose
    assert "9464" in expose  # the metrics port of the manifests
    volumes: list[str] = []
    for w, rest in stage:
        if w == "VOLUME":
            volumes += _exec_form(rest) if rest.startswith("[") else rest.split()
    assert {"/data/store", "/data/logs"} <= set(volumes)
    env = dockerfile_env()
    assert env["RLUTF_STORE_DIR"] == "/data/store"
    assert env["RLUTF_RECORD_DIR"] == "/data/logs"
    froms = [w for w, _ in dockerfile_instructions()].count("FROM")
    assert froms >= 2, "multi-stage: the runtime stage carries no build files"
    base = [rest for w, rest in dockerfile_instructions() if w == "ARG" and "PYTHON_IMAGE" in rest]
    assert base and "python:3.11" in base[0] and "slim" in base[0]


def test_dockerfile_compiles_the_kernels_into_a_cache_the_service_can_write() -> None:
    env = dockerfile_env()
    cache = env.get("NUMBA_CACHE_DIR")
    assert cache, "numba's cache must be writable by the service's user: set NUMBA_CACHE_DIR"
    stage = _final_stage(DOCKERFILE)
    runs = " ".join(rest for w, rest in stage if w == "RUN")
    assert "warm_up()" in runs, "compile the kernels at build time (rlutf.warmup.warm_up)"
    assert f"chown -R rlutf:rlutf {cache.rsplit('/', 1)[0]}" in runs
    # ...before the service's user takes over
    words = [w for w, _ in stage]
    last_run = max(i for i, w in enumerate(words) if w == "RUN")
    assert last_run < words.index("USER")


def test_build_context_holds_the_package_and_nothing_else() -> None:
    files = build_context_files()
    assert "pyproject.toml" in files
    for package in ("rlutf", "schemas", "service"):
        assert f"{package}/__init__.py" in files, package
    for f in files:
        top = f.split("/")[0]
        assert top not in {".git", "tests", "bench", "deploy", "docker", "logs", "store"}, f
        assert "__pycache__" not in f and not f.endswith((".pyc", ".mcap", ".key", ".pem")), f


def test_dockerfile_copy_sources_are_in_the_context() -> None:
    files = set(build_context_files())
    dirs = {"/".join(f.split("/")[:i]) for f in files for i in range(1, f.count("/") + 1)}
    for word, rest in dockerfile_instructions():
        if word not in {"COPY", "ADD"} or "--from=" in rest:
            continue
        args = [a for a in rest.split() if not a.startswith("--")]
        for source in args[:-1]:
            src = source.rstrip("/")
            assert src in {".", ""} or src in files or src in dirs, f"{word} {src}: not in context"


def test_pyproject_build_inputs_are_in_the_context() -> None:
    """`pip install .` in the image needs every file pyproject.toml names (readme, license)."""
    import tomllib

    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    files = set(build_context_files())
    readme = project.get("readme")
    if isinstance(readme, dict):
        readme = readme.get("file")
    needed = [readme] if isinstance(readme, str) else []
    license_ = project.get("license")
    if isinstance(license_, dict) and "file" in license_:
        needed.append(license_["file"])
    for name in needed:
        assert (REPO / name).is_file(), f"pyproject.toml names {name}, which does not exist"
        assert name in files, f"{name} is excluded from the build context by .dockerignore"


def test_rlutf_cli_has_the_healthcheck_subcommand() -> None:
    exe = Path(sys.executable).parent / "rlutf"
    if not exe.exists():
        pytest.skip("the rlutf console script is not installed in this environment")
    result = subprocess.run(
        [str(exe), "--help"], capture_output=True, text=True, timeout=30, check=False
    )
    assert result.returncode == 0
    assert "serve" in result.stdout
    _, argv = dockerfile_healthcheck()
    subcommand = healthcheck_rlutf_args(argv)[1]
    assert subcommand in result.stdout


@pytest.mark.integration
def test_image_entry_command_runs_outside_the_container(tmp_path: Path) -> None:
    """ENTRYPOINT + CMD with the image's ENV (paths moved into tmp) serves, answers the
    HEALTHCHECK command, and stops with exit 0 on SIGTERM."""
    exe = Path(sys.executable).parent / "rlutf"
    if not exe.exists():
        pytest.skip("the rlutf console script is not installed in this environment")
    port = free_port()
    env = dict(os.environ)
    for key, value in dockerfile_env().items():
        if key == "NUMBA_CACHE_DIR":
            continue  # the kernels this environment compiled already serve (see below)
        env[key] = str(tmp_path / value.lstrip("/")) if value.startswith("/data") else value
    env["RLUTF_LISTEN"] = f"tcp/127.0.0.1:{port}"
    env["RLUTF_HEALTH_ARGS"] = f"--connect tcp/127.0.0.1:{port}"
    env["RLUTF_WORKERS"] = "0"
    argv = dockerfile_command()
    assert argv[0] == "rlutf"
    proc = subprocess.Popen([str(exe), *argv[1:]], env=env, stderr=subprocess.PIPE, text=True)
    try:
        _, check = dockerfile_healthcheck()

        def healthy() -> bool:
            r = subprocess.run(
                check,
                env={**env, "PATH": f"{exe.parent}:{env['PATH']}"},
                capture_output=True,
                text=True,
                timeout=30,
                check=False,
            )
            return r.returncode == 0 and '"instance"' in r.stdout

        assert wait_until(healthy, 30.0), "the health check never passed"
        assert (tmp_path / "data" / "store").is_dir()
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            code = proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert code == 0, proc.stderr.read() if proc.stderr else ""


# ========================================================================= Zenoh configuration


@pytest.mark.parametrize("path", JSON5_FILES, ids=lambda p: str(p.relative_to(DEPLOY)))
def test_json5_config_loads(path: Path) -> None:
    """zenoh.Config.from_file validates the whole file (it does not open certificate files)."""
    import zenoh

    zenoh.Config.from_file(str(path))


def test_json5_files_found() -> None:
    names = {p.name for p in JSON5_FILES}
    assert {
        "router.json5",
        "router-secure.json5",
        "service-client.json5",
        "service-client-secure.json5",
    } <= names


def _check_storage_manager(sm: dict[str, Any]) -> None:
    """The checks zenohd's storage manager makes when it parses its configuration."""
    import zenoh

    volumes = set(sm.get("volumes", {})) | {"memory"}
    for name, storage in sm["storages"].items():
        key = zenoh.KeyExpr(storage["key_expr"])
        strip = storage.get("strip_prefix")
        if strip is not None:
            assert str(key).startswith(strip), f"{name}: strip_prefix is not a prefix"
            assert "*" not in strip, f"{name}: strip_prefix has wildcards"
        volume = storage["volume"]
        volume_id = volume if isinstance(volume, str) else volume["id"]
        assert volume_id in volumes, f"{name}: unknown volume {volume_id}"
        if isinstance(storage.get("complete"), str):
            assert storage["complete"] in {"true", "false"}


def test_router_storages() -> None:
    import zenoh

    plugins = zenoh_json(ZENOH_DIR / "router.json5", "plugins")
    sm = plugins["storage_manager"]
    _check_storage_manager(sm)
    by_key = {s["key_expr"]: s for s in sm["storages"].values()}
    maps = next(s for k, s in by_key.items() if zenoh.KeyExpr(k).includes("rlutf/maps/m1"))
    poses = next(s for k, s in by_key.items() if zenoh.KeyExpr(k).includes("rlutf/robots/r1/pose"))
    maps_volume = maps["volume"]["id"] if isinstance(maps["volume"], dict) else maps["volume"]
    assert sm["volumes"][maps_volume].get("backend", maps_volume) == "fs", "maps on the filesystem"
    assert maps.get("complete") is True
    assert poses["volume"] == "memory"
    assert not zenoh.KeyExpr(poses["key_expr"]).includes("rlutf/robots/r1/scan")
    assert zenoh_json(ZENOH_DIR / "router.json5", "mode") == "router"


def test_secure_router_matches_router_and_has_access_control() -> None:
    plain = zenoh_json(ZENOH_DIR / "router.json5", "plugins")
    secure_path = ZENOH_DIR / "router-secure.json5"
    secure = zenoh_json(secure_path, "plugins")
    assert secure["storage_manager"] == plain["storage_manager"]
    assert "rest" not in secure, "the REST plugin bypasses access control"
    acl = zenoh_json(secure_path, "access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    tls = zenoh_json(secure_path, "transport/link/tls")
    assert tls["enable_mtls"] is True
    assert all(e.startswith("tls/") for e in zenoh_json(secure_path, "listen/endpoints"))


def test_router_secure_is_the_generator_output() -> None:
    """The committed example is exactly what gen-acl.py writes for r1 r2 r3."""
    gen = load_gen_acl()
    args = gen.parse_args(["r1", "r2", "r3"])
    config = gen.router_config(args.robots)
    expected = gen.render(config, gen.canonical_options(args))
    committed = (ZENOH_DIR / "router-secure.json5").read_text(encoding="utf-8")
    assert committed == expected, "regenerate: python3 deploy/gen-acl.py -o <file> r1 r2 r3"
    assert "python3 deploy/gen-acl.py r1 r2 r3 -o" in committed


def test_every_zenoh_file_queues_a_fleets_bursts_on_each_link() -> None:
    """Each link of the deployment's sessions queues 16 batches of data, as rlutf serve's own
    sessions do without a file: zenoh's default, 2, let a router drop a burst of robots' scans
    unseen by the service (BENCHMARKS.md, "Scans lost on the host's own links")."""
    import zenoh

    from service.live.sessions import TX_QUEUE_BATCHES

    gen = load_gen_acl()
    usrpwd = gen.router_config(["r1"], auth="usrpwd")
    configs = [zenoh.Config.from_file(str(ZENOH_DIR / name)) for name in (
        "router.json5", "router-secure.json5", "service-client.json5",
        "service-client-secure.json5",
    )] + [zenoh.Config.from_json5(json.dumps(usrpwd))]  # fmt: skip
    for config in configs:
        sizes = json.loads(config.get_json("transport/link/tx/queue/size"))
        assert sizes["data"] == sizes["data_high"] == TX_QUEUE_BATCHES


def test_gen_acl_rejects_bad_robot_ids(capsys: pytest.CaptureFixture[str]) -> None:
    gen = load_gen_acl()
    for bad in ("r*", "a/b", "x" * 65, ""):
        with pytest.raises(SystemExit):
            gen.parse_args([bad])
    capsys.readouterr()


def test_service_client_configs_wait_for_the_router() -> None:
    for name in ("service-client.json5", "service-client-secure.json5"):
        path = ZENOH_DIR / name
        assert zenoh_json(path, "mode") == "client"
        assert zenoh_json(path, "connect/timeout_ms") == -1
        assert zenoh_json(path, "connect/exit_on_failure") is False
        endpoints = zenoh_json(path, "connect/endpoints")
        assert endpoints and all("zenoh-router:7447" in e for e in endpoints)
        assert zenoh_json(path, "scouting/multicast/enabled") is False


# ===================================================================================== compose


def _compose_bind_source(compose: Path, volume: Any) -> tuple[str | None, str]:
    """(host source or None for a named volume, container target) of a service volume entry."""
    if isinstance(volume, dict):
        source, target = volume.get("source"), volume["target"]
        return (source if volume.get("type") == "bind" else None), target
    parts = str(volume).split(":")
    if len(parts) == 1:
        return None, parts[0]
    source, target = parts[0], parts[1]
    if source.startswith((".", "/", "~")):
        return source, target
    return None, target


def _exists_or_generated(path: Path) -> bool:
    path = path.resolve()
    if path.exists():
        return True
    return any(path == gen.resolve() and script.exists() for gen, script in GENERATED.items())


@pytest.mark.parametrize("compose", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_references_existing_files(compose: Path) -> None:
    doc = yaml.safe_load(compose.read_text(encoding="utf-8"))
    assert isinstance(doc.get("services"), dict) and doc["services"]
    declared_volumes = set((doc.get("volumes") or {}).keys())
    base = yaml.safe_load((DEPLOY / "compose.yaml").read_text(encoding="utf-8"))
    declared_volumes |= set((base.get("volumes") or {}).keys())
    for name, service in doc["services"].items():
        build = service.get("build")
        if build is not None:
            context = compose.parent / (build if isinstance(build, str) else build["context"])
            assert context.is_dir(), f"{name}: build context {context}"
            dockerfile = "Dockerfile" if isinstance(build, str) else build["dockerfile"]
            assert (context / dockerfile).is_file(), f"{name}: {dockerfile}"
        for volume in service.get("volumes", []):
            source, target = _compose_bind_source(compose, volume)
            assert target.startswith("/"), f"{name}: {volume}"
            if source is None:
                vol_name = str(volume).split(":")[0] if not isinstance(volume, dict) else None
                if vol_name:
                    assert vol_name in declared_volumes, f"{name}: undeclared volume {vol_name}"
            else:
                host = (compose.parent / source).resolve()
                assert _exists_or_generated(host), f"{name}: {source} does not exist"


def _compose_services() -> dict[str, Any]:
    """compose.yaml with compose.secure.yaml kept apart (it is an override)."""
    doc = yaml.safe_load((DEPLOY / "compose.yaml").read_text(encoding="utf-8"))
    return dict(doc["services"])


def _mount_targets(service: dict[str, Any], compose: Path) -> dict[str, Path]:
    targets = {}
    for volume in service.get("volumes", []):
        source, target = _compose_bind_source(compose, volume)
        if source is not None:
            targets[target] = (compose.parent / source).resolve()
    return targets


def _container_file(path: str, mounts: dict[str, Path]) -> Path | None:
    for target, host in mounts.items():
        if path == target:
            return host
        if path.startswith(target.rstrip("/") + "/"):
            return host / path[len(target.rstrip("/")) + 1 :]
    return None


def test_compose_topology() -> None:
    doc = yaml.safe_load((DEPLOY / "compose.yaml").read_text(encoding="utf-8"))
    services = doc["services"]
    routers = [s for s in services.values() if ZENOH_IMAGE.match(str(s.get("image", "")))]
    assert routers, "a zenohd router from eclipse/zenoh"
    router = services["zenoh-router"]
    assert router["command"][:2] == ["-c", "/etc/zenoh/router.json5"]
    assert "7447:7447/tcp" in router["ports"] or "7447:7447" in router["ports"]
    assert router["environment"]["ZENOH_BACKEND_FS_ROOT"]
    rlutf = services["rlutf"]
    assert rlutf["deploy"]["replicas"] == 2
    command = rlutf["command"]
    assert command[0] == "serve" and "--no-store" in command
    assert command[command.index("--mode") + 1] == "client"
    assert any(v.startswith("logs:") for v in rlutf["volumes"]), "a log volume"
    # The pose state (default state_dir: {store_dir}/state) on a named volume, for restarts.
    assert "state:/data/store" in rlutf["volumes"] and "state" in doc["volumes"]
    assert "--state" not in command and "--no-state" not in command


@pytest.mark.parametrize("compose", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_config_files_are_mounted(compose: Path) -> None:
    """Every configuration path a command names is a file mounted into that container."""
    services = yaml.safe_load(compose.read_text(encoding="utf-8"))["services"]
    base = _compose_services()
    for name, service in services.items():
        mounts = _mount_targets(base.get(name, {}), DEPLOY / "compose.yaml")
        mounts.update(_mount_targets(service, compose))
        command = service.get("command") or []
        entrypoint = service.get("entrypoint") or []
        words = list(entrypoint) + list(command)
        for flag in ("-c", "--config"):
            if flag in words:
                path = words[words.index(flag) + 1]
                host = _container_file(path, mounts)
                assert host is not None and host.is_file(), f"{name}: {path} is not mounted"
        if entrypoint[:1] == ["/bin/sh"]:
            host = _container_file(entrypoint[1], mounts)
            assert host is not None and host.is_file(), f"{name}: {entrypoint[1]}"


def test_zenoh_image_matches_the_python_binding() -> None:
    """Routers use the eclipse/zenoh release of the installed eclipse-zenoh (same major.minor)."""
    from importlib.metadata import version

    major_minor = tuple(int(x) for x in version("eclipse-zenoh").split(".")[:2])
    images: list[str] = []
    for compose in COMPOSE_FILES:
        services = yaml.safe_load(compose.read_text(encoding="utf-8"))["services"].values()
        images += [s["image"] for s in services if "zenoh" in str(s.get("image", ""))]
    for path in K8S.glob("*.yaml"):
        for doc in load_yaml_docs(path):
            if doc.get("kind") == "Deployment":
                spec = doc["spec"]["template"]["spec"]
                containers = spec.get("containers", []) + spec.get("initContainers", [])
                images += [c["image"] for c in containers if "zenoh" in c["image"]]
    assert images
    for image in images:
        match = ZENOH_IMAGE.match(image)
        assert match, f"{image}: pin eclipse/zenoh to an exact release"
        assert (int(match[1]), int(match[2])) == major_minor, image
    assert len(set(images)) == 1, f"one zenoh release everywhere: {sorted(set(images))}"


def test_rlutf_image_tags_name_the_package_version() -> None:
    """Every ``rlutf:X.Y.Z`` tag the image and deployment files build, run or pull is the
    package's version: an image tagged with an older version than the code it holds would
    replay that version's logs with other code (an audit needs the code that wrote the log)."""
    version = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"][
        "version"
    ]
    files = [DOCKERFILE, DEPLOY / "README.md", *COMPOSE_FILES, *K8S.glob("*.yaml")]
    tags: dict[str, set[str]] = {}
    for path in files:
        text = path.read_text(encoding="utf-8")
        found = set(re.findall(r"rlutf:(\d+\.\d+\.\d+\S*)", text))
        found |= set(re.findall(r"newTag:\s*(\S+)", text))
        if found:
            tags[path.relative_to(REPO).as_posix()] = found
    assert "docker/Dockerfile" in tags and "deploy/k8s/kustomization.yaml" in tags
    stale = {name: sorted(found) for name, found in tags.items() if found != {version}}
    assert not stale, f"image tags other than the package's version {version}: {stale}"


# ================================================================================= kubernetes


def _k8s_docs() -> list[dict[str, Any]]:
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text(encoding="utf-8"))
    docs = []
    for resource in kustomization["resources"]:
        path = K8S / resource
        assert path.is_file(), f"kustomization.yaml: {resource} does not exist"
        docs += load_yaml_docs(path)
    return docs


def test_k8s_manifests() -> None:
    docs = _k8s_docs()
    kinds = sorted(d["kind"] for d in docs)
    assert kinds == sorted(
        ["ConfigMap", "ConfigMap", "Deployment", "Deployment", "PersistentVolumeClaim", "Service"]
    )
    by_kind_name = {(d["kind"], d["metadata"]["name"]): d for d in docs}
    for doc in docs:
        assert doc.get("apiVersion"), doc["metadata"]["name"]
        if doc["kind"] != "Deployment":
            continue
        spec = doc["spec"]
        labels = spec["template"]["metadata"]["labels"]
        assert spec["selector"]["matchLabels"].items() <= labels.items()
        pod = spec["template"]["spec"]
        volumes = {v["name"]: v for v in pod["volumes"]}
        for container in pod["containers"] + pod.get("initContainers", []):
            assert "resources" in container, f"{container['name']}: resource limits"
            for mount in container.get("volumeMounts", []):
                assert mount["name"] in volumes, f"{container['name']}: {mount['name']}"
        for volume in volumes.values():
            if "configMap" in volume:
                assert ("ConfigMap", volume["configMap"]["name"]) in by_kind_name
            if "persistentVolumeClaim" in volume:
                claim = volume["persistentVolumeClaim"]["claimName"]
                assert ("PersistentVolumeClaim", claim) in by_kind_name
    service = by_kind_name[("Service", "zenoh-router")]
    router = by_kind_name[("Deployment", "zenoh-router")]
    assert service["spec"]["selector"].items() <= (
        router["spec"]["template"]["metadata"]["labels"].items()
    )
    assert any(p["port"] == 7447 for p in service["spec"]["ports"])
    rlutf = by_kind_name[("Deployment", "rlutf")]
    assert rlutf["spec"]["replicas"] == 2
    args = rlutf["spec"]["template"]["spec"]["containers"][0]["args"]
    assert args[0] == "serve" and "--no-store" in args
    assert args[args.index("--mode") + 1] == "client"
    # The pose state (default state_dir: {store_dir}/state) is writable under the read-only
    # root filesystem and outlives a container restart: a volume of the pod.
    pod = rlutf["spec"]["template"]["spec"]
    mounts = {m["mountPath"]: m["name"] for m in pod["containers"][0]["volumeMounts"]}
    assert dockerfile_env()["RLUTF_STORE_DIR"] == "/data/store"
    volume = {v["name"]: v for v in pod["volumes"]}[mounts["/data/store"]]
    assert "emptyDir" in volume or "persistentVolumeClaim" in volume
    assert "--state" not in args and "--no-state" not in args


def _configmap_files(docs: list[dict[str, Any]]) -> dict[str, dict[str, str]]:
    return {d["metadata"]["name"]: d["data"] for d in docs if d["kind"] == "ConfigMap"}


def test_k8s_configmaps_equal_the_deploy_files() -> None:
    data = _configmap_files(_k8s_docs())
    assert data["zenoh-router-config"]["router.json5"] == (ZENOH_DIR / "router.json5").read_text()
    assert data["zenoh-router-config"]["fetch-fs-backend.sh"] == (
        (ZENOH_DIR / "fetch-fs-backend.sh").read_text()
    )
    assert data["rlutf-zenoh-config"]["zenoh.json5"] == (
        (ZENOH_DIR / "service-client.json5").read_text()
    )


def test_k8s_config_paths_are_mounted() -> None:
    docs = _k8s_docs()
    data = _configmap_files(docs)
    for doc in docs:
        if doc["kind"] != "Deployment":
            continue
        pod = doc["spec"]["template"]["spec"]
        volumes = {v["name"]: v for v in pod["volumes"]}
        for container in pod["containers"] + pod.get("initContainers", []):
            words = list(container.get("command", [])) + list(container.get("args", []))
            paths = [words[words.index(f) + 1] for f in ("-c", "--config") if f in words]
            if words[:1] == ["/bin/sh"]:
                paths.append(words[1])
            for path in paths:
                found = False
                for mount in container.get("volumeMounts", []):
                    prefix = mount["mountPath"].rstrip("/") + "/"
                    volume = volumes[mount["name"]]
                    if path.startswith(prefix) and "configMap" in volume:
                        key = path[len(prefix) :]
                        found = key in data[volume["configMap"]["name"]]
                assert found, f"{doc['metadata']['name']}/{container['name']}: {path}"


# ===================================================================== certificates and ACLs


needs_openssl = pytest.mark.skipif(
    shutil.which("openssl") is None, reason="openssl is not installed: cannot make dev certs"
)


def _gen_certs(out: Path, *robots: str) -> None:
    subprocess.run(
        ["bash", str(DEPLOY / "gen-certs.sh"), "-o", str(out), *robots],
        check=True,
        capture_output=True,
        timeout=60,
    )


@pytest.fixture(scope="module")
def dev_certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None or shutil.which("bash") is None:
        pytest.skip("openssl and bash are needed to make development certificates")
    out = tmp_path_factory.mktemp("certs")
    _gen_certs(out, "r1", "r2", "r9")
    return out


def test_gen_certs_writes_verifiable_certificates(dev_certs: Path) -> None:
    expected = {
        "router": "zenoh-router",
        "service": "rlutf-service",
        "operator": "rlutf-operator",
        "robot-r1": "robot-r1",
        "robot-r2": "robot-r2",
    }
    for stem, cn in expected.items():
        pem, key = dev_certs / f"{stem}.pem", dev_certs / f"{stem}.key"
        assert pem.is_file() and key.is_file(), stem
        assert key.stat().st_mode & 0o077 == 0, f"{key} must be private"
        subject = subprocess.run(
            ["openssl", "x509", "-in", str(pem), "-noout", "-subject"],
            capture_output=True,
            text=True,
            check=True,
            timeout=30,
        ).stdout
        assert f"CN = {cn}" in subject or f"CN={cn}" in subject, subject
        verify = subprocess.run(
            ["openssl", "verify", "-CAfile", str(dev_certs / "ca.pem"), str(pem)],
            capture_output=True,
            text=True,
            check=False,
            timeout=30,
        )
        assert verify.returncode == 0, verify.stdout + verify.stderr


def test_deploy_gitignore_keeps_secrets_out() -> None:
    ignored = (DEPLOY / ".gitignore").read_text(encoding="utf-8").split()
    assert "/certs/" in ignored and "*.key" in ignored
    assert not list(DEPLOY.rglob("*.key")) or all(
        p.is_relative_to(DEPLOY / "certs") for p in DEPLOY.rglob("*.key")
    )


class Observer:
    """Collects the keys a subscriber receives, thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._keys: list[str] = []

    def __call__(self, sample: Any) -> None:
        with self._lock:
            self._keys.append(str(sample.key_expr))

    @property
    def keys(self) -> list[str]:
        with self._lock:
            return list(self._keys)

    def saw(self, key: str) -> bool:
        return key in self.keys


def _client_config(port: int, proto: str, extra: dict[str, Any]) -> Any:
    import zenoh

    host = "127.0.0.1"
    config = {
        "mode": "client",
        "connect": {"endpoints": [f"{proto}/{host}:{port}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        **extra,
    }
    return zenoh.Config.from_json5(json.dumps(config))


def _router_config(path: Path) -> Any:
    import zenoh

    config = zenoh.Config.from_file(str(path))
    config.insert_json5("scouting/gossip/enabled", "false")
    return config


def _subscribe_and_sync(
    session: Any, key_expr: str, probe_from: Any, probe_key: str, observer: Observer
) -> Any:
    """Declare a subscriber and wait until a probe put from ``probe_from`` reaches it."""
    subscriber = session.declare_subscriber(key_expr, observer)

    def arrived() -> bool:
        probe_from.put(probe_key, b"probe")
        return wait_until(lambda: observer.saw(probe_key), timeout=0.3)

    assert wait_until(arrived), f"subscription {key_expr} never became active"
    return subscriber


def _check_acl(open_as: Callable[[str], Any]) -> None:
    """Robots, operator and service against a router running the generated ACL.

    A privileged subscriber (the service subject) observes which puts get through. Puts from
    one session on one link arrive in order, so once a later allowed put (the sentinel) has
    arrived, any earlier denied put would have arrived too: no fixed sleeps.
    """
    with ExitStack() as stack:
        observer_session = stack.enter_context(open_as("service"))
        service = stack.enter_context(open_as("service"))
        robot1 = stack.enter_context(open_as("robot-r1"))
        operator = stack.enter_context(open_as("operator"))

        seen = Observer()
        stack.callback(
            _subscribe_and_sync(
                observer_session, "rlutf/**", service, "rlutf/robots/r0/probe", seen
            ).undeclare
        )
        # Robot r1 writes: its own scan and odom yes; another robot's scan, a map, an initial
        # pose (operator's job) and a pose (service's job) no.
        robot1.put("rlutf/robots/r2/scan", b"{}")
        robot1.put("rlutf/maps/m1", b"{}")
        robot1.put("rlutf/robots/r1/initialpose", b"{}")
        robot1.put("rlutf/robots/r1/pose", b"{}")
        robot1.put("rlutf/robots/r1/odom", b"{}")
        robot1.put("rlutf/robots/r1/scan", b"{}")
        assert wait_until(lambda: seen.saw("rlutf/robots/r1/scan")), "own scan must pass"
        assert seen.saw("rlutf/robots/r1/odom"), "own odom must pass"
        for denied in (
            "rlutf/robots/r2/scan",
            "rlutf/maps/m1",
            "rlutf/robots/r1/initialpose",
            "rlutf/robots/r1/pose",
        ):
            assert not seen.saw(denied), f"robot r1 must not write {denied}"

        # Robot r1 may not DELETE its own scan key (issue 19): only puts are allowed.
        robot1.delete("rlutf/robots/r1/scan")
        robot1.put("rlutf/robots/r1/odom", b"{}")
        assert wait_until(lambda: seen.keys.count("rlutf/robots/r1/odom") == 2)
        assert seen.keys.count("rlutf/robots/r1/scan") == 1, "r1 must not DELETE its scan key"

        # The operator writes maps, initial poses and relocalize requests, not robot inputs.
        operator.put("rlutf/robots/r1/scan-not-allowed", b"{}")
        operator.put("rlutf/robots/r1/initialpose", b"{}")
        operator.put("rlutf/robots/r1/relocalize", b"{}")
        operator.put("rlutf/maps/m2", b"{}")
        assert wait_until(lambda: seen.saw("rlutf/maps/m2")), "operator map put must pass"
        assert seen.keys.count("rlutf/robots/r1/initialpose") == 1
        assert seen.keys.count("rlutf/robots/r1/relocalize") == 1, "operator relocalizes"
        assert not seen.saw("rlutf/robots/r1/scan-not-allowed")

        # Robot r1 reads its own pose and maps, not another robot's pose.
        robot_seen = Observer()
        stack.callback(
            _subscribe_and_sync(
                robot1, "rlutf/robots/r1/pose", service, "rlutf/robots/r1/pose", robot_seen
            ).undeclare
        )
        # Declarations travel in order on r1's link: once the later map subscription is
        # active, the router has already judged the subscription to r2's pose.
        other = robot1.declare_subscriber("rlutf/robots/r2/pose", robot_seen)
        stack.callback(other.undeclare)
        stack.callback(
            _subscribe_and_sync(
                robot1, "rlutf/maps/**", operator, "rlutf/maps/probe", robot_seen
            ).undeclare
        )
        service.put("rlutf/robots/r2/pose", b"{}")
        operator.put("rlutf/maps/m3", b"{}")
        service.put("rlutf/robots/r1/pose", b"{}")
        assert wait_until(lambda: robot_seen.keys.count("rlutf/robots/r1/pose") >= 2)
        assert wait_until(lambda: robot_seen.saw("rlutf/maps/m3")), "robots read maps"
        assert not robot_seen.saw("rlutf/robots/r2/pose"), "r1 must not read r2's pose"

        # Gets: the service answers pose queries; r1 gets its own pose only.
        def answer(query: Any) -> None:
            key = str(query.key_expr)
            if "*" not in key:
                query.reply(key, b"{}")
            query.drop()

        queryable = service.declare_queryable("rlutf/robots/*/pose", answer)
        stack.callback(queryable.undeclare)

        def own_pose() -> bool:
            # retried: the queryable's declaration reaches the router a moment after declare
            own = [r for r in robot1.get("rlutf/robots/r1/pose", timeout=1.0) if r.ok is not None]
            return [str(r.ok.key_expr) for r in own] == ["rlutf/robots/r1/pose"]

        assert wait_until(own_pose), "r1 must get its own pose"
        theirs = [r for r in robot1.get("rlutf/robots/r2/pose", timeout=1.0) if r.ok is not None]
        assert theirs == [], "r1 must not get r2's pose"

        # The operator sees the service's liveliness token.
        token = service.liveliness().declare_token("rlutf/service/test-1")
        stack.callback(token.undeclare)
        assert wait_until(
            lambda: any(
                r.ok is not None and str(r.ok.key_expr) == "rlutf/service/test-1"
                for r in operator.liveliness().get("rlutf/service/*", timeout=1.0)
            )
        )


@pytest.mark.integration
def test_acl_usrpwd_in_process_router(tmp_path: Path) -> None:
    import zenoh

    gen = load_gen_acl()
    port = free_port()
    names = {
        "service": "rlutf-service",
        "operator": "rlutf-operator",
        "robot-r1": "robot-r1",
        "robot-r2": "robot-r2",
    }
    users = tmp_path / "users.txt"
    users.write_text("".join(f"{n}:pw-{n}\n" for n in names.values()), encoding="utf-8")
    router_file = tmp_path / "router-usrpwd.json5"
    gen.main(
        [
            "--auth",
            "usrpwd",
            "--users-file",
            str(users),
            "--listen",
            f"tcp/127.0.0.1:{port}",
            "-o",
            str(router_file),
            "r1",
            "r2",
        ]
    )

    def open_as(who: str, password: str | None = None) -> Any:
        user = names[who]
        auth = {"usrpwd": {"user": user, "password": password or f"pw-{user}"}}
        return zenoh.open(_client_config(port, "tcp", {"transport": {"auth": auth}}))

    with zenoh.open(_router_config(router_file)):
        _check_acl(open_as)
        with pytest.raises(zenoh.ZError):
            open_as("robot-r1", password="wrong").close()


@pytest.mark.integration
@needs_openssl
def test_acl_tls_cert_common_names_in_process_router(tmp_path: Path, dev_certs: Path) -> None:
    import zenoh

    gen = load_gen_acl()
    port = free_port()
    router_file = tmp_path / "router-tls.json5"
    gen.main(
        [
            "--certs-dir",
            str(dev_certs),
            "--listen",
            f"tls/127.0.0.1:{port}",
            "-o",
            str(router_file),
            "r1",
            "r2",
        ]
    )

    def tls(stem: str | None) -> dict[str, Any]:
        conf: dict[str, Any] = {"root_ca_certificate": str(dev_certs / "ca.pem")}
        if stem is not None:
            conf |= {
                "connect_certificate": str(dev_certs / f"{stem}.pem"),
                "connect_private_key": str(dev_certs / f"{stem}.key"),
                "enable_mtls": True,
            }
        return {"transport": {"link": {"tls": conf}}}

    def open_as(who: str) -> Any:
        return zenoh.open(_client_config(port, "tls", tls(who)))

    with zenoh.open(_router_config(router_file)):
        _check_acl(open_as)
        with pytest.raises(zenoh.ZError):
            zenoh.open(_client_config(port, "tls", tls(None))).close()
        # A valid certificate of a robot the ACL does not know connects but may write nothing.
        with ExitStack() as stack:
            observer_session = stack.enter_context(open_as("service"))
            service = stack.enter_context(open_as("service"))
            stranger = stack.enter_context(open_as("robot-r9"))
            seen = Observer()
            stack.callback(
                _subscribe_and_sync(
                    observer_session, "rlutf/**", service, "rlutf/probe", seen
                ).undeclare
            )
            attempts = ("rlutf/robots/r9/scan", "rlutf/robots/r1/scan", "rlutf/maps/m9")
            for key in attempts:
                stranger.put(key, b"{}")
            time.sleep(0.3)  # nothing the stranger sends may pass, so no sentinel exists
            assert not set(attempts) & set(seen.keys), seen.keys


@pytest.mark.integration
def test_service_client_config_waits_for_a_late_router() -> None:
    """deploy/zenoh/service-client.json5: a client started before its router connects later."""
    import zenoh

    port = free_port()
    config = zenoh.Config.from_file(str(ZENOH_DIR / "service-client.json5"))
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    opened: dict[str, Any] = {}

    def open_session() -> None:
        try:
            opened["session"] = zenoh.open(config)
        except Exception as exc:  # recorded for the assertion below
            opened["error"] = exc

    thread = threading.Thread(target=open_session, daemon=True)
    thread.start()
    time.sleep(0.5)
    assert not opened, "open() must wait for the router, not fail"
    router = zenoh.Config.from_json5(
        json.dumps(
            {
                "mode": "router",
                "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
            }
        )
    )
    with zenoh.open(router) as router_session:
        thread.join(timeout=10.0)
        assert "session" in opened, f"client did not connect: {opened.get('error')}"
        with opened["session"] as client:
            seen = Observer()
            sub = router_session.declare_subscriber("rlutf/**", seen)
            try:

                def delivered() -> bool:
                    client.put("rlutf/robots/r1/scan", b"{}")
                    return wait_until(lambda: seen.saw("rlutf/robots/r1/scan"), timeout=0.3)

                assert wait_until(delivered)
            finally:
                sub.undeclare()


def _iter_json5_endpoints() -> Iterator[str]:
    for path in JSON5_FILES:
        for key in ("listen/endpoints", "connect/endpoints"):
            value = zenoh_json(path, key)
            if isinstance(value, list):
                yield from value


def test_endpoints_use_the_zenoh_port() -> None:
    endpoints = list(_iter_json5_endpoints())
    assert endpoints
    assert all(e.endswith(":7447") for e in endpoints), endpoints


# ==================================================================================== metrics

METRICS_PORT = 9464
DASHBOARD = DEPLOY / "grafana" / "rlutf-dashboard.json"
PROMETHEUS_CONFIG = DEPLOY / "prometheus" / "prometheus.yml"


def _metrics_port_of(words: list[str], env: dict[str, str], mp: pytest.MonkeyPatch) -> int | None:
    """The metrics port ``rlutf WORDS`` runs with in environment ``env`` (flags beat env)."""
    from service.cli.flags import load
    from service.cli.main import build_parser

    for key in [k for k in os.environ if k.startswith("RLUTF_")]:
        mp.delenv(key)
    for key, value in env.items():
        mp.setenv(key, value)
    port = load(build_parser().parse_args(words)).metrics_port
    return None if port is None else int(port)


def test_compose_serves_metrics_and_prometheus_scrapes_them(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    services = _compose_services()
    rlutf = services["rlutf"]
    env = {k: str(v) for k, v in rlutf.get("environment", {}).items()}
    assert _metrics_port_of(list(rlutf["command"]), env, monkeypatch) == METRICS_PORT
    assert str(METRICS_PORT) in [str(p).split("/")[0] for p in rlutf["expose"]]
    prometheus = services["prometheus"]
    assert prometheus["profiles"] == ["monitoring"], "optional: not started by a plain `up`"
    config = yaml.safe_load(PROMETHEUS_CONFIG.read_text(encoding="utf-8"))
    (job,) = config["scrape_configs"]
    assert job["honor_labels"] is True  # keeps the service's `instance` label
    (sd,) = job["dns_sd_configs"]
    assert sd["names"] == ["rlutf"] and sd["port"] == METRICS_PORT
    assert job.get("metrics_path", "/metrics") == "/metrics"


def test_k8s_pods_serve_metrics_with_scrape_annotations(monkeypatch: pytest.MonkeyPatch) -> None:
    docs = {(d["kind"], d["metadata"]["name"]): d for d in _k8s_docs()}
    template = docs[("Deployment", "rlutf")]["spec"]["template"]
    annotations = template["metadata"]["annotations"]
    assert annotations == {
        "prometheus.io/scrape": "true",
        "prometheus.io/port": str(METRICS_PORT),
        "prometheus.io/path": "/metrics",
    }
    (container,) = template["spec"]["containers"]
    env = {e["name"]: e["value"] for e in container["env"] if "value" in e}
    assert _metrics_port_of(list(container["args"]), env, monkeypatch) == METRICS_PORT
    ports = {p["containerPort"]: p for p in container["ports"]}
    assert ports[METRICS_PORT]["name"] == "metrics"


def _dashboard_exprs(dashboard: dict[str, Any]) -> list[str]:
    return [t["expr"] for panel in dashboard["panels"] for t in panel["targets"]]


def test_grafana_dashboard_queries_only_exported_metrics() -> None:
    from service.live.metrics import METRIC_NAMES

    dashboard = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    (source,) = dashboard["__inputs"]
    assert source["name"] == "DS_PROMETHEUS" and source["pluginId"] == "prometheus"
    for panel in dashboard["panels"]:
        assert panel["datasource"]["uid"] == "${DS_PROMETHEUS}", panel["title"]
        assert all(t["datasource"]["uid"] == "${DS_PROMETHEUS}" for t in panel["targets"])
    exprs = _dashboard_exprs(dashboard)

    def family(series: str) -> str:  # a histogram's series name to its family's
        for suffix in ("_bucket", "_sum", "_count"):
            if series.endswith(suffix) and series.removesuffix(suffix) in METRIC_NAMES:
                return series.removesuffix(suffix)
        return series

    used = {family(n) for e in exprs for n in re.findall(r"\brlutf_[a-z_]+", e)}
    assert used <= METRIC_NAMES, f"not exported: {sorted(used - METRIC_NAMES)}"
    assert used == METRIC_NAMES, f"not on the dashboard: {sorted(METRIC_NAMES - used)}"
    # per instance, latency and compute p50 and p99 from the histograms
    assert all('instance=~"$instance"' in e for e in exprs)
    for histogram in ("rlutf_scan_to_pose_latency_seconds", "rlutf_worker_compute_seconds"):
        for q in ("0.5", "0.99"):
            assert any(e.startswith(f"histogram_quantile({q},") and histogram in e for e in exprs)
    (variable,) = dashboard["templating"]["list"]
    assert variable["name"] == "instance"
