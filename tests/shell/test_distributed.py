"""Stages on separate hosts: network namespaces joined by veth pairs, a router on its own host.

Host A runs the replay, B the tracker, C the mapper, D the Zenoh router (`octolog router`); every
stage is a Zenoh client of the router. Needs root and `ip netns`; skips with the reason otherwise.
Addresses come from 198.18.0.0/15 (reserved for network tests) on the namespaces this test makes.
Link cuts and a killed mapper must end with the single-host result; the last test kills the mapper
of a plain `octolog run` on this host (no namespaces needed).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT, kill_then_finish, octolog, read_until, stop_all

from octolog.kit.mcaplog import summarize

FRAMES = 40
HOSTS = ("a", "b", "c")  # replay, tracker, mapper; "d" is the router


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True)


@pytest.fixture
def hosts():
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need root and iproute2")
    tag = f"o{os.getpid() % 100000}"
    names = {h: f"{tag}{h}" for h in (*HOSTS, "d")}
    probe = _ip("netns", "add", names["d"])
    if probe.returncode != 0:
        pytest.skip(f"ip netns not allowed here: {probe.stderr.strip()}")
    try:
        for h in HOSTS:
            _ip("netns", "add", names[h])
        for ns in names.values():
            _ip("-n", ns, "link", "set", "lo", "up")
        addr = {}
        for k, h in enumerate(HOSTS, 1):
            dev_h, dev_d = f"{tag}{h}0", f"{tag}{h}1"
            _ip("link", "add", dev_h, "type", "veth", "peer", "name", dev_d)
            _ip("link", "set", dev_h, "netns", names[h])
            _ip("link", "set", dev_d, "netns", names["d"])
            _ip("-n", names[h], "addr", "add", f"198.18.{k}.1/24", "dev", dev_h)
            _ip("-n", names["d"], "addr", "add", f"198.18.{k}.2/24", "dev", dev_d)
            _ip("-n", names[h], "link", "set", dev_h, "up")
            _ip("-n", names["d"], "link", "set", dev_d, "up")
            addr[h] = (f"198.18.{k}.2", dev_d)  # how host h reaches the router, and the router's end
        yield names, addr
    finally:
        for ns in names.values():
            _ip("netns", "del", ns)


def _start(ns: str, *args: str, log: Path | None) -> subprocess.Popen:
    """A stage in a namespace; output to `log`, or to a pipe (text) when `log` is None."""
    # OCTOLOG_STATUS_TTY: the replay's progress redrawn at every update, as on a terminal, so a test
    # waiting for "N/FRAMES frames" sees every count (off a terminal a line comes every few seconds)
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1", "PYTHONUNBUFFERED": "1", "OCTOLOG_STATUS_TTY": "1"}
    return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "octolog", *args], cwd=ROOT, env=env,
                            stdout=open(log, "w") if log else subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=log is None)


def _distributed_run(names: dict, addr: dict, out: Path, *, cut_s: float = 0.0, kill_mapper: bool = False) -> None:
    """The four-host pipeline; optionally the mapper's link cut for `cut_s` once 10 frames went
    out, or the mapper SIGKILLed once 20 frames went out and started again with the same args."""
    out.mkdir(parents=True)
    procs = {"router": _start(names["d"], "router", "--listen", "tcp/0.0.0.0:7447", log=out / "router.log")}
    try:
        def client(h: str) -> list[str]:
            return ["--mode", "client", "--connect", f"tcp/{addr[h][0]}:7447", "--no-multicast"]

        mapper = ["map", *client("c"), "--out", str(out)]
        procs["mapper"] = _start(names["c"], *mapper, log=out / "mapper.log")
        procs["tracker"] = _start(names["b"], "track", *client("b"), "--trajectory", str(out / "trajectory.txt"),
                                  log=out / "tracker.log")
        procs["replay"] = _start(names["a"], "replay", *client("a"), "--source", f"synthetic:{FRAMES}",
                                 "--set", 'wait_for=["tracker", "mapper"]', log=None)
        seen = ""

        def wait_output(text: str) -> None:
            # the replay's progress line says frames are flowing (blocking reads: the event is the output)
            nonlocal seen
            while text not in seen:
                ch = procs["replay"].stdout.read(1)
                assert ch, seen
                seen += ch

        wait_output(f"10/{FRAMES} frames")
        if cut_s:
            _ip("-n", names["d"], "link", "set", addr["c"][1], "down")
            time.sleep(cut_s)  # the outage itself, not a synchronization
            _ip("-n", names["d"], "link", "set", addr["c"][1], "up")
        if kill_mapper:
            wait_output(f"20/{FRAMES} frames")
            procs["mapper"].kill()
            assert procs["mapper"].wait(timeout=30) < 0
            procs["mapper"] = _start(names["c"], *mapper, log=out / "mapper-restarted.log")
        (out / "replay.log").write_text(seen + procs["replay"].communicate(timeout=300)[0])
        for stage in ("replay", "tracker", "mapper"):
            log = out / ("mapper-restarted.log" if stage == "mapper" and kill_mapper else f"{stage}.log")
            assert procs[stage].wait(timeout=300) == 0, log.read_text()
    finally:
        stop_all(procs)


@pytest.fixture(scope="module")
def single_host(octolog_run) -> Path:
    return octolog_run(f"synthetic:{FRAMES}")[0]


@pytest.mark.root
@pytest.mark.slow
def test_stages_on_four_hosts_match_one_host(hosts, single_host, tmp_path):
    names, addr = hosts
    _distributed_run(names, addr, tmp_path / "multi")
    for name in ("trajectory.txt", "map.bt"):
        assert (tmp_path / "multi" / name).read_bytes() == (single_host / name).read_bytes(), name
    # the mapper on its own host built `map` on the replay's up (octolog run resolved the same up itself)
    stats = json.loads((tmp_path / "multi" / "map_stats.json").read_text())
    assert stats["map_frame"]["note"] == "gravity-aligned (the replay's camera/gravity)"


def _same_result(run: Path, single: Path) -> None:
    for name in ("trajectory.txt", "map.bt"):
        assert (run / name).read_bytes() == (single / name).read_bytes(), name
    # every keyframe integrated exactly once: a duplicate or a gap would change the count
    stats = json.loads((run / "map_stats.json").read_text())
    # a mapper on its own took up from the replay's camera/gravity and says so (octolog run, restarting
    # its mapper, gives up in the config); the same up either way: map_from_world is in the stats
    found = stats.pop("map_frame", None)
    assert found is None or found["note"] == "gravity-aligned (the replay's camera/gravity)", found
    assert stats == json.loads((single / "map_stats.json").read_text())


# 6 s: the session survives (Zenoh's lease is 10 s) and only the data in flight is at stake;
# 12 s: the lease expires, the session closes and the mapper's client reconnects
@pytest.mark.root
@pytest.mark.slow
@pytest.mark.parametrize("cut_s", [6.0, 12.0], ids=["within-lease", "session-closed"])
def test_mapper_link_cut_and_restored_loses_nothing(hosts, single_host, tmp_path, cut_s):
    names, addr = hosts
    _distributed_run(names, addr, tmp_path / "cut", cut_s=cut_s)
    _same_result(tmp_path / "cut", single_host)


@pytest.mark.root
@pytest.mark.slow
def test_mapper_killed_and_restarted_ends_with_the_same_map(hosts, single_host, tmp_path):
    names, addr = hosts
    _distributed_run(names, addr, tmp_path / "restart", kill_mapper=True)
    _same_result(tmp_path / "restart", single_host)


def _pid(*words: str) -> int | None:
    """The process whose command line holds all these words (a child of `octolog run`)."""
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                argv = (d / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if all(w.encode() in argv for w in words):
                return int(d.name)
    return None


@pytest.mark.slow
def test_run_starts_a_killed_mapper_again(single_host, tmp_path):
    """`octolog run` on one host: the mapper SIGKILLed mid-run is started again, same map."""
    out = tmp_path / "run"
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1", "OCTOLOG_STATUS_TTY": "1"}  # every count shown (see _start)
    run = subprocess.Popen([sys.executable, "-m", "octolog", "run", "--source", f"synthetic:{FRAMES}", "--out",
                            str(out), "--rerun", "off"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        seen = ""
        while f"20/{FRAMES} frames" not in seen:  # the replay's progress: the event is the output
            ch = run.stderr.read(1)
            assert ch, seen
            seen += ch
        mapper = _pid("map", str(out))
        assert mapper is not None
        os.kill(mapper, signal.SIGKILL)
        stdout, stderr = run.communicate(timeout=300)
        assert run.returncode == 0, seen + stderr + (out / "logs" / "mapper.log").read_text()
    finally:
        if run.poll() is None:
            run.terminate()
            run.wait(timeout=30)
    assert "killed by signal 9; starting it again" in (out / "logs" / "mapper.log").read_text()
    _same_result(out, single_host)


def _link_bytes(ns: str, dev: str) -> int:
    """Bytes received on `dev` (the router's end of a host's link) so far."""
    proc = subprocess.run(["ip", "netns", "exec", ns, "cat", f"/sys/class/net/{dev}/statistics/rx_bytes"],
                          capture_output=True, text=True, check=True)
    return int(proc.stdout)


@pytest.mark.root
@pytest.mark.slow
def test_deployment_doc_robot_and_server_give_the_run_bytes(hosts, tmp_path, octolog_run):
    """docs/deployment.md as written, with TLS: the server (router, mapper, log) on one host, robot1
    (its own router, replay + `octolog track`, the first 40 frames of TUM fr1 first300) on another.
    No rolling-shutter setting anywhere: the readout comes with the frames (`camera/rgbd/properties`),
    so the trajectory and map.bt are those of `octolog run` on this host on the same frames (the
    shared run, tests/kit/test_wire.py reads it too). The camera frames stay on the robot (the server
    logs `--no-frames`); the server's log folder replays to the same map and holds the robot's
    trajectory."""
    from helpers import tum_first300

    from octolog.kit.tum import open_tum

    if shutil.which("openssl") is None:
        pytest.skip("openssl not installed")
    folder = tum_first300()
    source, frames = f"tum:{folder}", 40
    names, addr = hosts
    robot_ip, link = addr["a"]  # how the robot reaches the server; the server's end of that link
    examples = ROOT / "docs" / "examples"
    subprocess.run(["bash", str(examples / "make-certs.sh"), str(tmp_path / "certs"), robot_ip, "127.0.0.1"],
                   check=True, capture_output=True)

    def config(example: str, node: str) -> str:
        text = (examples / example).read_text().replace('"certs/', f'"{tmp_path}/certs/')
        # two namespaces of one machine share /dev/shm: Zenoh would pass large payloads through shared
        # memory and the link would carry only their descriptors. Off, the link carries what a real one would.
        text = text.replace("transport: {", "transport: { shared_memory: { enabled: false },", 1)
        path = tmp_path / f"{node}.json5"
        path.write_text(text.replace(f"{tmp_path}/certs/robot1.", f"{tmp_path}/certs/{node}."))
        return str(path)

    router_cfg, server_cfg = config("zenoh-tls-router.json5", "router"), config("zenoh-tls-client.json5", "server")
    robot_router_cfg = config("zenoh-tls-robot-router.json5", "robot1")
    local_cfg = tmp_path / "local.json5"
    local_cfg.write_text("{ transport: { shared_memory: { enabled: false } } }")
    out = tmp_path / "deployed"
    out.mkdir()
    server = ["--mode", "client", "--connect", "tls/127.0.0.1:7447", "--zenoh-config", server_cfg,
              "--namespace", "robot1"]
    robot = ["--mode", "client", "--connect", "tcp/127.0.0.1:7447", "--zenoh-config", str(local_cfg), "--no-multicast",
             "--namespace", "robot1"]
    procs = {"router": _start(names["d"], "router", "--zenoh-config", router_cfg, "--listen", "tls/0.0.0.0:7447",
                              log=out / "router.log"),
             "robot-router": _start(names["a"], "router", "--zenoh-config", robot_router_cfg, "--listen",
                                    "tcp/127.0.0.1:7447", "--connect", f"tls/{robot_ip}:7447",
                                    log=out / "robot-router.log")}
    try:
        procs["mapper"] = _start(names["d"], "map", *server, "--out", str(out / "maps" / "robot1"), log=out / "map.log")
        procs["log"] = _start(names["d"], "log", *server, "--no-frames", "--out", str(out / "logs" / "robot1"),
                              log=out / "log.log")
        procs["tracker"] = _start(names["a"], "track", *robot, "--trajectory", str(out / "traj.txt"), "--set",
                                  "wire_compression=jpeg:90", log=out / "tracker.log")
        before = _link_bytes(names["d"], link)
        procs["replay"] = _start(names["a"], "replay", *robot, "--source", source, "--set", f"end={frames}",
                                 "--set", 'wait_for=["tracker", "mapper"]', "--quiet", log=out / "replay.log")
        for stage in ("replay", "tracker", "mapper", "log"):
            log = out / f"{'map' if stage == 'mapper' else stage}.log"
            assert procs[stage].wait(timeout=600) == 0, log.read_text()
        crossed = _link_bytes(names["d"], link) - before
    finally:
        stop_all(procs)
    single = octolog_run(source, "--set", f"replay.end={frames}")[0]
    assert "warning" not in (out / "tracker.log").read_text()
    assert (out / "traj.txt").read_bytes() == (single / "trajectory.txt").read_bytes()
    # map.bt: occupancy comes from depth (lossless PNG either way); the JPEG colour only tints the cloud
    assert (out / "maps" / "robot1" / "map.bt").read_bytes() == (single / "map.bt").read_bytes()
    # the frames (the PNG files, sent as they are) stayed on the robot: what crossed is keyframes
    # (one in ten frames, JPEG colour), poses and the protocol
    sent = [f for _, rgb, _, depth in open_tum(folder).pairs[:frames] for f in (rgb, depth)]
    pngs = sum((folder / f).stat().st_size for f in sent)
    print(f"robot -> server: {crossed / 1e6:.1f} MB for {pngs / 1e6:.1f} MB of frames")
    assert crossed < 0.25 * pngs, (crossed, pngs)
    # the server's log folder: the robot's trajectory, and a session that replays to the same map
    served = out / "logs" / "robot1"
    assert (served / "trajectory.txt").read_bytes() == (out / "traj.txt").read_bytes()
    assert "camera/rgbd/compressed" not in summarize(served / "session.mcap").topics
    assert "session.mcap" in octolog("info", str(served)).stdout
    whole = octolog("replay", str(served), "--out", str(tmp_path / "whole"), "--quiet", check=False)
    assert whole.returncode == 1 and "a log without camera frames" in whole.stderr and "--stages mapper" in whole.stderr
    again = tmp_path / "again"
    octolog("replay", str(served), "--from", "tracker", "--out", str(again), "--quiet", "--rerun", "off")
    assert (again / "map.bt").read_bytes() == (out / "maps" / "robot1" / "map.bt").read_bytes()


@pytest.mark.root
@pytest.mark.slow
def test_three_robots_on_three_hosts_merge_without_start_poses(hosts, tmp_path):
    """Three robots, each a replay + tracker on its own namespace host, walk
    three stretches of the synthetic room (frames 0-29, 30-59, 60-89, shifted to run at once); the
    router and the mapper on a fourth; no start poses. r3 is killed once 10 of its frames went out.
    r1 and r2 finish; r2 is placed from a place r1 saw; each placed robot's keyframes follow the
    ground truth in the common world (r1's first camera)."""
    from octolog.kit.geometry import invert
    from octolog.kit.metrics import read_tum
    from octolog.replay.synthetic import SyntheticScene

    names, addr = hosts
    out = tmp_path / "fleet"
    out.mkdir()
    robots = {"r1": ("a", 0, 0.0), "r2": ("b", 30, -1.0 + 0.017), "r3": ("c", 60, -2.0 + 0.034)}
    procs = {"router": _start(names["d"], "router", "--listen", "tcp/0.0.0.0:7447", log=out / "router.log")}
    try:
        procs["mapper"] = _start(names["d"], "map", "--mode", "client", "--connect", "tcp/127.0.0.1:7447",
                                 "--no-multicast", "--out", str(out), "--set", 'robots=["r1", "r2", "r3"]',
                                 log=out / "mapper.log")
        for robot, (host, start, shift) in robots.items():
            bus = ["--mode", "client", "--connect", f"tcp/{addr[host][0]}:7447", "--no-multicast",
                   "--namespace", robot]
            procs[f"tracker-{robot}"] = _start(names[host], "track", *bus, log=out / f"tracker-{robot}.log")
            procs[f"replay-{robot}"] = _start(names[host], "replay", *bus, "--source", "synthetic:90", "--set",
                                              f"start={start}", "--set", f"end={start + 30}", "--set",
                                              f"time_shift_s={shift!r}", "--set", 'wait_for=["tracker", "mapper"]',
                                              log=None if robot == "r3" else out / f"replay-{robot}.log")
        read_until(procs["replay-r3"], "10/30 frames")  # its progress line: its frames are flowing
    except BaseException:
        kill_then_finish(procs, (), (), out)
        raise
    kill_then_finish(procs, ("tracker-r3", "replay-r3"), ("replay-r1", "replay-r2", "tracker-r1", "tracker-r2", "mapper"), out)
    stats = json.loads((out / "map_stats.json").read_text())
    assert stats["robots"]["r3"]["lost"] and not stats["robots"]["r1"]["lost"] and not stats["robots"]["r2"]["lost"]
    assert "r2" in {m["robot"] for m in stats["merges"]}, (stats, (out / "mapper.log").read_text())
    scene = SyntheticScene(n_frames=90)
    first = invert(scene.pose(0))  # the common world: r1's first camera
    for robot, (_, start, shift) in robots.items():
        if not stats["robots"][robot]["merged"] or not stats["robots"][robot]["keyframes"]:
            continue
        traj = read_tum(out / f"keyframes_{robot}.txt")
        index = {scene.stamp_ns(i) + round(shift * 1e9): i for i in range(start, start + 30)}
        errors = [float(np.linalg.norm(p - (first @ scene.pose(index[int(stamp)]))[:3, 3]))
                  for stamp, p in zip(traj.stamps_ns, traj.positions, strict=True)]
        print(f"{robot}: {len(errors)} keyframes, ATE max {max(errors) * 100:.2f} cm")
        assert max(errors) < 0.03, (robot, errors)


# Waits on one host for a mapper shard's first map update (its `mapper/update`, published per
# keyframe in its own namespace) and says so: the event a test kills the shard on.
_FIRST_UPDATE = """
import sys
from octolog.kit.bus import Bus, BusConfig
from octolog.schemas.topics import MAP_UPDATE
cfg = BusConfig(mode="client", connect=(sys.argv[1],), multicast_scouting=False, namespace=sys.argv[2])
with Bus(cfg, "probe") as bus:
    bus.start([MAP_UPDATE])
    print("listening", flush=True)
    while bus.receive(timeout_s=60.0) is None:
        pass
    print("updated", flush=True)
"""


def _sharded_run(names: dict, addr: dict, log: Path, out: Path, shards: tuple[str, ...], *, whole: bool,
                 kill: str = "", follow: str = "map/s1") -> dict[str, int]:
    """Router on host d; mapper shard K of 2 on host a (K=1) or b (K=2), each in namespace map/sK,
    shard 2 following shard 1's placement (`follow`: its namespace, or its journal file), and with
    `whole` one unsharded mapper on d (namespace map/all); two robots' keyframe streams replayed on
    host c from a session log, r2 from frame 4 on, no start poses. With `kill`, that shard is
    SIGKILLed at its first map update. The processes' exit codes."""
    out.mkdir(parents=True, exist_ok=True)
    procs = {"router": _start(names["d"], "router", "--listen", "tcp/0.0.0.0:7447", log=out / "router.log")}
    codes = {}
    try:
        def bus(h: str) -> list[str]:
            where = f"tcp/{addr[h][0]}:7447" if h != "d" else "tcp/127.0.0.1:7447"
            return ["--mode", "client", "--connect", where, "--no-multicast"]

        fleet = ["--rerun", "off", "--set", 'robots=["r1", "r2"]', "--set", "tile_m=2.0"]
        if kill:
            k = kill.split("/")[0]
            procs["probe"] = subprocess.Popen(
                ["ip", "netns", "exec", names["d"], sys.executable, "-c", _FIRST_UPDATE, "tcp/127.0.0.1:7447",
                 f"map/s{k}"], cwd=ROOT, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
            read_until(procs["probe"], "listening")
        waits = []
        for shard in shards:
            k = shard.split("/")[0]
            procs[f"mapper-{k}"] = _start(names["a" if k == "1" else "b"], "map", *bus("a" if k == "1" else "b"),
                                          "--namespace", f"map/s{k}", "--out", str(out / f"s{k}"), *fleet,
                                          "--set", f"shard={shard}", *(["--set", f"follow={follow}"] if k == "2" else []),
                                          log=out / f"mapper-{k}.log")
            waits.append(f"mapper-{k}")
        if whole:
            procs["mapper"] = _start(names["d"], "map", *bus("d"), "--namespace", "map/all", "--out",
                                     str(out / "all"), *fleet, log=out / "mapper.log")
            waits.append("mapper")
        for robot, start in (("r1", 0), ("r2", 4)):
            procs[robot] = _start(names["c"], "replay", *bus("c"), "--namespace", robot, "--quiet", "--source",
                                  f"mcap:{log}", "--set", "play=tracker", "--set", f"start={start}",
                                  "--set", f"wait_for={json.dumps(waits)}", log=out / f"{robot}.log")
        if kill:
            read_until(procs["probe"], "updated")
            procs[f"mapper-{kill.split('/')[0]}"].kill()
        for name, p in procs.items():
            if name not in ("router", "probe"):
                codes[name] = p.wait(timeout=300)
    finally:
        stop_all(procs)
    return codes


@pytest.mark.root
@pytest.mark.slow
def test_map_shards_on_two_hosts_stitch_into_one_mappers_map(hosts, single_host, tmp_path):
    """docs/deployment.md's sharded layout: two robots (keyframe streams replayed on host c), the
    map in 2 m tiles over two mapper shards on hosts a and b, shard 1 placing the robots and shard 2
    following its journal, and one whole mapper on d for reference, all at once, no start poses.
    `octolog stitch` of the two shards gives the whole mapper's map files byte for byte. Then shard 2
    is killed at its first map update: the robots and shard 1 finish, the stitch writes shard 1's
    tiles and names shard 2 in one line (exit 3); shard 2 run again alone on the same log, following
    shard 1's journal file, fills the map with the whole mapper's bytes. Last, the placing shard is
    killed: the follower says in one line that it cannot go on, and writes no shard."""
    names, addr = hosts
    log = single_host / "session.mcap"
    first = tmp_path / "first"
    codes = _sharded_run(names, addr, log, first, ("1/2", "2/2"), whole=True)
    assert set(codes.values()) == {0}, codes
    stitched = octolog("stitch", str(first / "s1"), str(first / "s2"), "--out", str(first / "stitched"), check=False)
    assert stitched.returncode == 0, stitched.stdout + stitched.stderr
    stats = json.loads((first / "all" / "map_stats.json").read_text())
    assert "r2" in {m["robot"] for m in stats["merges"]}, stats  # placed by a shared place, in each mapper
    for name in ("map.bt", "map.ot", "cloud.ply", "map.pgm"):
        assert (first / "stitched" / name).read_bytes() == (first / "all" / name).read_bytes(), name
    for k in ("1", "2"):
        assert json.loads((first / f"s{k}" / "map_stats.json").read_text())["occupied_voxels"] > 0

    second = tmp_path / "second"
    codes = _sharded_run(names, addr, log, second, ("1/2", "2/2"), whole=False, kill="2/2")
    assert codes["mapper-2"] < 0 and codes["mapper-1"] == codes["r1"] == codes["r2"] == 0, codes
    assert not (second / "s2" / "shard.npz").exists()
    partial = octolog("stitch", str(second / "s1"), str(second / "s2"), "--out", str(second / "partial"), check=False)
    assert partial.returncode == 3, partial.stdout + partial.stderr
    assert [line for line in partial.stdout.splitlines() if "shard 2/2 missing" in line], partial.stdout
    assert (second / "partial" / "map.bt").read_bytes() == (first / "s1" / "map.bt").read_bytes()
    codes = _sharded_run(names, addr, log, second / "again", ("2/2",), whole=False,
                         follow=f"journal:{second / 's1'}")
    assert set(codes.values()) == {0}, codes
    filled = octolog("stitch", str(second / "s1"), str(second / "again" / "s2"), "--out", str(second / "filled"),
                     check=False)
    assert filled.returncode == 0, filled.stdout + filled.stderr
    for name in ("map.bt", "map.ot", "cloud.ply", "map.pgm"):
        assert (second / "filled" / name).read_bytes() == (first / "all" / name).read_bytes(), name

    third = tmp_path / "third"
    codes = _sharded_run(names, addr, log, third, ("1/2", "2/2"), whole=False, kill="1/2")
    assert codes["mapper-1"] < 0 and codes["mapper-2"] > 0, codes
    said = (third / "mapper-2.log").read_text()
    assert [line for line in said.splitlines() if "the placing mapper in map/s1 is gone" in line], said
    assert not (third / "s2" / "shard.npz").exists()
