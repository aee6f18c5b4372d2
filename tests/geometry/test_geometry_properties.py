"""Property-based tests (hypothesis) of the geometry library.

Tolerances are derived from floating-point rounding (eps = 2.2e-16) and the conditioning of each
computation in the parameter domain drawn here; each test says how.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from parproj_ros.geometry import (
    AffineModel,
    GeometryError,
    ParallelProjection,
    affine_to_nonlinear,
    estimate_affine,
    nonlinear_to_affine,
    normalize_pair,
    ptp_forward,
    ptp_inverse,
    quaternion_to_rotation,
    rotation_from_angles,
    rotation_to_quaternion,
)

EPS = float(np.finfo(float).eps)
PIXEL = 12e-6
SETTINGS = settings(max_examples=200, deadline=None)


def _deg(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False).map(math.radians)


@st.composite
def projections(draw: st.DrawFn, s_exp: tuple[float, float] = (-6.0, -3.0)) -> ParallelProjection:
    """L^2 + M^2 <= 0.49 < 0.5, |omega|, |phi| <= 30 deg, |kappa| <= 180 deg, s in [1e-6, 1e-3],
    shifts within +-1 cm of the focal plane."""
    r = draw(st.floats(0.0, 0.7))
    az = draw(_deg(-180.0, 180.0))
    return ParallelProjection(
        L=r * math.cos(az),
        M=r * math.sin(az),
        omega=draw(_deg(-30.0, 30.0)),
        phi=draw(_deg(-30.0, 30.0)),
        kappa=draw(_deg(-180.0, 180.0)),
        s=10.0 ** draw(st.floats(*s_exp)),
        dx=draw(st.floats(-0.01, 0.01)),
        dy=draw(st.floats(-0.01, 0.01)),
    )


def _uv(pp: ParallelProjection) -> tuple[float, float]:
    rd = pp.rotation.T @ pp.direction
    return float(rd[0] / rd[2]), float(rd[1] / rd[2])


# --------------------------------------------------------------------------------------------
# Eq 3 followed by Eqs 4-6 (affine_to_nonlinear)
# --------------------------------------------------------------------------------------------


def _inverse_tolerances(u: float, v: float) -> tuple[float, float, float]:
    """Rounding bounds for affine_to_nonlinear at scene (U, V): (s relative, L/M and A, rotation).

    s^2 = p is the smaller root of p^2 - (T1 + T2) p + T1 T2 - T3^2 with T1 = s^2 (1 + U^2),
    T2 = s^2 (1 + V^2), T3 = s^2 U V; it is computed as a difference of terms of size
    s^2 (2 + U^2 + V^2), so its relative error is delta ~ c eps (2 + U^2 + V^2); c = 64 covers
    the ~30 operations of Eq 3 and T1..T3. s = sqrt(p) inherits <= delta.
    |U| = sqrt(T1 / p - 1): where U^2 >> delta its error is ~delta / |U|, but near the double root
    U = V = 0 (where the two mirror sets meet) it is ~sqrt(delta) ~ 2e-7 at worst; the library
    takes the smaller of |U|, |V| from T3 instead, so the bound uses hypot(U, V). The rotation
    inherits the (U, V) error, plus ordinary rounding ~eps (1 + U^2 + V^2) from the
    z = (n d - U a - V b) / n^2 reconstruction (here 1000 eps (1 + U^2 + V^2)).
    (L, M) is the normalised cross product of the rows: ~eps (1 + U^2 + V^2), same bound; so is
    the reproduction of A1..A8 relative to s.
    """
    g = 1.0 + u * u + v * v
    delta = 64.0 * EPS * (1.0 + g)
    plain = 1e3 * EPS * g
    rot = plain + delta / max(math.hypot(u, v), math.sqrt(delta))
    return delta, plain, rot


@SETTINGS
@given(pp=projections())
def test_eq3_then_inverse_contains_truth(pp):
    # In this domain the angle between (L, M, N) (<= 44.4 deg from vertical) and the scene normal
    # (<= 40.9 deg from vertical) is < 86 deg, so |U|, |V| <= tan 86 ~ 14 and nothing is
    # degenerate. Tolerances: see _inverse_tolerances (from ~4e-13 for U = V = 1 to ~2e-7 at
    # the double root U = V = 0). A wrong set (sign error, swapped rows) is O(1e-2) or more away;
    # the two mirror sets coincide only at U = V = 0, where both are right.
    aff = nonlinear_to_affine(pp)
    inv = affine_to_nonlinear(aff)
    assert 1 <= len(inv.solutions) <= 2
    u, v = _uv(pp)
    tol_s, tol_plain, tol_rot = _inverse_tolerances(u, v)
    r_true = pp.rotation
    dist = [float(np.abs(sol.rotation - r_true).max()) for sol in inv.solutions]
    best = inv.solutions[int(np.argmin(dist))]
    assert min(dist) <= tol_rot
    assert abs(best.s / pp.s - 1.0) <= tol_s
    assert abs(best.L - pp.L) <= tol_plain
    assert abs(best.M - pp.M) <= tol_plain
    assert (best.dx, best.dy) == (pp.dx, pp.dy)
    # The reported (U, V) are the true ones up to the mirror sign, to the same accuracy.
    assert abs(abs(inv.U) - abs(u)) <= tol_rot * (1.0 + abs(u))
    assert abs(abs(inv.V) - abs(v)) <= tol_rot * (1.0 + abs(v))
    assert inv.chosen in inv.solutions


@SETTINGS
@given(pp=projections())
def test_every_inverse_solution_reproduces_affine(pp):
    # Every returned set, the true one and its mirror, must map back (Eq 3) to the same A1..A8;
    # bound: _inverse_tolerances' plain rounding, relative to s (|A| <= s (1 + |U|)). A mirror
    # set with a wrong rotation would differ by O(s).
    aff = nonlinear_to_affine(pp)
    inv = affine_to_nonlinear(aff)
    _, tol_plain, _ = _inverse_tolerances(*_uv(pp))
    for sol in inv.solutions:
        back = nonlinear_to_affine(sol).array
        assert np.abs(back - aff.array).max() <= tol_plain * pp.s
        r = sol.rotation
        assert np.abs(r.T @ r - np.eye(3)).max() < 1e-14  # polar decomposition: orthonormal
        assert sol.N > 0.0
    if len(inv.solutions) == 2:
        # The two are the (U, V) -> (-U, -V) mirror pair: same s, same (L, M, N).
        a, b = inv.solutions
        assert (a.s, a.L, a.M) == (b.s, b.L, b.M)


# --------------------------------------------------------------------------------------------
# Eq 7 round trip
# --------------------------------------------------------------------------------------------


@SETTINGS
@given(
    y=st.floats(-0.1, 0.1),
    c=st.floats(0.05, 20.0),
    psi=_deg(-39.99, 39.99),
)
def test_ptp_round_trip(y, c, psi):
    # With u = y tan(psi) / c, y' = y / (1 - u). If y' carries a relative error d (which can be
    # as large as eps / |1 - u| near the pole u = 1), the inverse gives exactly
    # y (1 + d) / (1 + u d) = y (1 + d (1 - u) / (1 + u d)): the error collapses back to
    # ~eps |y| anywhere on the physical side, so rtol 1e-14 (~45 eps) holds there.
    # Rays at or above the horizon (u >= 1 forward, y' tan(psi)/c <= -1 inverse) have no image:
    # the functions must refuse them rather than return a number.
    u = y * math.tan(psi) / c
    if u >= 1.0:
        with pytest.raises(GeometryError):
            ptp_forward(y, c, psi)
        return
    assume(abs(1.0 - u) > 1e-9)
    yp = float(ptp_forward(y, c, psi))
    assert abs(float(ptp_inverse(yp, c, psi)) - y) <= 1e-14 * abs(y)
    if 1.0 + u <= 0.0:
        with pytest.raises(GeometryError):
            ptp_inverse(y, c, psi)
    elif abs(1.0 + u) > 1e-9:
        yq = float(ptp_inverse(y, c, psi))
        assert abs(float(ptp_forward(yq, c, psi)) - y) <= 1e-14 * abs(y)
    # On the physical side y' has the sign of y, and |y'| >= |y| exactly when y tan(psi) >= 0
    # (the denominator 1 - u is then <= 1).
    assert yp * y >= 0.0
    if u > 0.0:
        assert abs(yp) >= abs(y)
    elif u < 0.0:
        assert abs(yp) <= abs(y)


# --------------------------------------------------------------------------------------------
# Paper 2 Eq 8 normalization
# --------------------------------------------------------------------------------------------


@SETTINGS
@given(
    left=projections(),
    right=projections(),
    seed=st.integers(0, 2**32 - 1),
    with_params=st.booleans(),
)
def test_normalization_zero_y_parallax_linear_x_parallax(left, right, seed, with_params):
    # Base-to-height ratio |d1_xy/N1 - d2_xy/N2| >= 0.05 as asked; the scenes may have
    # different scales, rotations and shifts.
    d1, d2 = left.direction, right.direction
    base = math.hypot(*(d1[:2] / d1[2] - d2[:2] / d2[2]))
    assume(base >= 0.05)
    la, ra = nonlinear_to_affine(left), nonlinear_to_affine(right)
    kw = {"left_params": left, "right_params": right} if with_params else {}
    norm = normalize_pair(la, ra, **kw)
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-5000, 5000, (30, 2)), rng.uniform(-1000, 1000, 30)])
    # Exact parallel data through Eq 1 directly (independent of the affine form).
    ln = norm.apply_left(left.project(pts))
    rn = norm.apply_right(right.project(pts))
    # Tolerance: the normalized coordinates have magnitude up to
    # mag = s_n |P| + shifts (up to ~10 m for s = 1e-3). They pass through Eq 1 (~20 ops), the
    # 2x2 inverse of (A1 A2; A5 A6) (condition <= ~1/cos 86 deg ~ 15 here) and a rotation, so
    # rounding is <= ~300 eps mag ~ 7e-14 mag. Bound: 1e-12 mag. For the IKONOS case
    # (mag ~ 0.1 m) that is 1e-13 m ~ 1e-8 px (an absolute 1e-9 px would not be sound for
    # s = 1e-3, where eps * mag alone is 2e-15 m ~ 2e-10 px); a kappa_n wrong by 1e-8 rad would
    # already give 1e-8 * base * s_n * |Z| ~ 7e-11 mag at the highest points, far above it.
    mag = float(max(np.abs(ln).max(), np.abs(rn).max(), norm.s_n * np.abs(pts).max()))
    tol = 1e-12 * mag
    assert np.abs(ln[:, 1] - rn[:, 1]).max() <= tol
    # x-parallax exactly linear in height: x_n - x_n2 = k Z + p0 with the reported k, p0, and
    # |k| = s_n * base.
    px = ln[:, 0] - rn[:, 0]
    assert np.abs(px - (norm.parallax_per_height * pts[:, 2] + norm.parallax_offset)).max() <= tol
    assert abs(abs(norm.parallax_per_height) - norm.s_n * base) <= 1e-12 * norm.s_n * base
    # Consistency with the exact normalized coordinates from the object points.
    le, re = norm.project_object(pts)
    assert np.abs(le - ln).max() <= tol
    assert np.abs(re - rn).max() <= tol
    # Paper 2 Eq 8 and the steps after it: kappa_n = arctan((N M' - M N') / (N L' - L N'))
    # (modulo 180 deg), average scale and average shifts. The angle test is a cross product of
    # unit-size terms: rounding ~eps, bound 1e-12. s from Eqs 4-6 (when the parameters are not
    # passed) carries delta <= ~6e-12 relative (see _inverse_tolerances): rtol 1e-10.
    num = d1[2] * d2[1] - d1[1] * d2[2]
    den = d1[2] * d2[0] - d1[0] * d2[2]
    kn = norm.kappa_n
    assert abs(math.sin(kn) * den - math.cos(kn) * num) <= 1e-12 * math.hypot(num, den)
    assert abs(norm.s_n / (0.5 * (left.s + right.s)) - 1.0) <= 1e-10
    assert norm.dx_n == 0.5 * (left.dx + right.dx)
    assert norm.dy_n == 0.5 * (left.dy + right.dy)


# --------------------------------------------------------------------------------------------
# Quaternions
# --------------------------------------------------------------------------------------------


@SETTINGS
@given(q=st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4))
def test_quaternion_rotation_round_trip(q):
    # Each element of R from a unit q carries ~4 eps. Shepperd's method divides by
    # k = 4 max(|x|, |y|, |z|, |w|) >= 2 (the largest component is >= 1/2), so no
    # amplification: errors ~10 eps ~ 2e-15; atol 1e-14.
    qa = np.array(q)
    n = float(np.linalg.norm(qa))
    assume(n > 0.1)
    qn = qa / n
    r = quaternion_to_rotation(qa)
    assert np.abs(r.T @ r - np.eye(3)).max() < 1e-14
    assert abs(np.linalg.det(r) - 1.0) < 1e-14
    q2 = rotation_to_quaternion(r)
    assert q2[3] >= 0.0
    assert min(np.abs(q2 - qn).max(), np.abs(q2 + qn).max()) < 1e-14
    np.testing.assert_allclose(quaternion_to_rotation(q2), r, rtol=0, atol=1e-14)


@SETTINGS
@given(w=_deg(-180.0, 180.0), p=_deg(-89.0, 89.0), k=_deg(-180.0, 180.0))
def test_rotation_quaternion_rotation(w, p, k):
    r = rotation_from_angles(w, p, k)
    np.testing.assert_allclose(
        quaternion_to_rotation(rotation_to_quaternion(r)), r, rtol=0, atol=1e-14
    )


# --------------------------------------------------------------------------------------------
# Eq 8 estimation on exact data
# --------------------------------------------------------------------------------------------


@SETTINGS
@given(
    pp=projections(s_exp=(-6.0, -4.0)),
    psi=_deg(-30.0, 30.0),
    n=st.integers(10, 40),
    seed=st.integers(0, 2**32 - 1),
)
def test_estimate_affine_recovers_exact_eq8(pp, psi, n, seed):
    # Points uniform in a box (so well spread in 3-D), scaled so that the scene is as wide as an
    # IKONOS line (|q - A8| <= 0.08 m, 13816 px of 12 um) with c = 10 m; heights span 40 % of
    # the width. Exact Eq 8 data: the minimum of the least squares is the truth.
    # Tolerances: rounding in y is ~eps * 0.1 m ~ 2e-17 m. The roll enters through
    # q^2 tan(psi) / c: its sensitivity d y / d tan(psi) = q^2 / c ~ 6e-4 m at the edges, and the
    # part of q^2 not explained by a linear function of the points is >= ~1/10 of that for 10+
    # random points, so psi is fixed to ~1e-12 rad; 1e-9 rad leaves margin. A: scene errors of
    # ~1e-17 m over a lever arm W = 0.08 m / s give relative errors ~1e-16 x the condition of
    # the scaled design (<~1e3 for 10+ random points) and the Gauss-Newton stop (relative step
    # < 1e-13): rtol 1e-10 of the largest |A|, and 1e-13 m (1e-8 px) on A4, A8.
    c = 10.0
    aff = nonlinear_to_affine(pp)
    rng = np.random.default_rng(seed)
    raw = rng.uniform(-1.0, 1.0, (n, 3)) * np.array([1.0, 1.0, 0.4])
    q_raw = raw @ aff.array[4:7]
    pts = raw * (0.08 / np.abs(q_raw).max())
    x = pts @ aff.array[0:3] + aff.A[3]
    q = pts @ aff.array[4:7] + aff.A[7]
    obs = np.column_stack([x, q / (1.0 + math.tan(psi) * q / c)])
    est = estimate_affine(pts, obs, principal_distance=c, pixel_size=PIXEL, psi=None)
    assert abs(est.psi - psi) < 1e-9
    assert est.sigma0_px < 1e-6
    m_est, m_true = est.affine.matrix, aff.matrix
    assert np.abs(m_est[:, :3] - m_true[:, :3]).max() < 1e-10 * np.abs(m_true[:, :3]).max()
    assert np.abs(m_est[:, 3] - m_true[:, 3]).max() < 1e-13
    assert isinstance(est.affine, AffineModel)
