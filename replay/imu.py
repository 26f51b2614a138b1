"""A replay source's IMU: the samples the replay publishes on `camera/gyro/sample` and
`camera/accel/sample` (sensor_msgs/Imu) before each frame, as a D455 would have sent them.

- The synthetic room with `imu=HZ`: the simulated D455 IMU (replay/synthetic_imu.py), in the colour
  camera's optical frame.
- A TUM-layout folder with `imu.txt` (kit/imu.py: read_imu_txt): in the colour camera's optical frame.
- An octolog recording: its own `camera/gyro/sample` and `camera/accel/sample`, in the frames they
  name (the recording's `/tf_static` places them).

Every N-th frame (`replay.every`) keeps the whole IMU stream: the frames are fewer, the motion the
same. Retimed (`replay.retime`) has none: a faster camera would feel other accelerations.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from octolog.kit.imu import ImuNoise, ImuSamples, read_imu_txt, unite
from octolog.kit.mcaplog import message_counts, read_messages, read_wire
from octolog.replay.sources import McapSource, Retimed, Subsampled, SyntheticSource, TumSource
from octolog.schemas import codec, sensormsgs
from octolog.schemas.topics import ACCEL, GYRO, TRACKING_STATUS

COLOR_FRAME = "camera_color_optical_frame"
IMU_FRAME = "camera_imu_optical_frame"  # a calibration file's IMU, placed on the colour camera by camera_from_imu


@dataclass(frozen=True)
class SourceImu:
    samples: ImuSamples
    frame_id: str  # the IMU's frame (the /tf_static tree places it)
    camera_from_imu: np.ndarray | None = None  # where a calibration file puts it (the replay publishes it)
    # a recording's streams as recorded (stamps, values), and per consumed frame the samples of each
    # its tracker had (TrackingStatus imu_gyro_count, imu_accel_count): the replay hands over those
    streams: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    marks: dict[int, tuple[int, int]] | None = None


def source_imu(source: object) -> SourceImu | None:
    """The IMU samples of a replay source (octolog.replay.sources), None if it has none."""
    if isinstance(source, Subsampled):
        return source_imu(source.inner)
    if isinstance(source, Retimed):
        return None
    if isinstance(source, SyntheticSource):
        sim = source.scene.simulated_imu
        return None if sim is None else SourceImu(sim.samples, COLOR_FRAME)
    if isinstance(source, TumSource):
        return tum_imu(source)
    if isinstance(source, McapSource):
        imu = recorded_imu(source.path)
        if imu is not None and source.only_consumed:
            marks = consumed_imu_marks(source.path)
            return dataclasses.replace(imu, marks=marks) if marks else imu
        return imu
    return None


def source_imu_noise(source: object) -> ImuNoise | None:
    """The IMU's noise a calibration file gives (None: the tracker takes the D455's)."""
    inner = getattr(source, "inner", source)
    return inner.calibration.imu_noise if isinstance(inner, TumSource) and inner.calibration is not None else None


def tum_imu(source: TumSource) -> SourceImu | None:
    """A TUM-layout folder's imu.txt, placed and clocked by its calibration file if it has one."""
    path = source.path / "imu.txt"
    if not path.is_file():
        return None
    samples, cal = read_imu_txt(path), source.calibration
    if cal is None or (cal.camera_from_imu is None and not cal.imu_time_offset_s):
        return SourceImu(samples, COLOR_FRAME)
    shifted = ImuSamples(samples.stamp_ns + round(cal.imu_time_offset_s * 1e9), samples.gyro, samples.accel)
    if cal.camera_from_imu is None:
        return SourceImu(shifted, COLOR_FRAME)
    return SourceImu(shifted, IMU_FRAME, cal.camera_from_imu)


def has_imu(source: object) -> bool:
    """Whether a replay source has IMU samples (a recording by its topic counts, without reading them)."""
    inner = source.inner if isinstance(source, Subsampled) else source
    counts = message_counts(inner.path) if isinstance(inner, McapSource) else None
    if counts is not None:  # a complete recording's summary section
        return all(counts.get(name, 0) >= 2 for name in (GYRO.name, ACCEL.name))
    return source_imu(source) is not None


