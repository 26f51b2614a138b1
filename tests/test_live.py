"""A live session: the simulated D455 (pyrealsense2's software device, paced at its profile's rate)
through tracker and mapper with `octolog run --source d455:software`, and its exact replay."""

from __future__ import annotations

import json
import tomllib

import numpy as np
from helpers import octolog

from octolog.kit import metrics
from octolog.kit.gravity import level_on_plane
from octolog.kit.mcaplog import summarize
from octolog.replay.gravity import recorded_up
from octolog.replay.sources import open_source

VGA = ("--set", "recorder.color.width=640", "--set", "recorder.color.height=480",
       "--set", "recorder.depth.width=640", "--set", "recorder.depth.height=480")


def test_a_live_session_counts_its_skips_and_its_log_replays_to_the_same_bytes(tmp_path):
    live = tmp_path / "live"
    # a back end slower than the keyframes come (each job padded to 1 s): the live tracker lets
    # keyframes in without it (at most tracker.live_backend_defer in a row), on record for the replay
    octolog("run", "--source", "d455:software", "--duration", "3", "--out", str(live), "--quiet", "--rerun", "off",
            *VGA, "--set", "tracker.backend_throttle_ms=1000", timeout=300)
    frames = json.loads((live / "summary.json").read_text())["frames"]
    # how many frames keep up is the machine's business (bench/pipeline.py); here: every frame that
    # went out is accounted for, consumed or skipped, and the consumed ones replay exactly
    # (skipped by the tracker, or held back by the camera while the tracker had two frames in hand)
    assert frames["published"] >= 10
    assert frames["consumed"] + frames["skipped"] == frames["camera"]
    assert frames["camera"] - frames["held_back"] == frames["published"]
    assert frames["consumed"] >= 3
    # the camera in full (colour, depth, IMU) beside the session log; the frames on the wire are
    # the recorded JPEG colour with PNG depth, not raw
    recording = summarize(live / "recording.mcap")
    assert recording.complete and {"camera/color/image_raw/compressed", "camera/gyro/sample"} <= set(recording.topics)
    log = summarize(live / "session.mcap")
    assert log.topics["camera/rgbd/compressed"].count == frames["published"]
    assert log.topics["tracker/backend_deferred"].count >= 2
    # the map frame from the camera's accelerometer on the bus (the mapper's LiveUp), as the
    # file-based reading finds it at the first keyframe (within a degree: a live bus may drop IMU
    # samples the file keeps, and the software device's accelerometer is noisy)
    summary = json.loads((live / "summary.json").read_text())
    assert summary["map_frame"].startswith("gravity-aligned (the live camera's accelerometer")
    up = np.array(tomllib.loads((live / "config.toml").read_text())["mapper"]["grid_up"])
    first = int(metrics.read_tum(live / "trajectory.txt").stamps_ns[0])
    from_file = recorded_up(live / "recording.mcap", first, "camera_color_optical_frame")
    if "levelled" in summary["map_frame"]:  # on the first keyframe's floor, as a file's frame 0 is
        frame = next(f for f in open_source(f"mcap:{live / 'recording.mcap'}").frames() if f.stamp_ns == first)
        from_file, levelled = level_on_plane(from_file, frame)
        assert levelled
    assert np.degrees(np.arccos(np.clip(up @ from_file, -1, 1))) < 1.0
    assert log.topics["tf_static"].count == 2  # the camera's tree (camera_link ...) and map -> world
    again = tmp_path / "again"
    octolog("replay", str(live), "--out", str(again), "--quiet", "--rerun", "off", timeout=300)
    for name in ("trajectory.txt", "map.bt", "map.pgm", "map.yaml"):
        assert (again / name).read_bytes() == (live / name).read_bytes(), name
    replayed = json.loads((again / "summary.json").read_text())["frames"]
    assert replayed == {"published": frames["consumed"], "consumed": frames["consumed"], "skipped": 0}


def test_duration_is_for_live_sources_only(tmp_path):
    proc = octolog("run", "--source", "synthetic:5", "--duration", "3", "--out", str(tmp_path / "o"), check=False)
    assert proc.returncode == 1
    assert "--duration 3.0: only for a live source" in proc.stderr and proc.stderr.count("\n") == 1
