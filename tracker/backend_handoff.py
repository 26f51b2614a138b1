"""The SLAM core's hand-off to its back end (tracker/backend.py: local bundle adjustment, loop
closing): start a keyframe's job on a snapshot of the map, apply the pending result to the map,
decide when a live run lets a keyframe in without it, and the last bundle adjustment at the end.

`BackendHandoff` owns the job cycle and the loop state the jobs carry from one to the next. The job
for keyframe k starts when k is inserted and its result is applied when keyframe k+1 is inserted
(or at `finish`), or at a later one where `defer` says (live; then on record): fixed points in the
frame sequence, so a worker process (not a thread: the back end holds the GIL) changes no output.
"""

from __future__ import annotations

import numpy as np

from octolog.tracker.backend import BackendJob, BackendResult, LoopState, apply_result, build_job, run_backend
from octolog.tracker.config import OdometryParams
from octolog.tracker.local_map import LocalMap
from octolog.tracker.motion import scaled
from octolog.tracker.worker import Worker

Pending = Worker | BackendResult


class BackendHandoff:
    """Back-end jobs for `local_map`'s keyframes: `submit`, `sync`, `defer`, `finish`."""

    def __init__(self, params: OdometryParams, local_map: LocalMap, *, worker: Worker | None = None,
                 defer_backend: int = 0, backend_deferred_at: frozenset[int] = frozenset()) -> None:
        self.params = params
        self._map = local_map
        self.worker = worker  # None: inline
        self.defer_backend, self.backend_deferred_at, self._deferred_run = defer_backend, backend_deferred_at, 0
        self.worker_peak_rss_mb = self.worker_file_rss_mb = 0.0  # the worker's peak and file-backed MB (`finish`)
        self.pending: Pending | None = None
        self.loop_edges: list[tuple[int, int, np.ndarray]] = []
        self.loops: list[tuple[int, int]] = []  # (new, old) keyframe ids of closed loops
        self._last_loop_kf = -(10**9)
        self._loop_candidate: tuple[int, np.ndarray | None] = (-1, None)

    def submit(self, K: np.ndarray) -> None:
        """Start the back end for the newest keyframe (in the worker process when there is one)."""
        if not (self.params.local_ba or self.params.loop_closing):
            return
        p, ba = self.params, self.params.bundle_adjustment
        self._start(self._job(K, window_n=p.ba_window, max_points=ba.max_points, loop_closing=p.loop_closing,
                              iterations=ba.iterations))

    def sync(self) -> tuple[dict[int, np.ndarray], tuple[int, int] | None, np.ndarray | None]:
        """Apply the pending back-end result; returns (moved keyframes if a loop closed, the loop, how
        the newest keyframe moved: world_from_world, None when nothing was pending)."""
        res = self.pending
        if res is None:
            return {}, None, None
        self.pending = None
        if not isinstance(res, BackendResult):
            res = res.result()
        delta, moved = apply_result(res, self._map.keyframes, self._map.points, self._map.kf_pos, self._map.kf_axis,
                                    self.params.bundle_adjustment.max_point_move_m, self._map.frozen_points)
        self._loop_candidate = (res.kf_id, res.candidate) if res.candidate is not None else (-1, None)
        if res.loop is None:
            return {}, None, delta
        self.loop_edges.append(res.loop_edge)
        self.loops.append(res.loop)
        self._last_loop_kf = res.loop[0]
        return moved, res.loop, delta

    def defer(self, seq: int) -> bool:
        """Whether the keyframe at frame `seq` goes in without the pending back-end result: where a
        replayed live run's record says; live (`defer_backend` > 0), while the back end is at work, at
        most that many keyframes in a row; else never (the tracker waits for it)."""
        busy = self.pending is not None and not isinstance(self.pending, BackendResult) and not self.pending.done()
        defer = self.pending is not None and (seq in self.backend_deferred_at if self.backend_deferred_at else
                                              busy and self._deferred_run < self.defer_backend)
        self._deferred_run = self._deferred_run + 1 if defer else 0
        return defer

    def final_adjustment(self, K: np.ndarray) -> None:
        """A last bundle adjustment, as ORB-SLAM runs after a loop, so what is written out has the
        whole map's support: every keyframe (the first fixed, and a saved map's) up to
        `global_ba_keyframes`, else the newest that many, bounded in time and memory (in the worker
        when there is one). Its result is pending; nothing when the settings ask for none. Localizing,
        it moves only the temporary keyframes: the trajectory file gets the whole session's support."""
        p = self.params
        if p.global_ba_keyframes > 0 and p.local_ba and len(self._map.keyframes) >= 2:
            window_n = min(len(self._map.keyframes), p.global_ba_keyframes)
            self._start(self._job(K, window_n=window_n, max_points=None, loop_closing=False,
                                  iterations=p.bundle_adjustment.global_iterations))

    def close(self) -> None:
        """Stop the worker process, keeping its memory figures."""
        if self.worker is not None:
            self.worker.close()
            self.worker_peak_rss_mb, self.worker_file_rss_mb = self.worker.peak_rss_mb, self.worker.file_rss_mb
            self.worker = None

    def scale(self, s: float) -> None:
        """The map's translations scaled by `s`: the loop edges with them; a loop candidate is forgotten."""
        self.loop_edges = [(a, b, scaled(T, s)) for a, b, T in self.loop_edges]
        self._loop_candidate = (-1, None)

    def place(self, other: BackendHandoff, k0: int) -> None:
        """Another map's loop edges, its keyframes numbered from `k0`."""
        self.loop_edges += [(a + k0, b + k0, T) for a, b, T in other.loop_edges]

    def take(self, other: BackendHandoff) -> None:
        """Another map's job cycle and loops (a map of its own becomes the map); the worker stays."""
        self.loop_edges, self._last_loop_kf, self._loop_candidate = (
            other.loop_edges, other._last_loop_kf, other._loop_candidate)
        self.pending, self.loops = other.pending, other.loops

    def _start(self, job: BackendJob) -> None:
        self.pending = self.worker.submit(job) if self.worker else run_backend(job)

    def _job(self, K: np.ndarray, *, window_n: int, max_points: int | None, loop_closing: bool,
             iterations: int) -> BackendJob:
        """A snapshot of the map for the back end of the newest keyframe (see backend.build_job)."""
        candidate = self._loop_candidate[1]  # the previous job's: one job at a time, its result is in
        loops = LoopState(edges=self.loop_edges, last_loop_kf=self._last_loop_kf, previous_candidate=candidate)
        return build_job(self._map.points, self._map.keyframes, self.params, K=K, bow=self._map.index, loops=loops,
                         window_n=window_n, max_points=max_points, loop_closing=loop_closing, iterations=iterations,
                         frozen_keyframes=self._map.frozen_keyframes)

