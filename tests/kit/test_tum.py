from __future__ import annotations

import shutil

import pytest
from helpers import octolog, tum_first300
from helpers.recordings import make_tum

from octolog.kit.errors import InputError
from octolog.kit.tum import TUM_DEPTH_SCALE_M, TUM_INTRINSICS, associate, open_tum, seconds_to_ns
from octolog.replay.sources import open_source


def test_reads_pairs_with_units_and_exact_stamps(tmp_path):
    seq = open_tum(make_tum(tmp_path / "rgbd_dataset_freiburg1_tiny"))
    frames = list(seq.frames())
    assert len(frames) == 4
    assert frames[0].stamp_ns == 100_000_000_000
    assert frames[1].depth[0, 0] == 5001 and frames[1].depth_scale_m == TUM_DEPTH_SCALE_M
    assert frames[0].rgb.shape == (48, 64, 3)


def test_stamps_are_exact_integers():
    assert seconds_to_ns("1305031102.175304") == 1305031102175304000


def test_association_is_nearest_and_unique():
    assert associate([0, 33, 66], [1, 2, 70], max_dt_ns=10) == [(0, 0), (2, 2)]


def test_missing_folder(tmp_path):
    with pytest.raises(InputError, match="not a folder"):
        open_tum(tmp_path / "nope")


def test_missing_list(tmp_path):
    folder = make_tum(tmp_path / "s")
    (folder / "depth.txt").unlink()
    with pytest.raises(InputError, match=r"depth\.txt: missing"):
        open_tum(folder)


def test_malformed_list_names_line(tmp_path):
    folder = make_tum(tmp_path / "s")
    with open(folder / "rgb.txt", "a") as f:
        f.write("12x.5 rgb/oops.png\n")
    with pytest.raises(InputError, match=r"rgb\.txt:6: malformed line"):
        open_tum(folder)


def test_unreadable_png_names_file(tmp_path):
    folder = make_tum(tmp_path / "s")
    victim = sorted((folder / "rgb").iterdir())[2]
    victim.write_bytes(b"\x89PNG garbage")
    frames = open_tum(folder, camera="freiburg1").frames()
    next(frames), next(frames)
    with pytest.raises(InputError, match=f"{victim.name}: unreadable image"):
        next(frames)


def test_listed_but_missing_image(tmp_path):
    folder = make_tum(tmp_path / "s")
    shutil.rmtree(folder / "depth")
    with pytest.raises(InputError, match="listed but missing"):
        next(open_tum(folder, camera="freiburg1").frames())


def test_a_folder_whose_name_says_no_camera_needs_one(tmp_path):
    """A renamed folder or another dataset in TUM layout: an error naming the option, never freiburg1's
    calibration by default; named, it opens with that camera's intrinsics and readout."""
    folder = make_tum(tmp_path / "my_kitchen")
    with pytest.raises(InputError, match=r"my_kitchen: the folder name does not say which camera.*replay\.camera"):
        open_tum(folder)
    seq = open_tum(folder, camera="freiburg3")
    assert seq.camera == "freiburg3" and seq.intrinsics == TUM_INTRINSICS["freiburg3"]
    assert open_source(f"tum:{folder}", camera="freiburg3").readout_s == 0.0
    assert open_source(f"tum:{folder}", camera="freiburg1").readout_s == pytest.approx(0.020)
    with pytest.raises(InputError, match="camera 'kinect2': want one of freiburg1, freiburg2, freiburg3"):
        open_tum(folder, camera="kinect2")


@pytest.mark.slow
def test_run_on_a_renamed_folder_is_one_line_unless_the_camera_is_named(tmp_path):
    """TUM fr1/xyz under a neutral name (a symlink): refused in one line; with the camera named it runs,
    and the session's config says which camera it was."""
    folder = tmp_path / "my_kitchen"
    folder.symlink_to(tum_first300(), target_is_directory=True)
    proc = octolog("run", "--source", f"tum:{folder}", "--out", str(tmp_path / "o"), "--quiet", check=False)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1 and "--set replay.camera=freiburgN" in proc.stderr, proc.stderr
    assert not (tmp_path / "o" / "trajectory.txt").exists()
    octolog("run", "--source", f"tum:{folder}", "--out", str(tmp_path / "o1"), "--quiet", "--rerun", "off",
            "--set", "replay.camera=freiburg1", "--set", "replay.end=40", timeout=300)
    assert 'camera = "freiburg1"' in (tmp_path / "o1" / "config.toml").read_text()
    assert len((tmp_path / "o1" / "trajectory.txt").read_text().splitlines()) >= 35
