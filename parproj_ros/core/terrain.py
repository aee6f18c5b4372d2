"""The terrain of a normalized pair, measured from the pair itself (issue 24, Step 12).

A pair's x-parallax is linear in height (paper 2, section 4): a point at height ``Z`` lies at
``x_l`` in the left normalized image and at ``x_r`` in the right one with
``x_l - x_r = k Z + offset`` (normalized metres; ``k`` = :attr:`Normalization.parallax_per_height`,
``offset`` = :attr:`Normalization.parallax_offset`). Tie points matched between the two
normalized images therefore give the heights of the ground the pair sees. Their robust
percentiles, widened by a margin, are the pair's terrain: the heights the dense matcher searches
and the heights at which the output extent keeps the columns both scenes see.

Without it the pipeline assumes the terrain: the span of the pair's GCP (for an imported pair,
virtual points spread over the RPC's height span, often hundreds of metres away from the crop's
ground) or ``z_avg`` +- ``height_range``. That prior stays the fallback, and a WARN says so,
when too few tie points agree.

A DEM given (the node's ``dem`` parameter, ``parproj process --dem``) adds its heights over the
pair's ground (:mod:`parproj_ros.core.dem_terrain`): the terrain is then the hull of the DEM's
span and the tie points' (:func:`with_dem`, source ``dem+tie_points``), so that neither's gaps
shrink the search (a DEM misses trees, buildings and what changed since it was made; tie points
miss what has no texture); with too few tie points the DEM's alone (source ``dem``) replaces
the prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry import Normalization
from ..imaging.matching import Matches, match_normalized
from ..imaging.resample import OutputGrid

FloatArray = NDArray[np.float64]

#: Fewest tie points that measure a terrain (fewer: the prior is kept).
MIN_TERRAIN_POINTS = 20
#: Percentiles of the tie points' heights taken as the terrain's lowest and highest ground.
TERRAIN_PERCENTILES = (1.0, 99.0)
#: The measured span is widened on each side by this share of it ...
TERRAIN_PAD_SHARE = 0.2
#: ... and by at least this many pixels of x-parallax (heights of the matching's noise).
TERRAIN_PAD_PX = 4.0
#: Smallest correlation of a terrain tie point (a reduced pair of views 20 degrees apart keeps
#: few at the tie-point refinement's 0.85; the row check below removes gross errors).
MIN_CORRELATION = 0.6
#: Tie points whose y-parallax differs from the median by more are gross errors, pixels.
Y_OUTLIER_PX = 3.0


class TerrainSource(StrEnum):
    """Where a pair's terrain heights come from (a string in logs and messages)."""

    #: Measured from the pair: tie points between its normalized images.
    TIE_POINTS = "tie_points"
    #: The span of the pair's ground control points (and check points).
    GCP = "gcp"
    #: Assumed: ``z_avg`` +- ``height_range``.
    PRIOR = "prior"
    #: A DEM's heights over the pair's ground (too few tie points, or ``terrain`` prior).
    DEM = "dem"
    #: The hull of the DEM's heights and the tie points' (:func:`with_dem`).
    DEM_TIE_POINTS = "dem+tie_points"


#: Sources of a terrain measured on the pair's ground (not assumed): the output grids' zero
#: disparity height may move to their middle (:func:`~.normalization.zero_disparity_height`).
MEASURED = frozenset({TerrainSource.TIE_POINTS, TerrainSource.DEM, TerrainSource.DEM_TIE_POINTS})
#: Sources holding tie points measured on the pair (nothing more to measure on its images).
FROM_TIE_POINTS = frozenset({TerrainSource.TIE_POINTS, TerrainSource.DEM_TIE_POINTS})


