"""``rlutf serve|config|demo``: run the service, print its configuration, run the demo."""

from __future__ import annotations

import argparse
import errno
import json
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from schemas import MAX_BEAMS
from service.cli.envnames import warn_unknown
from service.cli.errors import CliError, session_failure
from service.cli.flags import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    PORT,
    SEED,
    checked_settings,
    load,
    number,
    ros2_flags,
    settings_flags,
    usable_folder,
    zenoh_file_config,
    zenoh_flags,
)
from service.cli.progress import starting_status


def register(sub: Any) -> None:
    """Add ``serve``, ``config`` and ``demo`` to the ``rlutf`` subcommands."""
    serve = sub.add_parser(
        "serve",
        help="run the localization service",
        description="Run the service. Default: zenoh router on "
        "tcp/[::]:7447 with the embedded file-backed map store; robots "
        "connect straight to it. SIGINT/SIGTERM stop it gracefully.",
    )
    zenoh_flags(serve, client=False)
    settings_flags(serve)
    ros2_flags(serve)
    # A process of `rlutf serve --processes N` stops when its host is gone, even by SIGKILL.
    serve.add_argument("--host-pid", type=int, help=argparse.SUPPRESS)
    serve.set_defaults(func=cmd_serve)

    config = sub.add_parser(
        "config",
        help="print the effective configuration as JSON",
        description="Print the configuration the service would run with: "
        "defaults, settings file, RLUTF_* environment, then flags.",
    )
    zenoh_flags(config, client=False)
    settings_flags(config)
    ros2_flags(config)
    config.set_defaults(func=cmd_config)

    demo = sub.add_parser(
        "demo",
        help="the service with a simulated fleet, live",
        description="Start the service on its embedded defaults, put a map "
        "into the store, and drive a simulated fleet (each robot its own "
        "Zenoh client session) at 10 Hz with drifting odometry. Shows a "
        "live table and a summary.",
    )
    demo.add_argument(
        "--robots", type=number(int, minimum=1), default=5, help="simulated robots (default 5)"
    )
    demo.add_argument("--duration", type=number(above=0), default=20.0, help="seconds (default 20)")
    demo.add_argument(
        "--rate",
        type=number(above=0, maximum=1000),
        default=10.0,
        help="scans per second per robot (default 10)",
    )
    demo.add_argument(
        "--beams",
        type=number(int, minimum=8, maximum=MAX_BEAMS),
        default=360,
        help=f"beams per scan (default 360, at most {MAX_BEAMS}: the wire's limit)",
    )
    demo.add_argument(
        "--seed", type=SEED, default=0, help="world and fleet seed, 0 or more (default 0)"
    )
    demo.add_argument(
        "--port", type=PORT, default=0, help="router port on 127.0.0.1 (default: a free one)"
    )
    demo.add_argument("--store", type=Path, help="map store folder (default: a temporary one)")
    demo.add_argument(
        "--record", type=Path, default=Path("logs"), help="MCAP log folder (default: logs)"
    )
    demo.add_argument("--no-record", action="store_true", help="do not record")
    demo.add_argument(
        "--workers",
        type=number(int, minimum=-1),
        help="run the service as one process with N worker processes (-1: one per core "
        "this process may use; 0: in-process thread) instead of its default layout",
    )
    demo.add_argument(
        "--processes",
        type=number(int, minimum=-1, maximum=64),
        help="N service processes behind the router (default -1: one per core this process "
        "may use, as `rlutf serve`; 0: one process with its workers)",
    )
    demo.add_argument("--quiet", action="store_true", help="no live table, summary only")
    demo.add_argument("--verbose-health", action="store_true", help="print the final health")
    demo.set_defaults(func=cmd_demo)


