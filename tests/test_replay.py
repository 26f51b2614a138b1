"""Replay controls: frame and time windows, looping, topic remapping."""

from __future__ import annotations

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


def test_remap_topics():
    assert remapped(RGBD, ("camera/rgbd=/cam2/rgbd",)).key("robot1") == "robot1/cam2/rgbd"
    assert remapped(RGBD, ("other=x",)) is RGBD
    with pytest.raises(ConfigError, match="want FROM=TO"):
        from octolog.kit.config import load

        load(ReplayConfig, None, ['remap=["camera/rgbd"]'])
