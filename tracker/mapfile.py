"""The tracker's SLAM map on disk (`slam_map.npz` in a session folder): saved at the end of a run,
loaded by the next one (`octolog run --map`, `octolog track --map`) to track in the same world.

Format (`FORMAT`, version `VERSION`): a NumPy `.npz` (a zip of `.npy` arrays, stored; entries in a
fixed order, zip times fixed), so the same map gives the same bytes. `header` is a JSON document
(format, version, intrinsics, the depth correction, counts, the versions of the libraries whose
arithmetic the map depends on); the rest are arrays, keyframes flattened with offsets:

| entry | shape | what |
|---|---|---|
| `kf_id`, `kf_seq` | (K,) int64 | keyframe ids (0..K-1) and the frame each was made from |
| `kf_pose` | (K, 4, 4) float64 | world_from_camera |
| `kf_baseline_overlap` | (K,) int64 | see tracker.keyframe_map.Keyframe |
| `feat_start` | (K+1,) int64 | keyframe k's keypoints are rows feat_start[k]:feat_start[k+1] of: |
| `feat_uv`, `feat_octave`, `feat_desc`, `feat_z`, `feat_xyz` | (F, ...) | undistorted pixels, pyramid level, ORB descriptor, depth (m, 0 = none), camera-frame point |
| `obs_start`, `obs_kp`, `obs_pid` | (K+1,), (O,), (O,) | keyframe k's observations: keypoint index and map point id |
| `pid_start`, `point_ids` | (K+1,), (P',) | the map points each keyframe observes (sorted) |
| `covis_start`, `covis` | (K+1,), (C,) | covisible earlier keyframes |
| `pt_xyz`, `pt_desc`, `pt_weight`, `pt_n_obs`, `pt_n_visible`, `pt_n_found`, `pt_bad`, `pt_ref_kf` | (N, ...) | map points |
| `loop_old`, `loop_new`, `loop_T` | (L,), (L,), (L, 4, 4) | closed loops: old keyframe, new keyframe, old_from_new |

The place-recognition index is not stored: it is made again from the keyframes' descriptors with
the loading tracker's vocabulary (the same vocabulary gives the same index). A file that is not
such a map, another version, or a map of another camera is a one-line `InputError` naming it.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.files import read_npz, write_npz
from octolog.kit.geometry import Intrinsics
from octolog.tracker.features import FrameFeatures
from octolog.tracker.keyframe_map import Keyframe, MapPoints

FORMAT = "octolog-slam-map"
VERSION = 1
FILENAME = "slam_map.npz"  # in a session folder
_POINT_FIELDS = ("xyz", "desc", "weight", "n_obs", "n_visible", "n_found", "bad", "ref_kf")
_FEAT_FIELDS = ("uv", "octave", "desc", "z", "xyz")


@dataclass
class SavedMap:
    """A loaded map: what `RgbdSlam.adopt_map` takes."""

    header: dict[str, Any]
    intrinsics: Intrinsics
    keyframes: list[Keyframe]
    points: MapPoints
    loop_edges: list[tuple[int, int, np.ndarray]]
    depth_offset: float


def map_path(given: str | Path) -> Path:
    """A map file, or the saved map of a session folder."""
    p = Path(given)
    return p / FILENAME if p.is_dir() else p


def save_map(path: Path, *, intrinsics: Intrinsics, keyframes: list[Keyframe], points: MapPoints,
             loop_edges: list[tuple[int, int, np.ndarray]], depth_offset: float) -> None:
    """Write the map (see the module) to `path`, through a temporary file: a crash leaves no half map."""
    K = len(keyframes)

    def starts(sizes: list[int]) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    def cat(values: list[np.ndarray], dtype: Any, shape: tuple[int, ...] = ()) -> np.ndarray:
        return np.concatenate(values).astype(dtype) if values else np.zeros((0, *shape), dtype)

    n = points.size
    arrays: dict[str, np.ndarray] = {
        "kf_id": np.array([kf.id for kf in keyframes], np.int64),
        "kf_seq": np.array([kf.seq for kf in keyframes], np.int64),
        "kf_pose": np.array([kf.world_from_camera for kf in keyframes], np.float64).reshape(K, 4, 4),
        "kf_baseline_overlap": np.array([kf.baseline_overlap for kf in keyframes], np.int64),
        "feat_start": starts([len(kf.feats) for kf in keyframes]),
        "feat_uv": cat([kf.feats.uv for kf in keyframes], np.float64, (2,)),
        "feat_octave": cat([kf.feats.octave for kf in keyframes], np.int32),
        "feat_desc": cat([kf.feats.desc for kf in keyframes], np.uint8, (32,)),
        "feat_z": cat([kf.feats.z for kf in keyframes], np.float64),
        "feat_xyz": cat([kf.feats.xyz for kf in keyframes], np.float64, (3,)),
        "obs_start": starts([kf.obs_kp.size for kf in keyframes]),
        "obs_kp": cat([kf.obs_kp for kf in keyframes], np.int64),
        "obs_pid": cat([kf.obs_pid for kf in keyframes], np.int64),
        "pid_start": starts([kf.point_ids.size for kf in keyframes]),
        "point_ids": cat([kf.point_ids for kf in keyframes], np.int64),
        "covis_start": starts([len(kf.covis) for kf in keyframes]),
        "covis": cat([np.asarray(kf.covis, np.int64) for kf in keyframes], np.int64),
        **{f"pt_{name}": getattr(points, name)[:n].copy() for name in _POINT_FIELDS},
        "loop_old": np.array([a for a, _, _ in loop_edges], np.int64),
        "loop_new": np.array([b for _, b, _ in loop_edges], np.int64),
        "loop_T": np.array([T for _, _, T in loop_edges], np.float64).reshape(len(loop_edges), 4, 4),
    }
    header = {"format": FORMAT, "version": VERSION,
              "intrinsics": {"width": intrinsics.width, "height": intrinsics.height, "fx": intrinsics.fx,
                             "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy,
                             "distortion": list(intrinsics.distortion)},
              "depth_inverse_offset": depth_offset, "keyframes": K, "map_points": n, "loops": len(loop_edges),
              "versions": {"numpy": np.__version__, "opencv": cv2.__version__}}
    write_npz(path, header, arrays)


def load_map(given: str | Path) -> SavedMap:
    """Read a saved map (a file, or a session folder's); InputError naming what is wrong."""
    path = map_path(given)
    try:
        header, a = read_npz(path)
        if header.get("format") != FORMAT:
            raise InputError(f"{path}: not an octolog SLAM map (format {header.get('format')!r})")
        if header.get("version") != VERSION:
            raise InputError(f"{path}: SLAM map version {header.get('version')!r}; this octolog reads "
                             f"version {VERSION} (make the map again with this version)")
    except FileNotFoundError:
        raise InputError(f"{path}: no saved SLAM map there ({FILENAME} is written by `octolog run`)") from None
    except (zipfile.BadZipFile, EOFError, ValueError, KeyError, OSError) as exc:
        raise InputError(f"{path}: damaged SLAM map ({type(exc).__name__}: {exc})") from None
    try:
        return _rebuild(header, a)
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise InputError(f"{path}: damaged SLAM map ({type(exc).__name__}: {exc})") from None


def _rebuild(header: dict[str, Any], a: dict[str, np.ndarray]) -> SavedMap:
    i = header["intrinsics"]
    intrinsics = Intrinsics(int(i["width"]), int(i["height"]), float(i["fx"]), float(i["fy"]), float(i["cx"]),
                            float(i["cy"]), tuple(float(k) for k in i["distortion"]))
    points = MapPoints()
    n = int(a["pt_xyz"].shape[0])
    points._grow(n)
    for name in _POINT_FIELDS:
        getattr(points, name)[:n] = a[f"pt_{name}"]
    points.size = n
    fs, os_, ps, cs = a["feat_start"], a["obs_start"], a["pid_start"], a["covis_start"]
    keyframes = []
    for k in range(a["kf_id"].size):
        f = slice(int(fs[k]), int(fs[k + 1]))
        feats = FrameFeatures(**{name: a[f"feat_{name}"][f].copy() for name in _FEAT_FIELDS})
        o = slice(int(os_[k]), int(os_[k + 1]))
        keyframes.append(Keyframe(int(a["kf_id"][k]), int(a["kf_seq"][k]), a["kf_pose"][k].copy(),
                                  a["point_ids"][int(ps[k]):int(ps[k + 1])].copy(), feats, a["obs_kp"][o].copy(),
                                  a["obs_pid"][o].copy(), [int(c) for c in a["covis"][int(cs[k]):int(cs[k + 1])]],
                                  int(a["kf_baseline_overlap"][k])))
        if keyframes[-1].id != k:
            raise ValueError(f"keyframe {k} has id {keyframes[-1].id}")
    if keyframes and int(a["obs_pid"].max(initial=-1)) >= n:
        raise ValueError("an observation names a map point the map does not have")
    loops = [(int(o), int(nw), T.copy()) for o, nw, T in zip(a["loop_old"], a["loop_new"], a["loop_T"], strict=True)]
    return SavedMap(header, intrinsics, keyframes, points, loops, float(header.get("depth_inverse_offset", 0.0)))
