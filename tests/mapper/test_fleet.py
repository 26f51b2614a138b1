"""Several robots into one map: the joint graph, the config, and robots through real processes
(the merge order: test_fleet_order.py).

The end-to-end test runs a router, one mapper for robots r1 and r2, and per robot a replay and a
tracker (each its own process, each robot under its own namespace) on the two halves of the
synthetic sequence, r2's half shifted in time to run alongside r1's (so their keyframes interleave);
r2's start pose comes from the scene's ground truth. The reference is built
without any of the fleet code: the tracker core and the mapper core in this process, keyframes
sorted by (stamp, robot index) with `sorted`, integrated one after the other.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from helpers import free_port, kill_then_finish, octolog, read_until, stop_all, tum_first300
from helpers.fleet import FRAMES, HALF, ROBOTS, SHIFT_S, run_fleet, spawn, start_router
from helpers.maps import cells, occupied_disagreement

from octolog.kit.errors import ConfigError
from octolog.mapper.config import MapperConfig


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, 0.0]
    return T


def test_the_joint_graph_closes_the_seam_a_rigid_placement_leaves():
    """After a merge: r2 is placed by a match at its first keyframe, but its own trajectory
    drifts (1 mm and 0.1 degree a 10 cm step); a second link where the robots meet again no longer fits
    one rigid placement. The joint pose graph moves r2's keyframes (and r1's, a little) so both
    links hold and r2's end comes back towards the truth; one link alone asks for no graph."""
    from octolog.kit.geometry import invert
    from octolog.mapper.fleet.joint_graph import Link, joint_poses, needs_graph

    n = 12
    truth1 = [_pose(0.1 * k, 0.0, 0.0) for k in range(n)]  # r1: along x
    truth2 = [_pose(0.1 * k, 0.5, 0.0) for k in range(n)]  # r2: alongside, half a metre over
    drift = [_pose(0.001 * k, 0.0, np.radians(0.1) * k) for k in range(n)]
    r2_own = [drift[k] @ invert(truth2[0]) @ truth2[k] for k in range(n)]  # r2's own world: its first camera
    robot_poses = [dict(enumerate(truth1)), {n + k: T for k, T in enumerate(r2_own)}]
    W2 = truth2[0] @ invert(r2_own[0])  # placed exactly by the first match
    first = Link(0, n, invert(truth1[0]) @ truth2[0], rmse_m=0.002)
    second = Link(n - 1, 2 * n - 1, invert(truth1[n - 1]) @ truth2[n - 1], rmse_m=0.002)
    assert not needs_graph([first], 2) and needs_graph([first, second], 2)
    def seam(P1: np.ndarray, P2: np.ndarray) -> float:  # how far the second link is from holding
        return float(np.linalg.norm((invert(P1) @ P2 @ invert(second.a_from_b))[:3, 3]))

    rigid = {g: T for g, T in robot_poses[0].items()} | {g: W2 @ T for g, T in robot_poses[1].items()}
    poses = joint_poses(robot_poses, [np.eye(4), W2], [first, second])
    before, after = seam(rigid[n - 1], rigid[2 * n - 1]), seam(poses[n - 1], poses[2 * n - 1])
    assert before > 0.02 and after < before / 3, (before, after)
    # both robots' trajectories carry the same weight: the truth lies in between, r2's end halfway back
    end = [float(np.linalg.norm(P[2 * n - 1][:3, 3] - truth2[-1][:3, 3])) for P in (rigid, poses)]
    assert end[1] < end[0] / 2, end
    np.testing.assert_array_equal(poses[0], truth1[0])  # the map's first keyframe holds the world
    # same inputs, same poses: the joint graph is part of the map's deterministic order
    again = joint_poses(robot_poses, [np.eye(4), W2], [first, second])
    assert all(np.array_equal(poses[g], again[g]) for g in poses)


