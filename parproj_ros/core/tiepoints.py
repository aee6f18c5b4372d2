"""Tie-point refinement of a normalized pair (issue: biases of navigation, GCP or RPC).

Features are matched between the two normalized images (:mod:`imaging.matching`), taken back to
the parallel (PTP-corrected) coordinates of each original scene, and outliers are rejected by
RANSAC on the affine epipolar constraint of paper 2 (G1..G4 from 4 conjugate points, Eq 5).
The inliers' remaining y-parallax is then fitted by an affine function of the right image's
normalized coordinates, ``dy = a + b x_n + c y_n``, and removed from the right image's
normalization (its rows only: the x coordinates, hence the x-parallax -> height relation, are
unchanged).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..geometry import GeometryError, epipolar_from_points, invert_affine_2x3
from ..imaging.matching import match_normalized
from ..imaging.resample import SceneGeometry
from .results import PairGeometry

FloatArray = NDArray[np.float64]

MIN_TIE_POINTS = 8


@dataclass(frozen=True)
class TieRefinement:
    """Result of :func:`refine_with_tie_points`.

    Attributes:
        geometry: the pair geometry with the corrected right normalization.
        matched: tie points matched.
        inliers: tie points kept by RANSAC.
        correction: (a, b, c) of dy = a + b x_n + c y_n, metres / dimensionless.
        before_px: inliers' y-parallax before the correction, pixels.
        residual_px: inliers' y-parallax after it, pixels.
        heights_m: inliers' heights from their x-parallax, ``Z = (x_l - x_r - offset) / k``
            (the correction changes rows only), metres in the object frame.
    """

    geometry: PairGeometry
    matched: int
    inliers: int
    correction: tuple[float, float, float]
    before_px: FloatArray
    residual_px: FloatArray
    heights_m: FloatArray

    @property
    def summary(self) -> str:
        """One line for the log and diagnostics."""
        b, r = np.abs(self.before_px), np.abs(self.residual_px)
        return (
            f"tie points: {self.matched} matched, {self.inliers} inliers (RANSAC on G1..G4); "
            f"y-parallax mean |y| {b.mean():.3f} -> {r.mean():.3f} px, "
            f"rms {np.sqrt(np.mean(self.before_px**2)):.3f} -> "
            f"{np.sqrt(np.mean(self.residual_px**2)):.3f} px"
        )


def _ransac(
    sl: FloatArray,
    sr: FloatArray,
    pixel: float,
    threshold_px: float,
    rng: np.random.Generator,
    iterations: int = 300,
) -> NDArray[np.bool_]:
    n = len(sl)
    best = np.zeros(n, dtype=bool)
    for _ in range(iterations):
        idx = rng.choice(n, 4, replace=False)
        try:
            epi = epipolar_from_points(sl[idx], sr[idx])
        except GeometryError:
            continue
        scale = float(np.hypot(epi.g[1], epi.g[3]))
        if scale < 1e-12:
            continue
        res = np.abs(epi.residual(sl, sr)) / scale / pixel
        inl = res < threshold_px
        if inl.sum() > best.sum():
            best = inl
    return best


def refine_with_tie_points(
    geo: PairGeometry,
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    *,
    nodata: float,
    pixel: float,
    threshold_px: float = 1.0,
    seed: int = 0,
) -> TieRefinement | str:
    """Refine the right normalization from tie points; a string says why it was not done."""
    m = match_normalized(left, right, nodata=nodata)
    if len(m) < MIN_TIE_POINTS:
        return f"only {len(m)} tie points matched (need {MIN_TIE_POINTS}): not refined"
    gl, gr = geo.left_grid, geo.right_grid
    nl = np.column_stack([gl.x_origin + gl.pixel * m.xl, gl.y_origin + gl.pixel * m.yl])
    nr = np.column_stack([gr.x_origin + gr.pixel * m.xr, gr.y_origin + gr.pixel * m.yr])
    hl = invert_affine_2x3(geo.normalization.left)
    hr = invert_affine_2x3(geo.normalization.right)
    sl = nl @ hl[:, :2].T + hl[:, 2]
    sr = nr @ hr[:, :2].T + hr[:, 2]
    inl = _ransac(sl, sr, pixel, threshold_px, np.random.default_rng(seed))
    if inl.sum() < MIN_TIE_POINTS:
        return (
            f"{len(m)} tie points matched but only {int(inl.sum())} agree on one epipolar "
            "geometry: not refined"
        )
    dy = nl[inl, 1] - nr[inl, 1]
    design = np.column_stack([np.ones(int(inl.sum())), nr[inl, 0], nr[inl, 1]])
    coef, *_ = np.linalg.lstsq(design, dy, rcond=None)
    a, b, c = (float(v) for v in coef)
    corr = np.array([[1.0, 0.0, 0.0], [b, 1.0 + c, a]])
    h = geo.normalization.right
    new_right = corr @ np.vstack([h, [0.0, 0.0, 1.0]])
    norm = replace(geo.normalization, right=new_right)
    rg = geo.right_geom
    right_geom = SceneGeometry(rg.frame, new_right, rg.psi, rg.principal_distance)
    residual = dy - design @ coef
    pix = gl.pixel
    par = geo.normalization
    heights = (nl[inl, 0] - nr[inl, 0] - par.parallax_offset) / par.parallax_per_height
    return TieRefinement(
        replace(geo, normalization=norm, right_geom=right_geom),
        len(m),
        int(inl.sum()),
        (a, b, c),
        dy / pix,
        residual / pix,
        heights,
    )
