"""TrajectoryBuffer and make_sample: navigation samples -> the constant motion of a scene."""

from __future__ import annotations

import re

import numpy as np
import pytest

from parproj_ros.core.trajectory import NavigationError, NavSample, TrajectoryBuffer, make_sample
from parproj_ros.geometry import quaternion_to_rotation, rotation_from_angles
from parproj_ros.geometry.rotation import rotation_to_quaternion

T0 = 1_700_000_000 * 1_000_000_000
P0 = np.array([-12_345.6, 2_500.25, 680_000.0])
VEL = np.array([7000.0, -35.0, 2.5])
R_BODY = rotation_from_angles(np.radians(-5.0), np.radians(-22.5), np.radians(3.0))
R_MOUNT = rotation_from_angles(np.radians(1.0), np.radians(14.0), np.radians(-2.0))


def sample(t_s: float, *, rot: np.ndarray = R_BODY, pos_offset: float = 0.0) -> NavSample:
    """Exact sample of the constant motion at t_s seconds after T0."""
    return NavSample(T0 + round(t_s * 1e9), P0 + t_s * VEL + pos_offset, rot, VEL)


def filled(t_from: float, t_to: float, rate: float = 20.0) -> TrajectoryBuffer:
    buf = TrajectoryBuffer(max_gap_s=1.0)
    for t in np.arange(t_from, t_to + 1e-9, 1.0 / rate):
        buf.add(sample(float(t)))
    return buf


def ns(t_s: float) -> int:
    return T0 + round(t_s * 1e9)


# ---- exact fit ----------------------------------------------------------------------------------


def test_fit_constant_motion_is_exact_with_mounting() -> None:
    buf = filled(-1.0, 3.0)
    fit = buf.fit(ns(0.5), ns(1.7), R_MOUNT)
    m = fit.motion
    # t0 of the motion is the scene's first line: position there, velocity, R_s = R_body R_mount.
    np.testing.assert_allclose(m.position, P0 + 0.5 * VEL, rtol=0, atol=1e-6)
    np.testing.assert_allclose(m.velocity, VEL, rtol=0, atol=1e-6)
    np.testing.assert_allclose(m.rotation, R_BODY @ R_MOUNT, rtol=0, atol=1e-12)
    assert not np.allclose(m.rotation, R_MOUNT @ R_BODY, atol=1e-3)  # the order matters
    assert m.t0 == 0.0
    np.testing.assert_allclose(m.station(1.2), P0 + 1.7 * VEL, rtol=0, atol=1e-6)
    # Samples used: the last one at or before 0.5 s to the first at or after 1.7 s (0.05 s step).
    assert fit.samples == 25
    assert fit.position_rms_m < 1e-6
    assert fit.attitude_spread_rad < 1e-7
    assert fit.velocity_mismatch < 1e-9


def test_fit_span_between_samples_uses_the_bracketing_samples() -> None:
    buf = filled(0.0, 2.0, rate=10.0)
    fit = buf.fit(ns(0.53), ns(0.91), np.eye(3))
    assert fit.samples == 6  # 0.5, 0.6, ..., 1.0
    np.testing.assert_allclose(fit.motion.position, P0 + 0.53 * VEL, rtol=0, atol=1e-6)


def test_out_of_order_insertion_gives_the_same_fit() -> None:
    ts = np.arange(-1.0, 3.0, 0.05)
    ordered, shuffled = TrajectoryBuffer(), TrajectoryBuffer()
    for t in ts:
        ordered.add(sample(float(t)))
    for t in np.random.default_rng(3).permutation(ts):
        shuffled.add(sample(float(t)))
    assert len(shuffled) == len(ts)
    assert shuffled.last_ns == ns(float(ts[-1]))
    a = ordered.fit(ns(0.1), ns(2.0), R_MOUNT)
    b = shuffled.fit(ns(0.1), ns(2.0), R_MOUNT)
    assert a.samples == b.samples
    np.testing.assert_array_equal(a.motion.position, b.motion.position)
    np.testing.assert_array_equal(a.motion.velocity, b.motion.velocity)
    np.testing.assert_array_equal(a.motion.rotation, b.motion.rotation)


