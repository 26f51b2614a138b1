"""Sessions replay deterministically, live ones included: the log says what each stage consumed."""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import pytest
from helpers import octolog, rerun_cli

from octolog.kit.mcaplog import read_wire


FRAMES = 40


@pytest.fixture(scope="module")
def live(tmp_path_factory, octolog_run) -> Path:
    """A live-paced session: frames at 1x sensor rate, a tracker too slow to keep up (skips frames);
    the frames are those of the shared run on the synthetic room."""
    src = octolog_run(f"synthetic:{FRAMES}")[0]
    out = tmp_path_factory.mktemp("live")
    octolog("run", "--source", f"mcap:{src / 'session.mcap'}", "--out", str(out), "--quiet",
            "--set", "replay.rate=1.0", "--set", "tracker.live=true", "--set", "tracker.throttle_ms=70")
    return out


def _payloads(log: Path, topic: str) -> list[bytes]:
    return [m.data for m in read_wire(log, [topic])]


def test_live_tracker_skipped_frames_on_record(live):
    frames = json.loads((live / "summary.json").read_text())["frames"]
    assert frames["published"] == FRAMES
    assert frames["skipped"] > 0 and frames["consumed"] + frames["skipped"] == FRAMES


def test_replaying_tracker_and_mapper_reproduces_the_live_session(live, tmp_path):
    octolog("replay", str(live), "--stages", "tracker,mapper", "--out", str(tmp_path), "--quiet")
    assert (tmp_path / "trajectory.txt").read_bytes() == (live / "trajectory.txt").read_bytes()
    assert (tmp_path / "map.bt").read_bytes() == (live / "map.bt").read_bytes()
    for topic in ("tracker/pose", "tracker/keyframe"):
        assert _payloads(tmp_path / "session.mcap", topic) == _payloads(live / "session.mcap", topic), topic
    replayed = json.loads((tmp_path / "summary.json").read_text())["frames"]
    live_frames = json.loads((live / "summary.json").read_text())["frames"]
    assert replayed == {"published": live_frames["consumed"], "consumed": live_frames["consumed"], "skipped": 0}


def test_from_tracker_rebuilds_the_same_map(live, tmp_path):
    octolog("replay", str(live), "--from", "tracker", "--out", str(tmp_path), "--quiet", "--rerun", "off")
    assert (tmp_path / "map.bt").read_bytes() == (live / "map.bt").read_bytes()
    assert (tmp_path / "cloud.ply").read_bytes() == (live / "cloud.ply").read_bytes()


def test_merged_rrd_holds_every_stage_on_one_timeline(live):
    out = octolog("view", str(live), "--headless").stdout
    merged = live / "rerun" / "session.rrd"
    assert str(merged) in out
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1"}
    stats = subprocess.run([rerun_cli(), "rrd", "stats", str(merged)], capture_output=True, text=True,
                           check=True, env=env, timeout=120).stdout
    entities = set(re.findall(r"^(/\S+): \d+$", stats, re.M))
    assert {"/world/tracker/camera/image", "/world/tracker/keyframe/depth", "/map/cloud"} <= entities
    assert "sensor_time:" in stats
    printed = subprocess.run([rerun_cli(), "rrd", "print", str(merged)], capture_output=True, text=True,
                             check=True, env=env, timeout=120).stdout
    ids = set(re.findall(r'Recording,\s*"octolog",\s*"([0-9a-f-]+)"', printed))
    assert len(ids) == 1  # one recording id: the stages merge into one recording


def test_broken_session_folders_say_what_is_missing(live, tmp_path):
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "config.toml").write_bytes((live / "config.toml").read_bytes())
    proc = octolog("replay", str(tmp_path / "s"), check=False)
    assert proc.returncode == 1 and "missing session.mcap" in proc.stderr and proc.stderr.count("\n") == 1
    data = (live / "session.mcap").read_bytes()
    (tmp_path / "s" / "session.mcap").write_bytes(data[: len(data) * 3 // 4])
    proc = octolog("replay", str(tmp_path / "s"), check=False)
    assert proc.returncode == 1 and "session.mcap: truncated" in proc.stderr and "messages are readable" in proc.stderr
    (tmp_path / "s" / "config.toml").unlink()
    (tmp_path / "s" / "session.mcap").write_bytes(data)
    proc = octolog("replay", str(tmp_path / "s"), check=False)
    assert proc.returncode == 1 and "missing config.toml" in proc.stderr and "octolog run --source mcap:" in proc.stderr
