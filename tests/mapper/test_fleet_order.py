"""Several robots into one map: the order the mapper integrates their items in (mapper/fleet/order.py),
the watermarks that let it decide sooner, and a robot that tracks without making keyframes
through the real processes."""

from __future__ import annotations

import json
import random

import pytest
from helpers import free_port, stop_all
from helpers.fleet import ROBOTS, spawn

from octolog.mapper.fleet.order import CorrectionItem, FleetMerge, KeyframeItem, Watermark, merged_order


def _kf(stamp: int, kf_id: int) -> KeyframeItem:
    return KeyframeItem(stamp, kf_id, None)


def test_merge_is_by_stamp_then_robot_and_waits_for_every_stream():
    streams = [[_kf(10, 0), _kf(30, 1), _kf(50, 2)], [_kf(10, 0), _kf(20, 1), _kf(60, 2)]]
    order = [(i, it.stamp_ns) for i, it in merged_order(streams)]
    assert order == [(0, 10), (1, 10), (1, 20), (0, 30), (0, 50), (1, 60)]
    m = FleetMerge(ROBOTS)
    m.push(0, _kf(10, 0))
    assert m.pop() is None and m.waiting_on() == [1]  # r2 might still send something older
    m.end(1)
    assert m.pop() == (0, _kf(10, 0))


# r2's correction, applied by its tracker at the frame of its keyframe at 30, after that keyframe;
# its last one (the final poses) at the stamp of its last frame, after that frame's status
STREAMS = [[_kf(s, k) for k, s in enumerate((5, 17, 18, 40))],
           [_kf(s, k) for k, s in enumerate((1, 17, 30))] + [CorrectionItem(30, {0: "moved"}), _kf(41, 3),
                                                              CorrectionItem(44, {0: "final"})]]


def _deliver(streams: list[list], rng: random.Random) -> list[tuple[int, str]]:
    """Merge `streams`, handing the merge the next message of a random robot it waits on (as a
    network might); the items in the order the merge gave them."""
    m = FleetMerge(ROBOTS)
    pending = [list(s) for s in streams]
    out = []
    while not m.done():
        nxt = m.pop()
        if nxt is not None:
            out.append((nxt[0], repr(nxt[1])))
            continue
        i = rng.choice(m.waiting_on())
        if pending[i]:
            m.push(i, pending[i].pop(0))
        else:
            m.end(i)
    return out


def test_merge_order_does_not_depend_on_arrival_order():
    """Whatever order the two robots' messages arrive in, the integration order is the same."""
    rng = random.Random(7)
    orders = {tuple(_deliver(STREAMS, rng)) for _ in range(50)}
    assert len(orders) == 1
    (order,) = orders
    kinds = [(i, r.split("(")[0]) for i, r in order]
    # r2's correction at 30 comes after its keyframe at 30 and before anything later
    assert kinds.index((1, "CorrectionItem")) == 6  # after 1, 5, 17, 17, 18, 30
    assert list(order) == [(i, repr(it)) for i, it in merged_order(STREAMS)]


def test_watermarks_let_the_merge_decide_sooner_and_change_no_order():
    """The per-robot watermark: a robot's tracker says after every frame it processed that
    nothing older will come (its status). Wherever those fall in its stream, the items come out in
    the order complete streams give; and a robot that only sends watermarks no longer holds the
    others back."""
    rng = random.Random(11)
    expected = [(i, repr(it)) for i, it in merged_order(STREAMS)]
    for _ in range(50):
        sent = []
        for items in STREAMS:  # statuses of some frames from an item's frame to the next item's
            out: list = []
            for k, it in enumerate(items):
                out.append(it)
                nxt = items[k + 1].stamp_ns if k + 1 < len(items) else it.stamp_ns + 1
                out += [Watermark(t) for t in range(it.stamp_ns, nxt + 1) if rng.random() < 0.5]
            sent.append(out)
        assert _deliver(sent, rng) == expected
    # r1 has keyframes at 10 and 30; r2 keeps tracking without a keyframe
    m = FleetMerge(ROBOTS)
    m.push(0, _kf(10, 0))
    m.push(0, _kf(30, 1))
    assert m.pop() is None and m.waiting_on() == [1]
    m.push(1, Watermark(20))  # r2 has processed its frame at 20: nothing older will come
    assert m.pop() == (0, _kf(10, 0))
    assert m.pop() is None and m.waiting_on() == [1]  # r1's keyframe at 30 might still be younger than r2's next
    m.push(1, Watermark(31))
    m.push(1, Watermark(32))  # in a row: they collapse, and are no items
    assert not m.has_items(1) and m.pop() == (0, _kf(30, 1))
    m.end(1)  # a watermark after the last item is dropped with the stream's end
    m.end(0)
    assert m.done() and m.canonical() == [(0, _kf(10, 0)), (0, _kf(30, 1))]


