"""Heights, DSM and ortho-image from the disparity map of a normalized pair.

A left normalized pixel (col, row) with disparity d has the height ``Z = a d + b`` (the pair's
``height_per_disparity_px`` a, metres per pixel, and ``height_offset_m`` b, metres). Its object
X, Y follow from inverting the chain the pair was resampled with (paper 1 Eqs 1-2, paper 2
Eq 8): normalized pixel -> normalized metres (the :class:`OutputGrid`) -> parallel scene
(x, y') (inverse of the scene's 2x3 normalization affine) -> object X, Y at the known Z from
``x = A1 X + A2 Y + A3 Z + A4``, ``y' = A5 X + A6 Y + A7 Z + A8``. For a fixed Z this chain is
affine, so :class:`GroundMapping` holds it as one 2x3 matrix plus the shift per metre of height
(the horizontal step along the scene's projection vector).

The DSM is a north-up grid in the object frame (:class:`DsmGrid`: row 0 at the largest Y);
cells take the mean (or median) height of the points falling in them; cells without points
are NaN (optionally filled from the nearest cell, and flagged). The ortho-image resamples the
left normalized image (or the original scene, through its :class:`SceneGeometry`) onto the DSM
grid with ``cv2.remap``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, Protocol, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry.epipolar import Normalization, invert_affine_2x3
from ..geometry.parallel import AffineModel
from .resample import OutputGrid, SceneGeometry
from .threads import row_parts, run_parts, workers

__all__ = [
    "Dsm",
    "DsmGrid",
    "GroundMapping",
    "PairLike",
    "bilinear_terms",
    "dsm_errors",
    "heights_from_disparity",
    "make_dsm",
    "orthoimage",
]

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]
BoolArray = NDArray[np.bool_]


def heights_from_disparity(
    disparity: ArrayLike, height_per_disparity_px: float, height_offset_m: float
) -> Float32Array:
    """``Z = a d + b`` per pixel, metres, float32 (NaN where the disparity is NaN).

    Args:
        disparity: col_left - col_right, pixels (any shape).
        height_per_disparity_px: a, metres per pixel.
        height_offset_m: b, metres.
    """
    d = np.asarray(disparity, dtype=np.float32)
    return cast(
        "Float32Array",
        (d * np.float32(height_per_disparity_px) + np.float32(height_offset_m)).astype(np.float32),
    )


class _SceneLike(Protocol):
    @property
    def affine(self) -> AffineModel: ...


class PairLike(Protocol):
    """What :meth:`GroundMapping.of_pair` reads of a pair (a ``core.results.PairResult``)."""

    @property
    def left(self) -> _SceneLike:
        """The left scene (its A1..A8 ``affine``)."""

    @property
    def right(self) -> _SceneLike:
        """The right scene."""

    @property
    def normalization(self) -> Normalization:
        """Paper 2 Eq 8 (the 2x3 affines ``left`` and ``right``)."""

    @property
    def left_grid(self) -> OutputGrid:
        """The left normalized image's grid."""

    @property
    def right_grid(self) -> OutputGrid:
        """The right normalized image's grid."""


