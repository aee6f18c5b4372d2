"""Epipolar geometry and normalization of parallel-projection stereo scenes (paper 2, section 4).

All scene coordinates here are parallel ones (after the PTP correction, Eq 7), metres in the focal
plane. The epipolar constraint (paper 2 Eq 5, corrected in ERRATA) is kept in homogeneous form
``g . (x, y', x2, y2') = k`` with |g| = 1, since the "= 1" form of the paper cannot represent
k = 0; :attr:`EpipolarConstraint.G` gives G1..G4 = g / k when k is not zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import DegenerateGeometryError, GeometryError, TooFewPointsError
from .parallel import AffineModel, ParallelProjection, affine_to_nonlinear

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class EpipolarConstraint:
    """``g1 x + g2 y' + g3 x2 + g4 y2' = k`` between left (x, y') and right (x2, y2') scenes.

    Attributes:
        g: unit 4-vector, dimensionless.
        k: constant, metres.

    """

    g: FloatArray
    k: float

    @property
    def G(self) -> FloatArray:  # noqa: N802 - the paper's symbol
        """G1..G4 of paper 2 Eq 5 (``... = 1``), in 1/metres. Raises if k is zero."""
        if abs(self.k) < 1e-15:
            raise DegenerateGeometryError("k = 0: the '= 1' form of Eq 5 does not exist")
        return np.asarray(self.g / self.k, dtype=float)

    def residual(self, left_xy: ArrayLike, right_xy: ArrayLike) -> FloatArray:
        """Signed distance-like residual g.(x, y', x2, y2') - k, metres, shape (n,)."""
        l_xy = np.asarray(left_xy, dtype=float)
        r_xy = np.asarray(right_xy, dtype=float)
        return np.asarray(np.hstack([l_xy, r_xy]) @ self.g - self.k, dtype=float)


def epipolar_from_affine(left: AffineModel, right: AffineModel) -> EpipolarConstraint:
    """G1..G4 from both scenes' A1..A8: the null vector of [a; b; a2; b2] (eliminating X, Y, Z)."""
    ml, mr = left.matrix, right.matrix
    stack = np.vstack([ml[:, :3], mr[:, :3]])  # 4 x 3
    _, sv, vt = np.linalg.svd(stack.T)
    if sv[-1] / sv[0] < 1e-9:
        raise DegenerateGeometryError("the two affine models do not span object space (no base)")
    g = vt[-1]
    k = float(g @ np.array([ml[0, 3], ml[1, 3], mr[0, 3], mr[1, 3]]))
    return _canonical(g, k)


def _canonical(g: FloatArray, k: float) -> EpipolarConstraint:
    g = np.asarray(g, dtype=float)
    nrm = float(np.linalg.norm(g))
    g, k = g / nrm, k / nrm
    if g[np.argmax(np.abs(g))] < 0:
        g, k = -g, -k
    return EpipolarConstraint(g, float(k))


def epipolar_from_points(left_xy: ArrayLike, right_xy: ArrayLike) -> EpipolarConstraint:
    """G1..G4 from >= 4 conjugate points (parallel coordinates, metres), total least squares.

    Coordinates are centred and scaled before the SVD so that the fit does not depend on units.
    Raises TooFewPointsError for fewer than 4 points and DegenerateGeometryError when the points
    do not determine the constraint (e.g. all on one epipolar line).
    """
    l_xy = np.asarray(left_xy, dtype=float)
    r_xy = np.asarray(right_xy, dtype=float)
    if l_xy.shape != r_xy.shape or l_xy.ndim != 2 or l_xy.shape[1] != 2:
        raise GeometryError("conjugate points must be two (n, 2) arrays of the same shape")
    if len(l_xy) < 4:
        raise TooFewPointsError(f"{len(l_xy)} conjugate points given, at least 4 needed")
    data = np.hstack([l_xy, r_xy])
    if not np.all(np.isfinite(data)):
        raise GeometryError("conjugate points contain NaN or Inf")
    mean = data.mean(axis=0)
    scale = float(np.abs(data - mean).max()) or 1.0
    z = (data - mean) / scale
    _, sv, vt = np.linalg.svd(z, full_matrices=False)
    if len(sv) < 4 or sv[2] / sv[0] < 1e-9:
        raise DegenerateGeometryError(
            "conjugate points do not determine the epipolar geometry (too little spread)"
        )
    h = vt[-1]
    # h . (data - mean) / scale = 0  ->  h . data = h . mean
    return _canonical(h, float(h @ mean))


