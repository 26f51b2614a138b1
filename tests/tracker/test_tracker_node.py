"""The real `octolog track` process fed bad frames over a real Zenoh link: each is LOST, none is a crash."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
from helpers import ROOT, free_port

from octolog.kit.bus import Bus, BusConfig
from octolog.kit.geometry import Intrinsics
from octolog.replay.synthetic import SyntheticScene
from octolog.schemas import rgbdmsgs, streammsgs
from octolog.schemas.topics import RGBD, RGBD_END, TRACKING_STATUS
from octolog.tracker.interface import TrackingState
from octolog.tracker.node import status_code


def _play(bus: Bus, frames: list) -> None:
    """Stand in for the replay: once the tracker is up, every frame and the stream's end; the
    tracker's statuses come back on `bus`."""
    bus.subscribe([TRACKING_STATUS])
    bus.announce()
    bus.watch(["tracker"])
    bus.wait_for(["tracker"], timeout_s=60)
    pub, end = bus.publisher(RGBD), bus.publisher(RGBD_END)
    for f in frames:
        pub.put(rgbdmsgs.rgbd_msg(f))
    end.put(streammsgs.stream_end_msg(RGBD.name, pub.count))


def test_bad_frames_are_lost_and_tracking_goes_on(tmp_path):
    frames = list(SyntheticScene(n_frames=16).frames())
    bad = {
        5: dataclasses.replace(frames[5], rgb=np.full_like(frames[5].rgb, 255)),  # saturated
        6: dataclasses.replace(frames[6], depth=np.zeros_like(frames[6].depth)),  # no valid depth
        7: dataclasses.replace(frames[7], rgb=np.zeros_like(frames[7].rgb)),  # black
        # the image is half the size its camera info says
        8: dataclasses.replace(frames[8], intrinsics=dataclasses.replace(
            frames[8].intrinsics, width=1280, height=960)),
    }
    assert isinstance(bad[8].intrinsics, Intrinsics)
    ep = f"tcp/127.0.0.1:{free_port()}"
    traj = tmp_path / "trajectory.txt"
    proc = subprocess.Popen([sys.executable, "-m", "octolog", "track", "--connect", ep, "--no-multicast",
                             "--trajectory", str(traj)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    states: dict[int, int] = {}
    try:
        with Bus(BusConfig(listen=(ep,), multicast_scouting=False), "replay") as bus:
            _play(bus, [bad.get(k, f) for k, f in enumerate(frames)])
            while len(states) < len(frames):
                r = bus.receive(timeout_s=1.0)
                if r is not None and r.topic == TRACKING_STATUS:
                    msg = r.decode()
                    states[int(msg.seq)] = int(msg.state)
                assert proc.poll() is None or r is not None, proc.stderr.read()
            out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    lost, ok = status_code(TrackingState.LOST), status_code(TrackingState.OK)
    assert [states[k] for k in (5, 7, 8)] == [lost] * 3, states
    # a frame without depth still tracks from its colour against the map (it just adds no points)
    assert states[6] in (lost, ok)
    assert all(states[k] == ok for k in range(9, 16)), states
    assert "1 rejected" in out and "rejected frame 8" in out and "1280x960" not in err, out
    assert "Traceback" not in err
    assert len(traj.read_text().splitlines()) >= 1 + 16 - 4  # header + every tracked frame


def test_state_codes_on_the_wire_are_the_messages_constants():
    """The enum's values name TrackingStatus's constants; their codes never change (logs keep them)."""
    assert [(str(s), status_code(s)) for s in TrackingState] == [("INIT", 0), ("OK", 1), ("LOST", 2), ("SKIPPED", 3),
                                                                         ("INERTIAL", 4)]


def test_rerun_logging_runs_off_the_tracking_thread_in_frame_order(tmp_path):
    """The tracker's Rerun log (images, keypoints, paths) is written by a thread of its own,
    frame after frame in order, while the tracking thread goes on to the next frame; what the log
    reads of the tracker is copied at hand-over. A logging error surfaces when the block ends."""
    import threading

    import pytest

    from octolog.kit.viz import Viz
    from octolog.tracker.config import TrackerConfig
    from octolog.tracker.factory import make_odometry
    from octolog.tracker.node import TrackerRunSummary, VizLog

    calls: list[tuple[str, int | None]] = []

    class Watched(Viz):  # the real Rerun stream, saving to a file; it notes who logs which frame
        def set_time(self, stamp_ns: int, frame: int | None = None) -> None:
            calls.append((threading.current_thread().name, frame))
            super().set_time(stamp_ns, frame)

    frames = list(SyntheticScene(n_frames=6).frames())
    odometry = make_odometry(TrackerConfig(background=False))
    result = TrackerRunSummary()
    with Watched(f"save:{tmp_path}", "tracker", "t") as viz, VizLog(viz) as shown:
        for f in frames:
            res = odometry.track(f)
            result.frames += 1
            result.keyframes += res.is_keyframe
            result.ms.append(1.0)
            result.poses.append(res.world_from_camera)
            shown.put(f, res, result, odometry)
    assert [frame for _, frame in calls] == [f.seq for f in frames]
    assert {name for name, _ in calls} == {"tracker-viz"}
    assert (tmp_path / "tracker.rrd").stat().st_size > 10_000

    class Broken(Viz):
        def points2d(self, *args: object, **kwargs: object) -> None:
            raise RuntimeError("viewer gone")

    with pytest.raises(RuntimeError, match="viewer gone"), Broken(f"save:{tmp_path / 'b'}", "tracker", "t") as viz, \
            VizLog(viz) as shown:
        shown.put(frames[-1], res, result, odometry)


class _Queue:
    """What `_skip_behind` needs of the intake: the frames waiting, oldest first."""

    def __init__(self, waiting: list[int]) -> None:
        self.waiting = [(_Msg(s), None) for s in waiting]

    def newer_frame(self):
        return self.waiting.pop(0) if self.waiting else None

    def skip(self, r) -> None:
        pass  # its IMU samples would go with the next frame


class _Msg:
    def __init__(self, seq: int) -> None:
        self.seq = seq

    def decode(self):
        return self


class _Out:
    def __init__(self) -> None:
        self.skipped: list[int] = []

    def untracked(self, msg, state) -> None:
        assert state == TrackingState.SKIPPED
        self.skipped.append(msg.seq)


def test_a_live_tracker_behind_skips_one_frame_far_behind_jumps_to_the_newest():
    """Behind, the frame in hand is skipped for the next (a tracked frame is at most two camera frames
    after the last, as a fast turn needs); far behind, every frame but the newest. Each skip on record."""
    from octolog.tracker.node import TrackerRunSummary, _skip_behind

    for far, want_skipped, want_taken in ((False, [0], 1), (True, [0, 1, 2, 3], 4)):
        intake, out, result = _Queue([1, 2, 3, 4]), _Out(), TrackerRunSummary()
        r, _ = _skip_behind(intake, _Msg(0), None, out, result, far=far)
        assert (out.skipped, r.seq) == (want_skipped, want_taken)
        assert result.skipped == result.frames == len(want_skipped)


def test_a_mapper_that_comes_after_the_stream_still_gets_every_keyframe(tmp_path):
    """A live camera does not wait for the mapper (it may come up late on a loaded machine): a
    tracker told to keep its keyframes for it (`keep_for`, as `octolog run` does live) waits for it
    after its stream, then until it is done. Here the mapper starts only once the tracker has taken
    every frame: it still maps every keyframe, and both exit cleanly."""
    frames = list(SyntheticScene(n_frames=20).frames())
    ep = f"tcp/127.0.0.1:{free_port()}"
    tracker = subprocess.Popen([sys.executable, "-m", "octolog", "track", "--connect", ep, "--no-multicast",
                                "--set", 'keep_for=["mapper"]'], cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    mapper = None
    try:
        with Bus(BusConfig(listen=(ep,), multicast_scouting=False), "replay") as bus:
            _play(bus, frames)
            seen = 0
            while seen < len(frames):  # every frame taken: the tracker's stream is over
                r = bus.receive(timeout_s=1.0)
                seen += r is not None and r.topic == TRACKING_STATUS
                assert tracker.poll() is None, tracker.stderr.read()
            mapper = subprocess.Popen([sys.executable, "-m", "octolog", "map", "--connect", ep, "--no-multicast",
                                       "--out", str(tmp_path / "map")], cwd=ROOT, stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True)
            m_out, m_err = mapper.communicate(timeout=180)
            t_out, t_err = tracker.communicate(timeout=120)
    finally:
        for proc in (tracker, mapper):
            if proc is not None and proc.poll() is None:
                proc.kill()
    assert tracker.returncode == 0 and mapper.returncode == 0, (t_err, m_err)
    kf = int(t_out.split(" keyframes,")[0].rsplit(" ", 1)[-1])
    assert kf >= 2 and f"mapper: {kf} keyframes (0 skipped)" in m_out, (t_out, m_out)
