"""The stage processes of an `octolog run`: each started as `python -m octolog STAGE`, its output in
logs/STAGE.log, watched until all end; the first failure stops the others, a killed mapper starts again."""

from __future__ import annotations

import io
import os
import socket
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from octolog.kit import logs
from octolog.kit.bus import Bus, BusConfig, wait_interruptibly
from octolog.kit.bus.diagnose import tcp_address
from octolog.kit.errors import StageExited, StageKilled
from octolog.shell import errorfile, statusline

# A killed mapper is started again: it rebuilds its map from the tracker's keyframe history (the
# tracker keeps every keyframe until the mapper is done; see octolog/bus.py). The other stages'
# outputs depend on what they already sent, so their death ends the session.
RESTARTABLE = ("mapper",)
MAX_RESTARTS = 3


# Stages that yield the CPU to the others of the run (`nice` levels): the mapper works on keyframes
# from a deep queue, so when the cores are short it is the one to wait, not the tracker (whose frames
# are live) nor the camera or the session log. Its outputs do not depend on when it runs.
NICENESS = {"mapper": 10}

# Stages that lead a session of their own: a live camera's recorder loses frames for good when it
# waits for a CPU (its capture queue overflows), so it competes with the machine as a job of its own,
# as any other session does, and the run's other stages never take its share. (Measured under load:
# in the run's session the simulated D455 dropped 136 and 203 of 600 frames in two of three runs.)
OWN_SESSION = ("recorder",)

AUTOGROUP = Path("/proc/sys/kernel/sched_autogroup_enabled")


def grouped_by_session() -> bool:
    """Whether Linux schedules by session (autogroup, the default of most distributions): each session
    then gets one share of the CPUs, and a nice level ranks a process only within its session."""
    try:
        return AUTOGROUP.read_text().strip() == "1"
    except OSError:
        return False  # not Linux, or a kernel without autogroup: nice ranks against every process


@dataclass(frozen=True)
class Launch:
    """How a stage process starts (the Popen options of the same names)."""

    nice: int  # its nice level
    start_new_session: bool  # a session, and so under autogroup a scheduling group, of its own
    process_group: int | None  # 0: a process group of its own, led by the stage (None: its session's)


def launch(name: str, *, grouped: bool) -> Launch:
    """How to start stage `name`. A stage stays in this process's session (but for OWN_SESSION), so
    under autogroup (`grouped`) the run competes with the rest of the machine as one group, as any
    shell job does, and a stage's nice level only ranks it against the run's other stages: the mapper
    yields to the tracker, never to unrelated jobs. A stage in a session of its own is never niced
    (nor is its session: no stage is ranked below unrelated jobs). Without that grouping a nice level
    would rank the mapper below every other process on the machine, so it stays at 0. Each stage
    leads a process group of its own (a session's leader leads one too), which `stop_all` signals
    whole; stdin is closed (a process group that is not the terminal's foreground one would be
    stopped for reading it)."""
    if name in OWN_SESSION:
        return Launch(0, start_new_session=True, process_group=None)
    return Launch(NICENESS.get(name, 0) if grouped else 0, start_new_session=False, process_group=0)


def _niced(n: int) -> list[str]:
    """The command prefix that starts a stage at nice level `n` (`nice -n N`), race-free: every thread
    the stage starts inherits it."""
    return ["nice", "-n", str(n)] if n and shutil.which("nice") else []


