"""Per-topic compression on the wire: JPEG/PNG colour and PNG/zstd depth, chosen in the producers' config.

Lossless settings must change nothing downstream; lossy JPEG changes the results but stays
deterministic (the same frames give the same bytes, run after run), and a session log recorded with
it replays to the same trajectory.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import octolog, tum_first300
from helpers.recordings import make_tum

from octolog.kit.errors import ConfigError, InputError
from octolog.kit.mcaplog import read_messages, read_wire
from octolog.kit.tum import open_tum
from octolog.replay.sources import SyntheticSource
from octolog.schemas import codec, imagecodec, rgbdmsgs, sensormsgs, topics, wirecompression

N_FRAMES = 30


@pytest.fixture(scope="module")
def frame():
    return next(SyntheticSource(2).frames())


@pytest.mark.parametrize("spec", ["png", "png:6,png", "jpeg:90", "jpeg:50,png", "png,zstd", "jpeg:90,zstd"])
def test_round_trip_keeps_depth_exact_and_colour_close(frame, spec):
    wire = wirecompression.parse_wire_compression(spec)
    data = codec.encode(rgbdmsgs.compressed_rgbd_msg(frame, wire), topics.RGBD_COMPRESSED.msgtype)
    assert data == codec.encode(rgbdmsgs.compressed_rgbd_msg(frame, wire), topics.RGBD_COMPRESSED.msgtype)
    back = rgbdmsgs.rgbd_from_msg(codec.decode(data, topics.RGBD_COMPRESSED.msgtype))
    assert back.depth.dtype == np.uint16 and np.array_equal(back.depth, frame.depth)
    assert back.intrinsics == frame.intrinsics and back.stamp_ns == frame.stamp_ns and back.seq == frame.seq
    err = np.abs(back.rgb.astype(int) - frame.rgb.astype(int))
    if spec.startswith("png"):
        assert err.max() == 0
    else:
        assert 0 < err.mean() < 12  # the synthetic texture is high-frequency: JPEG q90 is off by ~5 levels
    raw = len(codec.encode(rgbdmsgs.rgbd_msg(frame), topics.RGBD.msgtype))
    assert len(data) < raw


def test_keyframe_round_trip(frame):
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 3.0)
    wire = wirecompression.parse_wire_compression("jpeg:80")
    data = codec.encode(rgbdmsgs.compressed_keyframe_msg(4, T, frame, wire), topics.KEYFRAME_COMPRESSED.msgtype)
    kf_id, T2, back = rgbdmsgs.keyframe_from_msg(codec.decode(data, topics.KEYFRAME_COMPRESSED.msgtype))
    assert kf_id == 4 and np.allclose(T2, T) and np.array_equal(back.depth, frame.depth)


@pytest.mark.parametrize(("spec", "message"), [
    ("jpeg,jpeg", "depth can be png or zstd"),
    ("jpeg:0", "want raw, or jpeg"),
    ("png:x", "not an integer"),
    ("webp", "want raw, or jpeg"),
])
def test_bad_specs_are_config_errors(spec, message):
    with pytest.raises(ConfigError, match=message):
        wirecompression.parse_wire_compression(spec)


def test_bad_spec_on_the_command_line_is_one_line(tmp_path):
    proc = octolog("run", "--source", "synthetic:4", "--out", str(tmp_path), "--set",
                   "replay.wire_compression=jpeg,jpeg", check=False, timeout=120)
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1
    assert "replay.wire_compression: wire compression 'jpeg,jpeg': depth can be png or zstd" in proc.stderr


def test_garbled_compressed_image_is_an_input_error(frame):
    msg = rgbdmsgs.compressed_rgbd_msg(frame, wirecompression.parse_wire_compression("png"))
    msg.depth.data = msg.depth.data[:100]
    with pytest.raises(InputError, match="cannot decode"):
        rgbdmsgs.rgbd_from_msg(msg)


def test_zstd_depth_is_exact_at_the_edges_of_its_range():
    """Differences wrap modulo 2^16 (0 next to 65535), odd widths, one-pixel images."""
    rng = np.random.default_rng(3)
    for depth in (rng.integers(0, 65536, (5, 7), dtype=np.uint16), np.array([[0, 65535, 0, 1]], np.uint16),
                  np.full((1, 1), 65535, np.uint16), np.zeros((3, 640), np.uint16)):
        msg = sensormsgs.compressed_image_msg(imagecodec.depth_zstd(depth), wirecompression.DEPTH_ZSTD_FORMAT, 0, "f")
        back = imagecodec.wire_image_array(msg)
        assert back.dtype == np.uint16 and np.array_equal(back, depth)


def test_zstd_depth_that_lies_about_its_size_is_refused_before_decompressing(frame):
    """A zstd frame may claim any content size: a 12-byte header saying 640x480 in front of a frame
    of a gigabyte of zeros (a few kB compressed) must not be decompressed, nor a cut-off frame."""
    import zstandard

    good = imagecodec.depth_zstd(frame.depth)
    bomb = good[:12] + zstandard.ZstdCompressor().compress(bytes(2 * frame.depth.size + 2))
    for data, message in ((bomb, "zstd frame is not"), (good[:-100], "cannot decode"), (good[:12], "cannot decode")):
        msg = sensormsgs.compressed_image_msg(data, wirecompression.DEPTH_ZSTD_FORMAT, 0, "f")
        with pytest.raises(InputError, match=message):
            imagecodec.wire_image_array(msg)
    # the header's own size is what the bus checks before any stage allocates
    wire = rgbdmsgs.compressed_rgbd_msg(frame, wirecompression.parse_wire_compression("jpeg,zstd"))
    wire.depth.data = np.frombuffer(good[:4] + (1 << 20).to_bytes(4, "little") + good[8:], np.uint8)
    with pytest.raises(InputError, match="image sizes disagree"):
        rgbdmsgs.rgbd_from_msg(wire)


# --- through the pipeline -------------------------------------------------------------------------


def _run(out: Path, *sets: str) -> Path:
    args = [a for s in sets for a in ("--set", s)]
    octolog("run", "--source", f"synthetic:{N_FRAMES}", "--out", str(out), "--quiet", "--rerun", "off", *args)
    return out


@pytest.fixture(scope="module")
def raw(octolog_run) -> Path:
    """The run with the default (raw) wire: the shared run, read-only."""
    return octolog_run(f"synthetic:{N_FRAMES}")[0]


@pytest.mark.slow
@pytest.mark.parametrize("depth", ["png", "zstd"])
def test_lossless_compression_changes_no_output(raw, tmp_path, depth):
    png = _run(tmp_path / "png", f"replay.wire_compression=png,{depth}", f"tracker.wire_compression=png,{depth}")
    for name in ("trajectory.txt", "map.bt", "map.ot", "cloud.ply"):
        assert (png / name).read_bytes() == (raw / name).read_bytes(), name
    frames = json.loads((png / "summary.json").read_text())["frames"]
    assert frames == {"published": N_FRAMES, "consumed": N_FRAMES, "skipped": 0}
    info = octolog("info", str(png / "session.mcap")).stdout
    assert "/camera/rgbd/compressed" in info and "/tracker/keyframe/compressed" in info
    assert "/camera/rgbd " not in info


@pytest.mark.slow
def test_jpeg_is_deterministic_close_to_raw_and_its_log_replays(raw, tmp_path):
    sets = ("replay.wire_compression=jpeg:90,png", "tracker.wire_compression=jpeg:90")
    a, b = _run(tmp_path / "a", *sets), _run(tmp_path / "b", *sets)
    for name in ("trajectory.txt", "map.bt", "cloud.ply"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert (a / "trajectory.txt").read_bytes() != (raw / "trajectory.txt").read_bytes()  # lossy: it changes
    sa, sr = (json.loads((d / "summary.json").read_text()) for d in (a, raw))
    assert abs(sa["ate"]["rmse_m"] - sr["ate"]["rmse_m"]) < 0.003
    assert abs(sa["map"]["occupied_voxels"] - sr["map"]["occupied_voxels"]) < 0.02 * sr["map"]["occupied_voxels"]
    # the session log holds the JPEG frames: replayed (raw on the wire), the tracker sees the same pixels
    octolog("run", "--source", f"mcap:{a / 'session.mcap'}", "--out", str(tmp_path / "r"), "--quiet", "--rerun", "off")
    assert (tmp_path / "r" / "trajectory.txt").read_bytes() == (a / "trajectory.txt").read_bytes()


@pytest.mark.slow
def test_tum_frames_travel_and_are_logged_as_their_png_files(tmp_path, octolog_run):
    """The default (`source`) publishes a TUM folder's PNG files untouched: the session log holds
    their bytes, keyframes carry them on to the mapper, and every output equals a raw run's. The
    default run on the first 40 frames is the shared one (tests/shell/test_distributed.py reads it
    too), read-only."""
    folder = tum_first300()
    window = ("--set", "replay.end=40")
    source = octolog_run(f"tum:{folder}", *window)[0]
    raw = tmp_path / "raw"
    octolog("run", "--source", f"tum:{folder}", "--out", str(raw), "--quiet", "--rerun", "off", *window,
            "--set", "replay.wire_compression=raw", "--set", "tracker.wire_compression=raw", timeout=600)
    for name in ("trajectory.txt", "map.bt", "cloud.ply"):
        assert (source / name).read_bytes() == (raw / name).read_bytes(), name
    pngs = sorted((folder / "rgb").iterdir())[:2]
    logged = [codec.decode(m.data, topics.RGBD_COMPRESSED.msgtype)
              for m in read_wire(source / "session.mcap", [topics.RGBD_COMPRESSED.name])]
    assert len(logged) == 40
    assert [bytes(m.color.data) for m in logged[:2]] == [p.read_bytes() for p in pngs]
    # stored as standard CompressedImages on the recorder's topic names, the PNG bytes untouched
    stored = [codec.decode(m.data, topics.COLOR_JPEG.msgtype)
              for m in read_messages(source / "session.mcap", [topics.COLOR_JPEG.name])]
    assert [bytes(m.data) for m in stored[:2]] == [p.read_bytes() for p in pngs] and "png" in stored[0].format
    kfs = list(read_wire(source / "session.mcap", [topics.KEYFRAME_COMPRESSED.name]))
    assert kfs and not list(read_wire(source / "session.mcap", [topics.KEYFRAME.name]))
    # raw frames lz4-compress about 3:1 in the log; the PNGs are smaller still
    assert (source / "session.mcap").stat().st_size < 0.7 * (raw / "session.mcap").stat().st_size
    # the log replays its compressed frames as they are, to the same trajectory
    again = tmp_path / "again"
    octolog("replay", str(source), "--out", str(again), "--quiet", "--rerun", "off")
    assert (again / "trajectory.txt").read_bytes() == (source / "trajectory.txt").read_bytes()


def test_a_truncated_png_is_named_before_it_is_sent(tmp_path):
    folder = make_tum(tmp_path / "rgbd_dataset_freiburg1_t", n=3)
    victim = sorted((folder / "rgb").iterdir())[1]
    victim.write_bytes(victim.read_bytes()[:-20])
    frames = open_tum(folder).encoded_frames()
    assert next(frames).color[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(InputError, match=f"{victim.name}: truncated PNG"):
        next(frames)