def cmd_config(args: argparse.Namespace) -> int:
    """Print the effective configuration."""
    warn_unknown("rlutf config", os.environ)
    print(json.dumps(load(args).effective(), indent=2))
    return EXIT_OK


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the service until SIGINT or SIGTERM."""
    import zenoh

    from service.cluster.names import NameTaken, NameWaitStopped
    from service.live.heapdumps import install_from_env
    from service.live.node import LocalizationService
    from service.live.sessions import StoppedWaiting
    from service.live.worker import tune_gc
    from service.logs.recording import make_recorder

    if args.host_pid is None:  # a host's processes share its environment: it warned
        warn_unknown("rlutf serve", os.environ)
    settings = load(args)
    # Foxglove's SDK is imported only for a live view: a few MB in every process of a service.
    live_view_errors: tuple[type[OSError], ...] = ()
    if settings.foxglove_port is not None:
        from service.live.foxview import LiveViewError

        live_view_errors = (LiveViewError,)
    zenoh_file_config(settings)  # a bad -c/--config file is named before anything starts
    _addrs_usable(settings)
    if not settings.no_store:
        usable_folder(settings.store_dir, "--store")
        _store_free(
            settings.store_dir,
            "give this one a --store of its own, or --no-store to use the first one's maps "
            "over Zenoh (-e/--connect its endpoint)",
        )
    if not settings.no_record:
        usable_folder(settings.record_dir, "--record")
    if not settings.no_state:
        usable_folder(settings.state_dir, "--state")
    if args.host_pid is None and settings.ros2.enabled:  # said once, not by each process
        from service.ros2.entities import no_map_warning

        warning = no_map_warning(settings.ros2)
        if warning is not None:
            logging.getLogger("rlutf").warning("%s", warning)
    stop = threading.Event()

    # A host's process is stopped by its host, which says so itself: not a warning there.
    level = logging.INFO if args.host_pid is not None else logging.WARNING

    def on_signal(signum: int, _frame: object) -> None:
        logging.getLogger("rlutf").log(level, "signal %d: stopping", signum)
        stop.set()

    # A host's process is stopped by its host (SIGTERM), which takes a terminal's Ctrl-C (and its
    # hang-up) for all of them: a process that took the SIGINT sent to the whole group would stop
    # on its own and be started again as if it had crashed (service.live.stopping).
    terminal = signal.SIG_IGN if args.host_pid is not None else on_signal
    signal.signal(signal.SIGINT, terminal)
    signal.signal(signal.SIGTERM, on_signal)
    # A closed terminal or a dropped ssh session (SIGHUP) killed the service on the spot, its
    # log left unfinished (.mcap.part): it stops as on Ctrl-C. Under nohup it stays ignored.
    if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:
        signal.signal(signal.SIGHUP, terminal)
    install_from_env()  # RLUTF_TRACEMALLOC: a diagnosis of what grows (service.live.heapdumps)
    # a host's processes: the host checked the layout
    if args.host_pid is None and not _layout_fits("rlutf serve", settings):
        return EXIT_USAGE
    processes = settings.service_processes()
    if processes > 0:
        if settings.foxglove_port is not None:
            print(
                "rlutf serve: --foxglove-port needs --processes 0 (each of the processes sees "
                "only its own robots, and a live view must show them all)",
                file=sys.stderr,
            )
            return EXIT_USAGE
        return serve_host(settings.model_copy(update={"processes": processes}), stop)
    if args.host_pid is not None:
        follow_host(args.host_pid, stop)
    try:
        service = LocalizationService(settings, recorder=make_recorder(settings), stop=stop)
        with starting_status("rlutf serve") as progress:
            service.start(progress)
        tune_gc()
    except zenoh.ZError as err:
        print(f"rlutf serve: {session_failure(err, settings.listen)}", file=sys.stderr)
        return EXIT_FAILURE
    except live_view_errors as err:  # --foxglove-port taken or --foxglove-addr not local
        print(f"rlutf serve: {err} (choose another --foxglove-port)", file=sys.stderr)
        return EXIT_FAILURE
    except OSError as err:
        if err.filename is not None:  # a folder of the store, the state or the logs
            raise
        # the metrics port is taken or the address is not local
        print(f"rlutf serve: {_metrics_refused(settings, err)}", file=sys.stderr)
        return EXIT_FAILURE
    except (StoppedWaiting, NameWaitStopped):  # told to stop while waiting (router, name)
        service.close()
        return EXIT_OK
    except RuntimeError as err:  # a worker process could not start, or the name is taken
        if isinstance(err, NameTaken):  # after its worker processes started: stop them
            service.close()
        print(f"rlutf serve: {err}", file=sys.stderr)
        return EXIT_FAILURE
    if stop.is_set():  # told to stop as it came up: not ready, stopping
        service.close()
        return EXIT_OK
    ready = (
        f"rlutf serve: ready: instance {settings.instance}, mode {settings.mode}, "
        f"listening on {', '.join(settings.listen) if settings.mode != 'client' else '-'}"
        f"{', connecting to ' + ', '.join(settings.connect) if settings.connect else ''}"
    )
    if args.host_pid is None:
        print(ready, file=sys.stderr, flush=True)
    else:  # a host's process: the host says when all are ready, and where robots connect
        logging.getLogger("rlutf").info("%s", ready)
    if service.metrics.port is not None:
        metrics = f"metrics on http://{settings.metrics_addr}:{service.metrics.port}/metrics"
        if args.host_pid is None:
            print(f"rlutf serve: {metrics}", file=sys.stderr, flush=True)
        else:  # a loopback port the host scrapes; operators scrape the host's endpoint
            logging.getLogger("rlutf").info("%s", metrics)
    if service.live.url is not None:
        print(
            f"rlutf serve: live view on {service.live.url} (Foxglove app: Open connection, "
            "Foxglove WebSocket)",
            file=sys.stderr,
            flush=True,
        )
    try:
        service.wait(stop)
    finally:
        service.close()
    return _name_kept(service.name_claim.lost)


def _name_kept(lost: str | None) -> int:
    """The exit code of a service that stopped: 1, said on stderr, if it stopped because another
    instance of its name claimed the name first (service.cluster.names)."""
    if lost is None:
        return EXIT_OK
    print(f"rlutf serve: {lost}", file=sys.stderr, flush=True)
    return EXIT_FAILURE


def follow_host(host_pid: int, stop: threading.Event) -> None:
    """Set ``stop`` once ``host_pid`` is no longer this process's parent (the host died)."""

    def watch() -> None:
        import os

        while not stop.wait(0.5):
            if os.getppid() != host_pid:
                logging.getLogger("rlutf").warning("host process %d is gone: stopping", host_pid)
                stop.set()

    threading.Thread(target=watch, name="rlutf-host-watch", daemon=True).start()