@dataclass(frozen=True)
class PlanarRectification:
    """Paper 2 Eqs 6-7: rotation, scale and shift that remove y-parallax.

    They keep x-parallax non-linear in height: use :func:`normalize_pair` for products.

    Attributes:
        theta: left rotation, radians.
        theta2: right rotation, radians.
        S: scale (left scaled by 1/S, right by S), dimensionless.
        dy: y shift (left -dy/2, right +dy/2), metres.

    """

    theta: float
    theta2: float
    S: float
    dy: float

    def apply(self, left_xy: ArrayLike, right_xy: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Eq 6 on left (n, 2) and right (n, 2) coordinates; returns both transformed."""

        def rot(t: float) -> FloatArray:
            return np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])

        ln = np.asarray(left_xy, dtype=float) @ rot(self.theta).T / self.S
        rn = np.asarray(right_xy, dtype=float) @ rot(self.theta2).T * self.S
        shift = np.array([0.0, self.dy / 2])
        return ln - shift, rn + shift


def planar_rectification(epi: EpipolarConstraint) -> PlanarRectification:
    """Paper 2 Eq 7 from G1..G4, choosing the branch with |theta| <= 90 deg and S > 0.

    From Eq 6, (G2, -G1) = (cos t, sin t) / (S dy) and (-G4, G3) = (cos t2, sin t2) S / dy, so
    S^2 = |(G3, G4)| / |(G1, G2)| and dy = 1 / (S |(G1, G2)|) (the printed arctan forms are these
    up to the quadrant).
    """
    # Work with g and k (G = g / k) so that k = 0 (dy = 0) needs no special case.
    sgn = -1.0 if epi.k < 0 else 1.0
    g1, g2, g3, g4 = sgn * epi.g
    n12, n34 = float(np.hypot(g1, g2)), float(np.hypot(g3, g4))
    if n12 < 1e-12 or n34 < 1e-12:
        raise DegenerateGeometryError(
            "epipolar lines are undefined in one scene (G1 = G2 = 0 or G3 = G4 = 0)"
        )
    theta = float(np.arctan2(-g1, g2))
    theta2 = float(np.arctan2(g3, -g4))
    big_s = float(np.sqrt(n34 / n12))
    dy = abs(epi.k) / (big_s * n12)
    if abs(theta) > np.pi / 2:
        theta = float(theta - np.sign(theta) * np.pi)
        theta2 = float(theta2 - np.sign(theta2) * np.pi) if theta2 != 0 else float(np.pi)
        dy = -dy
    return PlanarRectification(theta, theta2, big_s, dy)


@dataclass(frozen=True)
class Normalization:
    """Paper 2 Eq 8: both scenes projected onto a common horizontal plane.

    Attributes:
        kappa_n: epipolar direction in the object XY plane, radians (normalized x axis azimuth
            measured from X towards Y).
        s_n: normalized scale (average of the scenes' scales), dimensionless.
        dx_n: normalized x shift (average of the scenes' dx), metres.
        dy_n: normalized y shift (average of the scenes' dy), metres.
        left: 2x3 affine from left parallel scene (x, y', 1) to normalized (x_n, y_n), metres.
        right: 2x3 affine for the right scene.
        parallax_per_height: k in ``x_n - x_n2 = k Z + p0``: scene metres per object metre.
        parallax_offset: p0, metres.
        left_params: the non-linear parameters used for the left scene.
        right_params: those of the right scene.

    """

    kappa_n: float
    s_n: float
    dx_n: float
    dy_n: float
    left: FloatArray
    right: FloatArray
    parallax_per_height: float
    parallax_offset: float
    left_params: ParallelProjection
    right_params: ParallelProjection

    def apply_left(self, xy: ArrayLike) -> FloatArray:
        """Left parallel scene coordinates (..., 2) -> normalized (..., 2), metres."""
        return _apply(self.left, xy)

    def apply_right(self, xy: ArrayLike) -> FloatArray:
        """Right parallel scene coordinates (..., 2) -> normalized (..., 2), metres."""
        return _apply(self.right, xy)

    def height_from_parallax(self, x_parallax: ArrayLike) -> FloatArray:
        """x-parallax x_n - x_n2 (metres) -> object height Z (metres)."""
        return (np.asarray(x_parallax, dtype=float) - self.parallax_offset) / (
            self.parallax_per_height
        )

    def project_object(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Object points (..., 3) -> exact normalized coordinates in the left and right scenes."""
        p = np.asarray(points, dtype=float)
        out = []
        for pp in (self.left_params, self.right_params):
            d = pp.direction
            foot = p[..., :2] - p[..., 2:3] * (d[:2] / d[2])
            out.append(self._plane_to_normalized(foot))
        return out[0], out[1]

    def _plane_to_normalized(self, xy_obj: FloatArray) -> FloatArray:
        c, s = np.cos(self.kappa_n), np.sin(self.kappa_n)
        rt = np.array([[c, s], [-s, c]])
        return np.asarray(self.s_n * xy_obj @ rt.T + [self.dx_n, self.dy_n], dtype=float)


def _apply(h: FloatArray, xy: ArrayLike) -> FloatArray:
    p = np.asarray(xy, dtype=float)
    return np.asarray(p @ h[:, :2].T + h[:, 2], dtype=float)


def invert_affine_2x3(h: ArrayLike) -> FloatArray:
    """Inverse of a 2x3 affine map (x -> A x + t), as a 2x3 array."""
    m = np.asarray(h, dtype=float)
    a_inv = np.linalg.inv(m[:, :2])
    return np.hstack([a_inv, (-a_inv @ m[:, 2])[:, None]])


def _scene_to_plane(affine: AffineModel) -> FloatArray:
    """2x3 affine: parallel scene (x, y') -> object (X, Y) on Z = 0 along the projection vector."""
    m = affine.matrix
    a2 = m[:, :2]
    if abs(np.linalg.det(a2)) < 1e-30:
        raise DegenerateGeometryError("scene plane is perpendicular to the horizontal plane")
    inv = np.linalg.inv(a2)
    return np.hstack([inv, (-inv @ m[:, 3])[:, None]])


def normalize_pair(
    left: AffineModel,
    right: AffineModel,
    *,
    left_params: ParallelProjection | None = None,
    right_params: ParallelProjection | None = None,
    min_base_ratio: float = 1e-3,
) -> Normalization:
    """Paper 2 Eq 8 normalization of a stereo pair from both scenes' A1..A8.

    The normalized scene of each side is the parallel projection, along that scene's own
    projection vector, onto a horizontal plane (omega_n = phi_n = 0) rotated by kappa_n (Eq 8),
    with the average scale and shifts. kappa_n has a 180 deg ambiguity: the branch whose x axis
    points along the left scene's x axis (projected on the horizontal plane) is chosen.

    Args:
        left: the left scene's A1..A8 (parallel, i.e. PTP-corrected, scene coordinates).
        right: the right scene's A1..A8.
        left_params: the left non-linear form, if known (else derived with Eqs 4-6; only its
            scale and scene x axis are used: the scale is the same for both mirror solutions).
        right_params: the right non-linear form, if known.
        min_base_ratio: smallest accepted |L/N - L2/N2, M/N - M2/N2| (base-to-height ratio).

    Raises:
        DegenerateGeometryError: no stereo base (projection vectors nearly equal).

    """
    lp = left_params or affine_to_nonlinear(left).chosen
    rp = right_params or affine_to_nonlinear(right).chosen
    d1, d2 = left.direction, right.direction
    if min(d1[2], d2[2]) <= 1e-9:
        raise DegenerateGeometryError(
            "a projection vector is horizontal or points down (N <= 0): no normalization plane"
        )
    diff = d1[:2] / d1[2] - d2[:2] / d2[2]
    base = float(np.hypot(*diff))
    if not np.isfinite(base):
        raise DegenerateGeometryError("the projection vectors are not finite")
    if base < min_base_ratio:
        raise DegenerateGeometryError(
            f"no usable stereo base: base-to-height ratio {base:.3g} < {min_base_ratio} "
            "(the projection vectors are nearly equal)"
        )
    kappa = float(np.arctan2(d1[2] * d2[1] - d1[1] * d2[2], d1[2] * d2[0] - d1[0] * d2[2]))
    x_left = lp.rotation[:2, 0]
    if np.cos(kappa) * x_left[0] + np.sin(kappa) * x_left[1] < 0:
        kappa = float(kappa - np.pi) if kappa > 0 else float(kappa + np.pi)
    s_n = 0.5 * (lp.s + rp.s)
    dx_n = 0.5 * (left.A[3] + right.A[3])
    dy_n = 0.5 * (left.A[7] + right.A[7])
    c, s = np.cos(kappa), np.sin(kappa)
    rt = s_n * np.array([[c, s], [-s, c]])
    mats = []
    for aff in (left, right):
        to_plane = _scene_to_plane(aff)
        mats.append(
            np.hstack([rt @ to_plane[:, :2], (rt @ to_plane[:, 2] + [dx_n, dy_n])[:, None]])
        )
    k = float(-s_n * (c * diff[0] + s * diff[1]))
    return Normalization(kappa, s_n, dx_n, dy_n, mats[0], mats[1], k, 0.0, lp, rp)
