"""Space intersection from two (or more) parallel-projection scenes by least squares.

Each scene contributes two linear equations per point (paper 1 Eq 2 after PTP): for two scenes,
four equations in the three object coordinates. The design matrix is the same for every point, so
all points are solved at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import DegenerateGeometryError, GeometryError
from .parallel import AffineModel
from .ptp import ptp_forward

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SceneObservation:
    """One scene's model and its measured coordinates.

    Attributes:
        affine: the scene's A1..A8.
        xy: measured (x, y) per point, shape (n, 2), metres; y perspective unless ``psi`` is None.
        psi: roll (rad) used to PTP-correct y before intersecting; 0 = no correction; None = the
            y values are already parallel (y').
        principal_distance: c (m), needed when psi is neither None nor 0.

    """

    affine: AffineModel
    xy: FloatArray
    psi: float | None = 0.0
    principal_distance: float | None = None


@dataclass(frozen=True)
class Intersection:
    """Result of :func:`space_intersection`.

    Attributes:
        points: object coordinates (n, 3), metres.
        residuals: (n, 2 k) scene residuals (observed minus modelled x, y' per scene), metres.
        condition: condition number of the design matrix (large: weak base-to-height ratio).

    """

    points: FloatArray
    residuals: FloatArray
    condition: float


def space_intersection(scenes: Sequence[SceneObservation]) -> Intersection:
    """Least-squares object coordinates of points observed in two or more scenes.

    Raises:
        GeometryError: fewer than two scenes or inconsistent shapes.
        DegenerateGeometryError: the scenes' projection directions give no stereo base.

    """
    if len(scenes) < 2:
        raise GeometryError("space intersection needs at least two scenes")
    n = len(scenes[0].xy)
    rows = []
    rhs = []
    for sc in scenes:
        xy = np.asarray(sc.xy, dtype=float)
        if xy.shape != (n, 2):
            raise GeometryError(f"every scene needs (n, 2) observations, got {xy.shape}")
        if sc.psi is None or sc.psi == 0.0:
            y = xy[:, 1]
        elif sc.principal_distance is None:
            raise GeometryError("a roll psi was given without the principal distance")
        else:
            y = ptp_forward(xy[:, 1], sc.principal_distance, sc.psi)
        m = sc.affine.matrix
        rows.append(m[:, :3])
        rhs.append(np.stack([xy[:, 0] - m[0, 3], y - m[1, 3]], axis=0))
    design = np.vstack(rows)
    b = np.vstack(rhs)  # (2k, n)
    sv = np.linalg.svd(design, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    if cond > 1e8:
        raise DegenerateGeometryError(
            f"no stereo base: the scenes' projection directions are (nearly) equal (condition "
            f"{cond:.3g})"
        )
    sol, *_ = np.linalg.lstsq(design, b, rcond=None)
    res = b - design @ sol
    return Intersection(np.asarray(sol.T, dtype=float), np.asarray(res.T, dtype=float), cond)


def affine_intersection(
    left: AffineModel, right: AffineModel, left_xy: ArrayLike, right_xy: ArrayLike
) -> Intersection:
    """Two-scene intersection of already parallel (PTP-corrected) coordinates."""
    return space_intersection(
        [
            SceneObservation(left, np.asarray(left_xy, dtype=float), None),
            SceneObservation(right, np.asarray(right_xy, dtype=float), None),
        ]
    )
