"""Each part of the tracker's IMU (tracker/inertial.py composes them) built and checked alone, on
samples made here from a known motion: the buffer and preintegration, the frame history, vision's
check of the gyro, the gyro's bias, the gravity alignment and the trust in the IMU's poses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from octolog.kit.imu import D455, GRAVITY_MS2, ImuSamples
from octolog.tracker.gravity_alignment import INIT_S, REALIGN_EVERY, GravityAlignment
from octolog.tracker.gyro import (
    GYRO_CHECK_MIN_RAD,
    GYRO_CHECK_SPANS,
    GYRO_SPAN,
    MAX_ROTATION_RESIDUAL,
    GyroBias,
    GyroCheck,
    GyroSpan,
)
from octolog.tracker.inertial import MAX_DISAGREEING, TRUST_FRAMES, TRUST_S, ImuTrust
from octolog.tracker.pose import so3_exp, so3_log
from octolog.tracker.preintegration import (
    MAX_GAP_NS,
    FrameHistory,
    FrameRecord,
    ImuBuffer,
    Preintegrator,
    bias_corrected,
)

START_NS = 1_000_000_000
IMU_HZ = 200.0
FPS = 30.0


def _stamps(hz: float, seconds: float) -> np.ndarray:
    return START_NS + np.round(np.arange(int(seconds * hz) + 1) * (1e9 / hz)).astype(np.int64)


def _frame_ns(i: int) -> int:
    return START_NS + round(i * 1e9 / FPS)


def _constant(gyro, accel, seconds: float) -> ImuSamples:
    t = _stamps(IMU_HZ, seconds)
    return ImuSamples(t, np.tile(np.asarray(gyro, float), (len(t), 1)), np.tile(np.asarray(accel, float), (len(t), 1)))


def _angle(R: np.ndarray) -> float:
    return float(np.linalg.norm(so3_log(R)))


# -- samples and preintegration ------------------------------------------------------------------


def test_a_constant_turn_preintegrates_to_its_angle_and_a_known_bias_takes_it_out() -> None:
    buffer, pre = ImuBuffer(), Preintegrator(D455)
    assert buffer.add(_constant((0.0, 0.0, 0.5), (0.0, 0.0, 2.0), 1.5)) == 301
    seg = buffer.segments(START_NS, START_NS + 1_000_000_000)
    assert seg is not None and float(seg[0].sum()) == pytest.approx(1.0)
    zero = np.zeros(3)
    dR, dp, dv = bias_corrected(pre.integrate(seg, zero, zero), zero, zero)
    np.testing.assert_allclose(so3_log(dR), (0.0, 0.0, 0.5), atol=1e-9)  # 0.5 rad/s for 1 s about z
    np.testing.assert_allclose(dv, (0.0, 0.0, 2.0), atol=1e-9)  # the force along the turn's axis
    np.testing.assert_allclose(dp, (0.0, 0.0, 1.0), atol=1e-9)
    # the gyro's bias, known at integration or re-applied to first order, takes the turn out
    bg = np.array([0.0, 0.0, 0.5])
    assert _angle(bias_corrected(pre.integrate(seg, zero, bg), zero, bg)[0]) < 1e-9
    assert _angle(bias_corrected(pre.integrate(seg, zero, zero), zero, bg)[0]) < 1e-6


def test_the_buffer_measures_only_intervals_its_samples_cover() -> None:
    buffer = ImuBuffer()
    assert buffer.segments(START_NS, START_NS + 10_000_000) is None  # no samples
    buffer.add(_constant((0.1, 0.0, 0.0), (0.0, 9.8, 0.0), 1.0))
    assert buffer.add(_constant((0.1, 0.0, 0.0), (0.0, 9.8, 0.0), 0.5)) == 0  # older than the newest held
    assert buffer.segments(START_NS - 1, START_NS + 10_000_000) is None  # starts before the first sample
    assert buffer.segments(START_NS, START_NS + 1_000_000_000 + MAX_GAP_NS + 1) is None  # runs past the last
    late = START_NS + 1_000_000_000 + 2 * MAX_GAP_NS
    buffer.add(ImuSamples(np.array([late]), np.zeros((1, 3)), np.zeros((1, 3))))
    assert buffer.segments(START_NS + 900_000_000, late) is None  # a silent stretch inside
    seg = buffer.segments(START_NS + 2_500_000, START_NS + 12_500_000)  # between samples: split at them
    assert seg is not None and np.allclose(seg[0], [2.5e-3, 5e-3, 2.5e-3])
    buffer.trim(START_NS + 500_000_000)
    assert buffer.segments(START_NS + 500_000_000, START_NS + 600_000_000) is not None
    assert buffer.segments(START_NS + 490_000_000, START_NS + 600_000_000) is None  # dropped


def test_the_frame_history_chains_placed_frames_and_breaks_where_motion_does() -> None:
    seg = (np.array([0.01]), np.zeros((1, 3)), np.zeros((1, 3)))
    history = FrameHistory()
    assert history.last is None and history.since_visual_s(START_NS) == float("inf")
    for i in range(8):
        relocalised = i in (0, 5)
        history.append(FrameRecord(_frame_ns(i), np.eye(4), i != 7, not relocalised, None if relocalised else seg))
    assert history.chain(2) is None  # the newest is propagated (INERTIAL)
    assert history.newest_chain(10.0) == []
    assert history.since_visual_s(_frame_ns(7)) == pytest.approx(1 / FPS, abs=1e-9)
    history.append(FrameRecord(_frame_ns(8), np.eye(4), True, True, seg))
    assert [r.stamp_ns for r in history.newest_chain(10.0)] == [_frame_ns(8)]
    assert history.segments_since(_frame_ns(5)) is not None and len(history.segments_since(_frame_ns(5))) == 3
    assert history.segments_since(_frame_ns(3)) is None  # the relocalisation at 5 breaks it
    moved = np.eye(4)
    moved[:3, 3] = (1.0, 2.0, 3.0)
    history.rebase(moved)
    assert np.allclose(history.last.world_from_imu[:3, 3], (1.0, 2.0, 3.0))
    history.trim(_frame_ns(6), 2)
    assert history.segments_since(_frame_ns(5)) is None and history.segments_since(_frame_ns(6)) is not None


# -- the gyro against vision ---------------------------------------------------------------------


def _span(rate, seconds: float, *, bias=(0.0, 0.0, 0.0), bg=np.zeros(3), vision_rate=None) -> GyroSpan:
    """A span turning at `rate` (rad/s, constant): the gyro measures rate + bias and is preintegrated
    with `bg`; vision sees `vision_rate` (default: the true rate)."""
    buffer, pre = ImuBuffer(), Preintegrator(D455)
    buffer.add(_constant(np.asarray(rate) + bias, (0.0, 0.0, 0.0), seconds + 0.1))
    seg = buffer.segments(START_NS, START_NS + round(seconds * 1e9))
    assert seg is not None
    pim = pre.integrate(seg, np.zeros(3), bg)
    R0, _, _ = bias_corrected(pim, np.zeros(3), bg)
    vision = so3_exp(np.asarray(rate if vision_rate is None else vision_rate, float) * seconds)
    return GyroSpan(pim, float(seg[0].sum()), R0, vision)


def test_vision_confirms_a_gyro_that_agrees_and_overrules_one_that_does_not() -> None:
    two_frames = 2 / FPS
    turn = np.array([0.0, 1.0, 0.0])  # 1 rad/s: 3.8 degrees over two frames
    off_axis = so3_exp(np.radians(30.0) * np.array([1.0, 0.0, 0.0])) @ turn  # axes 30 degrees apart

    agreeing = GyroCheck()
    assert agreeing.trusted and not agreeing.confirmed  # nothing said yet
    agreeing.add(_span(turn * GYRO_CHECK_MIN_RAD * 0.5 / two_frames, two_frames))  # too small a turn
    assert not agreeing.confirmed
    agreeing.add(_span(turn, two_frames))
    assert agreeing.trusted and agreeing.confirmed

    wrong = GyroCheck()
    for _ in range(GYRO_CHECK_SPANS):
        wrong.add(_span(turn, two_frames, vision_rate=off_axis))
        assert not wrong.trusted and not wrong.confirmed
    for _ in range(GYRO_CHECK_SPANS // 2):  # a minority of agreeing spans does not earn it back
        wrong.add(_span(turn, two_frames))
    assert not wrong.trusted
    for _ in range(GYRO_CHECK_SPANS // 2 + 1):  # a majority of the newest does
        wrong.add(_span(turn, two_frames))
    assert wrong.trusted and wrong.confirmed


def test_the_gyro_bias_converges_on_a_known_bias_from_vision_rotations() -> None:
    truth = np.array([0.01, -0.005, 0.008])
    rate = np.array([0.2, 0.1, -0.3])
    seconds = GYRO_SPAN / FPS
    bias = GyroBias(D455)
    sigma_unknown = bias.rotation_sigma(_segments_turning(rate, 1.0))
    for _ in range(20):
        assert bias.add(_span(rate, seconds, bias=truth, bg=bias.bg), np.zeros(3))
    assert np.linalg.norm(bias.bg - truth) < 0.02 * np.linalg.norm(truth), bias.bg
    # the bias's uncertainty has shrunk from its prior's
    assert bias.rotation_sigma(_segments_turning(rate, 1.0)) < sigma_unknown
    # a span vision placed far off (a bad pose) is no evidence
    before = bias.bg.copy()
    bad = _span(rate, seconds, bias=truth, bg=bias.bg, vision_rate=rate + 3 * MAX_ROTATION_RESIDUAL / seconds)
    assert not bias.add(bad, np.zeros(3)) and np.array_equal(bias.bg, before)


def _segments_turning(rate, seconds: float):
    buffer = ImuBuffer()
    buffer.add(_constant(rate, (0.0, 0.0, 0.0), seconds + 0.1))
    return buffer.segments(START_NS, START_NS + round(seconds * 1e9))


# -- gravity, velocity, the accelerometer's bias -------------------------------------------------

GRAVITY = GRAVITY_MS2 * np.array([0.3, -0.9, 0.2]) / np.linalg.norm([0.3, -0.9, 0.2])  # a tilted world
ACCEL_BIAS = np.array([0.05, -0.03, 0.04])
BODY_RATE = np.array([0.3, -0.2, 0.4])  # rad/s, constant in the IMU's frame


def _pose(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """world_from_imu (4x4), velocity and acceleration (world) of the known path at t (s)."""
    T = np.eye(4)
    T[:3, :3] = so3_exp(BODY_RATE * t)
    T[:3, 3] = (0.2 * np.sin(1.5 * t), 0.1 * np.cos(t), 0.05 * t * t)
    v = np.array([0.3 * np.cos(1.5 * t), -0.1 * np.sin(t), 0.1 * t])
    a = np.array([-0.45 * np.sin(1.5 * t), -0.1 * np.cos(t), 0.1])
    return T, v, a


def _degrees_off(g: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(g @ GRAVITY / (np.linalg.norm(g) * GRAVITY_MS2), -1.0, 1.0))))


def _moving_imu(seconds: float) -> ImuBuffer:
    t_ns = _stamps(IMU_HZ, seconds)
    gyro, accel = [], []
    for t in (t_ns - START_NS) * 1e-9:
        T, _, a = _pose(t)
        gyro.append(BODY_RATE)
        accel.append(T[:3, :3].T @ (a - GRAVITY) + ACCEL_BIAS)  # the specific force, biased
    buffer = ImuBuffer()
    buffer.add(ImuSamples(t_ns, np.array(gyro), np.array(accel)))
    return buffer


def _placed(buffer: ImuBuffer, frames: int) -> FrameHistory:
    history = FrameHistory()
    for i in range(frames):
        seg = None if i == 0 else buffer.segments(_frame_ns(i - 1), _frame_ns(i))
        history.append(FrameRecord(_frame_ns(i), _pose((_frame_ns(i) - START_NS) * 1e-9)[0], True, i > 0, seg))
    return history


def test_the_alignment_recovers_a_known_gravity_velocity_and_accelerometer_bias() -> None:
    buffer = _moving_imu(2.5)
    pre = Preintegrator(D455)
    short = GravityAlignment(pre, D455)
    assert short.due and not short.align(_placed(buffer, int(INIT_S * FPS)), np.zeros(3), True)  # too short
    assert short.gravity is None and short.up is None

    frames = int(2.0 * FPS) + 1
    history = _placed(buffer, frames)
    alignment = GravityAlignment(pre, D455)
    assert alignment.align(history, np.zeros(3), trusted=True)
    assert np.linalg.norm(alignment.gravity) == pytest.approx(GRAVITY_MS2)
    first = _degrees_off(alignment.gravity)
    assert first < 0.5, alignment.gravity  # the bias's prior holds part of it in gravity at first
    assert not alignment.due
    # each alignment's prior is on the bias's change: realigned, the bias comes out of gravity
    for _ in range(30):
        assert alignment.align(history, np.zeros(3), trusted=True)
    assert _degrees_off(alignment.gravity) < min(0.1, first / 3), alignment.gravity
    np.testing.assert_allclose(alignment.ba, ACCEL_BIAS, atol=2e-3)
    np.testing.assert_allclose(alignment.up, -GRAVITY / GRAVITY_MS2, atol=2e-3)
    t_last = (_frame_ns(frames - 1) - START_NS) * 1e-9
    np.testing.assert_allclose(alignment.velocity, _pose(t_last)[1], atol=1e-3)
    for _ in range(REALIGN_EVERY):
        alignment.count_frame()
    assert alignment.due

    # propagated over the next frame interval from the newest frame: where the path goes
    seg = buffer.segments(_frame_ns(frames - 1), _frame_ns(frames))
    pim = pre.integrate(seg, alignment.ba, np.zeros(3))
    dR, dp, dv = bias_corrected(pim, alignment.ba, np.zeros(3))
    T, v = alignment.propagate(history.last.world_from_imu, float(seg[0].sum()), dR, dp, dv)
    truth, v_true, _ = _pose((_frame_ns(frames) - START_NS) * 1e-9)
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 1e-3
    assert _angle(T[:3, :3].T @ truth[:3, :3]) < 1e-6
    np.testing.assert_allclose(v, v_true, atol=3e-3)


def test_an_untrusted_alignment_leaves_up_alone() -> None:
    alignment = GravityAlignment(Preintegrator(D455), D455)
    assert alignment.align(_placed(_moving_imu(2.5), int(2.0 * FPS) + 1), np.zeros(3), trusted=False)
    assert alignment.gravity is not None and alignment.up is None


# -- trust in the IMU's poses --------------------------------------------------------------------


def test_the_imu_earns_trust_by_agreeing_and_loses_it_to_repeated_vetoes() -> None:
    trust = ImuTrust()
    stamps = (round(i * 1e9 / 30) for i in range(10**6))  # 30 fps
    agreeing_for = math.ceil(TRUST_S * 30)  # frames after the first that span TRUST_S
    for _ in range(agreeing_for):
        trust.compare(0.005, next(stamps))
    assert not trust.trusted and not trust.disagrees()  # not yet: no veto
    trust.compare(0.05, next(stamps))  # one frame far off starts the run again
    for _ in range(agreeing_for):
        trust.compare(0.005, next(stamps))
    assert not trust.trusted
    trust.compare(0.005, next(stamps))
    assert trust.trusted
    trust.placed()
    assert all(trust.disagrees() for _ in range(MAX_DISAGREEING))
    assert not trust.disagrees()  # vision wins
    assert not trust.trusted and trust.distrusted == 1


def test_trust_takes_the_same_time_at_any_frame_rate_and_a_few_frames_at_least() -> None:
    """TRUST_S of agreement at 60 fps as at 30; at 5 fps TRUST_FRAMES frames, whatever their span."""
    for fps in (30, 60):
        trust = ImuTrust()
        stamps = [round(i * 1e9 / fps) for i in range(4 * fps)]
        first = next(i for i, t in enumerate(stamps) if (trust.compare(0.001, t), trust.trusted)[1])
        assert stamps[first] >= TRUST_S * 1e9 > stamps[first - 1]
    trust = ImuTrust()
    for i in range(TRUST_FRAMES):
        assert not trust.trusted
        trust.compare(0.001, i * 200_000_000)
    assert trust.trusted