@dataclass(frozen=True)
class Terrain:
    """The heights a pair's ground lies within.

    Attributes:
        low_m: lowest height, metres in the object frame.
        high_m: highest height, metres in the object frame.
        source: where they come from.
        points: tie points measured (0 unless ``source`` holds tie points).
        measured_m: (lowest, highest) percentile of the tie points' heights before the margin,
            metres; None unless measured.
        dem_m: (lowest, highest) height of the DEM over the pair's ground before the margin,
            metres in the object frame; None unless ``source`` holds the DEM.
        dem: the DEM in words (its files and vertical reference); "" without one.
    """

    low_m: float
    high_m: float
    source: TerrainSource
    points: int = 0
    measured_m: tuple[float, float] | None = None
    dem_m: tuple[float, float] | None = None
    dem: str = ""

    @property
    def range_m(self) -> tuple[float, float]:
        """(lowest, highest) height, metres."""
        return self.low_m, self.high_m

    def describe(self) -> str:
        """Words for logs: "terrain 52..371 m from 381 tie points" and the like."""
        text = f"terrain {self.low_m:.0f}..{self.high_m:.0f} m"
        ties = ""
        if self.measured_m is not None:
            lo, hi = self.measured_m
            ties = (
                f"{self.points} tie points (percentiles {TERRAIN_PERCENTILES[0]:g}-"
                f"{TERRAIN_PERCENTILES[1]:g}: {lo:.0f}..{hi:.0f} m"
            )
        dem = ""
        if self.dem_m is not None:
            lo, hi = self.dem_m
            dem = f"the DEM {self.dem} (its heights over the pair's ground: {lo:.0f}..{hi:.0f} m"
        if self.source == TerrainSource.TIE_POINTS:
            return f"{text} from {ties}, plus a margin)"
        if self.source == TerrainSource.DEM:
            return f"{text} from {dem}, plus a margin)"
        if self.source == TerrainSource.DEM_TIE_POINTS:
            return f"{text} from {dem}) and {ties}), plus a margin"
        if self.source == TerrainSource.GCP:
            return f"{text} from the pair's GCP"
        return f"{text} assumed (z_avg +- height_range)"


def with_dem(dem: Terrain | None, measured: Terrain) -> Terrain:
    """The terrain searched, from the DEM's (or None) and what the tie points measured.

    Both: their hull (source ``dem+tie_points``), neither's gaps shrinking the search; too few
    tie points (``measured`` is the prior, or the GCP's span): the DEM's alone; no DEM:
    ``measured``.
    """
    if dem is None:
        return measured
    if measured.source not in FROM_TIE_POINTS:
        return dem
    return Terrain(
        min(dem.low_m, measured.low_m),
        max(dem.high_m, measured.high_m),
        TerrainSource.DEM_TIE_POINTS,
        measured.points,
        measured.measured_m,
        dem.dem_m,
        dem.dem,
    )


#: The tie points' heights and the DEM's lying further apart than this are said (a WARN): a
#: DEM above another datum than the one its option says (the geoid undulation forgotten), of
#: another place or time, metres.
DISAGREE_M = 30.0


def disagreement(terrain: Terrain) -> str | None:
    """Why the DEM's heights and the tie points' of ``terrain`` do not agree; None if they do.

    They disagree when their spans (before the margins) lie more than :data:`DISAGREE_M` apart.
    """
    if terrain.measured_m is None or terrain.dem_m is None:
        return None
    (tlo, thi), (dlo, dhi) = terrain.measured_m, terrain.dem_m
    gap = max(tlo - dhi, dlo - thi)
    if gap <= DISAGREE_M:
        return None
    where = "above" if tlo > dhi else "below"
    return (
        f"the tie points' heights ({tlo:.0f}..{thi:.0f} m) lie {gap:.0f} m {where} the DEM's "
        f"({dlo:.0f}..{dhi:.0f} m, {terrain.dem}): a DEM of another datum (its vertical "
        "reference: geoid_undulation, geoid, dem_ellipsoidal), place or time? Both spans are "
        "searched"
    )


def match_heights(
    matches: Matches, left_grid: OutputGrid, right_grid: OutputGrid, norm: Normalization
) -> FloatArray:
    """Heights (m) of tie points between two normalized images, ``Z = (x_l - x_r - off) / k``.

    Args:
        matches: conjugate pixels (columns, rows) of the left and right images.
        left_grid: the left image's output grid.
        right_grid: the right image's output grid.
        norm: the pair's normalization (its parallax relation).
    """
    xl = left_grid.x_origin + left_grid.pixel * matches.xl
    xr = right_grid.x_origin + right_grid.pixel * matches.xr
    z: FloatArray = (xl - xr - norm.parallax_offset) / norm.parallax_per_height
    return z


def consistent_rows(matches: Matches, *, limit_px: float = Y_OUTLIER_PX) -> NDArray[np.bool_]:
    """Matches whose row difference is within ``limit_px`` of the median one (gross errors out).

    The images are epipolar up to the models' error, which is nearly constant over a pair
    (e.g. 4.8 px between the Ventoux RPCs before tie-point refinement): the median is taken
    out, not zero.
    """
    dy = matches.yl - matches.yr
    if dy.size == 0:
        return np.zeros(0, dtype=bool)
    keep: NDArray[np.bool_] = np.abs(dy - np.median(dy)) <= limit_px
    return keep


