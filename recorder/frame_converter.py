"""pyrealsense2 frames -> Captures: colour paired with depth, depth aligned to colour, IMU samples.

One converter serves both backends, so everything after the backend is one code path.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyrealsense2 as rs

from octolog.recorder.capture import Capture, MotionSample, VideoFrame


def stamp_ns(frame: Any) -> int:
    """A frame's sensor timestamp (librealsense milliseconds, a double) as integer nanoseconds."""
    return int(round(frame.get_timestamp() * 1e6))


class FrameConverter:
    """pyrealsense2 frames/framesets -> Captures (numpy copies, so device buffers go back at once).

    Colour and depth of one instant form a pair; a pair is aligned (depth registered to colour)
    when asked. librealsense's syncer sometimes hands the two over separately (at start-up, or
    when one is late): a lone frame is held until its partner arrives (same time within half a
    frame period) and paired then; if none comes, it goes out alone and the aligned depth it
    could not make is reported as unpaired.
    """

    def __init__(self, *, align: bool, raw_depth: bool, fps: int) -> None:
        self.align = align
        self.raw_depth = raw_depth
        self._tol_ns = 500_000_000 // max(fps, 1)
        self._aligner = rs.align(rs.stream.color) if align else None
        self._pending: Any = None
        self._partner: Any = None
        self._composed = rs.frame_queue(2, keep_frames=True)
        self._composer = rs.processing_block(self._compose)
        self._composer.start(self._composed)

    def _compose(self, frame: Any, source: Any) -> None:
        source.frame_ready(source.allocate_composite_frame([frame, self._partner]))

    def convert(self, item: Any) -> list[Capture]:
        frames = list(item.as_frameset()) if item.is_frameset() else [item]
        color = depth = None
        motion: list[MotionSample] = []
        seen: list[tuple[str, int]] = []
        for f in frames:
            st = f.get_profile().stream_type()
            if st == rs.stream.color:
                color = f
            elif st == rs.stream.depth:
                depth = f
            elif st in (rs.stream.gyro, rs.stream.accel):
                d = f.as_motion_frame().get_motion_data()
                name = "gyro" if st == rs.stream.gyro else "accel"
                motion.append(MotionSample(name, int(f.get_frame_number()), stamp_ns(f),
                                           (float(d.x), float(d.y), float(d.z))))
                seen.append((name, int(f.get_frame_number())))
        out: list[Capture] = []
        if color is not None and depth is not None:
            out += self.flush()
            out.append(self._pair(color, depth, item if item.is_frameset() else None))
        elif color is not None or depth is not None:
            lone = color if color is not None else depth
            p = self._pending
            if p is not None and p.get_profile().stream_type() != lone.get_profile().stream_type() \
                    and abs(stamp_ns(p) - stamp_ns(lone)) <= self._tol_ns:
                self._pending = None
                c, d = (lone, p) if lone is color else (p, lone)
                out.append(self._pair(c, d, None))
            else:
                out += self.flush()
                self._pending = lone
        if motion:
            out.append(Capture(motion=motion, seen=seen))
        return out

    def flush(self) -> list[Capture]:
        """The held lone frame, if any, as a Capture of its own."""
        if self._pending is None:
            return []
        f, self._pending = self._pending, None
        if f.get_profile().stream_type() == rs.stream.color:
            return [Capture(color=self._video("color", f), seen=[("color", int(f.get_frame_number()))],
                            unpaired=["aligned_depth"] if self.align else [])]
        cap = Capture(seen=[("depth", int(f.get_frame_number()))], unpaired=["aligned_depth"] if self.align else [])
        if self.raw_depth:
            cap.depth = self._video("depth", f)
        return [cap]

    def _pair(self, color: Any, depth: Any, frameset: Any) -> Capture:
        cap = Capture(color=self._video("color", color),
                      seen=[("color", int(color.get_frame_number())), ("depth", int(depth.get_frame_number()))])
        if self.raw_depth:
            cap.depth = self._video("depth", depth)
        if self._aligner is not None:
            if frameset is None:
                self._partner = depth
                self._composer.invoke(color)
                frameset = self._composed.wait_for_frame(1000).as_frameset()
                self._partner = None
            aligned = self._aligner.process(frameset).get_depth_frame()
            # the aligned image is depth measured at the depth frame's time, in colour's geometry
            cap.aligned_depth = self._video("aligned_depth", aligned)
        return cap

    @staticmethod
    def _video(stream: str, f: Any) -> VideoFrame:
        arr = np.asanyarray(f.get_data()).copy()
        return VideoFrame(stream, int(f.get_frame_number()), stamp_ns(f), arr)
