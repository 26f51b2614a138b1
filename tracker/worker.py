"""The tracker's back-end worker process: `python -m octolog.tracker.worker`, jobs in on stdin, results out.

The back end (tracker.backend: local BA, loop closing) runs in its own process because gtsam holds Python's GIL while
it optimises, which stalled the tracking thread for tens of milliseconds at every keyframe. Each
message is a pickle preceded by its length (8 bytes, little endian). The worker exits when its
input closes or its parent dies, whichever comes first.
"""

from __future__ import annotations

import ctypes
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
import time
import weakref
from typing import Any, BinaryIO

from octolog.kit.errors import TrackingError
from octolog.tracker.backend import BackendJob, BackendResult, run_backend

_LEN = struct.Struct("<Q")


def _write(stream: BinaryIO, obj: object) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LEN.pack(len(data)))
    stream.write(data)
    stream.flush()


def _read(stream: BinaryIO) -> Any:  # Any: whatever was pickled (a job, or a (kind, value) answer)
    head = stream.read(_LEN.size)
    if len(head) < _LEN.size:
        raise EOFError("back-end worker stream closed")
    (n,) = _LEN.unpack(head)
    data = stream.read(n)
    if len(data) < n:
        raise EOFError("back-end worker stream truncated")
    return pickle.loads(data)


class Worker:
    """One back-end job at a time in a child process: `submit(job)`, then `result()`."""

    def __init__(self, *, min_job_s: float = 0.0) -> None:
        """`min_job_s` pads each job to at least that long: rehearse a slower machine's back end."""
        self._proc = subprocess.Popen([sys.executable, "-m", "octolog.tracker.worker", str(os.getpid()), str(min_job_s)],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, close_fds=True)
        self._writer: threading.Thread | None = None
        self._busy = False
        self.peak_rss_mb = 0.0  # the child's VmHWM, read when it is closed (its own pages, not the fork's)
        # of which file-backed (RssFile at close): the numpy/OpenCV libraries, the same page-cache pages
        # the parent has mapped, so counted once on the machine however many processes map them
        self.file_rss_mb = 0.0
        # dropped without close(): end the child's input, so it exits
        weakref.finalize(self, self._proc.stdin.close)

    def submit(self, job: BackendJob | None) -> Worker:
        """Send `job` (None: a ping, see `ready`) without waiting."""
        assert not self._busy, "one job at a time"
        self._busy = True
        # a large job could fill the pipe: write it from a thread so the tracker never waits here
        self._writer = threading.Thread(target=_write, args=(self._proc.stdin, job), daemon=True)
        self._writer.start()
        return self

    def done(self) -> bool:
        """Whether `result()` would return without waiting for the job: sent in full, and the child
        has begun to answer (it writes a result whole, once the job is done)."""
        if self._writer is None or self._writer.is_alive():
            return False
        readable, _, _ = select.select([self._proc.stdout], [], [], 0)
        return bool(readable)

    def result(self) -> BackendResult:
        """The job's result, waiting for it (a ping's is None); a job's exception is raised here."""
        assert self._writer is not None
        self._writer.join()
        try:
            kind, value = _read(self._proc.stdout)
        except EOFError:
            raise TrackingError(f"the tracker's back-end worker died (exit code {self._proc.poll()})") from None
        self._busy = False
        if kind == "error":
            raise value
        return value

    def ready(self) -> float:
        """Wait until the child has imported what it needs; returns the CPU seconds that took (its
        start-up, which a benchmark reports apart from the per-frame work, as ORB-SLAM3's)."""
        self.submit(None).result()
        return _cpu_s(self._proc.pid)

    def close(self) -> None:
        if self._proc.poll() is None:
            self.peak_rss_mb = _status_mb(self._proc.pid, "VmHWM")
            self.file_rss_mb = _status_mb(self._proc.pid, "RssFile")
            self._proc.stdin.close()
            try:
                self._proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self._proc.kill()


def _status_mb(pid: int, key: str) -> float:
    """A memory figure of a live process (VmHWM: its peak) in MB, 0 where /proc does not say.
    RUSAGE_CHILDREN cannot tell the peak: a child's ru_maxrss counts the parent's pages it shared
    between fork and exec."""
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a live process (0 where /proc does not say)."""
    try:
        fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def _die_with(parent: int) -> None:
    try:  # Linux: the kernel kills this process when its parent dies
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(0)


# The back end yields the CPU to the tracking thread: its result is wanted at the next keyframe, the
# tracking thread's every frame. A back end behind is waited for there, and then has the cores.
NICENESS = 5


def main() -> None:
    _die_with(int(sys.argv[1]))
    min_job_s = float(sys.argv[2]) if len(sys.argv) > 2 else 0.0
    os.nice(NICENESS)
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    while True:
        try:
            job = _read(stdin)
        except EOFError:
            return
        t0 = time.monotonic()
        try:
            out = ("ok", None if job is None else run_backend(job))  # None: a ping (`Worker.ready`)
        except Exception as exc:  # the parent re-raises it where it waits for the result
            out = ("error", exc)
        if job is not None and min_job_s > 0:
            time.sleep(max(0.0, t0 + min_job_s - time.monotonic()))  # a slower back end, rehearsed
        _write(stdout, out)


if __name__ == "__main__":
    main()