class StageProcesses:
    """The stage processes; stops them all on the first failure or on exit."""

    def __init__(self, logs: Path, env: dict[str, str] | None = None) -> None:
        self.logs = logs
        self.env = env or {}  # for every stage, on top of this process's environment
        self.procs: dict[str, subprocess.Popen] = {}
        self.argv: dict[str, tuple[list[str], bool]] = {}
        self.restarts: dict[str, int] = {}
        self.relays: list[threading.Thread] = []
        self.line_open = False  # a relayed stderr (the replay's progress line) ended without a newline

    def start(self, name: str, argv: list[str], *, show_stderr: bool = False, append: bool = False) -> None:
        """Start stage `name` as `python -m octolog ARGV`, its output in logs/NAME.log, logging at this
        process's level (`--log-level`)."""
        log = open(self.logs / f"{name}.log", "ab" if append else "wb")  # noqa: SIM115 - owned by the child
        errorfile.reserve(self.error_file(name))
        env = {**os.environ, **self.env, "PYTHONHASHSEED": "0", "PYTHONUNBUFFERED": "1",
               errorfile.ENV: str(self.error_file(name)), errorfile.REPORT_ENV: str(self.logs / f"{name}.report.json"),
               errorfile.PARENT_ENV: str(os.getpid()),
               # its status line ends up on our stderr: redrawn only if that is a terminal
               statusline.ENV: "1" if show_stderr and statusline.is_terminal(sys.stderr) else "0"}
        self.argv[name] = (argv, show_stderr)
        # OCTOLOG_PROFILE=STAGE[,STAGE]: run those stages under cProfile, into logs/STAGE.prof
        profile = name in os.environ.get("OCTOLOG_PROFILE", "").split(",")
        prof = ["-m", "cProfile", "-o", str(self.logs / f"{name}.prof")] if profile else []
        how = launch(name, grouped=grouped_by_session())
        self.procs[name] = proc = subprocess.Popen(
            [*_niced(how.nice), sys.executable, *prof, "-m", "octolog", *argv, "--log-level", logs.level()], stdout=log,
            stderr=subprocess.PIPE if show_stderr else log, stdin=subprocess.DEVNULL, env=env,
            start_new_session=how.start_new_session, process_group=how.process_group)
        if show_stderr:
            relay = threading.Thread(target=self._relay, args=(proc.stderr,), daemon=True)
            relay.start()
            self.relays.append(relay)

    def _relay(self, pipe: io.BufferedReader) -> None:
        """Copy a stage's stderr to ours, remembering whether its last line is still open."""
        out = sys.stderr.buffer
        while chunk := pipe.read1(65536):
            try:
                out.write(chunk)
                out.flush()
            except (OSError, ValueError):
                pass  # our stderr is gone: keep draining, so the stage never blocks on a full pipe
            self.line_open = not chunk.endswith(b"\n")
        pipe.close()

    def say(self, line: str) -> None:
        """One line on stderr between the stages' relayed ones (an open progress line ended first)."""
        if self.line_open:
            sys.stderr.write("\n")
            self.line_open = False
        sys.stderr.write(line + "\n")
        sys.stderr.flush()

    def end_line(self) -> None:
        """Once the stages are gone: end a relayed progress line, so an error line starts on its own."""
        for relay in self.relays:
            relay.join(timeout=5)
        if self.line_open:
            sys.stderr.write("\n")
            sys.stderr.flush()
            self.line_open = False

    def restart(self, name: str, code: int) -> bool:
        """Start a restartable stage again after a kill (not a stop request); False if it may not."""
        if name not in RESTARTABLE or code >= 0 or -code in (signal.SIGTERM, signal.SIGINT) or \
                self.restarts.get(name, 0) >= MAX_RESTARTS:
            return False
        self.restarts[name] = self.restarts.get(name, 0) + 1
        with open(self.logs / f"{name}.log", "a") as log:
            log.write(f"octolog run: the {name} stage was killed by signal {-code}; starting it again\n")
        argv, show_stderr = self.argv[name]
        self.start(name, argv, show_stderr=show_stderr, append=True)
        return True

    def wait_all(self, on_done: Callable[[str, list[str]], None] | None = None,
                 on_wait: Callable[[list[str]], None] | None = None) -> None:
        """Wait until every stage has exited; restart a killed mapper; raise StageFailed for a failed
        stage. `on_done(stage, still running)`: a stage finished without error; `on_wait(still
        running)`: between looks, every 0.1 s."""
        pending = dict(self.procs)
        while pending:
            if on_wait is not None:
                on_wait(sorted(pending))
            for name, proc in list(pending.items()):
                code = proc.poll()
                if code is None:
                    continue
                del pending[name]
                if code == 0 and on_done is not None:
                    on_done(name, sorted(pending))
                if code != 0 and self.restart(name, code):
                    pending[name] = self.procs[name]
                    continue
                if code != 0:
                    self.stop_all()
                    log = f"{self.logs / name}.log"
                    if code < 0:
                        raise StageKilled(name, -code, self.reason(name), log)
                    raise StageExited(name, code, self.reason(name), log)
            time.sleep(0.1)
        for other, proc in self.procs.items():
            rc = proc.returncode
            if other != name and rc not in (None, 0) and errorfile.read(self.error_file(other)) is not None:
                record = errorfile.read(self.error_file(other))
                if record is not None and record.type != "KeyboardInterrupt":
                    return other, rc
        return name, code

    def error_file(self, name: str) -> Path:
        """Where stage `name` records its known error (shell/errorfile.py)."""
        return self.logs / f"{name}.error.json"

    def reason(self, name: str) -> str:
        """Why stage `name` failed: the error it recorded, else the last line of its log."""
        record = errorfile.read(self.error_file(name))
        if record is not None:
            return record.message
        lines = [ln for ln in (self.logs / f"{name}.log").read_text(errors="replace").splitlines() if ln.strip()]
        return (lines or ["(no output)"])[-1].strip()

    def stop_all(self) -> None:
        """Stop every stage still running: SIGTERM to its process group, SIGKILL after 5 s. Once all
        have ended, the error files of the stages that recorded no error are removed (their space was
        only reserved, errorfile.reserve)."""
        for proc in self.procs.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + 5
        for proc in self.procs.values():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        for name in self.procs:
            errorfile.release(self.error_file(name))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