def test_robots_running_ahead_never_starve_the_one_the_merge_awaits():
    """The fleet mapper's robot inboxes as `run_fleet` opens them (mapper/fleet/node.py: ROBOT_INBOX),
    on real Zenoh sessions in one process (one receive pool, as in the mapper): four robots send 300
    samples each that nobody takes yet (they ran ahead while the merge awaits a fifth), more than a
    bounded inbox holds; the fifth robot's sample still arrives, then all of the others', in order.
    With bounded inboxes the full ones block the pool's threads and the fifth's sample never comes."""
    import contextlib
    import threading
    import time

    from octolog.kit.bus import Bus, BusConfig
    from octolog.mapper.fleet.node import ROBOT_INBOX
    from octolog.schemas import streammsgs, topics

    n, robots, awaited = 300, ("r1", "r2", "r3", "r4", "r5"), "r2"
    with contextlib.ExitStack() as stack:
        mapper, sender = {}, {}
        for r in robots:
            ep = f"tcp/127.0.0.1:{free_port()}"
            mapper[r] = stack.enter_context(Bus(BusConfig(listen=(ep,), multicast_scouting=False, namespace=r),
                                                "mapper", inbox_size=ROBOT_INBOX))
            mapper[r].subscribe([topics.RGBD_END])
            mapper[r].announce()
            sender[r] = stack.enter_context(Bus(BusConfig(connect=(ep,), multicast_scouting=False, namespace=r),
                                                "tracker"))
            sender[r].watch(["mapper"])
            sender[r].wait_for(["mapper"], timeout_s=30)

        def send(r: str, count: int) -> None:
            pub = sender[r].publisher(topics.RGBD_END)
            for i in range(count):  # the message's `count` field carries its number
                pub.put(streammsgs.stream_end_msg("x", i))

        ahead = [threading.Thread(target=send, args=(r, n), daemon=True) for r in robots if r != awaited]
        for t in ahead:
            t.start()
        for t in ahead:
            t.join(timeout=120)
        assert not any(t.is_alive() for t in ahead), "a robot's sending blocked on the mapper's inbox"
        send(awaited, 1)
        deadline = time.monotonic() + 120
        got = None
        while got is None and time.monotonic() < deadline:
            got = mapper[awaited].receive(timeout_s=1.0)
        assert got is not None and int(got.decode().count) == 0, "the awaited robot's sample never arrived"
        for r in robots:
            if r != awaited:
                numbers = []
                while len(numbers) < n and (m := mapper[r].receive(timeout_s=5.0)) is not None:
                    numbers.append(int(m.decode().count))
                assert numbers == list(range(n)), r


@pytest.mark.slow
def test_a_fleet_of_five_robots_completes(tmp_path, octolog_run):
    """docs/deployment.md's fleet layout with 5 robots and no start poses (a fleet of 3 is its first
    three robots, the same windows: a run of its own would add nothing): a router, one
    mapper for every robot, and per robot its tracker's keyframe stream replayed from a session log
    (`replay.play = "tracker"`). Each robot replays another window of the log: robot k the keyframes
    made from frames 4k to 23 (the first robot five, the fifth robot the last two of those), so each
    starts at a view of its own and shares places with the first.
    The mapper ends; every robot is placed, every keyframe of every robot is in the map, and each
    keyframe lies where the first robot has it (the log's one world), within 2 cm."""
    from octolog.kit.metrics import read_tum

    log = octolog_run(f"synthetic:{FRAMES}")[0] / "session.mcap"
    n_robots = 5
    robots = [f"r{k + 1}" for k in range(n_robots)]
    starts, end = [4 * k for k in range(n_robots)], 24
    out = tmp_path / "fleet"
    procs, bus = start_router(out)
    try:
        procs["mapper"] = spawn(out / "mapper.log", "map", *bus, "--out", str(out), "--rerun", "off",
                                "--set", f"robots={json.dumps(robots)}")
        for robot, start in zip(robots, starts):
            procs[robot] = spawn(out / f"{robot}.log", "replay", *bus, "--namespace", robot, "--quiet",
                                 "--source", f"mcap:{log}", "--set", "play=tracker", "--set", f"start={start}",
                                 "--set", f"end={end}", "--set", 'wait_for=["mapper"]')
        for name in ("mapper", *robots):
            assert procs[name].wait(timeout=600) == 0, (name, (out / f"{name}.log").read_text())
    finally:
        stop_all(procs)
    stats = json.loads((out / "map_stats.json").read_text())
    per_robot = [stats["robots"][r]["keyframes"] for r in robots]
    assert all(stats["robots"][r]["merged"] for r in robots), stats["robots"]
    assert per_robot[0] > per_robot[-1] >= 2 and stats["keyframes"] == sum(per_robot), per_robot
    first = read_tum(out / "keyframes_r1.txt")
    where = dict(zip(first.stamps_ns.tolist(), first.positions))
    for robot in robots[1:]:
        traj = read_tum(out / f"keyframes_{robot}.txt")
        assert traj.stamps_ns[0] != first.stamps_ns[0]  # a view of its own to start from
        assert max(np.linalg.norm(p - where[t]) for t, p in zip(traj.stamps_ns.tolist(), traj.positions)) < 0.02, robot


