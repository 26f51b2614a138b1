from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from octolog.kit.errors import InputError
from octolog.kit.tum import TUM_DEPTH_SCALE_M, associate, open_tum, seconds_to_ns


def make_tum(folder: Path, n: int = 4) -> Path:
    """A tiny TUM-layout folder: random colour, planar depth, depth stamps 5 ms after colour."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rng = np.random.default_rng(0)
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for i in range(n):
        t = 100.0 + i / 30
        cv2.imwrite(str(folder / f"rgb/{t:.6f}.png"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
        cv2.imwrite(str(folder / f"depth/{t + 0.005:.6f}.png"), np.full((48, 64), 5000 + i, np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.005:.6f} depth/{t + 0.005:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    return folder


def test_reads_pairs_with_units_and_exact_stamps(tmp_path):
    seq = open_tum(make_tum(tmp_path / "fr1"))
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
    frames = open_tum(folder).frames()
    next(frames), next(frames)
    with pytest.raises(InputError, match=f"{victim.name}: unreadable image"):
        next(frames)


def test_listed_but_missing_image(tmp_path):
    folder = make_tum(tmp_path / "s")
    shutil.rmtree(folder / "depth")
    with pytest.raises(InputError, match="listed but missing"):
        next(open_tum(folder).frames())
