"""Small recordings in the formats octolog reads: a TUM folder, a camera-layout MCAP, ROS 1 and ROS 2
bags, and a run of the recorder on pyrealsense2's software device."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from octolog.kit.geometry import Intrinsics
from octolog.kit.mcaplog import McapWriter
from octolog.recorder.config import RecorderConfig
from octolog.schemas import codec, sensormsgs, topics

SMALL = Intrinsics(64, 48, 50.0, 51.0, 31.5, 23.5, (0.1, -0.2, 0.001, 0.002, 0.05))


def make_tum(folder: Path, n: int = 4) -> Path:
    """A tiny TUM-layout folder: random colour, planar depth, depth stamps 5 ms after colour."""
    import cv2

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


def write_ros2_bag(path: Path, *, names: dict[str, str], n: int = 4) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """A rosbag2 (.db3) with Image (bgr8 colour, mono16 depth), CameraInfo and Imu, via rosbags' Writer."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    rng = np.random.default_rng(2)
    out = []

    def hdr(ns: int, frame: str):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id=frame)

    with Writer(path, version=9) as w:
        conns = {k: w.add_connection(v, {"color": "sensor_msgs/msg/Image", "depth": "sensor_msgs/msg/Image",
                                         "info": "sensor_msgs/msg/CameraInfo", "imu": "sensor_msgs/msg/Imu"}[k],
                                     typestore=store) for k, v in names.items()}
        for i in range(n):
            t = 5_000_000_000 + i * 33_333_333
            rgb = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
            depth = rng.integers(0, 9000, (48, 64), dtype=np.uint16)
            out.append((t, rgb, depth))
            Image = T["sensor_msgs/msg/Image"]
            msgs = {
                "color": Image(header=hdr(t, "cam"), height=48, width=64, encoding="bgr8", is_bigendian=0, step=192,
                               data=np.ascontiguousarray(rgb[..., ::-1]).reshape(-1)),
                "depth": Image(header=hdr(t + 4_000_000, "cam"), height=48, width=64, encoding="mono16",
                               is_bigendian=0, step=128, data=depth.reshape(-1).view(np.uint8)),
                "info": T["sensor_msgs/msg/CameraInfo"](
                    header=hdr(t, "cam"), height=48, width=64, distortion_model="plumb_bob",
                    d=np.array(SMALL.distortion), k=SMALL.matrix.reshape(-1), r=np.eye(3).reshape(-1),
                    p=np.zeros(12), binning_x=0, binning_y=0,
                    roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                              do_rectify=False)),
                "imu": T["sensor_msgs/msg/Imu"](
                    header=hdr(t + 1000, "imu"), orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
                    orientation_covariance=np.full(9, -1.0), angular_velocity=T["geometry_msgs/msg/Vector3"](
                        x=0.1, y=0.2, z=0.3), angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=T["geometry_msgs/msg/Vector3"](x=0, y=9.8, z=0),
                    linear_acceleration_covariance=np.zeros(9)),
            }
            for k, conn in conns.items():
                typ = conn.msgtype
                w.write(conn, t + 10_000_000, store.serialize_cdr(msgs[k], typ))
    return out


def write_ros1_bag(path: Path) -> None:
    """A small ROS 1 bag (rosbags' rosbag1 Writer): rgb8 colour, 16UC1 depth, CameraInfo (upper-case K, D)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    T = store.types
    with Writer(path) as w:
        cc = w.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=store)
        dc = w.add_connection("/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image", typestore=store)
        ic = w.add_connection("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        for i in range(3):
            t = 7_000_000_000 + i * 50_000_000
            hdr = T["std_msgs/msg/Header"](seq=i, stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9,
                                                                                         nanosec=t % 10**9),
                                           frame_id="c")
            Image = T["sensor_msgs/msg/Image"]
            w.write(cc, t, store.serialize_ros1(Image(header=hdr, height=48, width=64, encoding="rgb8", is_bigendian=0,
                                                      step=192, data=np.full(48 * 64 * 3, i, np.uint8)),
                                                "sensor_msgs/msg/Image"))
            w.write(dc, t, store.serialize_ros1(Image(header=hdr, height=48, width=64, encoding="16UC1",
                                                      is_bigendian=0, step=128,
                                                      data=np.full(48 * 64, 1000 + i, np.uint16).view(np.uint8)),
                                                "sensor_msgs/msg/Image"))
            w.write(ic, t, store.serialize_ros1(T["sensor_msgs/msg/CameraInfo"](
                header=hdr, height=48, width=64, distortion_model="plumb_bob", D=np.zeros(5),
                K=SMALL.matrix.reshape(-1), R=np.eye(3).reshape(-1), P=np.zeros(12), binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                          do_rectify=False)), "sensor_msgs/msg/CameraInfo"))


def png_bytes(img: np.ndarray) -> bytes:
    """`img` as PNG file bytes."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    assert ok
    return buf.tobytes()


def layout_mcap(path: Path, *, color: topics.Topic = topics.COLOR, depth: topics.Topic | None = topics.ALIGNED_DEPTH,
                info: bool = True, calibration: dict | None = None) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Three frames in octolog's camera layout (`color`, `depth`: raw or compressed topics; `info`: with
    CameraInfo; `calibration`: the file's calibration metadata); the (stamp, rgb, depth) written."""
    rng = np.random.default_rng(3)
    frames = []
    with McapWriter(path) as w:
        if calibration is not None:
            w.add_metadata("calibration", calibration)
        for i in range(3):
            t = 1_000_000_000 + i * 33_000_000
            rgb = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
            d = rng.integers(0, 65535, (48, 64), dtype=np.uint16)
            frames.append((t, rgb, d))
            cm = (sensormsgs.compressed_image_msg(png_bytes(rgb[..., ::-1]), "rgb8; png compressed bgr8", t, "c")
                  if color.msgtype.endswith("CompressedImage") else sensormsgs.image_msg(rgb, t, "c"))
            w.write(color.name, color.msgtype, codec.encode(cm, color.msgtype), log_time_ns=t, publish_time_ns=t)
            if info:
                w.write(topics.COLOR_INFO.name, topics.COLOR_INFO.msgtype,
                        codec.encode(sensormsgs.camera_info_msg(SMALL, t, "c"), topics.COLOR_INFO.msgtype),
                        log_time_ns=t, publish_time_ns=t)
            if depth is not None:
                dm = (sensormsgs.compressed_image_msg(png_bytes(d), "16UC1; png compressed", t + 1, "c")
                      if depth.msgtype.endswith("CompressedImage") else sensormsgs.image_msg(d, t + 1, "c"))
                w.write(depth.name, depth.msgtype, codec.encode(dm, depth.msgtype), log_time_ns=t + 1,
                        publish_time_ns=t + 1)
    return frames


SOFTWARE = RecorderConfig(backend="software")  # the recorder on pyrealsense2's software device


def record_software(tmp_path: Path, cfg: RecorderConfig = SOFTWARE, *, frames: int = 30, name: str = "rec.mcap", **kw):
    """The recorder (recorder.node.run) on pyrealsense2's software device pushing `frames` frames of
    its synthetic pattern into `tmp_path / name` with `cfg`; the backend (what it pushed) and the run's
    result."""
    from octolog.recorder import node
    from octolog.recorder.software_d455 import SoftwareDeviceBackend

    backend = SoftwareDeviceBackend(frames=frames, unplug_after=cfg.software.unplug_after)
    res = node.run(cfg, tmp_path / name, backend=backend, **kw)
    return backend, res
