"""The IMU's own figures measured online, each part built and checked alone: its white noise from
its samples (tracker/imu_noise.py: NoiseMeter) and its rotation on the camera and clock offset from
vision's turns (tracker/imu_mounting.py: ImuMounting); and how the buffer, the frame history and the
gyro's weight take them."""

from __future__ import annotations

import numpy as np
import pytest

from octolog.kit.imu import D455, ImuNoise, ImuSamples
from octolog.replay.synthetic_imu import mismatch_rotation, simulate
from octolog.replay.synthetic_trajectory import camera_trajectory
from octolog.tracker.gyro import GyroBias
from octolog.tracker.imu_mounting import ImuMounting
from octolog.tracker.imu_noise import MIN_SAMPLES, NoiseMeter
from octolog.tracker.pose import so3_exp, so3_log
from octolog.tracker.preintegration import FrameHistory, FrameRecord, ImuBuffer

START_NS = 1_000_000_000


def _scaled(k: float) -> ImuNoise:
    return ImuNoise(D455.gyro_noise * k, D455.accel_noise * k, D455.gyro_walk * k, D455.accel_walk * k)


@pytest.mark.parametrize("motion", ["loop", "turns"])
@pytest.mark.parametrize("scale", [0.3, 1.0, 10.0])
def test_the_noise_is_measured_from_the_samples_of_a_moving_camera(motion: str, scale: float) -> None:
    """10 s of the synthetic walk (and of its fast head turns): the densities within 10 % of the
    simulated ones, whatever the datasheet the meter started from says; nothing before MIN_SAMPLES."""
    sim = simulate(lambda t: camera_trajectory(t, motion=motion), 10.0, 200.0, _scaled(scale), seed=3,
                   start_ns=START_NS)
    meter = NoiseMeter(D455)
    meter.add(sim.samples)
    assert meter.measure(START_NS + round(MIN_SAMPLES / 200.0 * 1e9) - 50_000_000) is None
    noise = meter.measure(int(sim.samples.stamp_ns[-1]))
    assert noise is not None
    assert noise.gyro_noise == pytest.approx(D455.gyro_noise * scale, rel=0.1)
    assert noise.accel_noise == pytest.approx(D455.accel_noise * scale, rel=0.1)
    assert noise.gyro_walk / noise.gyro_noise == pytest.approx(D455.gyro_walk / D455.gyro_noise)


def test_the_noise_meter_reads_samples_in_order_and_skips_a_gap() -> None:
    """Batches as they come (a batch overlapping the last is cut), and a dropped stretch of samples
    is no noise: the same densities as without the gap."""
    sim = simulate(lambda t: camera_trajectory(t), 6.0, 200.0, D455, seed=4, start_ns=START_NS)
    s = sim.samples
    whole = NoiseMeter(D455)
    whole.add(s)
    gappy = NoiseMeter(D455)
    keep = np.ones(len(s), bool)
    keep[300:340] = False  # 0.2 s without samples
    for lo in range(0, len(s), 77):  # batches, each overlapping the one before by 3 samples
        sel = np.arange(max(lo - 3, 0), min(lo + 77, len(s)))
        sel = sel[keep[sel]]
        gappy.add(ImuSamples(s.stamp_ns[sel], s.gyro[sel], s.accel[sel]))
    a, b = whole.measure(int(s.stamp_ns[-1])), gappy.measure(int(s.stamp_ns[-1]))
    assert a is not None and b is not None
    assert b.gyro_noise == pytest.approx(a.gyro_noise, rel=0.05)


def _turning_spans(rng: np.random.Generator, n: int, camera_from_imu: np.ndarray, late_s: float,
                   bias: np.ndarray, vision_sigma: float = 0.0):
    """Spans of 0.2 s whose rate changes linearly (as a turn starts or ends): the gyro's rotation in
    the IMU's frame over the span as its clock, `late_s` late, has it (its bias taken out), vision's
    (through the identity the tracker was told), the rate change, the length."""
    dt = 0.2
    for _ in range(n):
        w0 = rng.normal(0.0, 0.5, 3)
        alpha = rng.normal(0.0, 2.0, 3)
        true_imu = w0 * dt + alpha * dt * dt / 2  # the IMU frame's rotation vector, to first order
        gyro_imu = true_imu - alpha * late_s * dt  # its clock late: the rates of late_s earlier
        camera = camera_from_imu @ true_imu + rng.normal(0.0, vision_sigma, 3)
        yield so3_exp(gyro_imu), so3_exp(camera), alpha * dt, dt, bias


