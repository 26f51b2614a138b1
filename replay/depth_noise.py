"""What a real depth sensor would read where the synthetic room has exact depth.

Both sensors modelled here measure disparity, d = f b / z (focal length f in pixels, baseline b),
so their error lives in disparity: close to Gaussian with a constant sigma, then quantised to the
sensor's subpixel step. In depth that is an error growing with z^2 (sigma_z = z^2 sigma_d / (f b))
and depth values that come in steps, coarser with distance. Pixels read 0 (no depth) in a band
along depth discontinuities (the projector or the second camera does not see there), on dark
surfaces (too little returned light, structured light only) and at random (speckle dropouts).

- `kinect`: Kinect v1 / Xtion (TUM's freiburg cameras): structured light, b = 7.5 cm, f = 580 px,
  disparity in 1/8 px steps; sigma_d = 0.062 px gives Khoshelham and Elberink's (Sensors 2012)
  sigma_z = 1.43e-3 z^2 m (1.4 mm at 1 m, 3.6 cm at 5 m).
- `d455`: RealSense D455: active stereo, b = 9.5 cm, f = 382 px (depth at 640x480), subpixel
  sigma_d = 0.08 px (Intel's typical subpixel RMS), disparity in 1/32 px steps; its 2 % at 4 m
  specification allows 8 cm, the model gives 3.5 cm. Global shutter: nothing to do on colour.

Deterministic: the noise of frame i comes from its own generator seeded by (scene seed, i).
A systematic part can be added: a disparity offset (`bias_px`, the synthetic source's `bias=PX`),
as a stereo unit's or a structured-light camera's calibration error leaves it: depth off by about
z^2 bias / (f b), 0.9 % short at 4 m for 0.1 px on the Kinect. What is not modelled: spatially
correlated error (Kinect's 9x9 correlation window), lens-dependent depth distortion, temperature
drift, multipath.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DepthSensor:
    name: str
    baseline_m: float
    focal_px: float  # the depth camera's own focal length (its disparity is in its pixels)
    sigma_px: float  # disparity noise, one sigma
    step_px: float  # disparity quantisation
    edge_px: int  # width of the invalid band along a depth discontinuity
    edge_jump: float  # a neighbour farther by this fraction of z is a discontinuity
    dark_level: int  # mean colour below which a surface returns too little light (0: never)
    dark_loss: float  # probability that such a pixel reads 0
    dropout: float  # probability that any pixel reads 0


SENSORS = {
    "kinect": DepthSensor("kinect", 0.075, 580.0, 0.062, 1 / 8, 2, 0.05, 25, 0.6, 0.003),
    "d455": DepthSensor("d455", 0.095, 382.0, 0.08, 1 / 32, 2, 0.05, 0, 0.0, 0.002),
}


def names() -> tuple[str, ...]:
    return ("none", *SENSORS)


def apply(z: np.ndarray, rgb: np.ndarray, sensor: DepthSensor, rng: np.random.Generator,
          bias_px: float = 0.0) -> np.ndarray:
    """The depth `sensor` would read (metres, 0 = no reading) where the exact depth is `z` (H, W),
    0 or inf where there is none; `rgb` (H, W, 3) decides which surfaces are dark. `bias_px`: a
    systematic disparity offset (a unit's calibration error): depth reads short by about
    z^2 bias_px / (f b) (positive) or long (negative), the same in every frame."""
    z = np.where(np.isfinite(z), z, 0.0).astype(np.float64)
    valid = z > 0
    fb = sensor.focal_px * sensor.baseline_m
    d = np.zeros_like(z)
    d[valid] = fb / z[valid] + bias_px
    d[valid] += rng.normal(0.0, sensor.sigma_px, int(valid.sum()))
    d = np.rint(d / sensor.step_px) * sensor.step_px
    out = np.zeros_like(z)
    ok = valid & (d > 0)
    out[ok] = fb / d[ok]
    # discontinuities: a 4-neighbour farther by more than edge_jump * z, widened to edge_px
    edge = np.zeros(z.shape, dtype=np.uint8)
    for axis in (0, 1):
        a, b = (z[1:], z[:-1]) if axis == 0 else (z[:, 1:], z[:, :-1])
        jump = np.abs(a - b) > sensor.edge_jump * np.maximum(a, b)
        if axis == 0:
            edge[1:] |= jump
            edge[:-1] |= jump
        else:
            edge[:, 1:] |= jump
            edge[:, :-1] |= jump
    if sensor.edge_px > 1:
        edge = cv2.dilate(edge, np.ones((sensor.edge_px, sensor.edge_px), np.uint8))
    lost = edge.astype(bool) | (rng.random(z.shape) < sensor.dropout)
    if sensor.dark_level:
        dark = rgb.mean(axis=2) < sensor.dark_level
        lost |= dark & (rng.random(z.shape) < sensor.dark_loss)
    out[lost] = 0.0
    return out