def _addrs_usable(settings: Any) -> None:
    """Refuse a ``--metrics-addr`` or ``--foxglove-addr`` that is no address of this host (a
    name that does not resolve, another host's address), and a port another program holds,
    before anything starts: the endpoint binds it once the service has started, a host's
    processes included (seconds later). (A bad ``--foxglove-addr`` was "cannot serve the live
    view ...: choose another --foxglove-port", exit 1.)

    Raises:
        CliError: naming the flag, the address or port and the fix.
    """
    import socket

    for port, addr, flag in (
        (settings.metrics_port, settings.metrics_addr, "--metrics-addr"),
        (settings.foxglove_port, settings.foxglove_addr, "--foxglove-addr"),
    ):
        if port is None:
            continue
        try:
            family, kind, _, _, where = socket.getaddrinfo(addr, 0, type=socket.SOCK_STREAM)[0]
            with socket.socket(family, kind) as probe:
                probe.bind(where)  # port 0: takes no port the endpoint will want
        except (OSError, UnicodeError) as err:  # UnicodeError: a name no DNS label takes
            why = getattr(err, "strerror", None) or str(err)
            raise CliError(
                f"{flag} {addr}: not an address of this host ({why}); give one of its "
                "addresses, e.g. 0.0.0.0 (all of them) or 127.0.0.1",
                EXIT_USAGE,
            ) from None
        if port:  # taken? (the servers bind with SO_REUSEADDR, so the probe does too)
            try:
                with socket.socket(family, kind) as probe:
                    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                    probe.bind((where[0], port, *where[2:]))
            except OSError as err:
                raise CliError(
                    _metrics_refused(settings, err)
                    if flag == "--metrics-addr"
                    else f"cannot serve the live view on {addr}:{port} ({err.strerror or err}); "
                    "choose another --foxglove-port",
                    EXIT_FAILURE,
                ) from None


def _store_free(folder: Path, fix: str) -> None:
    """Refuse a --store that another running service serves, before anything starts (the
    service claims it for good when its store starts: service.maps.files.FileMapStore.claim);
    ``fix`` says what to do instead.

    Raises:
        CliError: another process serves the folder.
    """
    from service.maps.files import FileMapStore, StoreInUse

    store = FileMapStore(folder)
    try:
        store.claim()
    except StoreInUse as err:
        raise CliError(f"{err}; {fix}", EXIT_FAILURE) from None
    store.release()


