"""The tracker's hand-off to its back end (tracker.backend: local bundle adjustment, loop closing):
start a keyframe's job on a snapshot of the map, apply the pending result, decide when a live run
lets a keyframe in without it.

A mixin of `RgbdSlam` (tracker.odometry), which owns the map and the loop state these methods use.
"""

from __future__ import annotations

import numpy as np

from octolog.tracker.backend import BackendJob, BackendResult, LoopState, apply_result, build_job, run_backend


class BackendHandoff:
    """The back-end job cycle of `RgbdSlam`: submit, sync, defer."""

    def _submit_backend(self) -> None:
        """Start the back end for the newest keyframe (in the worker process when there is one)."""
        if not (self.params.local_ba or self.params.loop_closing):
            return
        p, ba = self.params, self.params.bundle_adjustment
        job = self._backend_job(window_n=p.ba_window, max_points=ba.max_points, loop_closing=p.loop_closing,
                                iterations=ba.iterations)
        self._pending = self.worker.submit(job) if self.worker else run_backend(job)

    def _backend_job(self, *, window_n: int, max_points: int | None, loop_closing: bool,
                     iterations: int) -> BackendJob:
        """A snapshot of the map for the back end of the newest keyframe (see backend.build_job)."""
        assert self._undistort is not None
        candidate = self._loop_candidate[1]  # the previous job's: one job at a time, its result is in
        loops = LoopState(edges=self._loop_edges, last_loop_kf=self._last_loop_kf, previous_candidate=candidate)
        return build_job(self._map, self._keyframes, self.params, K=self._undistort.K, bow=self._bow, loops=loops,
                         window_n=window_n, max_points=max_points, loop_closing=loop_closing, iterations=iterations)

    def _sync_backend(self, pose: np.ndarray) -> tuple[dict[int, np.ndarray], tuple[int, int] | None, np.ndarray]:
        """Apply the pending back-end result; returns (moved keyframes if a loop closed, the loop,
        `pose` moved with the newest keyframe)."""
        res = self._pending
        if res is None:
            return {}, None, pose
        self._pending = None
        if not isinstance(res, BackendResult):
            res = res.result()
        delta, moved = apply_result(res, self._keyframes, self._map, self._kf_pos, self._kf_axis,
                                    self.params.bundle_adjustment.max_point_move_m)
        if self._last_pose is not None:
            self._last_pose = delta @ self._last_pose
        self._loop_candidate = (res.kf_id, res.candidate) if res.candidate is not None else (-1, None)
        if res.loop is None:
            return {}, None, delta @ pose
        self._loop_edges.append(res.loop_edge)
        self.loops.append(res.loop)
        self._last_loop_kf = res.loop[0]
        return moved, res.loop, delta @ pose

    def _defer_backend(self, seq: int) -> bool:
        """Whether the keyframe at frame `seq` goes in without the pending back-end result: where a
        replayed live run's record says; live (`defer_backend` > 0), while the back end is at work, at
        most that many keyframes in a row; else never (the tracker waits for it)."""
        busy = self._pending is not None and not isinstance(self._pending, BackendResult) and not self._pending.done()
        defer = self._pending is not None and (seq in self.backend_deferred_at if self.backend_deferred_at else
                                               busy and self._deferred_run < self.defer_backend)
        self._deferred_run = self._deferred_run + 1 if defer else 0
        return defer
