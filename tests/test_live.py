"""A live session: the simulated D455 (pyrealsense2's software device, paced at its profile's rate)
through tracker and mapper with `octolog run --source d455:software`, and its exact replay."""

from __future__ import annotations

import json

from helpers import octolog

from octolog.kit.mcaplog import summarize

VGA = ("--set", "recorder.color.width=640", "--set", "recorder.color.height=480",
       "--set", "recorder.depth.width=640", "--set", "recorder.depth.height=480")


def test_a_live_session_counts_its_skips_and_its_log_replays_to_the_same_bytes(tmp_path):
    live = tmp_path / "live"
    octolog("run", "--source", "d455:software", "--duration", "3", "--out", str(live), "--quiet", "--rerun", "off",
            *VGA, timeout=300)
    frames = json.loads((live / "summary.json").read_text())["frames"]
    # how many frames keep up is the machine's business (bench/pipeline.py); here: every frame that
    # went out is accounted for, consumed or skipped, and the consumed ones replay exactly
    assert frames["published"] >= 10
    assert frames["consumed"] + frames["skipped"] == frames["published"]
    assert frames["consumed"] >= 3
    # the camera in full (colour, depth, IMU) beside the session log; the frames on the wire are
    # the recorded JPEG colour with PNG depth, not raw
    recording = summarize(live / "recording.mcap")
    assert recording.complete and {"camera/color/image_raw/compressed", "camera/gyro/sample"} <= set(recording.topics)
    log = summarize(live / "session.mcap")
    assert log.topics["camera/rgbd/compressed"].count == frames["published"]
    again = tmp_path / "again"
    octolog("replay", str(live), "--out", str(again), "--quiet", "--rerun", "off", timeout=300)
    for name in ("trajectory.txt", "map.bt"):
        assert (again / name).read_bytes() == (live / name).read_bytes(), name
    replayed = json.loads((again / "summary.json").read_text())["frames"]
    assert replayed == {"published": frames["consumed"], "consumed": frames["consumed"], "skipped": 0}


def test_duration_is_for_live_sources_only(tmp_path):
    proc = octolog("run", "--source", "synthetic:5", "--duration", "3", "--out", str(tmp_path / "o"), check=False)
    assert proc.returncode == 1
    assert "--duration 3.0: only for a live source" in proc.stderr and proc.stderr.count("\n") == 1
