"""Perspective-to-parallel (PTP) correction along the scan line (paper 1 Eq 7).

``y' = y / (1 - (y / c) tan(psi))`` maps the perspective coordinate y (metres in the focal plane,
measured from the principal point along the scan line) to the parallel-projection coordinate y'.
It is exact for flat terrain when ``tan(psi) = r_s32 / r_s33`` of the scanner rotation (ERRATA):
that is :func:`roll_from_rotation`, which differs from the nominal roll when the pitch is not 0.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError
from .rotation import check_rotation

FloatArray = NDArray[np.float64]


def _check(c: float, psi: float) -> None:
    if not (np.isfinite(c) and c > 0):
        raise GeometryError(f"principal distance must be > 0 m, got {c}")
    if not (np.isfinite(psi) and abs(psi) < np.pi / 2):
        raise GeometryError(f"roll psi must be finite and within +-90 deg, got {psi} rad")


def ptp_forward(y: ArrayLike, c: float, psi: float) -> FloatArray:
    """Eq 7: perspective y (m) -> parallel y' (m), for principal distance c (m), roll psi (rad)."""
    _check(c, psi)
    yy = np.asarray(y, dtype=float)
    den = 1.0 - yy * np.tan(psi) / c
    if np.any(den <= 0):
        raise GeometryError("a coordinate lies beyond the horizon of Eq 7 (y tan(psi) >= c)")
    return np.asarray(yy / den, dtype=float)


def ptp_inverse(y_parallel: ArrayLike, c: float, psi: float) -> FloatArray:
    """Inverse of Eq 7: parallel y' (m) -> perspective y (m): ``y = y' / (1 + (y'/c) tan psi)``."""
    _check(c, psi)
    yp = np.asarray(y_parallel, dtype=float)
    den = 1.0 + yp * np.tan(psi) / c
    if np.any(den <= 0):
        raise GeometryError(
            "a parallel coordinate has no perspective image (1 + y' tan(psi)/c <= 0)"
        )
    return np.asarray(yp / den, dtype=float)


def roll_from_rotation(rot: ArrayLike) -> float:
    """Roll psi (rad) that makes Eq 7 exact on flat terrain: ``tan(psi) = r32 / r33``.

    ``rot`` is the scanner rotation (sensor -> object axes, papers' convention).
    """
    r = np.asarray(rot, dtype=float)
    check_rotation(r)
    return float(np.arctan2(r[2, 1], r[2, 2]))
