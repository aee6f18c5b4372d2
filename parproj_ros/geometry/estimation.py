"""Estimating A1..A8 (and the scanner roll) from ground control points (paper 1 Eq 8).

Model, for object point (X, Y, Z) and measured scene coordinates (x, y) in metres (y perspective,
from the principal point, before PTP):

    x = A1 X + A2 Y + A3 Z + A4
    y = q / (1 + (tan(psi) / c) q),   q = A5 X + A6 Y + A7 Z + A8

With psi fixed (0 = no PTP, or a known roll) the y row is fitted with psi held; with psi estimated
the nine unknowns are solved by Gauss-Newton on centred, column-scaled unknowns, since the raw
problem is ill-conditioned (ERRATA). Residuals are in the measured (x, y) space; sigma0 is
``sqrt(sum r^2 / (2 n - u))`` with u the number of unknowns, reported in metres and in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import DegeneratePointsError, GeometryError, TooFewPointsError
from .parallel import AffineModel
from .ptp import ptp_forward, ptp_inverse

FloatArray = NDArray[np.float64]

#: Relative singular value below which a point set counts as coplanar / collinear.
PLANARITY_TOLERANCE = 1e-6
#: Gauss-Newton stops when a step moves the modelled y by less than this, pixels.
CONVERGED_PX = 1e-9


@dataclass(frozen=True)
class AffineEstimate:
    """Result of :func:`estimate_affine`.

    Attributes:
        affine: estimated A1..A8.
        psi: roll used for PTP, radians (0 for no PTP; estimated or given otherwise).
        psi_estimated: whether psi was an unknown.
        sigma0: a-posteriori standard deviation of unit weight, metres in the scene.
        sigma0_px: the same in pixels.
        covariance: 9x9 covariance of (A1..A8, psi), units of the parameters squared; the psi
            row/column is zero when psi was not estimated.
        residuals: (n, 2) measured minus modelled (x, y), metres.
        redundancy: 2 n - number of unknowns.
        iterations: Gauss-Newton iterations used.

    """

    affine: AffineModel
    psi: float
    psi_estimated: bool
    sigma0: float
    sigma0_px: float
    covariance: FloatArray
    residuals: FloatArray
    redundancy: int
    iterations: int
    principal_distance: float
    pixel_size: float

    def predict(self, points: ArrayLike) -> FloatArray:
        """Object points (n, 3) -> modelled measured coordinates (x, y) (perspective y), metres."""
        xy = self.affine.project(points)
        xy[..., 1] = ptp_inverse(xy[..., 1], self.principal_distance, self.psi)
        return xy

    def check(self, points: ArrayLike, observed: ArrayLike) -> FloatArray:
        """Check-point errors: observed minus predicted (n, 2), metres."""
        return np.asarray(observed, dtype=float) - self.predict(points)

    @property
    def residual_norms_px(self) -> FloatArray:
        """Per-point residual length, pixels, shape (n,)."""
        return np.asarray(np.hypot(*self.residuals.T) / self.pixel_size, dtype=float)


def check_point_set(points: ArrayLike, minimum: int, *, what: str = "GCP") -> FloatArray:
    """Validate an (n, 3) object point set for a 3-D affine fit; return it as float array.

    Raises:
        GeometryError: wrong shape or non-finite values.
        TooFewPointsError: fewer than ``minimum`` distinct points.
        DegeneratePointsError: the points are collinear or coplanar (A3/A7 undetermined).

    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise GeometryError(f"{what} object coordinates must have shape (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise GeometryError(f"{what} object coordinates contain NaN or Inf")
    distinct = len(np.unique(np.round(p, 6), axis=0))
    if distinct < minimum:
        raise TooFewPointsError(
            f"{distinct} distinct {what} given, at least {minimum} needed"
            + (f" ({len(p) - distinct} duplicates)" if distinct < len(p) else "")
        )
    centred = p - p.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[0] == 0.0 or sv[1] / sv[0] < PLANARITY_TOLERANCE:
        raise DegeneratePointsError(
            f"{what} are collinear (or all equal): add points off the line"
        )
    if sv[2] / sv[0] < PLANARITY_TOLERANCE:
        raise DegeneratePointsError(
            f"{what} are coplanar: A3 and A7 (height terms) are undetermined; "
            "use points with height variation"
        )
    return p


def estimate_affine(
    points: ArrayLike,
    observed: ArrayLike,
    *,
    principal_distance: float,
    pixel_size: float,
    psi: float | None = 0.0,
    max_iterations: int = 50,
) -> AffineEstimate:
    """Least-squares A1..A8 (and optionally psi) from GCP (paper 1 Eqs 2, 7 and 8).

    Args:
        points: GCP object coordinates (n, 3), metres.
        observed: measured scene coordinates (n, 2) (x, perspective y), metres.
        principal_distance: c, metres.
        pixel_size: metres per pixel (for sigma0 in pixels).
        psi: None to estimate the roll (Eq 8, >= 5 points); a number (radians) to apply a known
            roll; 0.0 for no PTP correction (>= 4 points).
        max_iterations: Gauss-Newton limit when psi is estimated.

    """
    estimate_psi = psi is None
    n_unknown = 9 if estimate_psi else 8
    minimum = 5 if estimate_psi else 4
    p = check_point_set(points, minimum)
    obs = np.asarray(observed, dtype=float)
    if obs.shape != (len(p), 2) or not np.all(np.isfinite(obs)):
        raise GeometryError(
            f"observations must be finite with shape ({len(p)}, 2), got {obs.shape}"
        )
    c = float(principal_distance)
    psi0 = 0.0 if psi is None else float(psi)
    ptp_forward(np.zeros(1), c, psi0)  # validates c and psi
    mean = p.mean(axis=0)
    scale = float(np.abs(p - mean).max())
    design = np.column_stack([(p - mean) / scale, np.ones(len(p))])
    # x row: linear.
    bx, *_ = np.linalg.lstsq(design, obs[:, 0], rcond=None)
    rx = obs[:, 0] - design @ bx
    # y row: start from the linear fit in PTP-corrected space, then Gauss-Newton in y space.
    yp = ptp_forward(obs[:, 1], c, psi0)
    by, *_ = np.linalg.lstsq(design, yp, rcond=None)
    theta = np.concatenate([by, [np.tan(psi0)]])
    iterations = 0
    cond = 0.0
    converged = False
    change = np.inf

    def y_model(th: FloatArray) -> tuple[FloatArray, FloatArray]:
        q = design @ th[:4]
        den = 1.0 + th[4] * q / c
        return q / den, q

    for iterations in range(1, max_iterations + 1):  # noqa: B007 - reported after the loop
        ym, q = y_model(theta)
        den = 1.0 + theta[4] * q / c
        jac_q = (1.0 / den**2)[:, None] * design
        cols = [jac_q]
        if estimate_psi:
            cols.append((-(q**2) / c / den**2)[:, None])
        jac = np.hstack(cols)
        col_norm = np.linalg.norm(jac, axis=0)
        col_norm[col_norm == 0] = 1.0
        js = jac / col_norm
        sv = np.linalg.svd(js, compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
        if cond > 1e10:
            raise DegeneratePointsError(
                "the roll cannot be separated from A5..A8 with these GCP (condition number "
                f"{cond:.3g}): spread the points along the scan line and in height"
            )
        step, *_ = np.linalg.lstsq(js, obs[:, 1] - ym, rcond=None)
        change = float(np.abs(js @ step).max())  # largest model change of this step, metres
        step = step / col_norm
        theta[: len(step)] += step
        if change < CONVERGED_PX * pixel_size:
            converged = True
            break
    if not converged:
        raise GeometryError(
            f"Eq 8 did not converge in {max_iterations} iterations (last step moved the model "
            f"by {change / pixel_size:.3g} px)"
        )
    if estimate_psi and abs(theta[4]) > 1e6:
        raise DegeneratePointsError("roll estimate diverged: the GCP do not determine psi")
    ym, q = y_model(theta)
    ry = obs[:, 1] - ym
    redundancy = 2 * len(p) - n_unknown
    ssr = float(rx @ rx + ry @ ry)
    sigma0 = float(np.sqrt(ssr / redundancy)) if redundancy > 0 else 0.0
    # Back to A1..A8 in the original object frame: q = (P - m) / k . b + b0.
    ax, ay = bx[:3] / scale, theta[:3] / scale
    a4 = bx[3] - ax @ mean
    a8 = theta[3] - ay @ mean
    affine = AffineModel.from_array(np.concatenate([ax, [a4], ay, [a8]]))
    # Covariance: linearised at the solution, then mapped through the linear reparametrisation.
    den = 1.0 + theta[4] * q / c
    jy = (1.0 / den**2)[:, None] * design
    if estimate_psi:
        jy = np.hstack([jy, (-(q**2) / c / den**2)[:, None]])
    nx = np.linalg.inv(design.T @ design)
    ny = np.linalg.pinv(jy.T @ jy)
    tmap = np.zeros((4, 4))
    tmap[:3, :3] = np.eye(3) / scale
    tmap[3, :3] = -mean / scale
    tmap[3, 3] = 1.0
    cov = np.zeros((9, 9))
    cov[:4, :4] = tmap @ nx @ tmap.T
    cy = tmap @ ny[:4, :4] @ tmap.T
    cov[4:8, 4:8] = cy
    if estimate_psi:
        dpsi = 1.0 / (1.0 + theta[4] ** 2)  # d psi / d tan(psi)
        cross = tmap @ ny[:4, 4]
        cov[4:8, 8] = cov[8, 4:8] = cross * dpsi
        cov[8, 8] = ny[4, 4] * dpsi**2
    cov *= sigma0**2
    return AffineEstimate(
        affine=affine,
        psi=float(np.arctan(theta[4])),
        psi_estimated=estimate_psi,
        sigma0=sigma0,
        sigma0_px=sigma0 / pixel_size,
        covariance=cov,
        residuals=np.column_stack([rx, ry]),
        redundancy=redundancy,
        iterations=iterations,
        principal_distance=c,
        pixel_size=float(pixel_size),
    )
