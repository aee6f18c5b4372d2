"""One test (or a few) per equation of the two papers, against values checked by hand.

Each expected value says in a comment how it was derived by hand (closed forms, with the
arithmetic to 5-7 digits). Conventions are those of shared/papers/ERRATA.md: R = Rx(omega) Ry(phi)
Rz(kappa) maps sensor/scene axes to object axes, (L, M, N) is its third column (pointing up),
scene coordinates are metres in the focal plane, 12 um pixels, c = 10 m.

Two tests document library bugs and fail with the current code (see their comments):
test_angles_from_rotation_near_gimbal_lock_reproduces_rotation and
test_planar_rectification_k_zero.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from parproj_ros.eval import paper
from parproj_ros.geometry import (
    AffineModel,
    ConstantMotion,
    CrabAngleError,
    DegenerateGeometryError,
    DegeneratePointsError,
    GeometryError,
    LineCamera,
    ParallelProjection,
    PushbroomModel,
    SceneObservation,
    TooFewPointsError,
    affine_to_nonlinear,
    angles_from_rotation,
    epipolar_from_affine,
    epipolar_from_points,
    estimate_affine,
    nonlinear_to_affine,
    normalize_pair,
    paper_eqs_4_to_6,
    parameters_from_navigation,
    planar_rectification,
    ptp_forward,
    ptp_inverse,
    quaternion_to_rotation,
    roll_from_rotation,
    rotation_from_angles,
    rotation_to_quaternion,
    space_intersection,
)

C = 10.0  # principal distance, m (IKONOS-like, ERRATA)
PIXEL = 12e-6  # detector pitch, m
D5, D22 = math.radians(5.0), math.radians(22.5)

# Table 2, left scene, at full precision (the paper prints these rounded to 3 digits). Derived
# by hand from Table 1 (roll -5, pitch -22.5, azimuth 0, Z0 = 680 km, Z_av = 0, c = 10 m):
#   L = sin(phi) = sin(-22.5) = -0.3826834
#   M = -sin(omega) cos(phi) = sin 5 cos 22.5 = 0.0871557 * 0.9238795 = 0.0805214
#   scene R = Rx(-5 deg) (see test_eqs_9_to_13_table2), so omega = -5 deg, phi = kappa = 0
#   s = r_s33 c / (Z0 - Z_av) = cos 5 cos 22.5 * 10 / 680000 = 0.9203639 * 1.4705882e-5
#     = 1.353476e-5
#   dx = -A3 * Z_centroid = 5.58495e-6 * 58.4 = 3.2616e-4 (middle line images the centroid at
#   X = Y = 0, Z = -58.4 m: x = A3 Z + A4 = 0 there), dy = 0.
S_LEFT = math.cos(D5) * math.cos(D22) * C / 680_000.0
TABLE2_LEFT = ParallelProjection(
    L=-math.sin(D22),
    M=math.sin(D5) * math.cos(D22),
    omega=-D5,
    phi=0.0,
    kappa=0.0,
    s=S_LEFT,
    dx=3.26e-4,
    dy=0.0,
)


def _rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(b)))


def _box_points(rng: np.random.Generator, n: int, half: float = 5500.0, dz: float = 1000.0):
    """n object points uniform over a 2 half x 2 half x 2 dz box centred on the origin, metres."""
    return np.column_stack([rng.uniform(-half, half, (n, 2)), rng.uniform(-dz, dz, n)])


def _eq8_observations(affine: AffineModel, points: np.ndarray, psi: float, c: float = C):
    """Paper 1 Eq 8 written out independently: x linear, y = q / (1 + tan(psi) q / c)."""
    a = affine.array
    x = points @ a[0:3] + a[3]
    q = points @ a[4:7] + a[7]
    return np.column_stack([x, q / (1.0 + math.tan(psi) * q / c)])


# --------------------------------------------------------------------------------------------
# Rotations and quaternions
# --------------------------------------------------------------------------------------------


def test_rotation_third_column_table1_left():
    # Rz(kappa) leaves e3 fixed, so R e3 = Rx(omega) Ry(phi) e3 = Rx(omega) (sin phi, 0, cos phi)
    # = (sin phi, -sin omega cos phi, cos omega cos phi). With omega = -5, phi = -22.5 deg:
    #   sin(-22.5) = -0.382683, sin 5 cos 22.5 = 0.080521, cos 5 cos 22.5 = 0.920364.
    r = rotation_from_angles(-D5, -D22, 0.0)
    np.testing.assert_allclose(r[:, 2], [-0.38268, 0.080521, 0.92036], atol=6e-6)
    np.testing.assert_allclose(
        r[:, 2],
        [math.sin(-D22), -math.sin(-D5) * math.cos(-D22), math.cos(-D5) * math.cos(-D22)],
        atol=1e-15,
    )


def test_rotation_full_matrix_order_x_y_z():
    # Multiplying out Rx(w) Ry(p) Rz(k) by hand gives
    #   [[cp ck,              -cp sk,              sp    ],
    #    [cw sk + sw sp ck,    cw ck - sw sp sk,   -sw cp],
    #    [sw sk - cw sp ck,    sw ck + cw sp sk,    cw cp]].
    # Any other multiplication order differs in at least one element for these angles.
    w, p, k = 0.3, -0.7, 2.1
    cw, sw, cp, sp, ck, sk = (
        math.cos(w),
        math.sin(w),
        math.cos(p),
        math.sin(p),
        math.cos(k),
        math.sin(k),
    )
    expected = np.array(
        [
            [cp * ck, -cp * sk, sp],
            [cw * sk + sw * sp * ck, cw * ck - sw * sp * sk, -sw * cp],
            [sw * sk - cw * sp * ck, sw * ck + cw * sp * sk, cw * cp],
        ]
    )
    np.testing.assert_allclose(rotation_from_angles(w, p, k), expected, atol=1e-15)


@pytest.mark.parametrize(
    "angles_deg",
    [
        (-5.0, -22.5, 0.0),
        (5.0, 22.5, 0.0),
        (30.0, -60.0, 170.0),
        (-120.0, 80.0, -179.0),
        (0.0, 0.0, 0.0),
        (179.0, -1.0, 90.0),
    ],
)
def test_angles_from_rotation_round_trip(angles_deg):
    # For phi strictly inside (-90, 90) deg the decomposition is unique with omega, kappa in
    # (-180, 180]: omega = atan2(-r23, r33), phi = asin(r13), kappa = atan2(-r12, r11) (from the
    # matrix above). Rounding: each element carries ~1e-16, atan2/asin amplify by <= 1/cos(phi)
    # (<= 5.8 at 80 deg), so 1e-13 rad is ample.
    ang = np.radians(angles_deg)
    got = angles_from_rotation(rotation_from_angles(*ang))
    np.testing.assert_allclose(got, ang, atol=1e-13)


def test_angles_from_rotation_gimbal_lock():
    # At phi = +90 deg only omega + kappa is defined; the library puts it all in omega, kappa = 0.
    # cos(pi/2) = 6e-17, so the matrix is exactly locked and the decomposition exact to rounding.
    r = rotation_from_angles(0.4, math.pi / 2, 0.3)
    om, ph, ka = angles_from_rotation(r)
    assert ka == 0.0
    assert ph == pytest.approx(math.pi / 2, abs=1e-15)
    assert om == pytest.approx(0.7, abs=1e-15)
    np.testing.assert_allclose(rotation_from_angles(om, ph, ka), r, atol=1e-15)


@pytest.mark.parametrize("dp", [1e-6, 1e-8, 1e-10, 2e-12])
def test_angles_from_rotation_near_gimbal_lock_reproduces_rotation(dp):
    # BUG (fails with the current library): near phi = +-90 deg, angles_from_rotation is not an
    # inverse of rotation_from_angles to rounding accuracy. Two causes:
    #  * phi = asin(r13): asin has infinite slope at 1, so phi is off by up to ~sqrt(eps) = 1.5e-8
    #    (r13 = 1 - dp^2/2 rounds to 1 for dp < 1e-8);
    #  * omega = atan2(-r23, r33) and kappa = atan2(-r12, r11) use elements of size cos(phi):
    #    absolute rounding eps in them (any matrix from a product, an SVD or a quaternion has it)
    #    turns into errors eps / cos(phi) in omega + kappa, which the matrix does depend on.
    # Observed: reproduction errors 1.7e-10, 1e-8, 4e-7, 5e-6 for dp = 1e-6 ... 2e-12 (just above
    # the 1e-12 gimbal-lock threshold). A well-conditioned decomposition
    # (phi = atan2(r13, hypot(r11, r12)); kappa = atan2(-r12, r11); omega from
    # R Rz(kappa)^T = Rx(omega) Ry(phi), whose (2,2), (3,2) elements are cos, sin omega) gives
    # <= 1e-15 everywhere, so 1e-12 (~4500 eps) is a sound bound.
    # It matters for affine_to_nonlinear, whose mirror set can lie near phi = -90 deg (e.g.
    # L = -0.6, M = 0.1, omega = 0.3, phi = -90 deg + 1e-9 rad, kappa = 0.5: the returned angles
    # reproduce A1..A8 only to 5e-7 relative).
    r_exact = rotation_from_angles(0.3, math.pi / 2 - dp, 0.5)
    r = quaternion_to_rotation(rotation_to_quaternion(r_exact))  # e.g. attitude from a ROS msg
    assert np.abs(r - r_exact).max() < 1e-15
    back = rotation_from_angles(*angles_from_rotation(r))
    assert np.abs(back - r).max() < 1e-12


def test_quaternion_90_deg_about_z():
    # q = (x, y, z, w) = (0, 0, sin 45, cos 45) is +90 deg about z: x axis -> y axis, y -> -x:
    # R = [[0, -1, 0], [1, 0, 0], [0, 0, 1]] (columns = images of the child axes).
    h = math.sqrt(0.5)
    expected = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(quaternion_to_rotation([0.0, 0.0, h, h]), expected, atol=1e-15)
    # A non-unit quaternion is normalised: (0, 0, 2, 2) is the same rotation.
    np.testing.assert_allclose(quaternion_to_rotation([0.0, 0.0, 2.0, 2.0]), expected, atol=1e-15)
    # And it agrees with the papers' rotation about z.
    np.testing.assert_allclose(rotation_from_angles(0.0, 0.0, math.pi / 2), expected, atol=1e-15)


def test_rotation_to_quaternion_inverse():
    # Rz(90 deg) -> (0, 0, sin 45, cos 45) = (0, 0, 0.7071068, 0.7071068), w >= 0.
    h = math.sqrt(0.5)
    q = rotation_to_quaternion(rotation_from_angles(0.0, 0.0, math.pi / 2))
    np.testing.assert_allclose(q, [0.0, 0.0, h, h], atol=1e-15)
    # 180 deg about x (trace -1, Shepperd's non-trace branch): q = (1, 0, 0, 0).
    np.testing.assert_allclose(
        rotation_to_quaternion(np.diag([1.0, -1.0, -1.0])), [1.0, 0.0, 0.0, 0.0], atol=1e-15
    )
    # Table 1 left scanner attitude: round trip through the quaternion.
    r = rotation_from_angles(-D5, -D22, 0.0)
    np.testing.assert_allclose(quaternion_to_rotation(rotation_to_quaternion(r)), r, atol=1e-15)


@pytest.mark.parametrize(
    "quat",
    [
        [0.0, 0.0, 0.0, 0.0],
        [float("nan"), 0.0, 0.0, 1.0],
        [0.0, float("inf"), 0.0, 1.0],
        [0.0, 0.0, 1.0],
    ],
)
def test_quaternion_invalid_raises(quat):
    with pytest.raises(GeometryError):
        quaternion_to_rotation(quat)


# --------------------------------------------------------------------------------------------
# Paper 1 Eqs 1-6
# --------------------------------------------------------------------------------------------


def test_eq3_table2_left_gives_table3():
    # By hand, with R = Rx(-5 deg) (r11 = 1, r12 = r13 = r21 = r31 = 0, r22 = r33 = cos 5,
    # r23 = sin 5, r32 = -sin 5), den = r13 L + r23 M + r33 N = sin5 M + cos5 N
    #   = 0.0871557 * 0.0805214 + 0.9961947 * 0.9203639 = 0.9238795 (= cos 22.5)
    #   U = L / den = -0.3826834 / 0.9238795 = -0.4142136 (= -tan 22.5)
    #   V = (cos5 M - sin5 N) / den = (0.0802150 - 0.0802150) / den = 0
    #   A1 = s (r11 - r13 U) = s                      = 1.353476e-5  (printed 1.35e-5)
    #   A2 = s (r21 - r23 U) = s sin5 tan22.5         = 4.88620e-7   (printed 4.89e-7)
    #   A3 = s (r31 - r33 U) = s cos5 tan22.5         = 5.58495e-6   (printed 5.59e-6, ERRATA)
    #   A5 = s (r12 - r13 V) = 0
    #   A6 = s (r22 - r23 V) = s cos5                 = 1.348326e-5  (printed 1.35e-5)
    #   A7 = s (r32 - r33 V) = -s sin5                = -1.179632e-6 (printed -1.18e-6)
    #   A4 = dx, A8 = dy.
    aff = nonlinear_to_affine(TABLE2_LEFT).array
    s, t = S_LEFT, math.tan(D22)
    closed = [
        s,
        s * math.sin(D5) * t,
        s * math.cos(D5) * t,
        3.26e-4,
        0.0,
        s * math.cos(D5),
        -s * math.sin(D5),
        0.0,
    ]
    np.testing.assert_allclose(aff, closed, rtol=1e-12, atol=1e-20)
    # Printed Table 3 (3 significant digits: half a unit of the last digit is <= 3.7e-3 relative).
    printed = {0: 1.35e-5, 1: 4.89e-7, 2: 5.585e-6, 3: 3.26e-4, 5: 1.35e-5, 6: -1.18e-6}
    for i, v in printed.items():
        assert aff[i] == pytest.approx(v, rel=5e-3), f"A{i + 1}"
    # A5 and A8 are exactly zero: r12 = r13 = 0 for Rx alone, dy = 0.
    assert aff[4] == 0.0
    assert aff[7] == 0.0
    # ERRATA: the exact A3 is 5.58495e-6 (the paper's 5.59e-6 is a rounding boundary).
    assert aff[2] == pytest.approx(5.58495e-6, rel=2e-6)


def test_eq3_projection_vector_in_kernel():
    # Rows (A1, A2, A3) = s (r1 - r3 U) with r1 . d = U (r3 . d) by definition of U, so
    # (A1, A2, A3) . (L, M, N) = s (r1.d - U r3.d) = 0; likewise for (A5, A6, A7) with V.
    # Rounding: |A| ~ s (1 + |U|), each product ~ eps, so |A . d| <= 1e-14 s is generous.
    for pp in (TABLE2_LEFT, ParallelProjection(0.3, -0.2, 0.25, -0.4, 2.5, 3e-5, 1e-3, -2e-3)):
        m = nonlinear_to_affine(pp).matrix
        d = pp.direction
        assert abs(m[0, :3] @ d) < 1e-14 * pp.s
        assert abs(m[1, :3] @ d) < 1e-14 * pp.s
        # And AffineModel.direction recovers +(L, M, N) (cross product of the rows points up).
        np.testing.assert_allclose(nonlinear_to_affine(pp).direction, d, atol=1e-13)


def test_eq1_hand_example():
    # Vertical-free example by hand: R = I, (L, M, N) = (0.5, 0, sqrt(0.75)), s = 1e-5.
    # Eq 1 third row: 0 = s lambda N + s Z -> lambda = -Z / N; then
    #   x = s (X + lambda L) + dx = s (X - Z tan 30) = 1e-5 (100 - 20 * 0.5773503) = 8.845299e-4
    #   y = s (Y + lambda M) + dy = s Y = 5e-4 (plus the shifts 1e-3, -2e-3).
    pp = ParallelProjection(0.5, 0.0, 0.0, 0.0, 0.0, 1e-5, 1e-3, -2e-3)
    got = pp.project([100.0, 50.0, 20.0])
    np.testing.assert_allclose(got, [8.845299e-4 + 1e-3, 5e-4 - 2e-3], rtol=1e-7)


def test_eq1_direct_equals_affine_after_eq3():
    # Both sides are exact forms of the same linear map. Rounding of either is ~ a few dozen eps
    # times the magnitude of the coordinates (s |P| + |shift|), so 1e-12 of that is ample; a
    # wrong sign or element would show up at the 1e-1 relative level.
    rng = np.random.default_rng(11)
    pts = _box_points(rng, 100)
    for pp in (
        TABLE2_LEFT,
        ParallelProjection(-0.35, 0.4, 0.4, -0.3, -2.0, 2e-5, 3e-3, 1e-3),
        ParallelProjection(0.1, 0.05, -0.2, 0.1, 3.0, 1e-3, -0.5, 0.2),
    ):
        direct = pp.project(pts)
        via_a = nonlinear_to_affine(pp).project(pts)
        scale = pp.s * np.abs(pts).max() + abs(pp.dx) + abs(pp.dy)
        assert np.abs(direct - via_a).max() < 1e-12 * scale


@pytest.mark.parametrize(
    "pp",
    [
        TABLE2_LEFT,
        ParallelProjection(0.38268, -0.0805, math.radians(5.0), 0.0, 0.0, 1.35e-5, -3.26e-4, 0.0),
        ParallelProjection(-0.3, 0.1, 0.05, -0.1, 0.3, 1.3e-5, 1e-3, -2e-3),
        ParallelProjection(0.2, 0.3, -0.2, 0.15, 0.6, 2e-5, 0.0, 5e-4),
    ],
    ids=["table2-left", "table2-right", "generic-1", "generic-2"],
)
def test_eqs_4_to_6_paper_literal_is_one_of_the_solutions(pp):
    # Eqs 4-6 (kappa misprint corrected) pick U with the sign of L; for these sets (x axis
    # towards +X, |omega| < 90) that is the true set. The closed-form inversion has rounding
    # ~1e-15 away from U = 0, so 1e-9 on rotation entries, L, M and relative s is loose but
    # still 8 orders of magnitude below the mirror solution's distance.
    aff = nonlinear_to_affine(pp)
    lit = paper_eqs_4_to_6(aff)
    inv = affine_to_nonlinear(aff)
    dist = [np.abs(sol.rotation - lit.rotation).max() for sol in inv.solutions]
    i = int(np.argmin(dist))
    match = inv.solutions[i]
    assert dist[i] < 1e-9
    assert abs(match.s / lit.s - 1.0) < 1e-9
    assert abs(match.L - lit.L) < 1e-9
    assert abs(match.M - lit.M) < 1e-9
    # The library's paper rule picks the same one, and both equal the true parameters here.
    assert np.abs(inv.chosen.rotation - lit.rotation).max() < 1e-9
    assert np.abs(lit.rotation - pp.rotation).max() < 1e-9
    assert (lit.dx, lit.dy) == (pp.dx, pp.dy)


def test_affine_to_nonlinear_returns_both_mirror_sets():
    # For Table 2 left the mirror set has (U, V) -> (-U, -V) = (+tan 22.5, 0): the same
    # A1..A8 with phi = -45 deg (worked out from z = (n d - U a - V b) / n^2). Both reproduce A.
    aff = nonlinear_to_affine(TABLE2_LEFT)
    inv = affine_to_nonlinear(aff)
    assert len(inv.solutions) == 2
    for sol in inv.solutions:
        np.testing.assert_allclose(
            nonlinear_to_affine(sol).array, aff.array, rtol=0, atol=1e-12 * S_LEFT
        )
    phis = sorted(math.degrees(sol.phi) for sol in inv.solutions)
    assert phis == pytest.approx([-45.0, 0.0], abs=1e-9)
    assert inv.U == pytest.approx(-math.tan(D22), rel=1e-12)
    assert inv.V == pytest.approx(0.0, abs=1e-12)
    assert inv.chosen.phi == pytest.approx(0.0, abs=1e-12)
    # rule="reference" picks the set closest to a reference rotation.
    ref = affine_to_nonlinear(aff, rule="reference", reference=TABLE2_LEFT)
    assert np.abs(ref.chosen.rotation - TABLE2_LEFT.rotation).max() < 1e-12
    with pytest.raises(GeometryError):
        affine_to_nonlinear(aff, rule="reference")


# --------------------------------------------------------------------------------------------
# Paper 1 Eq 7 (PTP)
# --------------------------------------------------------------------------------------------


def test_eq7_ptp_forward_hand_value():
    # tan 5 deg = 0.08748866; y/c tan psi = 0.005 * 0.08748866 = 4.374433e-4;
    # y' = 0.05 / (1 - 4.374433e-4) = 0.05 / 0.9995626 = 0.05002188 m.
    got = float(ptp_forward(0.05, 10.0, D5))
    assert got == pytest.approx(0.05 / (1.0 - 0.005 * math.tan(D5)), rel=1e-15)
    assert got == pytest.approx(0.0500218817, abs=1e-10)
    # Negative y and negative roll: the correction changes sign with y tan(psi).
    assert float(ptp_forward(-0.05, 10.0, -D5)) == pytest.approx(-0.0500218817, abs=1e-10)
    assert float(ptp_forward(-0.05, 10.0, D5)) == pytest.approx(
        -0.05 / (1.0 + 0.005 * math.tan(D5)), rel=1e-15
    )


def test_eq7_ptp_inverse_inverts():
    # y = y' / (1 + y'/c tan psi); substituting y' = y / (1 - y t / c) gives y exactly.
    y = np.linspace(-0.083, 0.083, 11)  # IKONOS half swath: 6908 px * 12 um
    for psi in (D5, -math.radians(5.4096), math.radians(30.0)):
        np.testing.assert_allclose(
            ptp_inverse(ptp_forward(y, C, psi), C, psi), y, rtol=1e-15, atol=1e-18
        )
        np.testing.assert_allclose(
            ptp_forward(ptp_inverse(y, C, psi), C, psi), y, rtol=1e-15, atol=1e-18
        )
    # psi = 0 is the identity.
    np.testing.assert_array_equal(ptp_forward(y, C, 0.0), y)


@pytest.mark.parametrize(
    ("c", "psi"), [(0.0, 0.1), (-1.0, 0.1), (1.0, math.pi / 2), (1.0, float("nan"))]
)
def test_eq7_invalid_parameters_raise(c, psi):
    with pytest.raises(GeometryError):
        ptp_forward(0.01, c, psi)


def test_roll_from_rotation_table1_left():
    # tan(psi) = r32 / r33 = (sin w ck + cw sp sk) / (cw cp) = tan(w) / cos(p) for kappa = 0:
    # atan(tan(-5) / cos(22.5)) = atan(-0.0874887 / 0.9238795) = atan(-0.0946966) = -5.4096 deg.
    psi = roll_from_rotation(rotation_from_angles(-D5, -D22, 0.0))
    assert psi == pytest.approx(math.atan(math.tan(-D5) / math.cos(D22)), abs=1e-15)
    assert math.degrees(psi) == pytest.approx(-5.4096, abs=5e-5)
    # Right scene: +5.4096 deg.
    assert math.degrees(roll_from_rotation(rotation_from_angles(D5, D22, 0.0))) == pytest.approx(
        5.4096, abs=5e-5
    )


def _rigorous_scene_xy(model: PushbroomModel, frame, points: np.ndarray) -> np.ndarray:
    """Rigorous (line, sample) -> scene metres (x, perspective y) via the scene frame."""
    ls = model.project(points)
    return frame.to_scene(ls[:, 0], ls[:, 1])


def test_eq7_exact_on_flat_terrain():
    # On the plane Z = Z_av the perspective ray through y hits G = S + lambda (y r2 - c r3) with
    # lambda = H / (c r33 - y r32); projecting G along r3 = (L, M, N) and reading it along r2
    # gives (H / (c r33)) y / (1 - y r32 / (c r33)): Eq 7 with tan(psi) = r32/r33, exactly.
    # So after PTP the rigorous scanner equals the navigation-derived parallel model on Z = 0
    # to rounding (1e-10 px observed); 1e-6 px is the brief's bound.
    models = paper.scanner_models()
    nav = paper.derive_navigation(models, np.zeros(3))
    rng = np.random.default_rng(7)
    pts = np.column_stack([rng.uniform(-5500.0, 5500.0, (300, 2)), np.zeros(300)])
    for side in paper.SIDES:
        n = nav[side]
        assert n.method == "navigation"
        assert n.psi == pytest.approx(roll_from_rotation(models[side].motion.rotation), abs=0.0)
        obs = _rigorous_scene_xy(models[side], n.frame, pts)
        obs[:, 1] = ptp_forward(obs[:, 1], C, n.psi)
        err_px = np.abs(obs - n.affine.project(pts)).max() / PIXEL
        assert err_px < 1e-6
        # With the nominal roll (5 deg instead of 5.41) it is not exact: Eq 7 needs r32/r33.
        obs_nom = _rigorous_scene_xy(models[side], n.frame, pts)
        obs_nom[:, 1] = ptp_forward(obs_nom[:, 1], C, math.copysign(D5, n.psi))
        assert np.abs(obs_nom - n.affine.project(pts)).max() / PIXEL > 0.1


# --------------------------------------------------------------------------------------------
# Paper 1 Eq 8 (affine + roll from GCP)
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def table3_left_affine() -> AffineModel:
    return nonlinear_to_affine(TABLE2_LEFT)


def test_eq8_exact_data_recovers_parameters(table3_left_affine):
    # Data generated by the Eq 8 model itself (A = Table 3 left, psi = -5.41 deg): the model is
    # exact, so the estimate equals the truth to rounding. Rounding of y is ~1e-17 m; the roll
    # signal q^2 tan(psi)/c is ~5e-4 m over the scene, so psi is fixed to ~1e-13 rad: 1e-9 is
    # safe. A: relative 1e-8 of |A| (errors ~1e-17 m / 5 km lever arm ~ 1e-21 on ~1e-5).
    aff = table3_left_affine
    psi = roll_from_rotation(rotation_from_angles(-D5, -D22, 0.0))
    rng = np.random.default_rng(8)
    pts = _box_points(rng, 40)
    obs = _eq8_observations(aff, pts, psi)
    est = estimate_affine(pts, obs, principal_distance=C, pixel_size=PIXEL, psi=None)
    assert est.psi_estimated
    assert abs(est.psi - psi) < 1e-9
    assert est.sigma0_px < 1e-6
    assert est.redundancy == 2 * 40 - 9
    m_est, m_true = est.affine.matrix, aff.matrix
    assert np.abs(m_est[:, :3] - m_true[:, :3]).max() < 1e-8 * np.abs(m_true[:, :3]).max()
    assert np.abs(m_est[:, 3] - m_true[:, 3]).max() < 1e-12  # metres, 1e-7 px
    # predict() reproduces the perspective observations.
    assert np.abs(est.predict(pts) - obs).max() < 1e-6 * PIXEL
    # Known roll: the same A, psi as given, 8 unknowns.
    known = estimate_affine(pts, obs, principal_distance=C, pixel_size=PIXEL, psi=psi)
    assert not known.psi_estimated
    assert known.psi == pytest.approx(psi, abs=1e-15)
    assert np.abs(known.affine.matrix - m_true).max() < 1e-8 * np.abs(m_true[:, :3]).max()
    assert known.redundancy == 2 * 40 - 8


def test_eq8_generic_affine_exact():
    # A set with every A nonzero and positive roll; same reasoning as above.
    aff = nonlinear_to_affine(ParallelProjection(-0.3, 0.1, 0.05, -0.1, 0.3, 1.3e-5, 1e-3, -2e-3))
    psi = math.radians(7.0)
    pts = _box_points(np.random.default_rng(9), 25)
    est = estimate_affine(
        pts, _eq8_observations(aff, pts, psi), principal_distance=C, pixel_size=PIXEL, psi=None
    )
    assert abs(est.psi - psi) < 1e-9
    assert est.sigma0_px < 1e-6
    assert _rel_err(est.affine.matrix[:, :3], aff.matrix[:, :3]) < 1e-8


def test_eq8_noise_sigma0(table3_left_affine):
    # 0.5 px Gaussian noise on x and y, 200 points, 9 unknowns: redundancy 391, so sigma0 is
    # 0.5 px * (1 +- 1/sqrt(2 * 391)) = 0.5 +- 0.018 px (1 sigma). [0.35, 0.65] is > 8 sigma.
    aff = table3_left_affine
    psi = math.radians(-5.41)
    rng = np.random.default_rng(2004)
    pts = _box_points(rng, 200)
    obs = _eq8_observations(aff, pts, psi) + rng.normal(0.0, 0.5 * PIXEL, (200, 2))
    est = estimate_affine(pts, obs, principal_distance=C, pixel_size=PIXEL, psi=None)
    assert 0.35 <= est.sigma0_px <= 0.65
    assert est.sigma0 == pytest.approx(est.sigma0_px * PIXEL, rel=1e-12)
    # The roll is within 5 of its own standard deviations of the truth.
    sd_psi = math.sqrt(est.covariance[8, 8])
    assert 0.0 < sd_psi < math.radians(1.0)
    assert abs(est.psi - psi) < 5.0 * sd_psi


def test_eq8_too_few_points(table3_left_affine):
    aff = table3_left_affine
    pts = _box_points(np.random.default_rng(1), 5)
    obs = _eq8_observations(aff, pts, 0.0)
    # Affine only (psi fixed): 8 unknowns, 2 equations per point -> 4 points needed.
    with pytest.raises(TooFewPointsError):
        estimate_affine(pts[:3], obs[:3], principal_distance=C, pixel_size=PIXEL, psi=0.0)
    # Roll estimated: 9 unknowns -> 5 points needed.
    with pytest.raises(TooFewPointsError):
        estimate_affine(pts[:4], obs[:4], principal_distance=C, pixel_size=PIXEL, psi=None)
    # Duplicates are counted once: 4 distinct + 1 repeat is still too few for psi=None.
    dup_p = np.vstack([pts[:4], pts[:1]])
    dup_o = np.vstack([obs[:4], obs[:1]])
    with pytest.raises(TooFewPointsError, match="duplicate"):
        estimate_affine(dup_p, dup_o, principal_distance=C, pixel_size=PIXEL, psi=None)
    # 4 distinct points are enough for psi fixed (exactly determined).
    est = estimate_affine(pts[:4], obs[:4], principal_distance=C, pixel_size=PIXEL, psi=0.0)
    assert est.redundancy == 0


def test_eq8_degenerate_points(table3_left_affine):
    aff = table3_left_affine
    rng = np.random.default_rng(2)
    # Coplanar (a tilted plane, not only Z = const): A3, A7 undetermined.
    xy = rng.uniform(-5000.0, 5000.0, (20, 2))
    plane = np.column_stack([xy, 0.1 * xy[:, 0] - 0.05 * xy[:, 1] + 30.0])
    for psi in (0.0, None):
        with pytest.raises(DegeneratePointsError):
            estimate_affine(
                plane,
                _eq8_observations(aff, plane, 0.0),
                principal_distance=C,
                pixel_size=PIXEL,
                psi=psi,
            )
    # Collinear points.
    t = np.linspace(0.0, 1.0, 10)[:, None]
    line = t * np.array([1000.0, 200.0, 50.0]) + np.array([1.0, 2.0, 3.0])
    with pytest.raises(DegeneratePointsError):
        estimate_affine(
            line,
            _eq8_observations(aff, line, 0.0),
            principal_distance=C,
            pixel_size=PIXEL,
            psi=0.0,
        )


def test_eq8_covariance_matches_monte_carlo():
    # The reported covariance (sigma0^2 N^-1, mapped to A1..A8 and psi) should predict the
    # scatter of the estimates over repeated noise. 200 trials: the sample standard deviation
    # has a relative error of 1/sqrt(2 * 199) = 5 %, so [0.8, 1.2] is a 4-sigma band per
    # parameter.
    aff = nonlinear_to_affine(ParallelProjection(-0.3, 0.1, 0.05, -0.1, 0.3, 1.3e-5, 1e-3, -2e-3))
    psi = math.radians(5.4)
    rng = np.random.default_rng(99)
    pts = _box_points(rng, 25)
    exact = _eq8_observations(aff, pts, psi)
    ests, covs = [], []
    for _ in range(200):
        est = estimate_affine(
            pts,
            exact + rng.normal(0.0, PIXEL, exact.shape),
            principal_distance=C,
            pixel_size=PIXEL,
            psi=None,
        )
        ests.append(np.r_[est.affine.array, est.psi])
        covs.append(est.covariance)
    emp_sd = np.std(np.array(ests), axis=0, ddof=1)
    pred_sd = np.sqrt(np.diag(np.mean(covs, axis=0)))
    ratio = emp_sd / pred_sd
    assert np.all((ratio > 0.8) & (ratio < 1.2)), ratio


# --------------------------------------------------------------------------------------------
# Paper 1 Eqs 9-13 (navigation) and the crab angle
# --------------------------------------------------------------------------------------------


def test_eqs_9_to_13_table2():
    # Hand derivation, left scene (omega = -5, phi = -22.5, kappa = 0, V = (7000, 0, 0)):
    #   Eq 9:  (L, M, N) = R_s e3 = (-0.3826834, 0.0805214, 0.9203639)
    #   Eq 11: y = R_s e2 = Rx(w) e2 = (0, cos w, sin w); z = V x y / |V x y| = (0, -sin w, cos w);
    #          x = y x z = (1, 0, 0)  ->  R = Rx(w): omega = -5 deg, phi = kappa = 0
    #   Eq 12: s = cos5 cos22.5 * 10 / 680000 = 1.353476e-5
    #   Eq 13: dy = 0 since the principal ray from Y0 = 680 km tan 5 meets Y = 0 (ERRATA);
    #          dx = -A3 Z_centroid = 5.58495e-6 * 58.4 = 3.2616e-4.
    models = paper.scanner_models()
    nav = paper.derive_navigation(models, np.array([0.0, 0.0, paper.CENTROID_Z]))
    left, right = nav["left"].params, nav["right"].params
    assert nav["left"].method == "navigation"
    assert left.L == pytest.approx(-0.3826834, abs=1e-7)
    assert left.M == pytest.approx(0.0805214, abs=1e-7)
    assert math.degrees(left.omega) == pytest.approx(-5.0, abs=1e-12)
    assert math.degrees(left.phi) == pytest.approx(0.0, abs=1e-12)
    assert math.degrees(left.kappa) == pytest.approx(0.0, abs=1e-12)
    assert left.s == pytest.approx(S_LEFT, rel=1e-12)
    assert left.dx == pytest.approx(5.58495e-6 * 58.4, rel=1e-5)
    assert abs(left.dy) < 1e-12  # metres (1e-7 px)
    # Rounded to the printed digits of Table 2.
    assert round(left.L, 3) == -0.383
    assert round(left.M, 4) == 0.0805
    assert float(f"{left.s:.2e}") == 1.35e-5
    assert float(f"{left.dx:.2e}") == 3.26e-4
    # Right scene: the mirror image (Table 2 right).
    assert right.L == pytest.approx(0.3826834, abs=1e-7)
    assert right.M == pytest.approx(-0.0805214, abs=1e-7)
    assert math.degrees(right.omega) == pytest.approx(5.0, abs=1e-12)
    assert right.dx == pytest.approx(-left.dx, rel=1e-9)
    # Eq 3 of these parameters is what the result carries as its affine (Table 3).
    np.testing.assert_allclose(
        nav["left"].affine.array, nonlinear_to_affine(left).array, rtol=0, atol=1e-20
    )
    np.testing.assert_allclose(
        nav["left"].affine.array[[0, 1, 2, 5, 6]],
        [1.35e-5, 4.89e-7, 5.585e-6, 1.35e-5, -1.18e-6],
        rtol=5e-3,
    )


def _crab_model(kappa_deg: float) -> PushbroomModel:
    cam = LineCamera(C, PIXEL, paper.DETECTORS, paper.LINE_PERIOD)
    rot = rotation_from_angles(-D5, -D22, math.radians(kappa_deg))
    motion = ConstantMotion(
        np.array([-288_000.0, paper.Y0, 680_000.0]), np.array([7000.0, 0.0, 0.0]), rot
    )
    return PushbroomModel(cam, motion)


def test_crab_angle_fallback():
    # Scanner azimuth rotated 2 deg from the velocity (along X). By hand:
    #   y_s = R_s e2, its X component = -sin(kappa) cos(phi) = -0.0348995 * 0.9238795 = -0.032243
    #   crab = asin(-0.032243) = -1.8477 deg
    #   predicted Eqs 10-13 error = s |V . y_s| T / 2 / pixel
    #     = 1.353476e-5 * 225.70 m/s * (10000 / 6500 s) / 2 / 12e-6 = 195.8 px
    model = _crab_model(2.0)
    line_mid = float(model.time_to_line(model.exposure_time(np.zeros(3))))
    kw = {"line_mid": line_mid, "z_avg": 0.0, "scene_lines": 10_000}
    res = parameters_from_navigation(model, **kw)
    assert res.method == "navigation_virtual_gcp"
    assert math.degrees(res.crab_angle) == pytest.approx(-1.8477, abs=1e-4)
    assert res.crab_error_px == pytest.approx(195.82, abs=0.01)
    # What Eqs 9-13 alone give (tolerance disabled) for comparison.
    eqs = parameters_from_navigation(model, crab_tolerance_px=math.inf, **kw)
    assert eqs.method == "navigation"
    # Flat-terrain points over the scene (Z = z_avg, where PTP is exact): the fitted affine
    # stays within 0.01 px of the rigorous model (observed 0.0025 px; the residual is the
    # compromise with the off-plane virtual points), Eqs 9-13 miss by ~ the predicted 196 px.
    ll, ss = np.meshgrid(
        np.linspace(line_mid - 5000, line_mid + 5000, 11),
        np.linspace(0.0, paper.DETECTORS - 1.0, 11),
        indexing="ij",
    )
    flat = model.locate(ll.ravel(), ss.ravel(), np.zeros(ll.size))

    def err_px(r) -> float:
        obs = _rigorous_scene_xy(model, r.frame, flat)
        obs[:, 1] = ptp_forward(obs[:, 1], C, r.psi)
        return float(np.abs(obs - r.affine.project(flat)).max() / PIXEL)

    e_fit, e_eqs = err_px(res), err_px(eqs)
    assert e_fit < 0.01
    assert e_eqs > 100.0
    assert e_eqs > 1e4 * e_fit
    assert res.fit_rms_px < 0.01
    # The non-linear parameters carried with the fit reproduce its A1..A8 (Eq 3).
    np.testing.assert_allclose(
        nonlinear_to_affine(res.params).array, res.affine.array, rtol=0, atol=1e-12 * res.params.s
    )
    with pytest.raises(CrabAngleError):
        parameters_from_navigation(model, allow_fallback=False, **kw)


def test_no_crab_no_fallback():
    model = _crab_model(0.0)
    line_mid = float(model.time_to_line(model.exposure_time(np.zeros(3))))
    res = parameters_from_navigation(
        model, line_mid=line_mid, z_avg=0.0, scene_lines=10_000, allow_fallback=False
    )
    assert res.method == "navigation"
    assert res.crab_angle == 0.0
    assert res.crab_error_px == 0.0
    assert res.fit_rms_px < 1e-6


# --------------------------------------------------------------------------------------------
# Space intersection
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def stereo_pair() -> tuple[AffineModel, AffineModel]:
    models = paper.scanner_models()
    nav = paper.derive_navigation(models, np.array([0.0, 0.0, paper.CENTROID_Z]))
    return nav["left"].affine, nav["right"].affine


def test_space_intersection_exact(stereo_pair):
    # 4 exact linear equations in 3 unknowns: the least-squares solution is the point. The
    # design's condition is ~3.5 (base-to-height ~0.8), so rounding of ~1e-17 m in the scene
    # (1e-16 relative) gives ~1e-11 m in object space; 1e-6 m is the brief's bound.
    left, right = stereo_pair
    pts = _box_points(np.random.default_rng(3), 50)
    res = space_intersection(
        [
            SceneObservation(left, left.project(pts), None),
            SceneObservation(right, right.project(pts), None),
        ]
    )
    assert np.abs(res.points - pts).max() < 1e-6
    assert np.abs(res.residuals).max() < 1e-15  # metres in the scene
    assert res.condition < 10.0
    # Perspective input with the roll: y = ptp_inverse(y') then PTP inside gives the same.
    psi_l, psi_r = -math.radians(5.4096), math.radians(5.4096)
    lxy, rxy = left.project(pts), right.project(pts)
    lxy[:, 1] = ptp_inverse(lxy[:, 1], C, psi_l)
    rxy[:, 1] = ptp_inverse(rxy[:, 1], C, psi_r)
    res2 = space_intersection(
        [SceneObservation(left, lxy, psi_l, C), SceneObservation(right, rxy, psi_r, C)]
    )
    assert np.abs(res2.points - pts).max() < 1e-6


def test_space_intersection_equal_projection_vectors_raise(stereo_pair):
    left, _ = stereo_pair
    pts = _box_points(np.random.default_rng(4), 5)
    xy = left.project(pts)
    with pytest.raises(DegenerateGeometryError):
        space_intersection([SceneObservation(left, xy, None), SceneObservation(left, xy, None)])
    # Same (L, M, N), different scene rotation and scale: still no base (rank 2 design).
    other = nonlinear_to_affine(
        ParallelProjection(TABLE2_LEFT.L, TABLE2_LEFT.M, 0.2, 0.1, -0.4, 2e-5, 0.0, 0.0)
    )
    with pytest.raises(DegenerateGeometryError):
        space_intersection(
            [SceneObservation(left, xy, None), SceneObservation(other, other.project(pts), None)]
        )
    with pytest.raises(GeometryError):
        space_intersection([SceneObservation(left, xy, None)])


# --------------------------------------------------------------------------------------------
# Paper 2: epipolar constraint, planar rectification (Eqs 6-7), normalization (Eq 8)
# --------------------------------------------------------------------------------------------

GENERIC_LEFT = ParallelProjection(-0.3, 0.1, 0.05, -0.1, 0.3, 1.3e-5, 1e-3, -2e-3)
GENERIC_RIGHT = ParallelProjection(0.25, -0.05, -0.05, 0.08, 0.25, 1.4e-5, -1e-3, 3e-3)


@pytest.fixture(
    scope="module",
    params=["paper-pair", "generic-pair"],
)
def pair(request) -> tuple[AffineModel, AffineModel, np.ndarray]:
    if request.param == "paper-pair":
        models = paper.scanner_models()
        nav = paper.derive_navigation(models, np.array([0.0, 0.0, paper.CENTROID_Z]))
        left, right = nav["left"].affine, nav["right"].affine
    else:
        left, right = nonlinear_to_affine(GENERIC_LEFT), nonlinear_to_affine(GENERIC_RIGHT)
    return left, right, _box_points(np.random.default_rng(5), 60)


def test_epipolar_from_affine_exact_points(pair):
    # Eliminating X, Y, Z from the 4 equations x = a.P + A4, y' = b.P + A8, ... gives the null
    # vector g of the 3x4 matrix [a b a2 b2]: g.(x, y', x2, y2') = g.(A4, A8, A4', A8') = k.
    # Residuals are ~eps |g| |coords| ~ 1e-17 m; 1e-14 m (1e-9 px) bounds them.
    left, right, pts = pair
    epi = epipolar_from_affine(left, right)
    assert np.linalg.norm(epi.g) == pytest.approx(1.0, abs=1e-15)
    assert np.abs(epi.residual(left.project(pts), right.project(pts))).max() < 1e-14
    # A point moved across the epipolar line violates it: 1 px in y of the left scene gives
    # a residual of |g2| * 12 um.
    lxy = left.project(pts[:1]) + np.array([0.0, PIXEL])
    r = epi.residual(lxy, right.project(pts[:1]))
    assert abs(r[0]) == pytest.approx(abs(epi.g[1]) * PIXEL, rel=1e-6)


def test_epipolar_from_points_matches_affine(pair):
    # Total least squares on exact conjugate points returns the same null vector (up to sign;
    # both are normalised to |g| = 1). With 4 points the centred 4x4 data has rank 3: exact.
    # Tolerance 1e-9 on g: rounding ~1e-16 divided by the relative smallest nonzero singular
    # value of the centred data (>~1e-4 for spread points).
    left, right, pts = pair
    ref = epipolar_from_affine(left, right)
    for n in (4, 5, 60):
        got = epipolar_from_points(left.project(pts[:n]), right.project(pts[:n]))
        sign = 1.0 if got.g @ ref.g > 0 else -1.0
        assert np.abs(sign * got.g - ref.g).max() < 1e-9
        assert abs(sign * got.k - ref.k) < 1e-9 * max(abs(ref.k), 1e-3)
    with pytest.raises(TooFewPointsError):
        epipolar_from_points(left.project(pts[:3]), right.project(pts[:3]))


def test_planar_rectification_eqs_6_7(pair):
    # Eq 6 with the Eq 7 parameters makes y_n = y_n' for every conjugate pair. y-parallax on
    # exact data is rounding only: coordinates ~1e-2 m, so ~1e-17 m; 1e-12 of a pixel-scaled
    # bound is 1e-9 px.
    left, right, pts = pair
    epi = epipolar_from_affine(left, right)
    rect = planar_rectification(epi)
    ln, rn = rect.apply(left.project(pts), right.project(pts))
    assert np.abs(ln[:, 1] - rn[:, 1]).max() < 1e-9 * PIXEL
    # The printed Eq 7 relations hold (ERRATA: G1 x + G2 y + G3 x' + G4 y' = 1):
    #   tan(theta) = -G1/G2, tan(theta') = -G3/G4,
    #   dy = -sin(t)/(S G1) = cos(t)/(S G2) = S sin(t')/G3 = -S cos(t')/G4.
    g1, g2, g3, g4 = epi.G
    t, t2, s, dy = rect.theta, rect.theta2, rect.S, rect.dy
    assert math.tan(t) == pytest.approx(-g1 / g2, rel=1e-9)
    assert math.tan(t2) == pytest.approx(-g3 / g4, rel=1e-9)
    assert abs(t) <= math.pi / 2
    assert s > 0
    for v in (
        -math.sin(t) / (s * g1),
        math.cos(t) / (s * g2),
        s * math.sin(t2) / g3,
        -s * math.cos(t2) / g4,
    ):
        assert v == pytest.approx(dy, rel=1e-9)


def test_planar_rectification_k_zero():
    # BUG (fails with the current library): the epipolar constant k is 0 whenever
    # g . (A4, A8, A4', A8') = 0, e.g. for the paper's own Table 1 pair when both middle lines
    # image the origin (dx = dy = 0 in both scenes). The rectification exists there (Eq 7:
    # theta, theta', S depend on ratios of G only, and dy = k / (S |(g1, g2)|) = 0), and the
    # module keeps the constraint in homogeneous form precisely so that k = 0 is representable,
    # but planar_rectification goes through EpipolarConstraint.G = g / k and raises
    # DegenerateGeometryError("k = 0 ..."). It is also discontinuous: |k| = 1.01e-15 m works,
    # 0.99e-15 m raises (the threshold is absolute, in metres).
    models = paper.scanner_models()
    nav = paper.derive_navigation(models, np.zeros(3))
    left, right = nav["left"].affine, nav["right"].affine
    epi = epipolar_from_affine(left, right)
    assert abs(epi.k) < 1e-15  # dx = -A3 * 0 = 0, dy = 0 in both scenes
    pts = _box_points(np.random.default_rng(6), 30)
    rect = planar_rectification(epi)
    ln, rn = rect.apply(left.project(pts), right.project(pts))
    assert np.abs(ln[:, 1] - rn[:, 1]).max() < 1e-9 * PIXEL
    assert abs(rect.dy) < 1e-12


def test_normalize_pair_eq8(pair):
    # Both scenes projected along their own (L, M, N) onto Z = 0 and rotated by kappa_n so that
    # the base is along x: y-parallax is 0 and x-parallax = k Z with
    # k = -s_n (cos kn, sin kn).(d1/N1 - d2/N2) (horizontal). Rounding: coordinates ~1e-1 m,
    # errors ~1e-17 m; bounds 1e-9 px for y, and for Z 1e-9 px / |k| (about 1e-9 m here).
    left, right, pts = pair
    norm = normalize_pair(left, right)
    ln, rn = norm.apply_left(left.project(pts)), norm.apply_right(right.project(pts))
    assert np.abs(ln[:, 1] - rn[:, 1]).max() < 1e-9 * PIXEL
    z = norm.height_from_parallax(ln[:, 0] - rn[:, 0])
    assert np.abs(z - pts[:, 2]).max() < 1e-9 * PIXEL / abs(norm.parallax_per_height)
    # Exact normalized coordinates computed from the object points agree with the transformed
    # scene coordinates.
    le, re = norm.project_object(pts)
    assert np.abs(le - ln).max() < 1e-9 * PIXEL
    assert np.abs(re - rn).max() < 1e-9 * PIXEL
    # Hand check of k: |k| = s_n * |d1_xy/N1 - d2_xy/N2|.
    d1, d2 = left.direction, right.direction
    base = np.hypot(*(d1[:2] / d1[2] - d2[:2] / d2[2]))
    assert abs(norm.parallax_per_height) == pytest.approx(norm.s_n * base, rel=1e-12)


def test_normalize_pair_paper_geometry_hand_values(stereo_pair):
    # Table 2 pair: d/N = (L/N, M/N) = (-tan22.5/cos5, tan5) left and the negative right, so the
    # horizontal base per unit height is d1/N1 - d2/N2 = (-2 * 0.4157958, 2 * 0.0874887)
    # = (-0.8315916, 0.1749773); |base| = 0.8498009; |k| = s |base| = 1.150185e-5.
    # kappa_n: the base direction, atan2(0.1749773, -0.8315916) = 168.1176 deg, taken on the
    # branch whose x axis points along the left scene's x axis (+X): -11.8824 deg.
    left, right = stereo_pair
    norm = normalize_pair(left, right)
    bx = -2 * math.tan(D22) / math.cos(D5)
    by = 2 * math.tan(D5)
    assert abs(norm.parallax_per_height) == pytest.approx(S_LEFT * math.hypot(bx, by), rel=1e-9)
    assert abs(norm.parallax_per_height) == pytest.approx(1.150185e-5, rel=1e-6)
    assert math.degrees(norm.kappa_n) == pytest.approx(-11.8824, abs=1e-4)
    assert norm.s_n == pytest.approx(S_LEFT, rel=1e-12)


def test_normalize_pair_nearly_equal_vectors_raise():
    a = nonlinear_to_affine(GENERIC_LEFT)
    near = nonlinear_to_affine(
        ParallelProjection(GENERIC_LEFT.L + 1e-5, GENERIC_LEFT.M, 0.2, 0.1, -0.4, 2e-5, 0.0, 0.0)
    )
    with pytest.raises(DegenerateGeometryError):
        normalize_pair(a, near)
    with pytest.raises(DegenerateGeometryError):
        normalize_pair(a, a)
    with pytest.raises(DegenerateGeometryError):
        epipolar_from_affine(a, a)
