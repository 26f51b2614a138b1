"""ORB-SLAM3 (RGB-D) behind the native tracker's interface, for comparison: `pyorbslam3`, an extra.

`OrbSlam3Odometry` implements tracker.interface.Tracker like `RgbdSlam`. The ORB-SLAM3 settings file
is generated from the first frame's intrinsics and depth scale; the vocabulary is a DBoW2 text
file (`octolog vocab build` trains one). What the binding does not expose is derived here:

- keyframes: pyorbslam3 0.1.1 reports no keyframe events, so a frame is published as a keyframe
  when its pose is the first valid one or has moved `kf_translation_m` / `kf_rotation_deg` from
  the last published keyframe. ORB-SLAM3's own keyframe count is read at `close()` from its
  keyframe trajectory (`orb_keyframes`);
- states: OK and OK_KLT → OK; RECENTLY_LOST (pose from the motion model) and LOST → LOST;
  not yet initialised → INIT. Without a valid pose the last valid pose is repeated.

ORB-SLAM3 runs local mapping and loop closing on its own threads, so its poses differ run to run:
this backend is outside the determinism contract (GPL-3.0, see docs/dependencies.md).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit.errors import ConfigError, TrackingError
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.tracker.interface import TrackingState, TrackResult
from octolog.tracker.pose import rotation_angle
from octolog.tracker.vocab import check_header

VOCABULARY_ENV = "OCTOLOG_ORB_VOCABULARY"
# A frame is published as a keyframe when its pose moved this far or turned this much from the last
# published one (pyorbslam3 reports no keyframe events).
KEYFRAME_TRANSLATION_M = 0.1
KEYFRAME_ROTATION_DEG = 10.0
# The camera rate written to ORB-SLAM3's settings (ORB-SLAM3 derives its keyframe timing from it).
CAMERA_FPS = 30.0


def _release(slam, folder: Path) -> None:
    """Stop ORB-SLAM3's threads and remove its settings folder: run by `close()`, or when an
    unclosed backend is garbage-collected or the interpreter exits (the tracker node never closes
    its odometry)."""
    try:
        if not slam.is_shutdown():
            slam.shutdown()
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def import_pyorbslam3():
    try:
        import pyorbslam3  # optional (the `orbslam3` extra, GPL-3.0): imported only when this backend is chosen
    except ImportError as exc:
        raise ConfigError(f"tracker.engine orbslam3 needs the pyorbslam3 package (pip install 'octolog[orbslam3]'; "
                          f"import failed: {exc})") from None
    return pyorbslam3


def resolve_vocabulary(path: str = "") -> Path:
    """The vocabulary file: `path` (tracker.vocabulary), else $OCTOLOG_ORB_VOCABULARY, else the
    pyorbslam3 cache (`$PYORBSLAM3_VOCAB` or a vocabulary it downloaded earlier: never downloads)."""
    source = "tracker.vocabulary"
    if not path:
        path, source = os.environ.get(VOCABULARY_ENV, ""), f"${VOCABULARY_ENV}"
    if not path:
        try:
            path, source = import_pyorbslam3().vocabulary_path(download=False), "the pyorbslam3 cache"
        except FileNotFoundError:
            raise ConfigError(f"tracker.engine orbslam3 needs an ORB vocabulary: set tracker.vocabulary or "
                              f"${VOCABULARY_ENV} (build one with `octolog vocab build IMAGE_DIR --out FILE`)"
                              ) from None
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"ORB vocabulary {p} (from {source}): no such file; build one with `octolog vocab build`")
    try:
        check_header(p)
    except Exception as exc:  # InputError: say which setting pointed at it
        raise ConfigError(f"{exc} (from {source})") from None
    return p


def settings_yaml(intr: Intrinsics, depth_scale_m: float, *, n_features: int = 1000, fps: float = 30.0,
                  baseline_m: float = 0.08, th_depth: float = 40.0, scale_factor: float = 1.2, n_levels: int = 8,
                  ini_th_fast: int = 20, min_th_fast: int = 7) -> str:
    """ORB-SLAM3 1.0 settings (the layout of its Examples/RGB-D/TUM1.yaml) for one RGB-D camera.

    RGB-D has no real baseline: `baseline_m` only scales ORB-SLAM3's close/far depth threshold
    (`th_depth` x baseline = 3.2 m by default, TUM's 40 x 0.0773 = 3.1 m).
    """
    dist = tuple(float(x) for x in intr.distortion)
    if len(dist) > 5 and any(dist[5:]):
        raise TrackingError(f"ORB-SLAM3 pinhole model takes k1 k2 p1 p2 k3; got {len(dist)} distortion terms")
    k1, k2, p1, p2, k3 = (dist + (0.0,) * 5)[:5]
    if not depth_scale_m > 0:
        raise TrackingError(f"depth scale {depth_scale_m} m/unit: want > 0")
    return "\n".join([
        "%YAML:1.0",
        'File.version: "1.0"',
        'Camera.type: "PinHole"',
        f"Camera1.fx: {intr.fx!r}", f"Camera1.fy: {intr.fy!r}", f"Camera1.cx: {intr.cx!r}", f"Camera1.cy: {intr.cy!r}",
        f"Camera1.k1: {k1!r}", f"Camera1.k2: {k2!r}", f"Camera1.p1: {p1!r}", f"Camera1.p2: {p2!r}",
        f"Camera1.k3: {k3!r}",
        f"Camera.width: {int(intr.width)}", f"Camera.height: {int(intr.height)}",
        f"Camera.fps: {int(round(fps))}",
        "Camera.RGB: 1",
        f"Stereo.ThDepth: {float(th_depth)!r}", f"Stereo.b: {float(baseline_m)!r}",
        f"RGBD.DepthMapFactor: {1.0 / depth_scale_m!r}",
        f"ORBextractor.nFeatures: {int(n_features)}", f"ORBextractor.scaleFactor: {float(scale_factor)!r}",
        f"ORBextractor.nLevels: {int(n_levels)}", f"ORBextractor.iniThFAST: {int(ini_th_fast)}",
        f"ORBextractor.minThFAST: {int(min_th_fast)}",
        # read even with the viewer off
        "Viewer.KeyFrameSize: 0.05", "Viewer.KeyFrameLineWidth: 1.0", "Viewer.GraphLineWidth: 0.9",
        "Viewer.PointSize: 2.0", "Viewer.CameraSize: 0.08", "Viewer.CameraLineWidth: 3.0",
        "Viewer.ViewpointX: 0.0", "Viewer.ViewpointY: -0.7", "Viewer.ViewpointZ: -1.8", "Viewer.ViewpointF: 500.0",
        "",
    ])


class OrbSlam3Odometry:
    """ORB-SLAM3 RGB-D tracking (a tracker.interface.Tracker). Call `track` once per frame in time
    order, `close` at the end. `n_features` is validated with the config (tracker.n_features)."""

    def __init__(self, vocabulary: str | os.PathLike[str] = "", *, n_features: int = 1000, fps: float = CAMERA_FPS,
                 kf_translation_m: float = KEYFRAME_TRANSLATION_M,
                 kf_rotation_deg: float = KEYFRAME_ROTATION_DEG) -> None:
        self._pos = import_pyorbslam3()
        self.vocabulary = resolve_vocabulary(os.fspath(vocabulary))
        self._n_features = n_features
        self._fps = fps
        self._kf_trans = kf_translation_m
        self._kf_rot = math.radians(kf_rotation_deg)
        self._slam = None
        self._dir: Path | None = None
        self._finalizer: weakref.finalize | None = None
        self._intrinsics: Intrinsics | None = None
        self._depth_scale = 0.0
        self._last_pose = np.eye(4)
        self._last_kf_pose: np.ndarray | None = None
        self._n_kf = 0
        self._kf_poses: dict[int, np.ndarray] = {}  # published keyframes: id -> world_from_camera
        self._stamps: list[int] = []  # every tracked frame's stamp and pose, for `trajectory`
        self._poses: list[np.ndarray] = []
        self.orb_keyframes: int | None = None  # ORB-SLAM3's own count, known after close()
        self.final_trajectory_tum: str | None = None  # its optimised trajectory, after close()
        self.closed = False

    @property
    def n_keyframes(self) -> int:
        """Keyframes published so far (see the module docstring for how they are chosen)."""
        return self._n_kf

    def finish(self) -> dict[int, np.ndarray]:
        """Nothing moved that the tracker process could report: ORB-SLAM3 corrects its map on its own
        threads and pyorbslam3 does not expose keyframe corrections. `close` stops it."""
        return {}

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return {i: T.copy() for i, T in self._kf_poses.items()}

    def trajectory(self) -> tuple[list[int], list[np.ndarray]]:
        """Stamps and poses as they were reported, every tracked frame (the last valid pose when none)."""
        return list(self._stamps), [T.copy() for T in self._poses]

    def keypoints(self) -> None:
        """pyorbslam3 does not expose keypoints."""
        return None

    def local_map(self) -> None:
        """pyorbslam3 does not expose the local map."""
        return None

    def start(self, frame: RgbdFrame) -> None:
        """Write the settings for this camera and start ORB-SLAM3 (loads the vocabulary: seconds)."""
        if self.closed:
            raise TrackingError("ORB-SLAM3 backend already closed")
        text = settings_yaml(frame.intrinsics, frame.depth_scale_m, n_features=self._n_features, fps=self._fps)
        self._dir = Path(tempfile.mkdtemp(prefix="octolog-orbslam3-"))
        settings = self._dir / "settings.yaml"
        settings.write_text(text)
        try:
            self._slam = self._pos.Slam(str(self.vocabulary), str(settings), self._pos.Sensor.RGBD, use_viewer=False)
        except Exception as exc:  # the binding raises RuntimeError/ValueError naming the problem
            shutil.rmtree(self._dir, ignore_errors=True)
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else repr(exc)
            raise TrackingError(f"ORB-SLAM3 did not start: {first}") from None
        self._intrinsics, self._depth_scale = frame.intrinsics, frame.depth_scale_m
        self._finalizer = weakref.finalize(self, _release, self._slam, self._dir)

    def prepare(self, frame: RgbdFrame) -> None:
        return None  # ORB-SLAM3 extracts inside its own Track call

    def track(self, frame: RgbdFrame, prepared: Any = None) -> TrackResult:
        if self._slam is None:
            self.start(frame)
        elif frame.intrinsics != self._intrinsics or frame.depth_scale_m != self._depth_scale:
            raise TrackingError(f"frame {frame.seq}: intrinsics or depth scale changed while tracking")
        if self.closed:
            raise TrackingError("ORB-SLAM3 backend already closed")
        rgb, depth = frame.rgb, frame.depth
        intr = frame.intrinsics
        if rgb.dtype != np.uint8 or rgb.shape[:2] != depth.shape or depth.shape != (intr.height, intr.width):
            raise TrackingError(f"frame {frame.seq}: want uint8 colour and depth of the intrinsics' "
                                f"{intr.width}x{intr.height}, got {rgb.dtype} {rgb.shape} and {depth.shape}")
        try:
            r = self._slam.track_rgbd(np.ascontiguousarray(rgb), depth.astype(np.float32), frame.stamp_ns * 1e-9)
        except (RuntimeError, ValueError) as exc:
            raise TrackingError(f"frame {frame.seq}: ORB-SLAM3: {exc}") from None
        name = r.state.name
        state = TrackingState.OK if name in ("OK", "OK_KLT") \
            else TrackingState.LOST if name in ("RECENTLY_LOST", "LOST") else TrackingState.INIT
        if r.pose_valid and r.pose_wc is not None:
            self._last_pose = np.array(r.pose_wc, dtype=np.float64)
        is_kf = state == TrackingState.OK and self._need_keyframe(self._last_pose)
        kf_id = -1
        if is_kf:
            kf_id = self._n_kf
            self._n_kf += 1
            self._last_kf_pose = self._last_pose.copy()
            self._kf_poses[kf_id] = self._last_pose.copy()
        self._stamps.append(frame.stamp_ns)
        self._poses.append(self._last_pose.copy())
        n = int(r.num_tracked_points)
        return TrackResult(seq=frame.seq, stamp_ns=frame.stamp_ns, world_from_camera=self._last_pose.copy(),
                           state=state, is_keyframe=is_kf, keyframe_id=kf_id, n_matches=n, n_inliers=n)

    def _need_keyframe(self, pose: np.ndarray) -> bool:
        if self._last_kf_pose is None:
            return True
        rel = np.linalg.inv(self._last_kf_pose) @ pose
        return bool(np.linalg.norm(rel[:3, 3]) > self._kf_trans or rotation_angle(rel[:3, :3]) > self._kf_rot)

    def close(self) -> None:
        """Stop ORB-SLAM3's threads; read its keyframe count and final trajectory; remove temp files."""
        if self.closed:
            return
        self.closed = True
        if self._slam is None:
            return
        assert self._dir is not None and self._finalizer is not None
        self._finalizer.detach()
        try:
            self._slam.shutdown()
            kf_file, traj_file = self._dir / "keyframes.txt", self._dir / "trajectory.txt"
            try:
                self._slam.save_keyframe_trajectory_tum(str(kf_file))
                self._slam.save_trajectory_tum(str(traj_file))
                self.orb_keyframes = sum(1 for line in kf_file.read_text().splitlines() if line.strip())
                self.final_trajectory_tum = traj_file.read_text()
            except (OSError, RuntimeError):
                pass  # the figures stay None: nothing was tracked
        finally:
            _release(self._slam, self._dir)
            self._slam = None

    def __enter__(self) -> OrbSlam3Odometry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