def test_config_checks_robots_and_start_poses():
    with pytest.raises(ConfigError, match="2 poses for 1 robots"):
        MapperConfig(robots=("r1",), start_poses=((0, 0, 0, 0, 0, 0, 1), (0, 0, 0, 0, 0, 0, 1))).validate()
    with pytest.raises(ConfigError, match="want 7 finite numbers"):
        MapperConfig(robots=("r1",), start_poses=((0, 0, 0),)).validate()
    with pytest.raises(ConfigError, match="quaternion is zero"):
        MapperConfig(robots=("r1",), start_poses=((0, 0, 0, 0, 0, 0, 0),)).validate()
    with pytest.raises(ConfigError, match="listed twice"):
        MapperConfig(robots=("r1", "r1")).validate()
    with pytest.raises(ConfigError, match="relink_after_m -1"):
        MapperConfig(robots=("r1", "r2"), relink_after_m=-1).validate()
    proc = octolog("map", "--set", "robots=[\"a\", \"b*\"]", "--no-multicast", check=False, timeout=60)
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1 and "mapper.robots 'b*'" in proc.stderr


# --- two robots through real processes --------------------------------------------------------------


def _start_poses() -> list[list[float]]:
    from octolog.kit.geometry import invert, matrix_to_pose
    from octolog.replay.synthetic import SyntheticScene

    scene = SyntheticScene(n_frames=FRAMES)
    poses = []
    for first in (0, HALF):  # each robot's tracker world is its first camera frame
        t, q = matrix_to_pose(invert(scene.pose(0)) @ scene.pose(first))
        poses.append([float(x) for x in (*t, *q)])
    return poses


def _reference(out: Path, start_poses: list[list[float]], *, source: str = f"synthetic:{FRAMES}",
               windows: tuple[tuple[int, int], ...] = ((0, HALF), (HALF, FRAMES)),
               shifts: tuple[float, ...] = SHIFT_S) -> None:
    """The map built from both inputs on one host, in one process, without mapper/fleet/order.py.

    The tracker's back end moves keyframes after they were sent (bundle adjustment, loop closing, its
    final poses), and the mapper's map always equals the map built from scratch, in integration order,
    with every keyframe's latest pose (mapper.core). So: the keyframes sorted by (stamp, robot), each
    at the last pose its robot sent for it after sending it, integrated once."""
    from octolog.kit.geometry import pose_to_matrix
    from octolog.kit.metrics import write_tum
    from octolog.mapper.core import make_mapper
    from octolog.replay import source_gravity
    from octolog.replay.sources import open_source
    from octolog.schemas import posemsgs
    from octolog.tracker.config import TrackerConfig, for_source
    from octolog.tracker.factory import make_odometry

    src = open_source(source)
    def wire(T: np.ndarray) -> np.ndarray:  # a pose as the messages carry it (position + quaternion)
        return posemsgs.pose_matrix(posemsgs.pose_msg(T))

    keyframes = []  # (stamp, robot index, robot keyframe id, frame)
    latest: list[dict[int, np.ndarray]] = []  # per robot: keyframe id -> the last pose sent for it
    for r, (start, end) in enumerate(windows):
        odometry = make_odometry(for_source(TrackerConfig(), src))  # the camera's readout, as the stream says
        poses: dict[int, np.ndarray] = {}
        for frame in src.frames(start, end):
            frame = dataclasses.replace(frame, stamp_ns=frame.stamp_ns + round(shifts[r] * 1e9))
            res = odometry.track(frame)
            # as tracker.node sends them: corrections (known keyframes only), then the new keyframe
            poses.update({k: wire(T) for k, T in (getattr(res, "corrected", None) or {}).items() if k in poses})
            if res.is_keyframe:
                poses[res.keyframe_id] = wire(res.world_from_camera)
                keyframes.append((frame.stamp_ns, r, res.keyframe_id, frame))
        if hasattr(odometry, "finish") and odometry.finish():
            poses.update({k: wire(T) for k, T in odometry.keyframe_poses().items() if k in poses})
        latest.append(poses)
    # the map's up: the first robot's replay serves it (camera/gravity) when its window starts at frame 0
    cfg = MapperConfig()
    # the fleet's keyframes come in turn: its map confirms an end point within two per robot
    cfg = dataclasses.replace(cfg, confirm_within=cfg.confirm_within * len(windows))
    found = source_gravity.source_up(src) if windows[0][0] == 0 else None
    if found is not None:
        q = np.array(start_poses[0][3:])
        R0 = pose_to_matrix(np.array(start_poses[0][:3]), q / np.linalg.norm(q))[:3, :3]
        cfg = dataclasses.replace(cfg, grid_up=tuple(float(c) for c in R0 @ found[0]))
    mapper = make_mapper(cfg)
    per_robot: dict[int, list] = {0: [], 1: []}
    for gid, (stamp, r, kf, frame) in enumerate(sorted(keyframes, key=lambda k: k[:3])):
        T = latest[r][kf]
        q = np.array(start_poses[r][3:])
        world_from_robot = pose_to_matrix(np.array(start_poses[r][:3]), q / np.linalg.norm(q))
        mapper.integrate(gid, world_from_robot @ T, frame)
        per_robot[r].append((stamp, mapper.keyframes[gid].world_from_camera))
    mapper.write(out)
    for r, rows in per_robot.items():
        write_tum(out / f"keyframes_{ROBOTS[r]}.txt", np.array([s for s, _ in rows]), np.array([T for _, T in rows]))
    assert len(per_robot[0]) >= 2 and len(per_robot[1]) >= 2, per_robot



