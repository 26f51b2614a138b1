"""The tracker's intake live (tracker/intake.py), over real Zenoh sessions on loopback: which frames
a tracker behind the camera tracks in order and when it skips to the newest (`tracker.live_lag_ms`)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from octolog.kit.bus import Bus, BusConfig
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.schemas import codec, rgbdmsgs, streammsgs, topics
from octolog.tracker.intake import Intake

FRAME_MS = 1000 / 30  # a burst of frames at 30 fps


def _frame(seq: int) -> RgbdFrame:
    return RgbdFrame(seq, round(seq * FRAME_MS * 1e6), np.full((8, 8, 3), seq, np.uint8),
                     np.full((8, 8), 1000 + seq, np.uint16), 0.001, Intrinsics(8, 8, 6.0, 6.0, 4.0, 4.0))


def _stamp_ms(r) -> float:
    return codec.stamp_ns(r.decode().header) / 1e6


@pytest.mark.parametrize("lag_ms", [150.0, 0.0])
def test_a_tracker_behind_by_less_than_the_lag_tracks_the_burst_in_order(lag_ms, endpoint):
    """Nine frames wait behind frame 0 (up to 267 ms of sensor time ahead of it). For each frame the
    tracker takes in turn, `behind` says whether the newest waiting frame is more than the lag ahead:
    with 150 ms the frames from 133 ms on are tracked in order, the older ones are behind; with lag 0
    every frame but the last two is (one frame waiting is the next in line, not a backlog).
    `behind` reorders and drops nothing."""
    ep = endpoint
    server = BusConfig(listen=(ep,), multicast_scouting=False, namespace="t")
    client = BusConfig(connect=(ep,), multicast_scouting=False, namespace="t")
    n = 9
    with Bus(server, "tracker") as sub, Bus(client, "replay") as pub:
        sub.subscribe([topics.RGBD, topics.RGBD_END])
        sub.announce()
        pub.watch(["tracker"])
        pub.wait_for(["tracker"], timeout_s=20)
        frames, end = pub.publisher(topics.RGBD), pub.publisher(topics.RGBD_END)
        for k in range(n):
            frames.put(rgbdmsgs.rgbd_msg(_frame(k)))
        end.put(streammsgs.stream_end_msg(topics.RGBD.name, n))
        with Intake(sub, None, viz=False, live=True, lag_ms=lag_ms) as intake:
            first = intake.get(30.0)
            assert first is not None and _stamp_ms(first[0]) == 0.0
            deadline = time.monotonic() + 30  # a guard against a hang: the loop ends when the end arrives
            while not any(r.topic == topics.RGBD_END for r, _ in intake._held):
                assert time.monotonic() < deadline, "the burst never arrived"
                intake.behind(first[0])
            newest = (n - 1) * FRAME_MS
            taken, verdicts = [], []
            r: object = first
            while r is not None:
                received, fut = r
                if received.topic == topics.RGBD_END:
                    break
                stamp = _stamp_ms(received)
                taken.append(stamp)
                verdicts.append(intake.behind(received))
                if fut is not None:  # what the tracker does with it: decoded and ready
                    assert intake.prepared(received, fut)[1].seq == round(stamp / FRAME_MS)
                r = intake.get(30.0)
            assert taken == pytest.approx([k * FRAME_MS for k in range(n)], abs=1e-3)
            # behind: two or more frames wait (one is just the next) and the newest is more than the lag ahead
            assert verdicts == [newest - t > lag_ms and n - 1 - k >= 2 for k, t in enumerate(taken)]
            assert verdicts.count(False) == (5 if lag_ms == 150.0 else 2)
