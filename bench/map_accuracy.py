"""Map accuracy on the synthetic room (ground-truth poses, 15 keyframes at 640x480), per config.

    python bench/map_accuracy.py

Same construction as tests/mapper/test_map_accuracy.py; definitions in mapper/evaluate.py. Prints, for the
default config, OctoMap's own model (every end point at once) and variants of the outlier filter:
the map's dense cloud to the true surface, observed surface voxels occupied, observed free voxels
occupied.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "mapper"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import numpy as np  # noqa: E402
from test_map_accuracy import KEYFRAMES, build, run  # noqa: E402

from octolog.mapper.cloud import transform  # noqa: E402
from octolog.mapper.config import MapperConfig  # noqa: E402
from octolog.mapper.evaluate import cloud_to_surface, voxel_accuracy  # noqa: E402


def main() -> None:
    r = run._get_wrapped_function()() if hasattr(run, "_get_wrapped_function") else run.__wrapped__()
    scene_from_map = np.linalg.inv(r.map_from_scene)

    def truth(points: np.ndarray) -> np.ndarray:  # exact distance to the room's mesh
        return r.scene.distance_to_surface(transform(points, scene_from_map))
    variants = {
        "default (image grid 5x5, 3 sigma)": MapperConfig(),
        "OctoMap's model (confirm_within 0, clamp 0.97)": MapperConfig(confirm_within=0, clamp_max=0.97),
        "SOR k=20, 3 sigma": dataclasses.replace(MapperConfig(), outliers="knn"),
        "SOR 2 sigma (PCL's usual)": dataclasses.replace(MapperConfig(), outliers="knn", sor_std_ratio=2.0),
        "SOR first (paper's order), 3 sigma": dataclasses.replace(MapperConfig(), outliers="knn", sor_first=True),
        "no outlier filter (std ratio 1e9)": dataclasses.replace(MapperConfig(), sor_std_ratio=1e9),
    }
    print(f"synthetic room, {len(KEYFRAMES)} keyframes 640x480, ground-truth poses, 5 cm voxels, 1 cm cloud")
    print(f"{'config':<48} {'cloud→surface mean/p90 mm':>26} {'surface occ %':>14} {'free occ %':>11} {'s':>6}")
    for name, cfg in variants.items():
        t0 = time.monotonic()
        m = build(r, cfg)
        dt = time.monotonic() - t0
        pts, _ = m.map_cloud()
        d = cloud_to_surface(pts, truth)
        a = voxel_accuracy(m.octree, r.observed)
        print(f"{name:<48} {d['mean_m'] * 1e3:>12.2f} / {d['p90_m'] * 1e3:<11.2f} "
              f"{a['surface_occupied_fraction'] * 100:>14.2f} {a['free_occupied_fraction'] * 100:>11.3f} {dt:>6.1f}")


if __name__ == "__main__":
    main()