@dataclass(frozen=True)
class GroundMapping:
    """Pixel of one normalized image <-> object X, Y at a known height Z (exact, affine in Z).

    Attributes:
        grid: the normalized image's grid (normalized metres per pixel, origin).
        to_normalized: 2x3 affine, parallel scene metres (x, y') -> normalized metres
            (``PairResult.normalization.left`` for the left image).
        affine: the scene's A1..A8 (``PairResult.left.affine``), object metres -> scene metres.
    """

    grid: OutputGrid
    to_normalized: FloatArray
    affine: AffineModel

    @classmethod
    def of_pair(cls, pair: PairLike, side: Literal["left", "right"] = "left") -> GroundMapping:
        """The mapping of one image of a pair: its grid, normalization affine and A1..A8."""
        if side == "left":
            return cls(pair.left_grid, pair.normalization.left, pair.left.affine)
        if side == "right":
            return cls(pair.right_grid, pair.normalization.right, pair.right.affine)
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")

    @property
    def _pixel_to_ground(self) -> tuple[FloatArray, FloatArray]:
        """(2x3 M, (2,) v): (X, Y) = M (col, row, 1) + v Z."""
        g = self.grid
        to_pix = np.array([[g.pixel, 0.0, g.x_origin], [0.0, g.pixel, g.y_origin]])
        scene = invert_affine_2x3(self.to_normalized)  # normalized metres -> scene (x, y')
        a = self.affine.matrix
        inv = np.linalg.inv(a[:, :2])
        # (X, Y) = inv ((x, y') - A[:, 2] Z - A[:, 3])
        m_scene = np.hstack([inv, (-inv @ a[:, 3])[:, None]])
        m = _compose(m_scene, _compose(scene, to_pix))
        return m, np.asarray(-inv @ a[:, 2], dtype=float)

    @property
    def ground_sample_distance(self) -> float:
        """Object metres per normalized pixel (square root of the pixel's ground area), m."""
        m, _ = self._pixel_to_ground
        return float(math.sqrt(abs(np.linalg.det(m[:, :2]))))

    def pixel_to_ground(
        self, col: ArrayLike, row: ArrayLike, z: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Normalized pixel (col, row) at height z (m) -> object (X, Y), metres."""
        m, v = self._pixel_to_ground
        c, r, zz = (np.asarray(t, dtype=float) for t in (col, row, z))
        x = m[0, 0] * c + m[0, 1] * r + m[0, 2] + v[0] * zz
        y = m[1, 0] * c + m[1, 1] * r + m[1, 2] + v[1] * zz
        return x, y

    def ground_to_normalized(
        self, x: ArrayLike, y: ArrayLike, z: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Object (X, Y, Z), metres -> normalized metres (x_n, y_n) (Eq 2, then Eq 8)."""
        a = self.affine.matrix
        xx, yy, zz = (np.asarray(t, dtype=float) for t in (x, y, z))
        xs = a[0, 0] * xx + a[0, 1] * yy + a[0, 2] * zz + a[0, 3]
        ys = a[1, 0] * xx + a[1, 1] * yy + a[1, 2] * zz + a[1, 3]
        h = self.to_normalized
        return h[0, 0] * xs + h[0, 1] * ys + h[0, 2], h[1, 0] * xs + h[1, 1] * ys + h[1, 2]

    def ground_to_pixel(
        self, x: ArrayLike, y: ArrayLike, z: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Object (X, Y, Z), metres -> normalized pixel (col, row)."""
        xn, yn = self.ground_to_normalized(x, y, z)
        g = self.grid
        return (xn - g.x_origin) / g.pixel, (yn - g.y_origin) / g.pixel


def _compose(outer: FloatArray, inner: FloatArray) -> FloatArray:
    """2x3 affine outer(inner(p))."""
    return np.hstack(
        [outer[:, :2] @ inner[:, :2], (outer[:, :2] @ inner[:, 2] + outer[:, 2])[:, None]]
    )


@dataclass(frozen=True)
class DsmGrid:
    """A north-up object-frame grid: cell (row, col) at X = x0 + col cell, Y = y0 - row cell.

    Attributes:
        x0: X of the centre of column 0, metres.
        y0: Y of the centre of row 0 (the largest Y), metres.
        cell: cell side, metres.
        width: columns.
        height: rows.
    """

    x0: float
    y0: float
    cell: float
    width: int
    height: int

    @classmethod
    def covering(cls, xmin: float, xmax: float, ymin: float, ymax: float, cell: float) -> DsmGrid:
        """The grid of cell side ``cell`` (m), centres on multiples of it, holding the box.

        Every point of [xmin, xmax] x [ymin, ymax] (metres) falls in one of its cells.
        """
        if not (cell > 0 and math.isfinite(cell)):
            raise ValueError(f"cell must be a finite size > 0 m, got {cell}")
        # Cell centres on multiples of ``cell``; the cells holding the extreme points.
        x0 = math.floor(xmin / cell + 0.5) * cell
        y0 = math.floor(ymax / cell + 0.5) * cell
        w = math.floor((xmax - x0) / cell + 0.5) + 1
        h = math.floor((y0 - ymin) / cell + 0.5) + 1
        return cls(x0, y0, cell, w, h)

    def centres(self, rows: tuple[int, int] | None = None) -> tuple[FloatArray, FloatArray]:
        """(X, Y) of the cell centres of rows[0]:rows[1] (all rows by default), metres."""
        r0, r1 = rows or (0, self.height)
        cols = self.x0 + self.cell * np.arange(self.width, dtype=float)
        ys = self.y0 - self.cell * np.arange(r0, r1, dtype=float)
        x, y = np.meshgrid(cols, ys)
        return x, y

    def index(self, x: FloatArray, y: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(row, col) of the cell holding each point (may be outside the grid)."""
        col = np.floor((x - self.x0) / self.cell + 0.5).astype(np.int64)
        row = np.floor((self.y0 - y) / self.cell + 0.5).astype(np.int64)
        return row, col


@dataclass(frozen=True)
class Dsm:
    """A gridded digital surface model.

    Attributes:
        heights: float32 (grid.height, grid.width), metres; NaN where no point fell (and
            not filled).
        grid: where the cells are.
        count: int32, points per cell (0 for holes and filled cells).
        filled: bool, True where the height was filled from the nearest cell with points.
    """

    heights: Float32Array
    grid: DsmGrid
    count: NDArray[np.int32]
    filled: BoolArray


def _spans(n: int, step: int) -> list[tuple[int, int]]:
    return [(s, min(n, s + step)) for s in range(0, n, step)]


def bilinear_terms(
    values: NDArray[Any], grid: DsmGrid, x: FloatArray, y: FloatArray, valid: NDArray[np.bool_]
) -> tuple[FloatArray, NDArray[np.bool_], FloatArray, FloatArray]:
    """The terms of a bilinear sample of a grid at object (x, y), metres, nodata kept out.

    Shared by every sampler of a grid (the GeoTIFF export, the fusion, the DSM comparisons),
    each of which decides what a point with some invalid neighbours gets.

    Args:
        values: (grid.height, grid.width).
        grid: where the cells are (centre of cell (r, c) at x0 + c cell, y0 - r cell).
        x: X of the points, metres (any shape; NaN allowed: outside).
        y: Y of the points, same shape.
        valid: (grid.height, grid.width), True where ``values`` holds data.

    Returns:
        (value, ok, weight_ok, nearest): ``value`` the weighted sum over the neighbours of
        non-zero weight that are ``valid``, ``ok`` True where all of those are valid and the
        point lies within the box of the cell centres, ``weight_ok`` their total weight (NaN
        outside the box), ``nearest`` the value of the nearest cell (NaN outside the box).
    """
    w, h = grid.width, grid.height
    c = (x - grid.x0) / grid.cell
    r = (grid.y0 - y) / grid.cell
    inside = (c >= 0.0) & (c <= w - 1) & (r >= 0.0) & (r <= h - 1)  # False for NaN
    c = np.where(inside, c, 0.0)
    r = np.where(inside, r, 0.0)
    c0 = np.clip(np.floor(c).astype(np.int64), 0, max(w - 2, 0))
    r0 = np.clip(np.floor(r).astype(np.int64), 0, max(h - 2, 0))
    c1 = np.minimum(c0 + 1, w - 1)
    r1 = np.minimum(r0 + 1, h - 1)
    fc = c - c0
    fr = r - r0
    total = np.zeros(c.shape)
    wsum = np.zeros(c.shape)
    ok = inside.copy()
    for rr, cc, wk in (
        (r0, c0, (1.0 - fr) * (1.0 - fc)),
        (r0, c1, (1.0 - fr) * fc),
        (r1, c0, fr * (1.0 - fc)),
        (r1, c1, fr * fc),
    ):
        good = valid[rr, cc]
        use = good & (wk > 0.0)
        total += np.where(use, wk * np.where(good, values[rr, cc], 0.0).astype(float), 0.0)
        wsum += np.where(use, wk, 0.0)
        ok &= good | (wk <= 0.0)
    nr = np.where(fr < 0.5, r0, r1)
    nc = np.where(fc < 0.5, c0, c1)
    nearest = np.where(inside, values[nr, nc].astype(float), np.nan)
    return total, ok, np.where(inside, wsum, np.nan), nearest


#: Largest fill distance (cells) done by shifted copies; farther, by a distance transform.
_SHIFT_FILL_CELLS = 3.0


def _fill_nearest(heights: Float32Array, max_cells: float) -> BoolArray:
    """Fill, in place, the NaN cells within ``max_cells`` of a cell with a height.

    Each takes the height of its nearest such cell (Euclidean distance; among equally near
    ones, the first in a fixed order of offsets). Up to :data:`_SHIFT_FILL_CELLS` by those
    offsets taken in turn on the holes near a height (on Marseille 1-2's 1.8 M cells some
    2 ms, against 12 ms for shifted copies of the whole grid), beyond by scipy's exact distance
    transform. Returns the filled cells.
    """
    if not heights.flags.c_contiguous:
        work = np.ascontiguousarray(heights)
        filled_cells = _fill_nearest(work, max_cells)
        heights[...] = work
        return filled_cells
    holes = ~np.isfinite(heights)
    if max_cells > _SHIFT_FILL_CELLS:
        from scipy.ndimage import distance_transform_edt

        dist, (ir, ic) = distance_transform_edt(holes, return_indices=True)
        filled: BoolArray = holes & (dist <= max_cells)
        heights[filled] = heights[ir[filled], ic[filled]]
        return filled
    r = math.floor(max_cells)
    offsets = sorted(
        ((dr * dr + dc * dc, dr, dc) for dr in range(-r, r + 1) for dc in range(-r, r + 1)),
    )
    rows, cols = heights.shape
    has = ~holes
    # Only the holes with a height within r cells (in rows and columns) can be filled: on a
    # DSM they are its edge and its gaps, a few % of the grid, handled as flat indices.
    near = cv2.dilate(has.view(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8))
    cand = np.flatnonzero(holes & near.view(bool))
    ci, cj = np.divmod(cand, cols)
    todo = np.ones(cand.size, dtype=bool)
    flat_h, flat_has = heights.ravel(), has.ravel()
    for d2, dr, dc in offsets:
        if d2 == 0 or d2 > max_cells * max_cells:
            continue
        # hole (i, j) takes the height of (i + dr, j + dc), the first such cell in this order
        si, sj = ci + dr, cj + dc
        at = np.flatnonzero(todo & (si >= 0) & (si < rows) & (sj >= 0) & (sj < cols))
        src = si[at] * cols + sj[at]
        take = flat_has[src]
        at, src = at[take], src[take]
        flat_h[cand[at]] = flat_h[src]  # a source has a height: it is never a hole written here
        todo[at] = False
    out: BoolArray = np.zeros(heights.shape, dtype=bool)
    out.ravel()[cand[~todo]] = True
    return out


@dataclass(frozen=True)
class _Binned:
    """The points of one block of rows binned into DSM cells lo .. lo + len(sums) - 1.

    ``sums``: of the heights; ``idx`` and ``z``: the points' cells and heights (for a
    median).
    """

    lo: int
    sums: FloatArray
    count: NDArray[np.int64]
    idx: NDArray[np.int64] | None
    z: Float32Array


def make_dsm(
    disparity: NDArray[np.floating[Any]],
    height_per_disparity_px: float,
    height_offset_m: float,
    mapping: GroundMapping,
    *,
    cell: float | None = None,
    grid: DsmGrid | None = None,
    reducer: Literal["mean", "median", "interpolated"] = "mean",
    fill: Literal["none", "nearest"] = "none",
    max_fill_cells: float = 3.0,
    block_px: int = 1 << 22,
) -> Dsm:
    """Grid the heights of a left disparity map in the object frame.

    Every valid left pixel (col, row) gives ``Z = a d + b`` and its object (X, Y) through
    ``mapping`` (:class:`GroundMapping` of the left image); each DSM cell takes the mean (or
    median) Z of the points falling in it; with "interpolated", each such cell then takes the
    height image (``a d + b``) interpolated bilinearly where its centre, at that mean height,
    projects into the left image (where the interpolation reaches a pixel without height,
    the mean stays): the height at the cell's centre rather than at the points scattered in
    it.

    Args:
        disparity: float (rows, cols) in the left normalized grid, pixels, NaN where invalid
            (:func:`parproj_ros.imaging.dense.match_pair`).
        height_per_disparity_px: a, metres per pixel.
        height_offset_m: b, metres.
        mapping: the left image's ground mapping.
        cell: cell side, metres (default: the ground sample distance of the normalized
            image, :attr:`GroundMapping.ground_sample_distance`). Ignored with ``grid``.
        grid: the DSM grid (default: the one covering the valid points).
        reducer: "mean" (memory: 16 bytes per cell), "median" (also 12 bytes per valid
            point) or "interpolated" (also 4 bytes per pixel of the part of the map a block
            of 512 cell rows projects into; on the Marseille pairs 0.010-0.015 m less NMAD
            than "mean" against s2p and CARS, less RMS, and on the simulated bags against
            truth too; docs/performance.md).
        fill: "nearest" fills holes from the nearest cell with points, up to
            ``max_fill_cells`` cells away, and flags them in :attr:`Dsm.filled`.
        max_fill_cells: largest filled distance, cells.
        block_px: disparity pixels handled at once, in whole rows (at least one; bounds the
            temporaries, some 40 bytes per pixel; each block also costs a pass over the
            cells it reaches, so blocks smaller than the grid cost more time).

    Returns:
        The DSM (all NaN when the map has no valid pixel).
    """
    h = disparity.shape[0]
    a, b = float(height_per_disparity_px), float(height_offset_m)
    valid = np.isfinite(disparity)
    if grid is None:
        size = cell if cell is not None else mapping.ground_sample_distance
        if not valid.any():
            grid = DsmGrid(0.0, 0.0, size, 1, 1)
        else:
            # The ground of the valid pixels lies within the ground of the corners of their
            # bounding box at the extreme heights (the mapping is affine).
            rows = np.flatnonzero(valid.any(axis=1))
            cols = np.flatnonzero(valid.any(axis=0))
            z = heights_from_disparity([np.nanmin(disparity), np.nanmax(disparity)], a, b).astype(
                float
            )
            cc, rr, zz = np.meshgrid([cols[0], cols[-1]], [rows[0], rows[-1]], z)
            x, y = mapping.pixel_to_ground(cc, rr, zz)
            grid = DsmGrid.covering(x.min(), x.max(), y.min(), y.max(), size)
    n_cells = grid.width * grid.height
    sums = np.zeros(n_cells, dtype=np.float64)
    count = np.zeros(n_cells, dtype=np.float64)  # whole numbers (float: a quick mean)
    keys: list[NDArray[np.int64]] = []
    vals: list[Float32Array] = []
    # The cell of pixel (c, r) at height z: floor(k . (c, r, z) + k0), k per cell axis (the
    # mapping is affine), with the terms of c and r broadcast over the block.
    m, v = mapping._pixel_to_ground
    kc = np.array([m[0, 0], m[0, 1], v[0], m[0, 2] - grid.x0]) / grid.cell
    kr = np.array([m[1, 0], m[1, 1], v[1], m[1, 2] - grid.y0]) / -grid.cell
    pix_cols = np.arange(disparity.shape[1], dtype=float)

    def grid_block(rows: tuple[int, int]) -> _Binned | None:
        r0, r1 = rows
        z = heights_from_disparity(disparity[r0:r1], a, b)  # NaN where no disparity
        pix_rows = np.arange(r0, r1, dtype=float)[:, None]
        fc = kc[0] * pix_cols + (kc[1] * pix_rows + (kc[3] + 0.5))
        fc += kc[2] * z
        np.floor(fc, out=fc)
        fr = kr[0] * pix_cols + (kr[1] * pix_rows + (kr[3] + 0.5))
        fr += kr[2] * z
        np.floor(fr, out=fr)
        # NaN (no disparity) compares False: outside
        inside = (fc >= 0) & (fc < grid.width) & (fr >= 0) & (fr < grid.height)
        fr *= grid.width
        fr += fc
        idx = fr[inside].astype(np.int64)
        if idx.size == 0:
            return None
        zin = z[inside]
        lo = int(idx.min())
        n = int(idx.max()) - lo + 1
        rel = idx - lo
        sums = cast("FloatArray", np.bincount(rel, weights=zin, minlength=n))
        count = np.bincount(rel, minlength=n)
        return _Binned(lo, sums, count, idx if reducer == "median" else None, zin)

    # Blocks of about block_px pixels, at least one per thread, binned a wave of one block per
    # thread at a time (bounded memory) and summed in order (the same sums on any threads).
    n_threads = workers()
    parts = max(n_threads, math.ceil(h * disparity.shape[1] / max(1, block_px)))
    blocks = row_parts(h, parts, min_rows=1)
    for i in range(0, len(blocks), n_threads):
        for binned in run_parts(grid_block, blocks[i : i + n_threads]):
            if binned is None:
                continue
            lo, n = binned.lo, binned.count.size
            count[lo : lo + n] += binned.count
            sums[lo : lo + n] += binned.sums
            if binned.idx is not None:
                keys.append(binned.idx)
                vals.append(binned.z)
    out = np.empty(n_cells, dtype=np.float32)
    with np.errstate(invalid="ignore"):  # 0 / 0: NaN, a cell without points
        np.divide(sums, count, out=out, casting="same_kind")
    if reducer == "median" and keys:
        k = np.concatenate(keys)
        v = np.concatenate(vals)
        order = np.lexsort((v, k))
        k, v = k[order], v[order]
        starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        lens = np.diff(np.r_[starts, k.size])
        lo_i = starts + (lens - 1) // 2
        hi_i = starts + lens // 2
        out[k[starts]] = 0.5 * (v[lo_i].astype(float) + v[hi_i].astype(float))
    heights = out.reshape(grid.height, grid.width)
    if reducer == "interpolated":
        _interpolate_cells(heights, disparity, (a, b), mapping, grid)
    filled = np.zeros(heights.shape, dtype=bool)
    if fill == "nearest" and np.isfinite(heights).any():
        filled = _fill_nearest(heights, max_fill_cells)
    return Dsm(
        heights,
        grid,
        count.reshape(grid.height, grid.width).astype(np.int32),
        filled,
    )


def _interpolate_cells(
    heights: Float32Array,
    disparity: NDArray[np.floating[Any]],
    relation: tuple[float, float],
    mapping: GroundMapping,
    grid: DsmGrid,
    block_rows: int = 512,
) -> None:
    """Each cell with a height takes the pixels' heights where its centre at that height projects.

    In place; bilinear (``cv2.remap``) in the heights ``a d + b`` of the part of the disparity
    map the block's cells project into; a cell whose interpolation reaches a pixel without a
    height (NaN) or the image's edge keeps its height. By blocks of rows, on threads.

    Args:
        heights: (grid.height, grid.width), metres, NaN without.
        disparity: the left disparity map, pixels, NaN without.
        relation: (a, b) of ``Z = a d + b``.
        mapping: the left image's ground mapping.
        grid: the cells.
        block_rows: cells' rows at once.
    """
    k = _ground_to_pixel_matrix(mapping)
    xs = grid.x0 + grid.cell * np.arange(grid.width, dtype=float)

    def sample(rows: tuple[int, int]) -> None:
        r0, r1 = rows
        z = heights[r0:r1]
        ok = np.isfinite(z)
        if not ok.any():
            return
        zz = np.where(ok, z, np.float32(0.0))
        ys = (grid.y0 - grid.cell * np.arange(r0, r1, dtype=float))[:, None]
        col, row = (
            (kk[0] * xs + (kk[1] * ys + kk[3])).astype(np.float32) + np.float32(kk[2]) * zz
            for kk in k
        )
        # the pixels they reach (and their bilinear neighbours), as heights
        h, w = disparity.shape
        left = min(max(math.floor(float(col[ok].min())) - 1, 0), w - 1)
        right = max(min(math.ceil(float(col[ok].max())) + 2, w), left + 1)
        top = min(max(math.floor(float(row[ok].min())) - 1, 0), h - 1)
        bottom = max(min(math.ceil(float(row[ok].max())) + 2, h), top + 1)
        part = heights_from_disparity(disparity[top:bottom, left:right], *relation)
        col -= np.float32(left)
        row -= np.float32(top)
        got = cv2.remap(
            part, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
        )
        use = ok & np.isfinite(got)
        z[use] = got[use]

    run_parts(sample, _spans(grid.height, block_rows))


def orthoimage(
    image: NDArray[Any],
    dsm: Dsm,
    mapping: GroundMapping,
    *,
    scene: SceneGeometry | None = None,
    nodata: float = 0.0,
    interpolation: int = cv2.INTER_LINEAR,
    block_rows: int = 512,
) -> NDArray[Any]:
    """Resample an image onto the DSM grid through its model; nodata where the DSM has none.

    Each DSM cell (X, Y, Z) is projected into the image: with ``scene`` None, ``image`` is the
    normalized image of ``mapping.grid``; with ``scene``, ``image`` is the original scene
    (lines, detectors) and the normalized metres go on through the scene's normalization
    affine, inverse PTP and frame (:meth:`SceneGeometry.normalized_to_image`; ``scene`` and
    ``mapping`` must share the normalization affine).

    Args:
        image: uint8, uint16 or float32 (rows, cols).
        dsm: heights and grid.
        mapping: ground mapping of the image's side of the pair.
        scene: the original scene's geometry, or None for a normalized image.
        nodata: value of cells without height or outside the image.
        interpolation: OpenCV interpolation flag.
        block_rows: DSM rows remapped at once.

    Returns:
        (dsm.grid.height, dsm.grid.width) of the image's dtype.
    """
    g = dsm.grid
    out = np.full((g.height, g.width), nodata, dtype=image.dtype)
    if scene is None:
        # pixel = K (X, Y, Z, 1) (affine): the terms of X and Y broadcast over each block
        pix = _ground_to_pixel_matrix(mapping)
        xs = g.x0 + g.cell * np.arange(g.width, dtype=float)

    def remap_rows(rows: tuple[int, int]) -> None:
        r0, r1 = rows
        z = dsm.heights[r0:r1]
        ok = np.isfinite(z)
        if scene is None:
            ys = (g.y0 - g.cell * np.arange(r0, r1, dtype=float))[:, None]
            col, row = (
                (k[0] * xs + (k[1] * ys + k[3])).astype(np.float32) + np.float32(k[2]) * z
                for k in pix
            )
        else:
            x, y = g.centres((r0, r1))
            zz = np.where(ok, z.astype(float), 0.0)
            xn, yn = mapping.ground_to_normalized(x, y, zz)
            row64, col64 = scene.normalized_to_image(xn, yn)
            col, row = col64.astype(np.float32), row64.astype(np.float32)
        col[~ok] = -1e6
        row[~ok] = -1e6
        out[r0:r1] = cv2.remap(
            image,
            col,
            row,
            interpolation,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float(nodata),
        )

    run_parts(remap_rows, _spans(g.height, block_rows))
    return out


def _ground_to_pixel_matrix(mapping: GroundMapping) -> FloatArray:
    """2x4 K: normalized pixel (col, row) = K (X, Y, Z, 1) of ``mapping`` (metres in)."""
    a = mapping.affine.matrix  # scene (x, y') = a (X, Y, Z, 1)
    h = mapping.to_normalized  # normalized metres = h (x, y', 1)
    g = mapping.grid
    k = h[:, :2] @ a
    k[:, 3] += h[:, 2]
    k[0, 3] -= g.x_origin
    k[1, 3] -= g.y_origin
    out: FloatArray = k / g.pixel
    return out


def dsm_errors(
    dsm: ArrayLike, truth: ArrayLike, mask: ArrayLike | None = None
) -> dict[str, float]:
    """Height errors of a DSM against the true heights of the same cells.

    Args:
        dsm: heights, metres, NaN for holes.
        truth: true heights of the same cells, metres, NaN where unknown.
        mask: optional bool, True for the cells to evaluate (e.g. seen by both images).

    Returns:
        ``rms`` and ``nmad`` (1.4826 median |e - median e|) of e = dsm - truth, metres,
        ``mean`` (bias), metres, ``n`` (cells compared) and ``completeness`` (share of the
        evaluated cells with a true height that have a DSM height, 0..1). The error figures
        are NaN when n is 0.
    """
    d = np.asarray(dsm, dtype=float)
    t = np.asarray(truth, dtype=float)
    if d.shape != t.shape:
        raise ValueError(f"dsm {d.shape} and truth {t.shape} differ in shape")
    sel = np.isfinite(t)
    if mask is not None:
        sel &= np.asarray(mask, dtype=bool)
    both = sel & np.isfinite(d)
    n_sel, n = int(sel.sum()), int(both.sum())
    e = d[both] - t[both]
    nan = float("nan")
    return {
        "rms": float(np.sqrt(np.mean(e**2))) if n else nan,
        "nmad": float(1.4826 * np.median(np.abs(e - np.median(e)))) if n else nan,
        "mean": float(e.mean()) if n else nan,
        "completeness": n / n_sel if n_sel else 0.0,
        "n": float(n),
    }
