"""Where a stage process spends its CPU: named buckets of thread CPU time, and the process's threads.

A stage wraps its work in `charge("features")`, `charge("tracking")`, ... (thread CPU time, so a
thread waiting for the GIL or the bus is not charged); a charge inside another pauses the outer
one, so nothing counts twice. `report()` gives the process's CPU seconds (all threads), its
waited-for children's (the tracker's back-end worker), the buckets, and the CPU of the threads the
libraries start, by the names they give them: Rerun's (`ChunkBatcher`, `RecordingStream`,
`file_writer`, `tokio-rt-worker`) and Zenoh's (`net-`, `rx-`, `tx-`, `acc-`, `app-`).
`octolog run` gathers each stage's report into summary.json (`cpu_s`); bench/pipeline.py turns it
into milliseconds of CPU per camera frame.
"""

from __future__ import annotations

import os
import resource
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager

_spent: defaultdict[str, float] = defaultdict(float)
_lock = threading.Lock()
_local = threading.local()
RERUN_THREADS = ("ChunkBatcher", "RecordingStream", "file_writer", "tokio-rt-worker")
ZENOH_THREADS = ("net-", "rx-", "tx-", "acc-", "app-")


@contextmanager
def charge(bucket: str) -> Iterator[None]:
    """Charge this thread's CPU time inside the block to `bucket` (an enclosing charge is paused)."""
    stack: list[list] = getattr(_local, "stack", None) or []
    _local.stack = stack
    now = time.thread_time()
    if stack:  # pause the enclosing charge
        outer = stack[-1]
        _add(outer[0], now - outer[1])
    entry = [bucket, now]
    stack.append(entry)
    try:
        yield
    finally:
        now = time.thread_time()
        stack.pop()
        _add(bucket, now - entry[1])
        if stack:
            stack[-1][1] = now  # the enclosing charge resumes


def _add(bucket: str, seconds: float) -> None:
    with _lock:
        _spent[bucket] += seconds


_seen: dict[str, tuple[str, float]] = {}  # thread id -> (library, CPU seconds when last looked at)


def note_threads() -> None:
    """Look at the library threads now: call before closing what runs them (a thread that has
    ended can no longer be read, only its last look counts)."""
    tick = os.sysconf("SC_CLK_TCK")
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return
    for task in tasks:
        try:
            comm = open(f"/proc/self/task/{task}/comm").read().strip()
            fields = open(f"/proc/self/task/{task}/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue  # the thread ended meanwhile
        owner = "rerun" if comm.startswith(RERUN_THREADS) else "zenoh" if comm.startswith(ZENOH_THREADS) else ""
        if owner:
            with _lock:
                _seen[task] = (owner, (int(fields[11]) + int(fields[12])) / tick)


def _thread_cpu_s() -> dict[str, float]:
    """CPU seconds of the library threads ("rerun", "zenoh") seen in this process, ended ones at their
    last look; other threads are left to the buckets and the process total."""
    note_threads()
    out: defaultdict[str, float] = defaultdict(float)
    with _lock:
        for owner, seconds in _seen.values():
            out[owner] += seconds
    return dict(out)


def report() -> dict:
    """This process's CPU so far: `process` (all threads), `children` (waited-for child processes),
    `buckets` (the charges), `threads` (library threads still running, by library); seconds."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    with _lock:
        buckets = {k: round(v, 4) for k, v in sorted(_spent.items())}
    return {"process": round(time.process_time(), 4), "children": round(children.ru_utime + children.ru_stime, 4),
            "buckets": buckets, "threads": {k: round(v, 4) for k, v in sorted(_thread_cpu_s().items())}}