ROUTER_WAIT_S = 3.0  # a router started just before the run (a script's `octolog router &`) is given this long


def router_unreachable(endpoint: str, wait_s: float = ROUTER_WAIT_S) -> str | None:
    """Why the stages could not meet at the router `endpoint` (tcp/ or tls/HOST:PORT): nothing
    listens there, or the host does not resolve or answer, still so after `wait_s`; None once a TCP
    connection opens. Other protocols are not probed (None): Zenoh itself reports on them."""
    address = tcp_address(endpoint)
    if address is None:
        return None
    _, host, port = address
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=min(2.0, wait_s)):
                return None
        except socket.gaierror as exc:
            return f"cannot resolve {host!r} ({exc.strerror})"
        except ConnectionRefusedError:
            why = f"nothing listens at {host}:{port}"
        except OSError as exc:
            why = f"no answer from {host}:{port} ({exc.strerror or exc})"
        if time.monotonic() >= deadline:
            return f"{why} (tried for {wait_s:.0f} s)"
        time.sleep(0.25)  # a router starting up: try again


class HostedRouter:
    """The endpoint the stages meet at: `given`, or a Zenoh router this process hosts on a free
    loopback port (on a thread, until the session ends). Its start (~0.5 s) overlaps the stages'
    own (their imports take longer, and a stage that connects first retries until it listens):
    `ready()` waits for it and raises what stopped it."""

    def __init__(self, given: str | None) -> None:
        self.given = given
        self.endpoint = given if given is not None else f"tcp/127.0.0.1:{free_port()}"
        self._stop, self._ready = threading.Event(), threading.Event()
        self._error: list[BaseException] = []
        self._thread: threading.Thread | None = None

    def __enter__(self) -> HostedRouter:
        if self.given is None:
            self._thread = threading.Thread(target=self._host, daemon=True, name="octolog-router")
            self._thread.start()
        return self

    def _host(self) -> None:
        try:
            with Bus(BusConfig(mode="router", listen=(self.endpoint,), multicast_scouting=False), "router"):
                self._ready.set()
                self._stop.wait()
        except BaseException as exc:  # reported by the main thread (`ready`)
            self._error.append(exc)
            self._ready.set()

    def ready(self) -> None:
        if self._thread is None:
            return
        wait_interruptibly(self._ready)
        if self._error:
            raise self._error[0]

    def __exit__(self, *exc: object) -> None:
        if self._thread is not None:
            self._stop.set()
            # let the router's session close before the interpreter exits: a daemon thread still
            # inside Zenoh at exit aborts the process
            self._thread.join(timeout=10)
