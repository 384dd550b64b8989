"""``rlutf serve --processes N``: N service processes behind one router and one map store.

Each process is a full instance of the service (:class:`service.live.node.
LocalizationService`, localizing in-process on the thread that takes its inputs in,
:mod:`service.live.loop`): its own Zenoh session, liveliness token, subscription, recorder and
Health. They split the robots among themselves with the mechanism that already spreads robots
over instances (rendezvous ownership over liveliness tokens, handover seeds,
:mod:`service.cluster`), so nothing crosses a pipe: a process drops another's inputs on the
key. Process 0 runs in the process you started, the host, which also holds what there is one
of:

- the Zenoh router the robots connect to (``--listen``; process 0's session): the other
  processes are its clients on a loopback port;
- the embedded map store (process 0's);
- the host's Health on ``{prefix}/service/{instance}/health``: the processes' figures added
  up, ``ready`` once every process is ready, each process's Health in
  ``extra["by_process"]``;
- the supervision: a process that dies is started again (its robots are served meanwhile by
  the others: their owners change when its token goes, as when an instance dies); when the
  host dies, the processes stop (``--host-pid``);
- the metrics endpoint, which merges the processes' own (each serves its metrics on a
  loopback port the host chose: :mod:`service.live.hostmetrics`).

The processes are named ``{instance}-p{k}``; each records its own log files in the record
folder, with a run of its own (``rlutf.run``: a start of a process is a start of a service),
so ``rlutf replay`` audits a folder the host wrote one process run at a time, exactly, across
handovers between the processes too. The host's own name has no liveliness token: it owns no
robot (process 0 does, under its name).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from schemas import Health, LatencyPercentiles, SchemaError, decode, encode
from service.config import Settings
from service.keys import Keys
from service.live.heapdumps import TRACE
from service.live.sessions import free_port
from service.live.stopping import ended_with_the_service

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON
#: Seconds between two reads of the processes' Health (the host's answers are this old at most).
HEALTH_POLL_S = 1.0
#: A process that dies is started again after this long, doubled while it keeps dying early.
RESTART_DELAY_S = 0.5
RESTART_DELAY_MAX_S = 30.0
#: A process that lived this long before it died starts again after the first delay.
STABLE_S = 60.0


def process_name(instance: str, k: int) -> str:
    """The instance name of the host's process ``k``."""
    return f"{instance}-p{k}"


def process_settings(
    settings: Settings, k: int, endpoint: str, metrics_port: int | None
) -> dict[str, Any]:
    """The effective settings of the host's process ``k`` (as a settings file holds them).

    Everything as the host was configured, but: its own name, a client of the host's router on
    ``endpoint``, no map store (the host's), in-process localization on the thread that takes
    the inputs in (``intake`` ``loop``: one thread, no hand-off per input), no processes of its own,
    metrics (if any) on a loopback port, and no live view (the host's processes each see only
    their own robots).
    """
    data: dict[str, Any] = settings.effective()
    data.update(
        instance=process_name(settings.instance, k),
        mode="client",
        listen=[],
        connect=[endpoint],
        multicast_scouting=False,
        zenoh_config=None,
        no_store=True,
        workers=0,
        intake="loop",
        processes=0,
        metrics_port=metrics_port,
        metrics_addr="127.0.0.1",
        foxglove_port=None,
    )
    return data


#: The start of the name of a host's folder of settings files, ``rlutf-host-{pid}-XXXXXXXX`` in
#: the temporary folder.
FOLDER_PREFIX = "rlutf-host-"


def settings_folder() -> tempfile.TemporaryDirectory[str]:
    """A new folder for the processes' settings files, named with this host's pid, once the
    folders of hosts that are gone are removed: a host ended by a signal it cannot handle
    (``kill -9``, the OOM killer) leaves its folder behind, one per crash of a supervised unit."""
    sweep_folders()
    return tempfile.TemporaryDirectory(prefix=f"{FOLDER_PREFIX}{os.getpid()}-")