def terrain_from_heights(
    z: FloatArray, prior: Terrain, *, metres_per_px: float, min_points: int = MIN_TERRAIN_POINTS
) -> Terrain:
    """The terrain of tie-point heights ``z`` (m), or ``prior`` when there are too few.

    The lowest and highest ground are the :data:`TERRAIN_PERCENTILES` of ``z`` (a few gross
    errors fall outside them), each widened by :data:`TERRAIN_PAD_SHARE` of their span and at
    least :data:`TERRAIN_PAD_PX` pixels of x-parallax (``metres_per_px``: |metres of height per
    pixel|).
    """
    z = z[np.isfinite(z)]
    if z.size < max(min_points, 2):
        return prior
    lo, hi = (float(v) for v in np.percentile(z, TERRAIN_PERCENTILES))
    pad = max(TERRAIN_PAD_SHARE * (hi - lo), TERRAIN_PAD_PX * abs(metres_per_px))
    return Terrain(lo - pad, hi + pad, TerrainSource.TIE_POINTS, int(z.size), (lo, hi))


def measure_terrain(
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    left_grid: OutputGrid,
    right_grid: OutputGrid,
    norm: Normalization,
    prior: Terrain,
    *,
    nodata: float,
    min_points: int = MIN_TERRAIN_POINTS,
) -> Terrain:
    """The terrain of a normalized pair from tie points matched between its images.

    Args:
        left: left normalized image (rows, cols).
        right: right normalized image, same shape.
        left_grid: its output grid.
        right_grid: the right image's output grid.
        norm: the pair's normalization.
        prior: returned when fewer than ``min_points`` tie points agree.
        nodata: pixel value outside the scenes.
        min_points: fewest tie points that measure a terrain.
    """
    if left.shape != right.shape or min(left.shape[:2]) < 32:
        return prior
    f = reduction_factor(left.shape[1], left.shape[0])
    if f > 1:
        left, left_grid = reduce_image(left, left_grid, f, nodata)
        right, right_grid = reduce_image(right, right_grid, f, nodata)
    # One window over the whole (reduced) image: conjugate points may lie far apart along
    # the rows when the heights assumed so far are far from the ground. ORB, not SIFT: SIFT
    # doubles the image first and holds some 200 bytes per input pixel (the overload test's
    # node peaked 60 MB higher with it), ORB a few.
    m = match_normalized(
        left,
        right,
        nodata=nodata,
        whole=True,
        max_per_window=1000,
        max_y_px=None,
        min_corr=MIN_CORRELATION,
        detector="orb",
    )
    m = m.subset(consistent_rows(m))
    z = match_heights(m, left_grid, right_grid, norm)
    return terrain_from_heights(
        z, prior, metres_per_px=left_grid.pixel / norm.parallax_per_height, min_points=min_points
    )


def reduce_image(
    image: NDArray[np.generic], grid: OutputGrid, factor: int, nodata: float
) -> tuple[NDArray[np.generic], OutputGrid]:
    """``image`` reduced by an integer ``factor`` (block means), and its grid.

    A reduced pixel with any no-data pixel in its block is no-data. The last rows and columns
    that do not fill a block are dropped.

    Args:
        image: (rows, cols) pixels on ``grid``.
        grid: the image's output grid.
        factor: block side, pixels (>= 1).
        nodata: the no-data value.
    """
    rows, cols = image.shape[0] // factor, image.shape[1] // factor
    full = image[: rows * factor, : cols * factor]
    size = (cols, rows)
    small = cv2.resize(np.asarray(full), size, interpolation=cv2.INTER_AREA)
    valid = cv2.resize((full != nodata).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    small[valid < 1.0] = nodata
    half = 0.5 * (factor - 1) * grid.pixel  # centre of the first block
    out = OutputGrid(grid.pixel * factor, grid.x_origin + half, grid.y_origin + half, cols, rows)
    return small, out


def reduction_factor(width: int, height: int, target_px: int = 1024) -> int:
    """Integer reduction bringing the longer side of an image to ``target_px`` or less (1: none).

    Args:
        width: columns of the full image.
        height: rows of the full image.
        target_px: longest side wanted, pixels.
    """
    return max(1, math.ceil(max(width, height) / target_px))