def test_duplicate_time_replaces_the_sample() -> None:
    buf = filled(-1.0, 2.0)
    n = len(buf)
    buf.add(sample(0.5, pos_offset=100.0))  # a wrong sample ...
    assert len(buf) == n
    assert buf.fit(ns(0.0), ns(1.0), np.eye(3)).position_rms_m > 10.0
    buf.add(sample(0.5))  # ... replaced by the right one at the same time
    assert len(buf) == n
    fit = buf.fit(ns(0.0), ns(1.0), np.eye(3))
    assert fit.position_rms_m < 1e-6
    np.testing.assert_allclose(fit.motion.position, P0, rtol=0, atol=1e-6)


def test_covers_and_prune() -> None:
    buf = filled(0.0, 2.0, rate=10.0)
    assert buf.covers(ns(0.0), ns(2.0))
    assert not buf.covers(ns(-0.01), ns(1.0))
    assert not buf.covers(ns(0.5), ns(2.01))
    buf.prune_before(ns(1.05))
    assert len(buf) == 11  # 1.0 (the one before), 1.1, ..., 2.0
    assert buf.covers(ns(1.0), ns(2.0)) and not buf.covers(ns(0.9), ns(2.0))


def test_max_samples_drops_the_oldest() -> None:
    buf = TrajectoryBuffer(max_samples=5)
    for k in range(8):
        buf.add(sample(0.1 * k))
    assert len(buf) == 5
    assert buf.covers(ns(0.3), ns(0.7)) and not buf.covers(ns(0.2), ns(0.7))


# ---- errors -------------------------------------------------------------------------------------


def test_no_samples() -> None:
    with pytest.raises(NavigationError, match="no navigation received"):
        TrajectoryBuffer().fit(ns(0.0), ns(1.0), np.eye(3))


def test_navigation_starts_after_the_first_line() -> None:
    buf = filled(0.5, 3.0)
    with pytest.raises(NavigationError, match=re.escape("starts 0.250 s after the first line")):
        buf.fit(ns(0.25), ns(1.0), np.eye(3))


def test_navigation_ends_before_the_last_line() -> None:
    buf = filled(-1.0, 1.0)
    with pytest.raises(
        NavigationError, match=re.escape("ends 0.375 s before the scene's last line")
    ):
        buf.fit(ns(0.0), ns(1.375), np.eye(3))


def test_gap_inside_the_span() -> None:
    buf = filled(-1.0, 0.4)
    for t in np.arange(2.0, 4.0, 0.05):
        buf.add(sample(float(t)))
    with pytest.raises(NavigationError) as err:
        buf.fit(ns(0.0), ns(3.0), np.eye(3))
    text = str(err.value)
    assert "gap of 1.600 s (> 1.0 s)" in text
    assert "at 0.400 s into the scene" in text
    # The same gap outside the span is harmless.
    assert buf.fit(ns(2.1), ns(3.0), np.eye(3)).samples == 19


def test_single_sample_exactly_on_a_one_line_span() -> None:
    buf = TrajectoryBuffer()
    buf.add(sample(0.0))
    with pytest.raises(NavigationError, match="fewer than 2"):
        buf.fit(ns(0.0), ns(0.0), np.eye(3))


# ---- quality ------------------------------------------------------------------------------------


def test_attitude_spread_reported() -> None:
    buf = TrajectoryBuffer()
    ts = np.arange(0.0, 2.0001, 0.1)
    yaw = np.radians(np.linspace(-0.2, 0.2, ts.size))  # yaw drifts by +-0.2 deg
    for t, y in zip(ts, yaw, strict=True):
        buf.add(sample(float(t), rot=R_BODY @ rotation_from_angles(0.0, 0.0, float(y))))
    fit = buf.fit(ns(0.0), ns(2.0), np.eye(3))
    assert fit.attitude_spread_rad == pytest.approx(np.radians(0.2), rel=1e-6)
    # The mean attitude is the middle one (symmetric drift).
    np.testing.assert_allclose(fit.motion.rotation, R_BODY, rtol=0, atol=1e-10)


