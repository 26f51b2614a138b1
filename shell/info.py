"""`octolog info`: what an MCAP file holds, readable by a person."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from octolog.kit.errors import InputError, MapError, McapError
from octolog.kit.mcaplog import summarize
from octolog.shell.sessiondir import INCOMPLETE, incomplete_reason


def describe(path: Path) -> str:
    """An MCAP recording/session, a session folder, or an OctoMap file (.bt, .ot)."""
    if path.is_dir():
        return describe_session(path)
    if path.suffix in (".bt", ".ot"):
        return describe_map(path)
    text = describe_mcap(path)
    why = incomplete_reason(path.parent) if path.name == "session.mcap" else None
    return text if why is None else f"{text}\n  session {path.parent}: INCOMPLETE ({INCOMPLETE}: {why})"


def describe_session(folder: Path) -> str:
    """A session folder: whether its run finished, then its session.mcap."""
    why = incomplete_reason(folder)
    log = folder / "session.mcap"
    if why is None and not (folder / "summary.json").is_file():
        raise InputError(f"{folder}: not an octolog session folder (no summary.json, no {INCOMPLETE})")
    head = f"session {folder}: " + ("complete" if why is None else f"INCOMPLETE ({INCOMPLETE}: {why})")
    summary = _summary(folder)
    if "imu" in summary:  # a run's summary says whether the tracker had an IMU
        head += "\n  " + imu_line(summary["imu"])
    if summary.get("depth_bias"):
        head += "\n" + depth_bias_line(summary["depth_bias"])
    if summary.get("prior_map"):
        head += "\n  " + prior_line(summary["prior_map"])
    if summary.get("movers"):
        head += "\n  " + movers_line(summary["movers"])
    if not log.is_file():
        return f"{head}\n  no session.mcap"
    return f"{head}\n{describe_mcap(log)}"


def _summary(folder: Path) -> dict:
    try:
        data = json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def depth_bias_line(b: dict) -> str:
    """The tracker's estimate of the depth camera's systematic error (summary.json `depth_bias`)."""
    bands = b.get("bands") or {}
    at = ", ".join(f"{-100 * v['bias_m'] / float(z):+.2f} ± {100 * v['sigma_m'] / float(z):.2f} % at {z} m"
                   for z, v in bands.items()) if bands else \
        ", ".join(f"{-100 * v / float(z):+.2f} % at {z} m" for z, v in b["bias_m"].items() if float(z) in (2.0, 4.0))
    if b.get("disparity_offset_px") is not None:
        at += f" (a disparity offset of {b['disparity_offset_px']:+.3f} px)"
    corrected = float(b.get("corrected_per_m", 0.0))
    if corrected:
        return (f"  depth bias (from the map): reads short by {at}; corrected by {corrected:.5f} 1/m"
                + (f" ({b['corrections']} times while tracking)" if b.get("corrections") else "")
                + f", {b['inverse_offset_per_m']:.5f} 1/m left" + ("" if b["confident"] else " (not significant)"))
    return (f"  depth bias (from the map): reads short by {at}" + ("" if b["confident"] else " (not significant)")
            + f"; inverse offset {b['inverse_offset_per_m']:.5f} 1/m (tracker.depth.inverse_offset corrects it)")


def imu_line(imu: dict | None) -> str:
    """Whether the tracker used an IMU and what it found (summary.json `imu`)."""
    if not imu:
        return "IMU: none (vision only)"
    if imu.get("initialised_at_ns", -1) < 0:
        return f"IMU: {imu['samples']} samples, gravity and velocity never aligned (rotation prediction only)"
    bg = [round(float(np.degrees(v)), 3) for v in imu["gyro_bias"]]
    ba = [round(float(v), 3) for v in imu["accel_bias"]]
    trusted = imu.get("trusted_frames", 0)
    if not trusted:
        return (f"IMU: {imu['samples']} samples, never trusted: its motion did not agree with vision's "
                f"(the camera-IMU transform, clock offset or noise?); gyro bias {bg} deg/s")
    return (f"IMU: used ({imu['samples']} samples, trusted at {trusted} frames), {imu['inertial_frames']} frames "
            f"placed by the IMU alone (INERTIAL); gyro bias {bg} deg/s, accelerometer bias {ba} m/s²"
            + imu_measured(imu))


def imu_measured(imu: dict) -> str:
    """What the tracker measured of its IMU against what it was told (summary.json `imu`)."""
    parts = []
    measured, assumed = imu.get("noise_measured") or [], imu.get("noise_assumed") or []
    if measured and assumed:
        parts.append("noise {:.2g}x (gyro) and {:.2g}x (accelerometer) the stated".format(
            *(m / a for m, a in zip(measured[:2], assumed[:2]))))
    if imu.get("camera_from_imu"):
        parts.append(f"camera-IMU rotation {imu.get('rotation_change_deg', 0.0):.2f} deg from the stated")
    if imu.get("late_ms"):
        parts.append(f"its clock {imu['late_ms']:.1f} ms late")
    return "; measured: " + ", ".join(parts) if parts else ""


def describe_mcap(path: Path) -> str:
    """An MCAP file: profile, topics, rates, gaps, calibration and metadata."""
    s = summarize(path)
    if not s.complete and not (s.topics or s.metadata):  # a header alone says nothing of what was recorded
        raise McapError(f"{path}: no readable MCAP records after the {'header' if s.profile else 'magic'} "
                        f"({s.problem}); nothing to recover")
    lines = [f"{path}: {s.size_bytes / 1e6:.1f} MB, profile {s.profile or '(none)'}, "
             + ("complete" if s.complete else f"INCOMPLETE: {s.problem}")]
    if s.topics:
        t0 = min(t.first_ns for t in s.topics.values())
        t1 = max(t.last_ns for t in s.topics.values())
        lines.append(f"  span {(t1 - t0) * 1e-9:.2f} s, {sum(t.count for t in s.topics.values())} messages")
    width = max((len(n) for n in s.topics), default=0)
    wire = s.wire_topics
    for name in sorted(s.topics):
        t = s.topics[name]
        kind = t.msgtype if wire[name].msgtype == t.msgtype else f"{t.msgtype} (wire: {wire[name].msgtype})"
        span = (t.last_ns - t.first_ns) * 1e-9
        rate = (t.count - 1) / span if span > 0 else 0.0
        n_gaps, longest = t.gaps()
        gaps = f"  {n_gaps} gaps (longest {longest * 1e-6:.0f} ms)" if n_gaps else ""
        lines.append(f"  /{name:<{width}}  {t.count:6d} msgs  {span:7.2f} s  {rate:6.1f} Hz  {kind}{gaps}")
    calib = s.metadata.get("calibration", {})
    if "depth_scale_m" in calib:
        lines.append(f"  calibration: depth scale {calib['depth_scale_m']} m/unit"
                     + (f", depth registered to colour: {calib['depth_registered_to_color']}"
                        if "depth_registered_to_color" in calib else ""))
    for key in ("color_intrinsics", "depth_intrinsics"):
        if key in calib:
            lines.append(f"    {key}: {calib[key]}")
    rec = s.metadata.get("recording", {})
    if rec:
        lines.append(f"  recording: stopped: {rec.get('stop_reason', '?')}, dropped: {rec.get('dropped_total', '?')}")
    for name in sorted(s.metadata):
        keys = ", ".join(sorted(s.metadata[name]))
        lines.append(f"  metadata {name}: {keys}")
    if not s.complete:
        lines.append(f"  {sum(t.count for t in s.topics.values())} messages are readable before the damage")
    return "\n".join(lines)


def describe_map(path: Path) -> str:
    """Header and leaf counts of an OctoMap file, read by OctoMap itself; MapError if unreadable."""
    try:
        head = path.read_bytes()[:512]
    except FileNotFoundError:
        raise MapError(f"{path}: no such map file") from None
    lines = head.split(b"\n")
    fields = dict(ln.decode("ascii", "replace").split(" ", 1) for ln in lines[1:6] if b" " in ln)
    if not lines[0].startswith(b"# Octomap OcTree") or "res" not in fields or "id" not in fields:
        raise MapError(f"{path}: not an OctoMap file (no '# Octomap OcTree' header with id and res)")
    import pyoctomap  # here, not at the top: it loads numpy (~0.2 s), which MCAP summaries never need

    res = float(fields["res"])
    tree = pyoctomap.OcTree(res)
    if path.suffix == ".bt":
        ok = tree.readBinary(str(path))
    else:
        tree = tree.read(str(path)) if fields["id"].strip() == "OcTree" else pyoctomap.ColorOcTree(res).read(str(path))
        ok = tree is not None
    expected = int(fields.get("size", "0"))
    if not ok or tree is None or (expected and tree.size() != expected):
        raise MapError(f"{path}: truncated or corrupt OctoMap file (header says {expected} nodes, "
                       f"read {tree.size() if tree is not None else 0})")
    occupied = free = 0
    for leaf in tree.begin_leafs():
        if tree.isNodeOccupied(leaf):
            occupied += 1
        else:
            free += 1
    return (f"{path}: OctoMap {fields['id'].strip()}, resolution {res:g} m, {expected} nodes, "
            f"{occupied} occupied and {free} free leaves")


def uninitialised_line(u: dict) -> str:
    """Why the tracker never made its first keyframe (summary.json `uninitialised`)."""
    return (f"never initialised: no frame had {u['min_init_points']} corners with depth "
            f"(tracking.min_init_points), the best had {u['best_points']} (a dark, blank or out-of-range view; "
            f"--set tracker.tracking.min_init_points=N starts from fewer)")


def movers_line(m: dict) -> str:
    """What a session's map kept out as moving (people walking through), as summary.json counts it."""
    return (f"movers: {m['masked_voxels']} end points in space seen free kept out of the octree, "
            f"{m['cleared_points']} cloud points left out")


def prior_line(p: dict) -> str:
    """What became of a saved map the tracker was given (summary.json `prior_map`)."""
    mode = " (localize: not changed)" if p.get("mode") == "localize" else ""
    if p.get("dropped"):
        return (f"saved map {p['map']}: the camera was not found in it within {p['frames_before']} frames; "
                f"tracked as a separate map in its own world, not merged")
    if p.get("found_at_frame", -1) < 0:
        return f"saved map {p['map']}: the camera was never found in it ({p['frames_before']} frames LOST)"
    n = p.get("placed_keyframes", 0)
    temporary = " (temporary)" if p.get("mode") == "localize" else ""
    placed = f"; {n} keyframe{'s' if n != 1 else ''} made while looking placed in it{temporary}" if n else ""
    n_re = p.get("relocalised", 0)
    after = (f"; then {p['localized']} frames localized in it, {p['carried']} carried by this session's own "
             f"points or the IMU, {p['lost']} lost, {n_re} relocalisation{'s' if n_re != 1 else ''}"
             if "localized" in p else "")
    return (f"saved map {p['map']} ({p['keyframes']} keyframes){mode}: found at frame {p['found_at_frame']}, "
            f"after {p['frames_before']} frames not found (LOST){placed}{after}")
