"""A live session: the simulated D455 (pyrealsense2's software device, paced at its profile's rate)
through tracker and mapper with `octolog run --source d455:software`, and its exact replay; the
recorder holding back the frames a live tracker would skip."""

from __future__ import annotations

import dataclasses
import json
import threading
import tomllib

import numpy as np
import pytest
from helpers import free_port, octolog
from helpers.recordings import SOFTWARE, record_software

from octolog.kit import metrics
from octolog.kit.up_vector import level_on_plane
from octolog.kit.mcaplog import summarize
from octolog.replay.source_gravity import recorded_up
from octolog.replay.sources import open_source
from octolog.schemas import codec
from octolog.schemas import topics as T
from octolog.shell.run import skipped_line

VGA = ("--set", "recorder.color.width=640", "--set", "recorder.color.height=480",
       "--set", "recorder.depth.width=640", "--set", "recorder.depth.height=480")


@pytest.mark.slow
def test_a_live_session_counts_its_skips_and_its_log_replays_to_the_same_bytes(tmp_path):
    live = tmp_path / "live"
    # a back end slower than the keyframes come (each job padded to 1 s): the live tracker lets
    # keyframes in without it (at most tracker.live_backend_defer in a row), on record for the replay
    said = octolog("run", "--source", "d455:software", "--duration", "3", "--out", str(live), "--quiet",
                   "--rerun", "off", *VGA, "--set", "tracker.backend_throttle_ms=1000", timeout=300).stdout
    frames = json.loads((live / "summary.json").read_text())["frames"]
    # the summary says how much of the camera's stream the tracker kept up with, when not all of it
    assert (skipped_line(frames) in said) == (frames["skipped"] > 0)
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
    # samples the file keeps, and the software device's accelerometer is noisy); when the tracker
    # came to trust its IMU within the run (how many frames it tracked is the machine's business),
    # its estimate replaced that reading: gravity and the accelerometer's bias together, a few
    # degrees from a single mean at most
    summary = json.loads((live / "summary.json").read_text())
    from_accel = summary["map_frame"].startswith("gravity-aligned (the live camera's accelerometer")
    assert from_accel or summary["map_frame"].startswith("gravity-aligned (the tracker's IMU estimate")
    up = np.array(tomllib.loads((live / "config.toml").read_text())["mapper"]["grid_up"])
    first = int(metrics.read_tum(live / "trajectory.txt").stamps_ns[0])
    from_file = recorded_up(live / "recording.mcap", first, "camera_color_optical_frame")
    if "levelled" in summary["map_frame"]:  # on the first keyframe's floor, as a file's frame 0 is
        frame = next(f for f in open_source(f"mcap:{live / 'recording.mcap'}").frames() if f.stamp_ns == first)
        from_file, levelled = level_on_plane(from_file, frame)
        assert levelled
    assert np.degrees(np.arccos(np.clip(up @ from_file, -1, 1))) < (1.0 if from_accel else 5.0)
    # the camera's tree (camera_link ...) and map -> world, announced again at each of the tracker's estimates
    assert log.topics["tf_static"].count == 2 if from_accel else log.topics["tf_static"].count > 2
    # the camera's IMU reached the tracker over the bus, and is on record for the replay below
    assert summary["imu"]["samples"] > 0 and log.topics["camera/gyro/sample"].count > 0
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


@pytest.mark.parametrize("lag_ms", [0.0, 100.0])
def test_publish_window_holds_back_what_the_tracker_has_no_hand_for(tmp_path, lag_ms):
    """With recorder.publish_window = 1 and a consumer that answers no frame (no tracker/status),
    exactly one frame goes out; every other one is recorded, not published, and counted. With
    recorder.publish_lag_ms, the frames within that lag of the unanswered one go out too (a live
    tracker tracks such a burst in order), and none later."""
    from octolog.kit.bus import Bus, BusConfig

    ep = f"tcp/127.0.0.1:{free_port()}"
    sub_cfg = BusConfig(listen=(ep,), multicast_scouting=False, namespace="win")
    pub_cfg = BusConfig(connect=(ep,), multicast_scouting=False, namespace="win")
    frames: list[bytes] = []
    end = None
    with Bus(sub_cfg, "tracker", inbox_size=64) as sub:
        sub.start([T.RGBD_COMPRESSED, T.RGBD_END])
        cfg = dataclasses.replace(SOFTWARE, wait_for=("tracker",), wait_timeout_s=30.0, publish_window=1,
                                  publish_lag_ms=lag_ms)
        result: dict = {}
        t = threading.Thread(target=lambda: result.update(res=record_software(tmp_path, cfg, frames=20, bus_cfg=pub_cfg)[1]))
        t.start()
        while end is None:
            r = sub.receive(30.0)
            assert r is not None, "no end message"
            if r.topic is T.RGBD_END:
                end = codec.decode(r.payload, T.RGBD_END.msgtype)
            else:
                frames.append(r.payload)
    t.join(60)
    res = result["res"]
    stamps = [codec.stamp_ns(codec.decode(f, T.RGBD_COMPRESSED.msgtype).header) for f in frames]
    assert int(end.count) == len(frames)
    if lag_ms:  # the first frame and those within the lag after it (a slow sink may drop one, counted)
        fps = cfg.color.fps
        window = {stamps[0] + n * 10**9 // fps for n in range(fps) if n * 10**9 // fps <= lag_ms * 1e6}
        assert len(frames) >= 2 and set(stamps) <= window, (stamps, window)
    else:
        assert len(frames) == 1
    assert res.held_back + res.streams["color"].live_drops == 20 - len(frames)
    assert res.streams["color"].frames == 20  # the file has them all
