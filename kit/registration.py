"""Depth registered to colour: a depth image as the colour camera would see it.

A RealSense recording made without the `aligned_depth_to_color` stream (RealSense Viewer's `.bag`
files, `octolog record --depth-streams raw`) holds depth in the depth imager's own pixels. The tracker
and mapper want depth per colour pixel, so the replay registers it: each depth pixel is
back-projected with the depth camera's intrinsics, moved into the colour camera's frame by the
recorded extrinsics (`color_from_depth`) and its footprint (the pixel's square, projected) filled in
the colour image, the nearest surface kept where several land (a z-buffer). What librealsense's
`rs2::align` to colour computes, without lens distortion (the D4xx depth stream is rectified; its
colour distortion is under a pixel at the D455's calibration) and without hole filling: colour
pixels no depth reaches read 0.
"""

from __future__ import annotations

import numpy as np

from octolog.kit.geometry import Intrinsics


def register_depth(depth: np.ndarray, depth_k: Intrinsics, color_k: Intrinsics, color_from_depth: np.ndarray,
                   depth_scale_m: float) -> np.ndarray:
    """`depth` (uint16, depth_k's size, units of `depth_scale_m`) in the colour camera's pixels
    (color_k's size, the same units); 0 where no depth lands."""
    v, u = np.nonzero(depth)
    z = depth[v, u].astype(np.float64) * depth_scale_m
    T = np.asarray(color_from_depth, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    out = np.full((color_k.height, color_k.width), np.iinfo(np.uint16).max, dtype=np.uint16)
    corners = []
    for du in (-0.5, 0.5):  # the pixel's footprint: its two opposite corners, projected
        for dv in (-0.5, 0.5):
            x = (u + du - depth_k.cx) / depth_k.fx * z
            y = (v + dv - depth_k.cy) / depth_k.fy * z
            p = np.stack([x, y, z]).T @ R.T + t
            with np.errstate(divide="ignore", invalid="ignore"):
                corners.append((p[:, 0] / p[:, 2] * color_k.fx + color_k.cx,
                                p[:, 1] / p[:, 2] * color_k.fy + color_k.cy, p[:, 2]))
    cu = np.stack([c[0] for c in corners])
    cv = np.stack([c[1] for c in corners])
    zc = np.stack([c[2] for c in corners]).mean(axis=0)
    ok = (zc > 0) & np.isfinite(cu).all(axis=0) & np.isfinite(cv).all(axis=0)
    # the colour pixels whose centres (integer coordinates, OpenCV's convention) the footprint covers
    u0 = np.ceil(cu.min(axis=0)[ok]).astype(np.int64)
    u1 = np.floor(cu.max(axis=0)[ok]).astype(np.int64)
    v0 = np.ceil(cv.min(axis=0)[ok]).astype(np.int64)
    v1 = np.floor(cv.max(axis=0)[ok]).astype(np.int64)
    zu = np.clip(np.rint(zc[ok] / depth_scale_m), 1, np.iinfo(np.uint16).max - 1).astype(np.uint16)
    u1, v1 = np.maximum(u1, u0), np.maximum(v1, v0)  # a footprint smaller than a pixel: its nearest pixel
    span = int(max((u1 - u0).max(initial=0), (v1 - v0).max(initial=0))) + 1
    for dy in range(span):
        for dx in range(span):
            uu, vv = u0 + dx, v0 + dy
            sel = (uu <= u1) & (vv <= v1) & (uu >= 0) & (vv >= 0) & (uu < color_k.width) & (vv < color_k.height)
            np.minimum.at(out, (vv[sel], uu[sel]), zu[sel])
    out[out == np.iinfo(np.uint16).max] = 0
    return out