def test_position_noise_reported_as_rms() -> None:
    buf = TrajectoryBuffer()
    for k, t in enumerate(np.arange(0.0, 1.0001, 0.1)):
        buf.add(sample(float(t), pos_offset=0.5 if k % 2 else -0.5))  # 11 samples, +-0.5 m
    fit = buf.fit(ns(0.0), ns(1.0), np.eye(3))
    assert 0.45 < fit.position_rms_m < 0.5


def test_velocity_mismatch_when_reported_velocity_disagrees() -> None:
    buf = TrajectoryBuffer()
    for t in np.arange(0.0, 1.0001, 0.1):
        s = sample(float(t))
        buf.add(NavSample(s.t_ns, s.position, s.rotation, 1.1 * VEL))
    fit = buf.fit(ns(0.0), ns(1.0), np.eye(3))
    assert fit.velocity_mismatch == pytest.approx(0.1, rel=1e-6)


# ---- make_sample --------------------------------------------------------------------------------


def test_make_sample_rotates_body_velocity_into_the_object_frame() -> None:
    q = rotation_to_quaternion(R_BODY)
    v_body = R_BODY.T @ VEL
    s = make_sample(ns(1.0), P0, q, v_body)
    assert s.t_ns == ns(1.0)
    np.testing.assert_allclose(s.rotation, R_BODY, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.velocity, VEL, rtol=0, atol=1e-9)
    assert not np.allclose(s.velocity, v_body, atol=1.0)
    # A non-unit quaternion is normalised.
    s2 = make_sample(ns(1.0), P0, 3.0 * q, v_body)
    np.testing.assert_allclose(s2.velocity, VEL, rtol=0, atol=1e-9)


def test_make_sample_velocity_through_fit() -> None:
    # Samples built from body-frame velocities fit with no velocity mismatch.
    q = rotation_to_quaternion(R_BODY)
    buf = TrajectoryBuffer()
    for t in np.arange(0.0, 1.0001, 0.1):
        buf.add(make_sample(ns(float(t)), P0 + float(t) * VEL, q, R_BODY.T @ VEL))
    fit = buf.fit(ns(0.0), ns(1.0), np.eye(3))
    assert fit.velocity_mismatch < 1e-9
    np.testing.assert_allclose(quaternion_to_rotation(q), fit.motion.rotation, atol=1e-12)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_make_sample_rejects_non_finite_position(bad: float) -> None:
    with pytest.raises(NavigationError, match="position is not 3 finite numbers"):
        make_sample(0, np.array([0.0, bad, 1.0]), np.array([0.0, 0.0, 0.0, 1.0]), VEL)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_make_sample_rejects_non_finite_velocity(bad: float) -> None:
    with pytest.raises(NavigationError, match="velocity is not 3 finite numbers"):
        make_sample(0, P0, np.array([0.0, 0.0, 0.0, 1.0]), np.array([bad, 0.0, 0.0]))


@pytest.mark.parametrize(
    "quat", [[0.0, 0.0, 0.0, 0.0], [1e-12, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 1.0]]
)
def test_make_sample_rejects_bad_quaternion(quat: list[float]) -> None:
    with pytest.raises(NavigationError, match="quaternion"):
        make_sample(0, P0, np.array(quat), VEL)


def test_make_sample_rejects_wrong_shapes() -> None:
    with pytest.raises(NavigationError, match="position"):
        make_sample(0, np.zeros(2), np.array([0.0, 0.0, 0.0, 1.0]), VEL)
    with pytest.raises(NavigationError, match="velocity"):
        make_sample(0, P0, np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(4))