def sweep_folders(root: Path | None = None) -> list[Path]:
    """Remove this user's settings folders in ``root`` (default: the temporary folder) whose
    host is no longer running; returns them."""
    root = Path(tempfile.gettempdir()) if root is None else root
    removed = []
    for path in root.glob(f"{FOLDER_PREFIX}*-*"):
        pid = path.name[len(FOLDER_PREFIX) :].split("-", 1)[0]
        try:
            mine = not hasattr(os, "getuid") or path.stat().st_uid == os.getuid()
        except OSError:
            continue
        if pid.isdigit() and mine and path.is_dir() and not _running(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's: running
        return True
    return True


class _Process:
    """One of the host's processes: its command, the running child, its restarts."""

    def __init__(self, name: str, command: list[str], env: dict[str, str]) -> None:
        self.name = name
        self.command = command
        self.env = env
        self.child: subprocess.Popen[bytes] | None = None
        self.started = 0.0
        self.restarts = 0
        self.delay = RESTART_DELAY_S
        self.due = 0.0  # when to start it again after a death (monotonic)

    def start(self) -> None:
        self.child = subprocess.Popen(self.command, env=self.env, stdin=subprocess.DEVNULL)
        self.started = time.monotonic()

    @property
    def pid(self) -> int | None:
        if not self.command:  # process 0, the host itself
            return os.getpid()
        return self.child.pid if self.child is not None else None

    @property
    def alive(self) -> bool:
        return not self.command or (self.child is not None and self.child.poll() is None)


class Host:
    """The host of ``processes`` service processes (see the module docstring).

    Args:
        settings: the effective configuration (``settings.processes`` processes).
        python: the interpreter that runs the processes.
        stop: set when the host is told to stop (its signal handler), before :meth:`close`:
            a process that the same signal ended is not started again
            (:mod:`service.live.stopping`).
    """

    def __init__(
        self,
        settings: Settings,
        python: str = sys.executable,
        stop: threading.Event | None = None,
    ) -> None:
        if settings.processes < 1:
            raise ValueError(f"processes: {settings.processes}, a host needs at least 1")
        self.settings = settings
        self.keys = Keys(settings.prefix)
        self._python = python
        self._session: zenoh.Session | None = None
        self.service: Any = None  # process 0, a LocalizationService in this process
        self._declared: list[Any] = []
        self._folder = settings_folder()
        self.processes: list[_Process] = []
        self.metrics_ports: list[int] = []
        self.metrics: Any = None
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._stop_requested = stop if stop is not None else self._stopping
        self._supervisor: threading.Thread | None = None
        self.started = time.monotonic()
        self.ready = False
        self._healths: dict[str, Health] = {}

    # ------------------------------------------------------------------------ lifecycle
    def start(self, progress: Callable[[str], None] | None = None, timeout: float = 900.0) -> Host:
        """Open the router and the store, start the processes, return once all are ready.

        Raises:
            RuntimeError: a process exited before it was ready, or none was ready in time.
        """
        s = self.settings
        inner = f"tcp/127.0.0.1:{free_port()}"
        ports = [free_port() if s.metrics_port is not None else None for _ in range(s.processes)]
        self.metrics_ports = [p for p in ports if p is not None]
        # Process 0 runs here: the router the robots connect to and the map store are its
        # session's; the others are its clients on a loopback port.
        own = Settings(
            **{
                **process_settings(s, 0, inner, ports[0]),
                "mode": s.mode if s.mode != "client" else "router",
                "listen": [*s.listen, inner] if s.mode != "client" else [inner],
                "connect": list(s.connect),
                "multicast_scouting": s.multicast_scouting,
                "zenoh_config": s.zenoh_config,
                "no_store": s.no_store,
            }
        )
        from service.cluster.names import HostNameClaim
        from service.live.node import LocalizationService
        from service.live.worker import tune_gc
        from service.logs.recording import make_recorder

        self.processes.append(_Process(own.instance, [], {}))
        # Told of the host's stop; and when another instance takes its name, it sets it.
        stop = self._stop_requested
        self.service = LocalizationService(own, recorder=make_recorder(own), stop=stop)
        # The host's own name is claimed too: it answers Health under it, and a single process
        # of that name beside it would take robots as another member (service.cluster.names).
        self.service.name_claim = HostNameClaim(
            own.instance, s.instance, self.keys, self.service._name_taken
        )
        # It compiles the localizer's kernels on a first start after an install (or loads
        # them); the others start once it is ready and load them from numba's cache, instead
        # of all compiling the same kernels at once.
        self.service.start(progress)
        self._session = session = self.service.session
        self._declared.append(
            session.declare_queryable(self.keys.health(s.instance), self._on_health_query)
        )
        # Settings go by file; of the RLUTF_ variables only the diagnosis's (heapdumps) pass.
        env = {k: v for k, v in os.environ.items() if not k.startswith("RLUTF_") or k in TRACE}
        folder = Path(self._folder.name)
        for k in range(1, s.processes):
            data = process_settings(s, k, inner, ports[k])
            path = folder / f"process-{k}.json"
            path.write_text(json.dumps(data))
            command = [self._python, "-m", "service", "serve", "--settings", str(path)]
            command += ["--host-pid", str(os.getpid())]  # it stops when this process is gone
            self.processes.append(_Process(data["instance"], command, env))
        others = self.processes[1:]
        for p in others:
            p.start()
        self._wait_ready(others, progress, timeout)
        # The host's own service process handles its share of the robots as any other does:
        # its start-up objects frozen out of collections, young collections less often (without
        # this, at 200 robots it made a young collection every 0.2 s and a full one of about
        # 0.1 s, every robot of it waiting, in a 20-s run).
        tune_gc()
        if s.metrics_port is not None:
            from service.live.hostmetrics import HostMetrics

            self.metrics = HostMetrics(self.metrics_ports, s.metrics_port, s.metrics_addr)
            self.metrics.start()
        self._healths = self.process_health()
        self.ready = True
        threading.Thread(target=self._poll_health, name="rlutf-host-health", daemon=True).start()
        self._supervisor = threading.Thread(
            target=self._supervise, name="rlutf-host-supervisor", daemon=True
        )
        self._supervisor.start()
        log.info("rlutf host %s: %d processes ready", s.instance, len(self.processes))
        return self

    def _wait_ready(
        self, procs: list[_Process], progress: Callable[[str], None] | None, timeout: float
    ) -> None:
        """Block until each process's liveliness token is declared (it does so once ready)."""
        assert self._session is not None
        end = time.monotonic() + timeout
        said = 0.0
        waiting = {p.name: p for p in procs}
        while waiting:
            for p in waiting.values():
                if p.child is not None and p.child.poll() is not None:
                    raise RuntimeError(
                        f"process {p.name} exited with code {p.child.returncode} before it "
                        "was ready (its log is above)"
                    )
            live = self._live_tokens()
            for name in [n for n in waiting if n in live]:
                del waiting[name]
            if not waiting:
                return
            now = time.monotonic()
            if now > end:
                raise RuntimeError(f"processes {sorted(waiting)} not ready in {timeout:g} s")
            if progress is not None and now - said > 5.0:
                said = now
                progress(f"starting {len(waiting)} of {len(self.processes)} service processes")
            time.sleep(0.1)

    def _live_tokens(self) -> set[str]:
        assert self._session is not None
        base = self.keys.service("")
        names = set()
        for reply in self._session.liveliness().get(self.keys.service("*"), timeout=1.0):
            if reply.ok is not None:
                names.add(str(reply.ok.key_expr)[len(base) :])
        return names

    def _supervise(self) -> None:
        """Start again every process that died, with a growing delay while it keeps dying."""
        while not self._stopping.wait(0.2):
            now = time.monotonic()
            for p in self.processes:
                with self._lock:
                    code = None if p.child is None else p.child.poll()
                    first = code is not None and p.due == 0.0
                if first and (
                    self._stopping.is_set() or ended_with_the_service(code, self._stop_requested)
                ):
                    continue  # stopped with the host (a whole process group signalled)
                with self._lock:
                    if self._stopping.is_set() or self._stop_requested.is_set() or code is None:
                        continue
                    if p.due == 0.0:
                        lived = now - p.started
                        p.delay = (
                            RESTART_DELAY_S
                            if lived > STABLE_S
                            else min(p.delay * 2, RESTART_DELAY_MAX_S)
                        )
                        p.due = now + p.delay
                        log.error(
                            "process %s (pid %s) exited with code %s after %.1f s; its robots "
                            "go to the other processes; starting it again in %.1f s",
                            p.name, p.pid, code, lived, p.delay,
                        )  # fmt: skip
                    elif now >= p.due:
                        p.due = 0.0
                        p.restarts += 1
                        p.start()

    def wait(self, stop: threading.Event) -> None:
        """Block until ``stop`` is set (timed waits, so that signal handlers run)."""
        self.service.wait(stop)

    def close(self, timeout: float = 30.0) -> None:
        """SIGTERM every process (each stops gracefully), then close the store and router."""
        self._stopping.set()
        with self._lock:
            children = [p.child for p in self.processes if p.child is not None]
        for child in children:
            if child.poll() is None:
                child.send_signal(signal.SIGTERM)
        end = time.monotonic() + timeout
        for child in children:
            try:
                child.wait(max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("process pid %d did not stop in %g s: killed", child.pid, timeout)
                child.kill()
                child.wait()
        if self._supervisor is not None:
            self._supervisor.join(timeout=2.0)
        if self.metrics is not None:
            self.metrics.close()
        for d in reversed(self._declared):
            d.undeclare()
        if self.service is not None:
            self.service.close()  # and its session
        self._folder.cleanup()

    # ------------------------------------------------------------------------ health
    def _on_health_query(self, query: zenoh.Query) -> None:
        # From the figures the poller took: a get from a Zenoh callback would wait on the
        # threads that deliver its own replies.
        with query:
            query.reply(self.keys.health(self.settings.instance), self.health(), encoding=JSON)

    def _poll_health(self) -> None:
        """Take the processes' Health every :data:`HEALTH_POLL_S` (the host's thread)."""
        while True:
            self._refresh()
            if self._stopping.wait(HEALTH_POLL_S):
                return

    def _refresh(self) -> None:
        got = self.process_health()
        with self._lock:
            self._healths = got

    def process_health(self, timeout: float = 2.0) -> dict[str, Health]:
        """Each live process's Health, by name (a get on the bus: not from a callback)."""
        assert self._session is not None
        names = {p.name for p in self.processes}
        found: dict[str, Health] = {}
        for reply in self._session.get(self.keys.all_health, timeout=timeout):
            if reply.ok is None:
                continue
            try:
                h = decode(Health, reply.ok.payload.to_bytes())
            except SchemaError:
                continue
            if h.instance in names:
                found[h.instance] = h
        return found

    def health(self, fresh: bool = False) -> bytes:
        """The host's Health: its processes' counters added up (see the module docstring).

        From the figures the poller took (a second old at most), or with ``fresh`` from the
        processes' Health asked for now (a get on the bus: not from a Zenoh callback)."""
        if fresh:
            self._refresh()
        with self._lock:
            got = dict(self._healths)
        parts = list(got.values())
        with self._lock:
            states = [
                {
                    "name": p.name,
                    "pid": p.pid,
                    "alive": p.alive,
                    "restarts": p.restarts,
                    "answered": p.name in got,
                }
                for p in self.processes
            ]
        worst = max((h.latency_ms for h in parts), key=lambda lat: lat.p99, default=None)
        health = Health(
            instance=self.settings.instance,
            stamp_ns=time.time_ns(),
            uptime_s=time.monotonic() - self.started,
            robots=sum(h.robots for h in parts),
            received=sum(h.received for h in parts),
            rejected=sum(h.rejected for h in parts),
            processed=sum(h.processed for h in parts),
            dropped=sum(h.dropped for h in parts),
            ready=self.ready and len(got) == len(self.processes) and all(h.ready for h in parts),
            latency_ms=worst or LatencyPercentiles(),
            extra={
                **merged_extra([h.extra for h in parts]),
                "host": True,
                "processes": states,
                "processes_restarted": sum(p.restarts for p in self.processes),
                "latency_note": "latency_ms: the process with the largest p99",
                "by_process": {h.instance: h.model_dump(mode="json") for h in parts},
            },
        )
        return encode(health)


def merged_extra(extras: list[dict[str, Any]]) -> dict[str, Any]:
    """The processes' ``extra`` figures as one: counts added, percentiles the worst p99's."""
    out: dict[str, Any] = {}
    for key in {k for e in extras for k in e}:
        values = [e[key] for e in extras if key in e]
        if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            out[key] = sum(values)
        elif all(isinstance(v, dict) and isinstance(v.get("p99"), int | float) for v in values):
            out[key] = max(values, key=lambda v: v["p99"])
    return out
