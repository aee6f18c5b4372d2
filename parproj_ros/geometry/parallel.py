"""The parallel projection model of a linear array scanner scene (paper 1, section 3).

Frames and units used throughout:

* object space: a local Cartesian, right-handed frame with Z up; coordinates in metres;
* scene space: the scene plane of paper 1 Eq 1, coordinates (x, y') in metres in the focal plane
  (one pixel = the detector pitch, e.g. 12e-6 m); x along track, y' across track (along the scan
  line) after the perspective-to-parallel (PTP) correction of Eq 7;
* angles in radians unless a name ends in ``_deg``.

The non-linear form (``ParallelProjection``: L, M, omega, phi, kappa, s, dx, dy) and the linear
form (``AffineModel``: A1..A8) describe the same mapping (Eqs 1 and 2); Eq 3 goes one way and
Eqs 4-6 the other. The inverse has two solutions with identical A1..A8 (the "mirror" sets,
shared/papers/ERRATA.md): :func:`affine_to_nonlinear` returns both and says which it picked.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import DegenerateGeometryError, GeometryError
from .rotation import angles_from_rotation, rotation_from_angles

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ParallelProjection:
    """Non-linear scene parallel projection parameters (paper 1 Eq 1).

    Attributes:
        L: X component of the unit projection vector (object frame, points from ground to sensor).
        M: Y component of the unit projection vector.
        omega: scene plane rotation about X, radians (R = Rx(omega) Ry(phi) Rz(kappa)).
        phi: scene plane rotation about Y, radians.
        kappa: scene plane rotation about Z, radians.
        s: scale, scene metres per object metre (dimensionless), > 0.
        dx: shift along x, metres in the scene plane.
        dy: shift along y', metres in the scene plane.

    """

    L: float
    M: float
    omega: float
    phi: float
    kappa: float
    s: float
    dx: float
    dy: float

    @property
    def N(self) -> float:  # noqa: N802 - the paper's symbol
        """Z component of the unit projection vector, sqrt(1 - L^2 - M^2) >= 0."""
        return float(np.sqrt(max(0.0, 1.0 - self.L**2 - self.M**2)))

    @property
    def direction(self) -> FloatArray:
        """Unit projection vector (L, M, N), object frame, pointing up towards the sensor."""
        return np.array([self.L, self.M, self.N])

    @property
    def rotation(self) -> FloatArray:
        """Scene rotation R (columns: scene x, y, z axes in the object frame)."""
        return rotation_from_angles(self.omega, self.phi, self.kappa)

    def project(self, points: ArrayLike) -> FloatArray:
        """Object points (..., 3) in metres -> scene coordinates (..., 2) (x, y') in metres (Eq 1).

        Evaluated directly from Eq 1 (lambda from its third row), not through A1..A8.
        """
        p = np.asarray(points, dtype=float)
        rt = self.rotation.T
        d_scene = rt @ self.direction
        p_scene = p @ rt.T
        lam = -p_scene[..., 2] / d_scene[2]
        xy = self.s * (p_scene[..., :2] + lam[..., None] * d_scene[:2])
        return np.asarray(xy + np.array([self.dx, self.dy]), dtype=float)


@dataclass(frozen=True)
class AffineModel:
    """Linear form of the parallel projection, the "2-D affine" A1..A8 (paper 1 Eq 2).

    ``x = A1 X + A2 Y + A3 Z + A4`` and ``y' = A5 X + A6 Y + A7 Z + A8`` with X, Y, Z in object
    metres and x, y' in scene metres. A1..A3, A5..A7 are dimensionless; A4, A8 are metres.
    """

    A: tuple[float, float, float, float, float, float, float, float]

    @classmethod
    def from_array(cls, values: ArrayLike) -> AffineModel:
        """Build from any 8 finite numbers A1..A8."""
        v = np.asarray(values, dtype=float).reshape(-1)
        if v.shape != (8,) or not np.all(np.isfinite(v)):
            raise GeometryError(f"an affine model needs 8 finite numbers, got {v}")
        return cls(tuple(float(a) for a in v))  # type: ignore[arg-type]

    @property
    def array(self) -> FloatArray:
        """A1..A8 as a float array of shape (8,)."""
        return np.array(self.A, dtype=float)

    @property
    def matrix(self) -> FloatArray:
        """2x4 matrix [[A1 A2 A3 A4], [A5 A6 A7 A8]] so that (x, y') = M @ (X, Y, Z, 1)."""
        return self.array.reshape(2, 4)

    @property
    def direction(self) -> FloatArray:
        """Unit projection vector implied by A: along (A1,A2,A3) x (A5,A6,A7) (see Eq 4).

        For any proper scene rotation this cross product points along +(L, M, N); a model whose
        cross product points downwards (N < 0) has no valid non-linear form.
        """
        m = self.matrix
        c = np.cross(m[0, :3], m[1, :3])
        n = float(np.linalg.norm(c))
        if n == 0.0 or not np.isfinite(n):
            raise DegenerateGeometryError(
                "A1..A3 and A5..A7 are parallel or zero: the affine model is degenerate"
            )
        out: FloatArray = np.asarray(c / n, dtype=float)
        return out

    def project(self, points: ArrayLike) -> FloatArray:
        """Object points (..., 3) in metres -> scene coordinates (..., 2) (x, y') in metres."""
        p = np.asarray(points, dtype=float)
        m = self.matrix
        return np.asarray(p @ m[:, :3].T + m[:, 3], dtype=float)


def nonlinear_to_affine(pp: ParallelProjection) -> AffineModel:
    """Paper 1 Eq 3: non-linear parameters -> A1..A8.

    U and V are the scene x and y components of the projection vector divided by its z component.
    """
    r = pp.rotation
    d = pp.direction
    rd = r.T @ d
    if abs(rd[2]) < 1e-12:
        raise DegenerateGeometryError("projection vector lies in the scene plane (U, V infinite)")
    u, v = rd[0] / rd[2], rd[1] / rd[2]
    a = pp.s * (r[:, 0] - r[:, 2] * u)
    b = pp.s * (r[:, 1] - r[:, 2] * v)
    return AffineModel.from_array([a[0], a[1], a[2], pp.dx, b[0], b[1], b[2], pp.dy])


SelectionRule = Literal["paper", "reference"]


@dataclass(frozen=True)
class AffineInversion:
    """Result of :func:`affine_to_nonlinear`.

    Attributes:
        solutions: every valid non-linear parameter set reproducing A1..A8 (one or two; two are
            "mirror" sets with (U, V) -> (-U, -V)).
        chosen: the picked solution.
        rule: which rule picked it, in words a user can check.
        U: the (U, V) of the chosen solution (Eq 5), dimensionless.
        V: see U.

    """

    solutions: tuple[ParallelProjection, ...]
    chosen: ParallelProjection
    rule: str
    U: float
    V: float


def _solutions_uv(affine: AffineModel) -> tuple[float, float, float]:
    """Scale s and |U|, signed V/U ratio information from T1, T2, T3 (Eq 5, closed form).

    Returns (s, |U|, V_for_positive_U). The quadratic of Eq 5 in w = U^2 is equivalent to
    p^2 - (T1 + T2) p + T1 T2 - T3^2 = 0 in p = s^2, whose smaller root is the only one with
    U^2, V^2 >= 0.
    """
    m = affine.matrix
    a, b = m[0, :3], m[1, :3]
    t1, t2, t3 = float(a @ a), float(b @ b), float(a @ b)
    disc = float(np.hypot(t1 - t2, 2.0 * t3))
    p = 0.5 * ((t1 + t2) - disc)
    if not p > 0.0:
        raise DegenerateGeometryError("affine model has no positive scale (T1 T2 <= T3^2)")
    u_abs = float(np.sqrt(max(0.0, t1 / p - 1.0)))
    v_abs = float(np.sqrt(max(0.0, t2 / p - 1.0)))
    # The smaller of |U|, |V| comes more accurately from T3 = s^2 U V (Eq 5's V) than from a
    # square root of a difference that rounding leaves near zero.
    if u_abs >= v_abs and u_abs > 0.0:
        v_for_pos_u = t3 / (p * u_abs)
    elif v_abs > 0.0:
        u_abs = abs(t3) / (p * v_abs)
        v_for_pos_u = v_abs if t3 >= 0 else -v_abs
    else:
        v_for_pos_u = 0.0
    return float(np.sqrt(p)), u_abs, float(v_for_pos_u)


def _rotation_from_uv(affine: AffineModel, s: float, u: float, v: float) -> FloatArray:
    """Scene rotation from A, s, U, V: z = (n d - U a/s - V b/s) / n^2, x = a/s + U z, ..."""
    m = affine.matrix
    a, b = m[0, :3] / s, m[1, :3] / s
    d = affine.direction
    n2 = 1.0 + u * u + v * v
    z = (np.sqrt(n2) * d - u * a - v * b) / n2
    x = a + u * z
    y = b + v * z
    r = np.column_stack([x, y, z])
    # Remove rounding drift: nearest rotation (polar decomposition).
    uu, _, vt = np.linalg.svd(r)
    return np.asarray(uu @ vt, dtype=float)


def affine_to_nonlinear(
    affine: AffineModel,
    *,
    rule: SelectionRule = "paper",
    reference: ParallelProjection | None = None,
) -> AffineInversion:
    """Paper 1 Eqs 4-6: A1..A8 -> non-linear parameters, every valid solution.

    Args:
        affine: the linear model.
        rule: ``"paper"`` picks the solution with sign(U) = sign(L) (the sign rule of Eqs 5-6; it
            assumes the scene x axis has a positive X component, so it fails for a platform
            flying towards -X); ``"reference"`` picks the solution whose rotation is closest to
            ``reference`` (e.g. parameters derived from navigation).
        reference: required with ``rule="reference"``.

    Raises:
        DegenerateGeometryError: the model has no valid non-linear form (parallel rows, no
            positive scale, or a projection vector pointing down, N < 0).

    """
    d = affine.direction
    if d[2] <= 0.0:
        raise DegenerateGeometryError(
            "projection vector implied by A1..A8 points downwards (N < 0): the rows "
            "(A1,A2,A3) and (A5,A6,A7) are in the wrong order or one has the wrong sign"
        )
    s, u_abs, v_pos = _solutions_uv(affine)
    candidates: list[tuple[float, float]] = [(u_abs, v_pos)]
    if u_abs > 1e-12 or abs(v_pos) > 1e-12:
        candidates.append((-u_abs, -v_pos))
    sols: list[ParallelProjection] = []
    for u, v in candidates:
        r = _rotation_from_uv(affine, s, u, v)
        om, ph, ka = angles_from_rotation(r)
        sols.append(ParallelProjection(d[0], d[1], om, ph, ka, s, affine.A[3], affine.A[7]))
    if rule == "paper":
        want = 1.0 if d[0] >= 0 else -1.0
        idx = 0 if len(sols) == 1 or np.sign(candidates[0][0]) == want else 1
        why = (
            f"paper rule sign(U) = sign(L): L = {d[0]:+.4g}, so U = {candidates[idx][0]:+.4g}"
            + (" (only one solution: U = V = 0)" if len(sols) == 1 else "")
        )
    elif rule == "reference":
        if reference is None:
            raise GeometryError("rule='reference' needs reference parameters")
        r_ref = reference.rotation
        dist = [float(np.linalg.norm(p.rotation - r_ref)) for p in sols]
        idx = int(np.argmin(dist))
        why = f"closest rotation to the reference (Frobenius distances {np.round(dist, 6)})"
    else:
        raise GeometryError(f"unknown selection rule {rule!r}")
    u, v = candidates[idx]
    return AffineInversion(tuple(sols), sols[idx], why, u, v)


def paper_eqs_4_to_6(affine: AffineModel) -> ParallelProjection:
    """Paper 1 Eqs 4-6 evaluated literally, with the kappa misprint corrected (ERRATA).

    Kept as the paper states them so that tests can check :func:`affine_to_nonlinear` against
    them; prefer :func:`affine_to_nonlinear`, which also returns the mirror solution and works
    when A3 or (A3 A6 - A2 A7) is zero.
    """
    a1, a2, a3, a4, a5, a6, a7, a8 = affine.A
    ratio = (a1 * a7 - a3 * a5) / (a3 * a6 - a2 * a7)
    lp = a3 / np.sqrt(ratio**2 * (a2**2 + a3**2) + ratio * 2 * a1 * a2 + a1**2 + a3**2)
    mp = lp * ratio
    np_ = (-lp * a1 - mp * a2) / a3
    sgn_n = np.sign(np_)
    big_l, big_m = lp * sgn_n, mp * sgn_n
    t1 = a1**2 + a2**2 + a3**2
    t2 = a5**2 + a6**2 + a7**2
    t3 = a1 * a5 + a2 * a6 + a3 * a7
    qa = t3**2 - t1 * t2
    qb = 2 * t3**2 + t1**2 - t1 * t2
    qc = t3**2
    sgn_l = np.sign(big_l)
    u = np.sqrt((-qb - np.sqrt(qb**2 - 4 * qa * qc)) / (2 * qa)) * sgn_l
    v = t3 * (1 + u**2) / (t1 * u)
    s = np.sqrt(t1 / (1 + u**2))
    dd = u**2 + v**2 + 1
    ee = 2 * u * a1 / s + 2 * v * a5 / s
    ff = a1**2 / s**2 + a5**2 / s**2 - 1
    phi = np.arcsin((-ee + sgn_l * np.sqrt(ee**2 - 4 * dd * ff)) / (2 * dd))
    kappa = np.arctan2(-v * np.sin(phi) - a5 / s, u * np.sin(phi) + a1 / s)
    pq = np.sin(phi) * np.cos(kappa) + u * np.cos(phi)
    omega = np.arcsin((a2 / s * pq + a3 / s * np.sin(kappa)) / (np.sin(kappa) ** 2 + pq**2))
    return ParallelProjection(
        float(big_l), float(big_m), float(omega), float(phi), float(kappa), float(s), a4, a8
    )
