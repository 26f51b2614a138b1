"""A depth camera's error model: what its readings deserve, from its baseline and focal length.

Structured-light cameras (Kinect v1, Xtion) and active stereo (RealSense D4xx) measure disparity
d = f b / z (f: the depth camera's focal length in its own pixels, b: the baseline), with an error
close to a constant sigma_d in disparity. In depth that is an error growing with the square of the
range, sigma_z = z^2 sigma_d / (f b): a constant sigma_d / (f b) in inverse depth. A per-unit
calibration error leaves a disparity offset, a bias of z^2 offset / (f b) (tracker/depth_bias.py
reports it in disparity pixels).

The model sets:
- `inverse_sigma`: the floor under the tracker's inverse-depth sigmas (a reading is never trusted
  more than the camera measures);
- `metric_range_m`: where the relative error z sigma_d / (f b) reaches METRIC_RELATIVE_ERROR;
  beyond it a reading is not metric evidence: the keypoint is used as a bearing (no depth
  residual, no new map point from it).

Defaults, with their sources:
- `KINECT` (TUM's freiburg cameras, Kinect v1 and Xtion): b = 7.5 cm, f = 580 px (the infrared
  camera at 640x480), sigma_d = 0.062 px: Khoshelham and Elberink, Sensors 2012, whose measured
  sigma_z = 1.43e-3 z^2 m it reproduces. Metric range 14 m: beyond any reading it gives.
- `d455(focal_px)`: RealSense D455: b = 95 mm (Intel's datasheet), sigma_d = 0.08 px (Intel's
  typical subpixel RMS), f the depth stream's own (382 px at 640x480). Metric range 9 m at 640x480.
  `realsense(name, focal_px)` also knows the D415 (55 mm), D435 (50 mm; 2.7 m at 424x240) and D405 (18 mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# a reading is metric evidence up to the range where its random error is this fraction of it: the
# D455's own accuracy specification (2 % at 4 m) as the line between depth and a bearing
METRIC_RELATIVE_ERROR = 0.02
# the calibration keys (a calibration TOML file, an MCAP recording's `calibration` metadata record)
FIELDS = ("depth_baseline_m", "depth_focal_px", "depth_disparity_sigma_px")


@dataclass(frozen=True)
class DepthModel:
    """A disparity-measuring depth camera: baseline (m), focal length of its depth camera (px),
    disparity noise (px, one sigma)."""

    baseline_m: float
    focal_px: float
    disparity_sigma_px: float

    def __post_init__(self) -> None:
        for name in FIELDS:
            value = getattr(self, name.removeprefix("depth_"))
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} = {value!r}: want a positive number")

    @property
    def fb(self) -> float:
        """Focal length times baseline (px m): disparity = fb / z."""
        return self.focal_px * self.baseline_m

    @property
    def inverse_sigma(self) -> float:
        """One sigma of a reading's inverse depth (1/m), the same at every range."""
        return self.disparity_sigma_px / self.fb

    def sigma_m(self, z: float) -> float:
        """One sigma of a reading at range z (m)."""
        return z * z * self.inverse_sigma

    @property
    def metric_range_m(self) -> float:
        """The range up to which a reading is metric evidence (METRIC_RELATIVE_ERROR)."""
        return METRIC_RELATIVE_ERROR / self.inverse_sigma

    def disparity_px(self, inverse_offset: float) -> float:
        """An inverse-depth offset (1/m) as the disparity offset (px) that makes it."""
        return inverse_offset * self.fb

    def fields(self) -> dict[str, float]:
        return {"depth_baseline_m": self.baseline_m, "depth_focal_px": self.focal_px,
                "depth_disparity_sigma_px": self.disparity_sigma_px}


KINECT = DepthModel(0.075, 580.0, 0.062)
# RealSense D400 stereo baselines (Intel's D400 series datasheet) and their typical subpixel RMS
REALSENSE_BASELINE_M = {"D455": 0.095, "D415": 0.055, "D435": 0.050, "D405": 0.018}
REALSENSE_DISPARITY_SIGMA_PX = 0.08


def d455(focal_px: float) -> DepthModel:
    """The RealSense D455 with a depth stream of focal length `focal_px`."""
    return DepthModel(REALSENSE_BASELINE_M["D455"], focal_px, REALSENSE_DISPARITY_SIGMA_PX)


def realsense(device_name: str, focal_px: float) -> DepthModel | None:
    """A RealSense D400 camera's model from its product name ("Intel RealSense D435I") and its depth
    stream's focal length; None for a name it does not know."""
    for product, baseline in REALSENSE_BASELINE_M.items():
        if product in device_name.upper():
            return DepthModel(baseline, focal_px, REALSENSE_DISPARITY_SIGMA_PX)
    return None


def from_fields(values: dict, *, focal_px: float | None = None) -> DepthModel | None:
    """The model a calibration record gives (FIELDS; `depth_focal_px` defaults to `focal_px`, the
    registered depth's), None when it gives none. ValueError names a key that is missing or bad."""
    given = [k for k in FIELDS if k in values]
    if not given:
        return None
    if "depth_focal_px" not in values and focal_px is not None:
        values = {**values, "depth_focal_px": focal_px}
    missing = [k for k in FIELDS if k not in values]
    if missing:
        raise ValueError(f"{missing[0]} missing ({', '.join(FIELDS)} go together; depth_focal_px defaults to fx)")
    try:
        numbers = [float(values[k]) for k in FIELDS]
    except (TypeError, ValueError):
        bad = next(k for k in FIELDS if not _is_number(values[k]))
        raise ValueError(f"{bad} = {values[bad]!r}: want a positive number") from None
    return DepthModel(*numbers)


def _is_number(v: object) -> bool:
    try:
        float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return False
    return not isinstance(v, bool)
