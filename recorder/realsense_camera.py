"""A RealSense camera as a capture backend: device selection by serial, streaming through a
pyrealsense2 pipeline, and detecting a camera that went away."""

from __future__ import annotations

import time
from typing import Any

import pyrealsense2 as rs

from octolog.kit.errors import DeviceLost, RecorderError
from octolog.recorder.capture import CaptureProfile, DeviceDescription
from octolog.recorder.device_profiles import apply_options, describe, resolve

QUEUE_FRAMES = 64  # librealsense's frame queue between its pipeline thread and our capture thread
STALL_S = 3.0  # no frames for this long means the camera is gone (a streaming one sends many a second)
NO_DEVICE = ("no RealSense device found (is the camera plugged in, and does `rs-enumerate-devices` list it?); "
             "without one, the simulated D455 stands in: `octolog record --backend software`, "
             "`octolog run --source d455:software`")


def check_attached() -> None:
    """RecorderError(NO_DEVICE) unless a RealSense device is attached: what a live run checks before
    it writes anything."""
    if not len(rs.context().query_devices()):
        raise RecorderError(NO_DEVICE)


class RealSenseBackend:
    """A RealSense camera through a pyrealsense2 pipeline; frames queue in librealsense
    (QUEUE_FRAMES deep) and go to the recorder as they come. No frames for `stall_s` means the
    camera is gone."""

    realtime = True

    def __init__(self, serial: str = "", *, stall_s: float = STALL_S) -> None:
        self.serial = serial
        self.stall_s = stall_s
        self._pipeline: Any = None
        self._queue: Any = None
        self._last = 0.0

    def open(self, profile: CaptureProfile) -> DeviceDescription:
        devices = list(rs.context().query_devices())
        if not devices:
            raise RecorderError(NO_DEVICE)
        serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
        if self.serial and self.serial not in serials:
            raise RecorderError(f"no RealSense device with serial {self.serial} (attached: {', '.join(serials)})")
        device = devices[serials.index(self.serial)] if self.serial else devices[0]
        self.serial = device.get_info(rs.camera_info.serial_number)
        res = resolve(device, profile)
        options = apply_options(res, profile.options)
        cfg = rs.config()
        cfg.enable_device(self.serial)
        for stream, (_, p) in res.profiles.items():
            if p.is_video_stream_profile():
                v = p.as_video_stream_profile()
                cfg.enable_stream(p.stream_type(), v.width(), v.height(), p.format(), p.fps())
            else:
                cfg.enable_stream(p.stream_type(), p.format(), p.fps())
        self._queue = rs.frame_queue(QUEUE_FRAMES, keep_frames=True)
        self._pipeline = rs.pipeline()
        try:
            self._pipeline.start(cfg, self._queue.enqueue)
        except RuntimeError as exc:
            raise RecorderError(f"cannot start streaming from {self.serial}: {exc}") from None
        self._last = time.monotonic()
        return describe(device, res, "realsense", options)

    def wait(self, timeout_s: float) -> list[Any] | None:
        ok, frame = self._queue.try_wait_for_frame(int(timeout_s * 1000))
        if not ok:
            if time.monotonic() - self._last > self.stall_s:
                attached = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
                if self.serial not in attached:
                    raise DeviceLost(f"camera {self.serial} disconnected")
                raise DeviceLost(f"camera {self.serial} sent no frames for {self.stall_s:.0f} s")
            return []
        self._last = time.monotonic()
        out = [frame]
        while (more := self._queue.poll_for_frame()):
            out.append(more)
        return out

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass  # already gone with the device
            self._pipeline = None