@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("fleet")
    poses = _start_poses()
    _reference(tmp / "reference", poses)
    run_fleet(tmp / "processes", poses, rerun=f"save:{tmp / 'processes' / 'rerun'}")
    return tmp / "reference", tmp / "processes"


@pytest.mark.slow
def test_two_robots_fuse_into_the_map_built_on_one_host(fleet):
    ref, procs = fleet
    for name in ("map.bt", "map.ot", "cloud.ply", "keyframes_r1.txt", "keyframes_r2.txt"):
        assert (procs / name).read_bytes() == (ref / name).read_bytes(), name
    import json

    from octolog.kit.metrics import read_tum

    r1, r2 = (read_tum(procs / f"keyframes_{r}.txt").stamps_ns for r in ROBOTS)
    assert r2[0] < r1[-1] and r1[0] < r2[-1]  # the two robots' keyframes interleave in time
    stats = json.loads((procs / "map_stats.json").read_text())
    assert stats["robots"]["r1"]["keyframes"] + stats["robots"]["r2"]["keyframes"] == stats["keyframes"]
    assert stats["skipped_keyframes"] == 0


@pytest.mark.slow
def test_a_silent_robot_no_longer_stalls_the_others_and_the_map_is_the_same(fleet, tmp_path):
    """Robot r2's tracker is up but its camera sends nothing; after mapper.robot_stall_s the
    mapper goes on with r1 (it says so at once), and r2's keyframes, when its replay starts, come
    late. The mapper then builds the map again in the defined order: the same bytes as the run
    where both robots came at once."""
    _, together = fleet
    out = tmp_path / "late"
    out.mkdir()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = ["--mode", "client", "--connect", endpoint, "--no-multicast"]
    poses = "[" + ", ".join("[" + ", ".join(repr(x) for x in p) + "]" for p in _start_poses()) + "]"
    procs = {"router": spawn(out / "router.log", "router", "--listen", endpoint)}
    replay = {robot: ("replay", *bus, "--namespace", robot, "--quiet", "--source", f"synthetic:{FRAMES}",
                      "--set", f"start={start}", "--set", f"end={end}", "--set", f"time_shift_s={shift!r}",
                      "--set", 'wait_for=["tracker", "mapper"]')
              for robot, (start, end), shift in zip(ROBOTS, ((0, HALF), (HALF, FRAMES)), SHIFT_S)}
    try:
        procs["mapper"] = spawn(None, "map", *bus, "--out", str(out), "--rerun", "off", "--set", 'robots=["r1", "r2"]',
                                "--set", f"start_poses={poses}", "--set", "robot_stall_s=2.0")
        for robot in ROBOTS:
            procs[f"tracker-{robot}"] = spawn(out / f"tracker-{robot}.log", "track", *bus, "--namespace", robot)
        procs["replay-r1"] = spawn(out / "replay-r1.log", *replay["r1"])
        said = read_until(procs["mapper"], "the others went on without it")  # the event: r2 is paused
        assert "r2: silent for" in said, said
        procs["replay-r2"] = spawn(out / "replay-r2.log", *replay["r2"])
        rest, _ = procs["mapper"].communicate(timeout=600)
        assert procs["mapper"].returncode == 0, said + rest
        for name in ("replay-r1", "replay-r2", "tracker-r1", "tracker-r2"):
            assert procs[name].wait(timeout=600) == 0, (name, (out / f"{name}.log").read_text())
    finally:
        stop_all(procs)
    assert "built again in the defined order" in said + rest
    for name in ("map.bt", "map.ot", "cloud.ply", "keyframes_r1.txt", "keyframes_r2.txt"):
        assert (out / name).read_bytes() == (together / name).read_bytes(), name