def test_the_camera_imu_rotation_and_clock_offset_are_recovered_from_turns() -> None:
    """An IMU turned 5 degrees, 8 ms late, with a bias the tracker already knows: the rotation within
    0.1 degree and the offset within 0.3 ms from a few hundred turning spans; none before the turns
    have spanned two directions."""
    truth = mismatch_rotation(5.0).T
    mounting = ImuMounting(np.eye(4))
    rng = np.random.default_rng(11)
    spans = list(_turning_spans(rng, 400, truth, 0.008, np.zeros(3), vision_sigma=3e-4))
    mounting.add(*spans[0])
    assert mounting.solve_rotation() is None
    for span in spans[1:]:
        mounting.add(*span)
    R = mounting.solve_rotation()
    assert R is not None
    assert np.degrees(np.linalg.norm(so3_log(truth.T @ R))) < 0.1
    late = mounting.solve_late()
    assert late is not None and late == pytest.approx(0.008, abs=3e-4)


def test_a_turn_about_one_axis_only_leaves_the_rotation_unsolved() -> None:
    mounting = ImuMounting(np.eye(4))
    for k in range(200):
        w = np.array([0.0, 0.0, 0.3 + 0.2 * np.sin(k)])
        mounting.add(so3_exp(w * 0.2), so3_exp(w * 0.2), np.zeros(3), 0.2, np.zeros(3))
    assert mounting.solve_rotation() is None


def test_the_buffer_retimes_and_the_history_remounts() -> None:
    """Samples retimed 2 ms earlier part way, and those that come after, are the samples stamped 2 ms
    earlier; the frames' IMU poses turn with the IMU's new place on the camera."""
    t = START_NS + np.arange(0, 400) * 5_000_000
    w = np.zeros((400, 3))
    w[:, 2] = np.arange(400) * 1e-3
    retimed, earlier = ImuBuffer(), ImuBuffer()
    retimed.add(ImuSamples(t[:200], w[:200], np.zeros((200, 3))))
    retimed.retime(2_000_000)
    retimed.add(ImuSamples(t[200:], w[200:], np.zeros((200, 3))))
    earlier.add(ImuSamples(t - 2_000_000, w, np.zeros((400, 3))))
    a, b = retimed.segments(int(t[10]), int(t[390])), earlier.segments(int(t[10]), int(t[390]))
    assert a is not None and b is not None
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert retimed.late_ns == 2_000_000
    history = FrameHistory()
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    history.append(FrameRecord(START_NS, T.copy(), True, True, None))
    move = np.eye(4)
    move[:3, :3] = mismatch_rotation(5.0)
    history.remount(move)
    assert np.allclose(history.last.world_from_imu, T @ move)


def test_a_restarted_gyro_bias_holds_the_bias_it_restarts_from() -> None:
    """After the IMU moved on the camera (Inertial._remount), the gyro's bias starts again from the
    one fitted along with the rotation: nothing read through the old rotation pulls it."""
    bias = GyroBias(D455)
    bias.restart(np.array([0.01, -0.02, 0.003]))
    assert np.array_equal(bias.bg, [0.01, -0.02, 0.003])
    assert np.allclose(np.linalg.solve(bias._H, bias._g), bias.bg)


def test_the_accelerometers_noise_is_measured_on_its_own_samples_not_the_interpolated_ones() -> None:
    """A D455 sends its accelerometer at 100 Hz, the gyro at 200 Hz, and the tracker takes them
    united on the gyro's stamps (kit/imu.py: unite): the interpolation halves the noise it would
    show, so the meter reads the accelerometer's own samples."""
    from octolog.kit.imu import unite

    path = lambda t: camera_trajectory(t)  # noqa: E731
    gyro = simulate(path, 8.0, 200.0, _scaled(3.0), seed=5, start_ns=START_NS).samples
    accel = simulate(path, 8.0, 100.0, _scaled(3.0), seed=6, start_ns=START_NS).samples
    united = unite(gyro.stamp_ns, gyro.gyro, accel.stamp_ns, accel.accel)
    meter = NoiseMeter(D455)
    meter.add(united)
    noise = meter.measure(int(gyro.stamp_ns[-1]))
    assert noise is not None
    assert noise.accel_noise == pytest.approx(3.0 * D455.accel_noise, rel=0.1)
    assert noise.gyro_noise == pytest.approx(3.0 * D455.gyro_noise, rel=0.1)
