"""Depth registered to colour (kit/registration.py) against the synthetic room's own rendering."""

from __future__ import annotations

import numpy as np

from octolog.kit.geometry import invert
from octolog.kit.registration import register_depth
from octolog.replay.synthetic import SyntheticScene


def _cameras(colour_size: tuple[int, int], angle_deg: float, offset_m: float):
    """Depth from a 320x240 camera at the room's first pose and the depth a colour camera of
    `colour_size`, turned and moved sideways from it, renders itself; color_from_depth."""
    depth_cam = SyntheticScene(n_frames=2, width=320, height=240)
    colour_cam = SyntheticScene(n_frames=2, width=colour_size[0], height=colour_size[1])
    world_from_depth = depth_cam.pose(0)
    move = np.eye(4)
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    move[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    move[0, 3] = offset_m
    world_from_colour = world_from_depth @ move
    _, raw = depth_cam.render_pose(world_from_depth)
    _, want = colour_cam.render_pose(world_from_colour)
    got = register_depth(raw, depth_cam.intrinsics, colour_cam.intrinsics,
                         invert(world_from_colour) @ world_from_depth, depth_cam.depth_scale_m)
    return raw, got, want


def test_registered_depth_is_the_depth_the_colour_camera_sees():
    """Into a colour camera 5 cm to the side, turned 2 degrees, of 1.5x the resolution: where both
    have a reading, 99 % agree with the depth rendered from the colour camera itself within 1 % (a
    depth pixel's footprint spans that much depth on the slanted floor; edges, where the views see
    different surfaces, make the rest); what the depth camera never saw stays 0. The same camera
    registers to itself bit for bit."""
    _, got, want = _cameras((480, 360), 2.0, 0.05)
    assert got.shape == want.shape and got.dtype == np.uint16
    both = (got > 0) & (want > 0)
    assert both.mean() > 0.9
    error = np.abs(got[both].astype(np.int64) - want[both].astype(np.int64)) / want[both]
    assert (error < 0.01).mean() >= 0.99, (error < 0.01).mean()
    assert (got > 0).mean() < (want > 0).mean()  # the strip only the colour camera sees is not made up
    raw, same, _ = _cameras((320, 240), 0.0, 0.0)
    assert np.array_equal(same, raw)