def test_a_paused_robot_holds_the_others_back_no_longer_and_the_defined_order_stays():
    """A robot paused for silence is not waited for; its item that comes later is taken
    late (out of the defined order, and the merge says so), and `canonical` gives every item in the
    order complete streams would have had."""
    a0, a1, b0 = KeyframeItem(10, 0, "a0"), KeyframeItem(30, 1, "a1"), KeyframeItem(5, 0, "b0")
    merge = FleetMerge(("a", "b"))
    merge.push(0, a0)
    merge.push(0, a1)
    assert merge.pop() is None and merge.waiting_on() == [1]
    merge.pause(1)
    assert merge.waiting_on() == [] and merge.paused() == [1]
    assert merge.pop() == (0, a0) and merge.jumped
    merge.push(1, b0)  # older than what was taken: late
    assert merge.paused() == [] and merge.pop() == (1, b0)
    merge.end(1)
    assert merge.pop() == (0, a1)
    assert merge.canonical() == [(1, b0), (0, a0), (0, a1)]
    steady = FleetMerge(("a", "b"))
    for i, item in ((0, a0), (1, b0), (0, a1)):
        steady.push(i, item)
    assert steady.pop() == (1, b0) and not steady.jumped


@pytest.mark.slow
def test_a_robot_that_tracks_without_keyframes_holds_the_others_back_no_longer(tmp_path):
    """The watermark through the real processes: r2's camera stands still (one synthetic
    frame played 120 times at a fifth of the camera's rate, 6 frames a second: 20 s of wall time
    however fast the machine, a status from its tracker every 0.17 s), so after
    its first keyframe its tracker makes none for 20 s, while r1 maps the room. With
    `mapper.robot_stall_s` 10 s, a mapper that heard nothing from r2 would pause it and build the map
    again at the end; its tracker's statuses tell the mapper r2 is alive and how far it got, so r1's
    keyframes go in as they come, in the defined order. (10 s of silence is far beyond what a loaded
    machine's scheduling gives either tracker between two statuses; a tighter stall is a timing margin.)"""
    out = tmp_path / "fleet"
    out.mkdir()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = ["--mode", "client", "--connect", endpoint, "--no-multicast"]
    procs = {"router": spawn(out / "router.log", "router", "--listen", endpoint)}
    frames = 40
    still, rate = 120, 0.2
    try:
        procs["mapper"] = spawn(None, "map", *bus, "--out", str(out), "--rerun", "off",
                                "--set", 'robots=["r1", "r2"]', "--set", "robot_stall_s=10.0",
                                "--set", "start_poses=[[0, 0, 0, 0, 0, 0, 1], [0, 0, 0, 0, 0, 0, 1]]")
        for robot in ROBOTS:
            procs[f"tracker-{robot}"] = spawn(out / f"tracker-{robot}.log", "track", *bus, "--namespace", robot)
        window = {"r1": ("--set", "start=0", "--set", f"end={frames}"),
                  "r2": ("--set", "start=0", "--set", "end=1", "--set", f"loop={still}", "--set", f"rate={rate}")}
        for robot in ROBOTS:
            procs[f"replay-{robot}"] = spawn(out / f"replay-{robot}.log", "replay", *bus, "--namespace", robot,
                                             "--quiet", "--source", f"synthetic:{frames}", *window[robot],
                                             "--set", 'wait_for=["tracker", "mapper"]')
        said, _ = procs["mapper"].communicate(timeout=600)
        assert procs["mapper"].returncode == 0, said
        for name in ("replay-r1", "replay-r2", "tracker-r1", "tracker-r2"):
            assert procs[name].wait(timeout=600) == 0, (name, (out / f"{name}.log").read_text())
    finally:
        stop_all(procs)
    stats = json.loads((out / "map_stats.json").read_text())
    assert stats["robots"]["r2"]["keyframes"] == 1 and stats["robots"]["r1"]["keyframes"] >= 3, stats["robots"]
    assert "silent for" not in said and "built again" not in said, said