def test_fused_map_lies_on_the_scene_and_trajectories_follow_ground_truth(fleet):
    """Both robots in one world: the fused map's voxels on the scene's surfaces, each robot's
    keyframes where the ground truth says (the start poses put r2 where it began), within the
    tracker's drift."""
    import octomap
    from scipy.spatial import cKDTree

    from octolog.kit.metrics import read_tum
    from octolog.replay.synthetic import SyntheticScene

    _, procs = fleet
    scene = SyntheticScene(n_frames=FRAMES)
    T0 = scene.pose(0)
    tree = octomap.OcTree(0.05)
    assert tree.readBinary(str(procs / "map.bt").encode())
    centres = np.array([it.getCoordinate() for it in tree.begin_leafs() if tree.isNodeOccupied(it)])
    # the map is in `map`; map_stats.json says where the tracker's world (r1's first camera) is in it
    M = np.array(json.loads((procs / "map_stats.json").read_text())["map_from_world"])
    S = T0 @ np.linalg.inv(M)
    dist, _ = cKDTree(scene.surface_samples(0.02)).query(centres @ S[:3, :3].T + S[:3, 3])
    assert np.mean(dist < 0.1) > 0.95
    for robot, shift in zip(ROBOTS, SHIFT_S):
        stamps = {scene.stamp_ns(i) + round(shift * 1e9): i for i in range(FRAMES)}
        traj = read_tum(procs / f"keyframes_{robot}.txt")
        for stamp, p in zip(traj.stamps_ns, traj.positions):
            gt = (np.linalg.inv(T0) @ scene.pose(stamps[int(stamp)]))[:3, 3]
            # the tracker's own drift over 20 frames (3.4 cm at worst with its back end, 2026-12-01)
            assert np.linalg.norm(p - gt) < 0.05, (robot, stamp)


def test_rerun_has_a_trajectory_per_robot(fleet):
    _, procs = fleet
    from helpers import rerun_cli

    rrd = procs / "rerun" / "mapper.rrd"
    proc = subprocess.run([rerun_cli(), "rrd", "print", str(rrd)], check=False, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "RERUN_DISABLE_ANALYTICS": "1"})
    text = proc.stdout + proc.stderr
    for robot in ROBOTS:
        assert f"/world/{robot}/trajectory" in text, text[-2000:]


# --- real data: TUM fr1/xyz first300's first 200 frames in two halves ------------------------------------


TUM_FRAMES = 200  # r1 plays frames 0-99, r2 frames 100-199


@dataclasses.dataclass(frozen=True)
class _Halves:
    source: str
    windows: tuple[tuple[int, int], ...]
    stamps: list[int]
    shifts: tuple[float, float]
    gt: object
    start_poses: list[list[float]]  # each half's first camera in the first half's, from the ground truth

    def gt_pose(self, stamp: int) -> np.ndarray:
        from octolog.kit.metrics import associate

        _, ig = associate(np.array([stamp]), self.gt.stamps_ns)  # type: ignore[attr-defined]
        return self.gt.matrices()[ig[0]]  # type: ignore[attr-defined]