def recorded_imu(path: Path) -> SourceImu | None:
    """A recording's gyro and accelerometer samples, united on the gyro's stamps (None without both)."""
    streams: dict[str, list[tuple[int, float, float, float]]] = {GYRO.name: [], ACCEL.name: []}
    frame_id = ""
    for m in read_messages(path, [GYRO.name, ACCEL.name]):
        name = m.topic.lstrip("/")
        msg = codec.decode(m.data, GYRO.msgtype)
        v = msg.angular_velocity if name == GYRO.name else msg.linear_acceleration
        streams[name].append((codec.stamp_ns(msg.header), v.x, v.y, v.z))
        if name == GYRO.name:
            frame_id = frame_id or msg.header.frame_id
    if len(streams[GYRO.name]) < 2 or len(streams[ACCEL.name]) < 2:
        return None

    def arrays(rows: list[tuple[int, float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
        return np.array([r[0] for r in rows], np.int64), np.array([r[1:] for r in rows], np.float64)

    logged = arrays(streams[GYRO.name]), arrays(streams[ACCEL.name])  # in log order: as the bus sent them
    (g_ns, g), (a_ns, a) = (arrays(sorted(streams[n])) for n in (GYRO.name, ACCEL.name))
    return SourceImu(unite(g_ns, g, a_ns, a), frame_id, streams=logged)


def consumed_imu_marks(path: Path) -> dict[int, tuple[int, int]]:
    """Per frame a logged tracker consumed, the IMU samples of each stream it had taken by then
    (none: a log from before the record, or without an IMU)."""
    marks = {}
    for m in read_wire(path, [TRACKING_STATUS.name]):
        st = codec.decode(m.data, TRACKING_STATUS.msgtype)
        if st.imu_gyro_count or st.imu_accel_count:
            marks[int(st.seq)] = (int(st.imu_gyro_count), int(st.imu_accel_count))
    return marks


class ImuFeed:
    """Publishes a source's IMU samples up to each frame's stamp just before the frame (one
    numbered publisher per stream: the frame's dependencies bring them to a subscriber first)."""

    LEAD_NS = 50_000_000  # before the first frame: the samples of this long

    def __init__(self, imu: SourceImu | None, gyro_pub, accel_pub, shift_ns: int = 0) -> None:
        self.imu, self.gyro_pub, self.accel_pub, self.shift_ns = imu, gyro_pub, accel_pub, shift_ns
        self.last_ns: int | None = None
        self.count = 0
        self._sent = [0, 0]  # recorded samples sent per stream (as recorded)

    def before(self, seq: int, frame_stamp_ns: int) -> None:
        if self.imu is None:
            return
        if self.imu.marks is not None and self.imu.streams is not None:
            self._as_recorded(self.imu.marks.get(seq))
            return
        t = frame_stamp_ns - self.shift_ns  # on the source's clock
        after = t - self.LEAD_NS if self.last_ns is None else self.last_ns
        batch = self.imu.samples.between(after, t)
        fid = self.imu.frame_id
        for stamp, w, a in zip(batch.stamp_ns.tolist(), batch.gyro.tolist(), batch.accel.tolist()):
            self.gyro_pub.put(sensormsgs.imu_msg(stamp + self.shift_ns, fid, angular_velocity=tuple(w)))
            self.accel_pub.put(sensormsgs.imu_msg(stamp + self.shift_ns, fid, linear_acceleration=tuple(a)))
        self.count += len(batch)
        self.last_ns = max(t, after)

    def _as_recorded(self, mark: tuple[int, int] | None) -> None:
        """Each stream's recorded samples up to the counts the logged tracker had taken at this frame."""
        if mark is None:
            return
        assert self.imu is not None and self.imu.streams is not None
        fid = self.imu.frame_id
        for k, (pub, (stamps, values)) in enumerate(zip((self.gyro_pub, self.accel_pub), self.imu.streams)):
            for i in range(self._sent[k], min(mark[k], len(stamps))):
                v = tuple(values[i].tolist())
                pub.put(sensormsgs.imu_msg(int(stamps[i]), fid, **({"angular_velocity": v} if k == 0 else
                                                                   {"linear_acceleration": v})))
            self._sent[k] = max(self._sent[k], mark[k])
