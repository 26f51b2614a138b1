"""Tracker accuracy and scale under realistic depth noise, where the truth is exact.

The synthetic room (replay/synthetic.py) rendered with exact depth and with the Kinect and D455
depth models (replay/depth_noise.py), along a slow path (as rendered, 30 fps) and a fast one (every
3rd frame: the same path three times faster). The native tracker runs in this process with
`octolog track`'s parameters, its back end inline (the same results as on its worker, no
transport, Rerun off). Per case: ATE after SE(3)
alignment, ATE after Sim(3) alignment and the Sim(3) scale (what the estimate's lengths must be
multiplied by; 1 = no scale error). `--bias` adds a systematic disparity offset to the noisy
sensors (a unit's calibration error: depth short by about z^2 bias / (f b)), 0 for none.

`--correct` runs each case again with `tracker.depth.inverse_offset` set to what the first run's
map estimated (tracker/depth_bias.py): the two-session workflow a user follows.

    python bench/depth_scale.py [--frames 300] [--noise none,kinect,d455] [--every 1,3] [--bias 0,0.1] [--correct]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from octolog.kit import metrics
from octolog.replay.depth_noise import SENSORS
from octolog.replay.synthetic import SyntheticScene
from octolog.tracker.config import TrackerConfig
from octolog.tracker.slam import RgbdSlam


def track_scene(noise: str, frames: int, every: int, *, seed: int = 0, bias_px: float = 0.0,
                inverse_offset: float = 0.0, online: bool = False) -> dict:
    """Track the synthetic room with `noise` (and a disparity offset `bias_px`, corrected by
    `inverse_offset`: tracker.depth.inverse_offset); ATE (SE(3), Sim(3)) in metres, the scale, the
    map's depth-bias estimate (tracker/depth_bias.py), timing."""
    scene = SyntheticScene(n_frames=frames, seed=seed, depth_noise=noise, depth_bias_px=bias_px)
    cfg = TrackerConfig()
    cfg = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, inverse_offset=inverse_offset,
                                                             correct_bias=online))
    odo = RgbdSlam(cfg.odometry_params(), background=False)
    idx = list(range(0, frames, every))
    t0 = time.perf_counter()
    for i in idx:
        odo.track(scene.render(i))
    odo.finish()
    wall = time.perf_counter() - t0
    stamps, poses = odo.trajectory()
    est = metrics.Trajectory.from_matrices(np.array(stamps), np.array(poses))
    gt = metrics.Trajectory.from_matrices(np.array([scene.stamp_ns(i) for i in idx]), scene.poses()[idx])
    se3, sim3 = metrics.ate(est, gt), metrics.ate(est, gt, correct_scale=True)
    return {"noise": noise, "bias_px": bias_px, "every": every, "frames": len(idx), "tracked": len(stamps), "ate_m": se3.rmse,
            "ate_sim3_m": sim3.rmse, "scale": sim3.scale, "depth_bias": odo.depth_bias(), "wall_s": wall,
            "offset": odo.depth_offset, "corrections": odo.depth_corrections}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=300, help="rendered frames (the slow path)")
    ap.add_argument("--noise", default="none,kinect,d455")
    ap.add_argument("--every", default="1,3")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bias", default="0", help="disparity offsets, px (noisy sensors only)")
    ap.add_argument("--correct", action="store_true",
                    help="also run each case again with tracker.depth.inverse_offset set to the map's own estimate")
    ap.add_argument("--online", action="store_true",
                    help="also run each case with tracker.depth.correct_bias (the estimate corrected while tracking)")
    args = ap.parse_args()
    print(f"synthetic room, {args.frames} frames at 30 fps, seed {args.seed}")
    print("| depth | bias, px | path | correction, 1/m | frames tracked | ATE SE(3), cm | ATE Sim(3), cm | "
          "Sim(3) scale | scale error, % | estimated bias at 4 m (truth), cm | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    cases = [(noise, float(b)) for noise in args.noise.split(",") for b in args.bias.split(",")
             if noise != "none" or float(b) == 0.0]
    for every in (int(e) for e in args.every.split(",")):
        for noise, bias in cases:
            r = track_scene(noise, args.frames, every, seed=args.seed, bias_px=bias)
            _row(r, noise, bias, every, 0.0)
            if args.correct and r["depth_bias"] is not None:
                offset = r["depth_bias"].inverse_offset
                _row(track_scene(noise, args.frames, every, seed=args.seed, bias_px=bias, inverse_offset=offset),
                     noise, bias, every, offset)
            if args.online:
                r = track_scene(noise, args.frames, every, seed=args.seed, bias_px=bias, online=True)
                _row(r, noise, bias, every, r["offset"], f"online ({r['corrections']}x)")


def _row(r: dict, noise: str, bias: float, every: int, offset: float, how: str = "") -> None:
    path = "slow (every frame)" if every == 1 else f"fast (every {every}rd)" if every == 3 else f"every {every}"
    est = r["depth_bias"]
    fb = SENSORS[noise].focal_px * SENSORS[noise].baseline_m if noise in SENSORS else 0.0
    truth = 4.0 / (1.0 + (bias / fb - offset) * 4.0) - 4.0 if fb else 0.0  # a reading at 4 m, what is left
    at4 = f"{est.bias_m[4.0] * 100:+.2f} ({truth * 100:+.2f})" if est is not None else "-"
    print(f"| {noise} | {bias:g} | {path} | {offset:.5f}{' ' + how if how else ''} | {r['tracked']}/{r['frames']} | {r['ate_m'] * 100:.2f} | "
          f"{r['ate_sim3_m'] * 100:.2f} | {r['scale']:.4f} | {(r['scale'] - 1) * 100:+.2f} | {at4} | "
          f"{r['wall_s']:.0f} |", flush=True)

if __name__ == "__main__":
    main()
