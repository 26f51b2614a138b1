"""Replay controls: frame and time windows, looping, topic remapping."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from octolog.kit.errors import ConfigError
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.replay.config import ReplayConfig, remapped
from octolog.replay.node import looped
from octolog.schemas.topics import RGBD


class FakeSource:
    """Ten frames at 10 Hz."""

    name = "fake"
    readout_s = 0.0
    depth_model = None
    encoded = False

    def __init__(self, n: int = 10) -> None:
        self.n = n
        self.intr = Intrinsics(4, 3, 2.0, 2.0, 1.5, 1.0)

    def __len__(self) -> int:
        return self.n

    @property
    def duration_ns(self) -> int:
        return (self.n - 1) * 100_000_000

    def frames(self, start=0, end=None):
        for i in range(start, self.n if end is None else min(end, self.n)):
            yield RgbdFrame(i, 1_000_000_000 + i * 100_000_000, np.zeros((3, 4, 3), np.uint8),
                            np.zeros((3, 4), np.uint16), 0.001, self.intr)

    def groundtruth_tum(self):
        return None


def _seqs(cfg: ReplayConfig) -> list[tuple[int, int]]:
    return [(f.seq, f.stamp_ns) for f in looped(FakeSource(), cfg)]


def test_frame_and_time_windows():
    assert [s for s, _ in _seqs(ReplayConfig(start=2, end=5))] == [2, 3, 4]
    assert [s for s, _ in _seqs(ReplayConfig(start_s=0.25, end_s=0.55))] == [3, 4, 5]


def test_loop_keeps_sequence_and_time_moving_on():
    got = _seqs(ReplayConfig(loop=3))
    seqs, stamps = zip(*got)
    assert list(seqs) == list(range(30))
    assert all(b - a == 100_000_000 for a, b in zip(stamps, stamps[1:]))
    # the sensor time `octolog run` reports (summary.json duration_s, the real-time factor) is what played
    from octolog.shell.run import played_ns

    src = FakeSource()
    assert played_ns(src.duration_ns, len(src), 3) == stamps[-1] - stamps[0]
    assert played_ns(src.duration_ns, len(src), 1) == src.duration_ns


def test_every_nth_frame_keeps_the_stamps_and_numbers_frames_anew(tmp_path):
    from octolog.replay.sources import Subsampled, open_source

    sub = Subsampled(FakeSource(), 3)
    assert len(sub) == 4
    assert [(f.seq, f.stamp_ns) for f in sub.frames()] == [(i, 1_000_000_000 + 3 * i * 100_000_000) for i in range(4)]
    assert [f.seq for f in sub.frames(1, 3)] == [1, 2]
    # TUM: the pairs in between are never read (here: they do not even exist)
    folder = tmp_path / "rgbd_dataset_freiburg1_every"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for name in ("rgb", "depth"):
        (folder / f"{name}.txt").write_text("".join(f"{1 + i / 10:.6f} {name}/{i}.png\n" for i in range(7)))
    for i in (0, 3, 6):
        cv2.imwrite(str(folder / "rgb" / f"{i}.png"), np.full((4, 4, 3), i, np.uint8))
        cv2.imwrite(str(folder / "depth" / f"{i}.png"), np.full((4, 4), 1000 + i, np.uint16))
    frames = list(open_source(f"tum:{folder}", every=3).frames())
    assert [(f.seq, int(f.depth[0, 0])) for f in frames] == [(0, 1000), (1, 1003), (2, 1006)]
    with pytest.raises(ConfigError, match="replay.every 0: want >= 1"):
        open_source("synthetic:4", every=0)


def test_remap_topics():
    assert remapped(RGBD, ("camera/rgbd=/cam2/rgbd",)).key("robot1") == "robot1/cam2/rgbd"
    assert remapped(RGBD, ("other=x",)) is RGBD
    with pytest.raises(ConfigError, match="want FROM=TO"):
        from octolog.kit.config import load

        load(ReplayConfig, None, ['remap=["camera/rgbd"]'])


class TruthSource(FakeSource):
    """FakeSource with ground truth: at x = t (m), one pose per frame."""

    def groundtruth_tum(self):
        return "# timestamp tx ty tz qx qy qz qw\n" + "".join(
            f"{1 + i / 10:.9f} {i / 10} 0 0 0 0 0 1\n" for i in range(self.n))


def test_retimed_every_nth_frame_plays_at_the_source_rate_and_so_does_the_truth():
    """replay.retime: every 3rd frame, stamped 3x closer: the camera 3x faster at the same frame rate;
    the ground truth is re-timed the same way, so a pose still meets the truth of its own instant."""
    from octolog.kit import metrics
    from octolog.replay.sources import Retimed, Subsampled

    src = Retimed(Subsampled(TruthSource(), 3), 3)
    frames = list(src.frames())
    assert [f.stamp_ns for f in frames] == [1_000_000_000 + i * 100_000_000 for i in range(4)]  # 10 Hz, as the source
    assert src.duration_ns == 300_000_000 and len(src) == 4
    truth = metrics.parse_tum(src.groundtruth_tum())
    at = {int(s): p[0] for s, p in zip(truth.stamps_ns, truth.positions)}
    # frame k was source frame 3k, where the camera was at x = 0.3 k
    assert [round(at[f.stamp_ns], 6) for f in frames] == [0.0, 0.3, 0.6, 0.9]
    assert [f.stamp_ns for f in src.frames(1, 3)] == [1_100_000_000, 1_200_000_000]


def test_retime_through_open_source_and_the_config():
    from octolog.kit.config import load
    from octolog.replay.sources import open_source

    assert load(ReplayConfig, None, ["every=3", "retime=true"]).retime
    plain, fast = open_source("synthetic:9", every=3), open_source("synthetic:9", every=3, retime=True)
    assert fast.duration_ns * 3 == plain.duration_ns
    assert [f.stamp_ns - 1_700_000_000_000_000_000 for f in fast.frames()] == [0, 33_333_333, 66_666_667]
    assert open_source("synthetic:9", retime=True).duration_ns == open_source("synthetic:9").duration_ns  # every 1
