"""Robots that meet again are linked again (inter-robot loop closure, mapper/fleet/placement.py:
relinking): in process on rendered views of the synthetic room, and through the real processes
(tests/helpers/fleet.py's `run_fleet`: a router, a mapper for r1+r2, and per robot a replay and a tracker)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.fleet import ROBOTS, run_fleet

from octolog.mapper.config import MapperConfig


@pytest.mark.slow
def test_robots_that_meet_again_later_are_linked_again():
    """Inter-robot loop closure: r2 is placed where r1 started (X) and refined there, goes
    where r1 never was, then comes past the place r1 saw at the end (Y): a new link between r2's
    keyframe at Y and r1's, found among r1's nearest kept keyframes. Without relinking (as before)
    the robots stay tied at X only; same keyframes, same links (the defined order). r1 has three
    keyframes at X: each of r2's five matches there is a verified match against one of them."""
    from octolog.kit.geometry import RgbdFrame, invert
    from octolog.mapper.fleet import placement as pl
    from octolog.replay.synthetic import SyntheticScene

    scene = SyntheticScene(n_frames=600)  # one loop round the room; X at frame 0, Y at 300, 1.8 m apart

    def frame(i: int) -> RgbdFrame:  # the view from frame i's pose (octolog's frame cache keeps it)
        return scene.render(i)

    r1 = [0, 6, 12, 300, 303, 306]
    after_m = MapperConfig().relink_after_m
    r2 = [1, 4, 7, 10, 13, 16] + [150 + 3 * k for k in range(10)] + [301, 304]  # X to Y by way of 150: ~3.6 m
    frames = {i: frame(i) for i in sorted(set(r1 + r2))}
    r2_own = {i: invert(scene.pose(r2[0])) @ scene.pose(i) for i in r2}  # r2's world: its first camera

    def run(relink: bool) -> pl.Placement:
        p = pl.Placement.by_place(2, after_m if relink else 0.0)
        for kid, i in enumerate(r1):  # r1's world is the map's (its first camera's, here the scene's)
            p.remember(0, kid, kid, scene.pose(i), frames[i])
        gid = len(r1)
        for kid, i in enumerate(r2):
            if not p.placed(1):
                assert p.offer(1, kid, scene.stamp_ns(i), r2_own[i], frames[i]) is not None, "r2 placed at X"
                assert [w.kf_id for w in p.take(1)] == [kid]
            p.remember(1, kid, gid, p.world_from_robot[1] @ r2_own[i], frames[i])
            gid += 1
        return p

    p = run(True)
    assert p.link_kinds[:pl.REFINE_MATCHES] == ["place"] + ["refine"] * (pl.REFINE_MATCHES - 1)
    pairs = [(r, k) for _, r, k, _ in p.links]
    assert len(set(pairs)) == len(pairs), pairs  # one link per keyframe: the placing match is not counted twice
    relinks = [lk for lk, kind in zip(p.links, p.link_kinds) if kind == "relink"]
    assert relinks, p.link_kinds
    at_y = {r1.index(i) for i in (300, 303, 306)}
    assert all(r == 1 and r2[k] in (301, 304) and a in at_y for a, r, k, _ in relinks), relinks
    gid, _, k, al = relinks[0]  # the link says where r2's keyframe is from r1's: as the scene does
    truth = invert(scene.pose(r1[gid])) @ scene.pose(r2[k])
    assert np.linalg.norm(al.a_from_b[:3, 3] - truth[:3, 3]) < 0.01
    off = run(False)
    assert "relink" not in off.link_kinds and len(off.links) == pl.REFINE_MATCHES
    assert [(a, r, k) for a, r, k, _ in run(True).links] == [(a, r, k) for a, r, k, _ in p.links]


@pytest.mark.slow
def test_robots_linked_again_through_the_real_processes(tmp_path):
    """Inter-robot loop closure end to end: r1 walks frames 0-199 of a 600-frame loop round
    the synthetic room, r2 frames 150-249 (every second frame of each), both at once, no start poses.
    r2 starts ahead of r1, waits, and is placed once r1 reaches where r2 began; r1 then comes past
    places r2 saw seconds before and is linked to them again (r1 has come mapper.relink_after_m,
    2 m, by its frame ~155; relinks count as r2's refinement, which r1 behind it cannot give). Both
    robots' keyframes follow the scene after one rigid alignment, and a second run (other arrival
    timing) gives the same links and map bytes: placing and relinking at defined points of the merge
    order (also for test_fleet.py's merge without start poses on TUM frames)."""
    from octolog.kit.metrics import read_tum, umeyama
    from octolog.replay.synthetic import SyntheticScene

    # every second frame (the loop at twice the speed, 15 fps): the same places and overlaps in half the frames
    kw = {"source": "synthetic:600", "windows": ((0, 100), (75, 125)), "shifts": (0.0, -4.983),
          "replay_sets": ("every=2",)}
    run_fleet(tmp_path / "a", [], **kw)
    stats = json.loads((tmp_path / "a" / "map_stats.json").read_text())
    assert stats["links"]["place"] == 1 and stats["links"]["relink"] >= 1, stats["links"]
    scene = SyntheticScene(n_frames=600)
    index = {scene.stamp_ns(i): i for i in range(600)}
    est, truth = [], []
    for robot, shift in zip(ROBOTS, kw["shifts"]):
        traj = read_tum(tmp_path / "a" / f"keyframes_{robot}.txt")
        for stamp, p in zip(traj.stamps_ns, traj.positions):
            est.append(p)
            truth.append(scene.pose(index[int(stamp) - round(shift * 1e9)])[:3, 3])
    est_all, truth_all = np.array(est), np.array(truth)
    R, t, _ = umeyama(est_all, truth_all, with_scale=False)
    err = np.linalg.norm(est_all @ R.T + t - truth_all, axis=1)
    print(f"links {stats['links']}; keyframes vs the scene: rmse {np.sqrt(np.mean(err ** 2)) * 100:.2f} cm, "
          f"max {err.max() * 100:.2f} cm")
    assert err.max() < 0.02, err
    run_fleet(tmp_path / "b", [], **kw)
    for name in ("map.bt", "keyframes_r1.txt", "keyframes_r2.txt", "map_stats.json"):
        assert (tmp_path / "b" / name).read_bytes() == (tmp_path / "a" / name).read_bytes(), name