def serve_host(settings: Any, stop: threading.Event) -> int:
    """``rlutf serve --processes N``: the host of N service processes, until ``stop``."""
    import zenoh

    from service.cluster.names import NameWaitStopped
    from service.live.host import Host
    from service.live.sessions import StoppedWaiting

    def say(text: str) -> None:
        print(f"rlutf serve: {text}", file=sys.stderr, flush=True)

    host = Host(settings, stop=stop)
    try:
        with starting_status("rlutf serve") as progress:
            host.start(progress)
    except (StoppedWaiting, NameWaitStopped):  # told to stop while starting: a stop, not a fault
        host.close()
        return EXIT_OK
    except zenoh.ZError as err:
        host.close()
        say(session_failure(err, settings.listen))
        return EXIT_FAILURE
    except OSError as err:
        host.close()
        if err.filename is not None:  # a folder of the store, the state or the logs
            raise
        # The host's metrics port is taken or its address is not local: said as a single
        # process says it ("[Errno 98] Address already in use" named neither port nor fix).
        bind = err.errno in (errno.EADDRINUSE, errno.EADDRNOTAVAIL)
        say(_metrics_refused(settings, err) if bind else str(err))
        return EXIT_FAILURE
    except RuntimeError as err:
        host.close()
        say(str(err))
        return EXIT_FAILURE
    if stop.is_set():  # told to stop as the last process came up: not ready, stopping
        host.close()
        return EXIT_OK
    names = ", ".join(p.name for p in host.processes)
    # As a single process says it: a client listens on nothing robots can reach (a host in
    # --mode client said "listening on tcp/[::]:7447", the default it never bound).
    where = ", ".join(settings.listen) if settings.mode != "client" else "-"
    connect = f", connecting to {', '.join(settings.connect)}" if settings.connect else ""
    say(f"ready: instance {settings.instance} with {len(host.processes)} processes ({names}), "
        f"listening on {where}{connect}")  # fmt: skip
    if host.metrics is not None:
        say(f"metrics on http://{settings.metrics_addr}:{host.metrics.port}/metrics")
    try:
        host.wait(stop)
    finally:
        host.close()
    return _name_kept(host.service.name_claim.lost)  # its process 0's name: the host's


def _metrics_refused(settings: Any, err: OSError) -> str:
    """Why the metrics endpoint could not listen (its port taken, its address not local), and
    what to do."""
    return (
        f"cannot serve metrics on {settings.metrics_addr}:{settings.metrics_port} "
        f"({err.strerror or err}); choose another --metrics-port (0: any free one) or "
        "--metrics-addr"
    )


def _layout_fits(command: str, settings: Any) -> bool:
    """Whether the processes ``settings`` start fit this machine's memory
    (:func:`service.cores.layout_problem`); says why not, or warns, on stderr."""
    from service.cores import layout_problem

    refusal, warning = layout_problem(settings)
    if refusal is not None:
        print(f"{command}: {refusal}", file=sys.stderr)
        return False
    if warning is not None:
        print(f"{command}: warning: {warning}", file=sys.stderr)
    return True


def cmd_demo(args: argparse.Namespace) -> int:
    """``rlutf demo``."""
    from service.cli.present import console
    from service.config import Settings
    from service.sim.demo import demo_layout, demo_spec, run_demo
    from service.sim.fleet import memory_problem

    problem = memory_problem(demo_spec(args, named=False))  # before a too big fleet's ids
    if problem is not None:
        print(f"rlutf demo: {problem} (--robots, --duration, --beams)", file=sys.stderr)
        return EXIT_USAGE
    # An RLUTF_* value the settings refuse, named as `serve` names it (exit 2; it was
    # "unexpected error: ValidationError", exit 1, from the demo's own settings).
    layout = checked_settings(lambda: Settings(**demo_layout(args)))
    if not _layout_fits("rlutf demo", layout):
        return EXIT_USAGE
    if args.store is not None:
        usable_folder(args.store, "--store")
        _store_free(args.store, "give the demo a --store of its own (or none: a temporary one)")
    if not args.no_record:
        usable_folder(args.record, "--record")

    return run_demo(args, console())