def _tum_halves() -> _Halves:
    """The first TUM_FRAMES frames of TUM fr1/xyz first300 as two robots: the first half and the second,
    shifted to run alongside."""
    from octolog.kit.geometry import invert, matrix_to_pose
    from octolog.kit.metrics import parse_tum
    from octolog.replay.sources import open_source

    source = f"tum:{tum_first300()}"
    src = open_source(source)
    n = TUM_FRAMES
    windows = ((0, n // 2), (n // 2, n))
    stamps = [f.stamp_ns for f in src.frames(0, n)]
    shifts = (0.0, -round((stamps[n // 2] - stamps[0]) * 1e-9, 2) + 0.01)
    h = _Halves(source, windows, stamps, shifts, parse_tum(src.groundtruth_tum() or "", "groundtruth"), [])
    for start, _ in windows:
        t, q = matrix_to_pose(invert(h.gt_pose(stamps[0])) @ h.gt_pose(stamps[start]))
        h.start_poses.append([float(x) for x in (*t, *q)])
    return h


@pytest.fixture(scope="module")
def tum_halves_placed(tmp_path_factory) -> Path:
    """The two halves (`_tum_halves`) through the real processes, r2 placed by its ground-truth start pose:
    one run read by the byte-for-byte check against the reference and by the merge's map check."""
    h = _tum_halves()
    out = tmp_path_factory.mktemp("tum-halves") / "processes"
    run_fleet(out, h.start_poses, source=h.source, windows=h.windows, shifts=h.shifts)
    return out


@pytest.mark.slow
def test_two_halves_of_a_tum_sequence_fuse_like_on_one_host(tmp_path, tum_halves_placed):
    """Two robots on real frames: r1 frames 0-99 of first300, r2 frames 100-199, shifted to run
    alongside; r2's start pose from the TUM ground truth. Byte-identical to the in-process reference,
    and each robot's keyframes near the ground truth in the common world."""
    from octolog.kit.geometry import invert
    from octolog.kit.metrics import read_tum

    h = _tum_halves()
    source, windows, shifts, gt_pose, start_poses = h.source, h.windows, h.shifts, h.gt_pose, h.start_poses
    world_from_first = gt_pose(h.stamps[0])
    kw = {"source": source, "windows": windows, "shifts": shifts}
    _reference(tmp_path / "reference", start_poses, **kw)
    for name in ("map.bt", "map.ot", "cloud.ply", "keyframes_r1.txt", "keyframes_r2.txt"):
        assert (tum_halves_placed / name).read_bytes() == (tmp_path / "reference" / name).read_bytes(), name
    r1, r2 = (read_tum(tum_halves_placed / f"keyframes_{r}.txt") for r in ROBOTS)
    assert r2.stamps_ns[0] < r1.stamps_ns[-1]  # interleaved
    worst = 0.0
    for traj, shift in ((r1, shifts[0]), (r2, shifts[1])):
        for stamp, p in zip(traj.stamps_ns, traj.positions):
            truth = (invert(world_from_first) @ gt_pose(int(stamp) - round(shift * 1e9)))[:3, 3]
            worst = max(worst, float(np.linalg.norm(p - truth)))
            assert np.linalg.norm(p - truth) < 0.05, (stamp, p, truth)
    print(f"{len(r1.stamps_ns)} + {len(r2.stamps_ns)} keyframes vs ground truth: max {worst * 100:.1f} cm")


@pytest.mark.slow
def test_two_halves_merge_without_start_poses(tmp_path, first300_run, tum_halves_placed):
    """Robot r1 frames 0-99 of first300, r2 frames 100-199, no start poses. The mapper
    places r2 from a place both saw; every keyframe of both lies within 5 cm of the ground truth
    after one rigid alignment of the merged trajectory, and the map agrees with one robot's. (That
    placing happens at defined points of the merge order, so another run gives the same bytes:
    test_relink.py's fleet without start poses, run twice.)"""
    from octolog.kit.metrics import associate, read_tum, umeyama

    h = _tum_halves()
    source, windows, shifts, gt = h.source, h.windows, h.shifts, h.gt
    logs = run_fleet(tmp_path / "merged", [], source=source, windows=windows, shifts=shifts)
    out = tmp_path / "merged"
    stats = json.loads((out / "map_stats.json").read_text())
    assert stats["robots"]["r2"]["merged"] and stats["robots"]["r1"]["merged"], (stats, logs["mapper"])
    est, truth = [], []
    for robot, shift in zip(ROBOTS, shifts):
        traj = read_tum(out / f"keyframes_{robot}.txt")
        assert len(traj.stamps_ns) >= 3, robot
        ie, ig = associate(traj.stamps_ns - round(shift * 1e9), gt.stamps_ns)
        est.append(traj.positions[ie])
        truth.append(gt.positions[ig])
    est_all, truth_all = np.vstack(est), np.vstack(truth)
    R, t, _ = umeyama(est_all, truth_all, with_scale=False)
    err = np.linalg.norm(est_all @ R.T + t - truth_all, axis=1)
    print(f"merged keyframes vs ground truth: max {err.max() * 100:.1f} cm, mean {err.mean() * 100:.1f} cm; "
          f"placed by {stats['merges'][0]['inliers'] if stats['merges'] else 0} inliers")
    assert err.max() < 0.05, err
    # the map: against the same two robots placed by their ground-truth start poses (what the merge
    # should reproduce), and, for the record, against one robot tracking the whole of first300 (on the
    # voxels both maps know; two trackers choose other keyframes: surfaces move by a voxel here and
    # there whatever the merge)
    known = tum_halves_placed
    single = first300_run[0]
    disagree, n_cells = occupied_disagreement(out / "map.bt", known / "map.bt")
    floor, _ = occupied_disagreement(known / "map.bt", single / "map.bt")
    merged = cells(out / "map.bt")
    vs_single, _ = occupied_disagreement(merged, single / "map.bt")
    # the target is <= 2 %; at 5 cm voxels two trackers' maps differ by a voxel along most surfaces
    # (13.5 % even with ground-truth start poses): printed, not asserted (docs/results.md)
    print(f"occupied voxels known to both maps: {n_cells}; merged vs known start poses {disagree:.1%}; "
          f"vs one robot: merged {vs_single:.1%}, known start poses {floor:.1%}")
    # a voxel's tolerance (5 cm, the keyframes' bound): the merged map's surfaces are where one
    # robot's are; the same measure fails a merge 10 cm off along any axis
    near_single, _ = occupied_disagreement(merged, single / "map.bt", tolerance=1)
    off = [occupied_disagreement({tuple(np.add(c, d)): v for c, v in merged.items()}, single / "map.bt", 1)[0]
           for d in ((2, 0, 0), (0, 2, 0), (0, 0, 2))]
    print(f"within one voxel: merged vs one robot {near_single:.2%}; merged shifted 10 cm: "
          + ", ".join(f"{x:.1%}" for x in off))
    assert near_single <= 0.02 < min(off), (near_single, off)
    assert [m["robot"] for m in stats["merges"]] == ["r2"] and stats["merges"][0]["inliers"] >= 60


# --- placing by place: the verification (mapper/fleet/align.py) ------------------------------------------


def test_a_shared_place_aligns_and_another_room_does_not():
    """Two first300 frames 80 apart align to the tracker's relative pose; a different room does not."""
    from octolog.kit.geometry import invert
    from octolog.mapper.fleet.align import align, features
    from octolog.replay.sources import SyntheticSource, open_source
    from octolog.tracker.config import TrackerConfig, for_source
    from octolog.tracker.factory import make_odometry

    src = open_source(f"tum:{tum_first300()}")
    frames = list(src.frames(0, 81))
    odometry = make_odometry(for_source(TrackerConfig(), src))
    poses = [odometry.track(f).world_from_camera for f in frames]
    a, b = features(frames[0]), features(frames[80])
    found = align(a, b)
    assert found is not None and found.inliers >= 60
    rel = invert(poses[0]) @ poses[80]
    assert np.linalg.norm(found.a_from_b[:3, 3] - rel[:3, 3]) < 0.02
    assert align(a, features(next(SyntheticSource(2).frames()))) is None


@pytest.mark.slow
def test_a_robot_that_shares_no_place_stays_out_with_a_map_of_its_own(tmp_path):
    """Robot r1 in the synthetic room, r2 at the TUM desk, no start poses. No merge;
    r2 is reported unmerged with a map of its own; the fused map is r1's alone, byte for byte the
    map `octolog run` makes of r1's frames."""
    n = 20
    out = tmp_path / "fleet"
    run_fleet(out, [], windows=((0, n), (0, n)), shifts=(0.0, 0.0),
              sources=(f"synthetic:{n}", f"tum:{tum_first300()}"))
    stats = json.loads((out / "map_stats.json").read_text())
    assert stats["merges"] == [] and stats["robots"]["r1"]["merged"] and not stats["robots"]["r2"]["merged"]
    assert (out / "r2" / "map.bt").stat().st_size > 0
    single = tmp_path / "single"
    # the fleet's map frame: r1's up, from its replay's camera/gravity (as `octolog run` finds it)
    assert stats["map_frame"]["note"] == "gravity-aligned (the first robot's camera/gravity)"
    up = stats["map_frame"]["up"]
    octolog("run", "--source", f"synthetic:{n}", "--out", str(single), "--quiet", "--rerun", "off",
            "--set", f"mapper.grid_up={up!r}", "--set", "mapper.confirm_within=4")  # a fleet's window: two per robot
    assert (out / "map.bt").read_bytes() == (single / "map.bt").read_bytes()


@pytest.mark.slow
def test_a_robot_killed_mid_run_leaves_the_others_to_finish(tmp_path):
    """Robot r2's tracker and replay are killed once 10 of its 20 frames went out; the mapper
    takes r2 for gone after the peer timeout, keeps what arrived, and finishes r1's map (no start
    poses: r2 is placed from the room both see)."""
    out = tmp_path / "fleet"
    procs, bus = start_router(out)
    try:
        procs["mapper"] = spawn(out / "mapper.log", "map", *bus, "--out", str(out), "--set", 'robots=["r1", "r2"]')
        for robot, (start, end), shift in zip(ROBOTS, ((0, HALF), (HALF, FRAMES)), SHIFT_S):
            ns = ["--namespace", robot]
            procs[f"tracker-{robot}"] = spawn(out / f"tracker-{robot}.log", "track", *bus, *ns)
            procs[f"replay-{robot}"] = spawn(None if robot == "r2" else out / f"replay-{robot}.log", "replay", *bus,
                                             *ns, "--source", f"synthetic:{FRAMES}", "--set", f"start={start}",
                                             "--set", f"end={end}", "--set", f"time_shift_s={shift!r}",
                                             "--set", 'wait_for=["tracker", "mapper"]')
        read_until(procs["replay-r2"], f"10/{FRAMES - HALF} frames")  # its progress line: its frames are flowing
    except BaseException:
        kill_then_finish(procs, (), (), out)
        raise
    kill_then_finish(procs, ("tracker-r2", "replay-r2"), ("replay-r1", "tracker-r1", "mapper"), out)
    stats = json.loads((out / "map_stats.json").read_text())
    assert stats["robots"]["r2"]["lost"] and not stats["robots"]["r1"]["lost"], stats["robots"]
    assert "r2: lost mid-run" in (out / "mapper.log").read_text()
    assert stats["robots"]["r1"]["keyframes"] >= 2 and stats["occupied_voxels"] > 1000


@pytest.mark.parametrize("source", ["synthetic:61", "tum"])
def test_a_photo_of_a_place_is_not_that_place(source):
    """A look-alike: the same image on a flat poster (the frame's colour, its
    depth flattened to a wall at the median distance) matches descriptor for descriptor, but no
    rigid motion takes the room's 3D points onto it: refused, in the room and at the TUM desk."""
    from octolog.mapper.fleet.align import align, features
    from octolog.replay.sources import open_source

    spec = f"tum:{tum_first300()}" if source == "tum" else source
    frames = list(open_source(spec).frames(0, 61))
    for f in (frames[0], frames[30], frames[60]):
        flat = np.where(f.depth > 0, np.median(f.depth[f.depth > 0]), 0).astype(np.uint16)
        assert align(features(f), features(dataclasses.replace(f, depth=flat))) is None
