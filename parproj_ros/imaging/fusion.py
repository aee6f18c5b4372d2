"""Fusion of the DSMs of several pairs of one area into one DSM (issue 24, item 4).

The pair DSMs (:class:`~parproj_ros.imaging.heights.DsmGrid` grids in one object frame, Z
metres, NaN holes) are sampled bilinearly onto a common grid (:func:`sample_bilinear`: the
valid neighbours' weights renormalized, "nodata kept out"; a cell whose valid neighbours weigh
less than ``min_weight`` of the support stays empty, so a hole shrinks by at most half a cell
and nothing is extrapolated). Then, per cell:

1. the median ``m`` of the pairs' samples;
2. samples farther than ``tolerance_m`` from ``m`` are rejected (blunders, occlusions, a
   mismatched repetitive pattern);
3. the fused height is the mean of the samples kept (weighted: ``weights``, e.g. 1 / a^2 with
   ``a`` a pair's metres of height per pixel of disparity, so that a pair of twice the base
   counts four times); ``count`` is their number and ``spread`` their range (max - min,
   metres; 0 for one sample).

With an odd number of samples the median is one of them, so a cell with data keeps at least one.
Two samples farther apart than ``2 tolerance_m`` (and, rarely, an even number of samples that
split the same way) leave no sample within the tolerance of their median: the cell takes the
sample closer to the local consensus (the median of the fused heights of the 5 x 5 cells around
it, among the cells that were resolved in step 3) if that sample lies within
``2 tolerance_m`` of it, and stays empty otherwise (no resolved neighbour, or no sample near).
A fused cell is never empty where a pair has a height, except in that last case.

Level of the pairs. Each pair's DSM has its own height level (the relative error of the RPC
models along the epipolar lines: 2.4 and 4.9 m between the Marseille pairs, README of the
data). :func:`mutual_offsets` measures it (median of A - B over the cells valid in both);
with ``align`` each DSM is shifted by the least-squares offset ``o_i`` (``o_i - o_j``
closest to the pairwise medians, weighted by the shared cells, ``sum o_i = 0``) before the
combination, so that the fused DSM lies at the mean level of the pairs (what s2p does by
subtracting each pair's mean offset before averaging). A multi-view adjustment of the models
that puts the pairs on one level leaves these offsets near 0.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry.geodesy import LocalTangentPlane
from .heights import DsmGrid, bilinear_terms

__all__ = [
    "FusedDsm",
    "common_grid",
    "frame_box",
    "fuse",
    "level_offsets",
    "mutual_offsets",
    "on_grid",
    "reframe",
    "sample_bilinear",
]

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]

#: Default tolerance about the per-cell median, metres (s2p's triplet fusion uses 3 m).
TOLERANCE_M = 3.0
#: Fewest shared cells for a pairwise offset to count.
MIN_SHARED_CELLS = 100
#: Side of the window of the local consensus that settles a split cell, cells.
CONSENSUS_WINDOW = 5


def sample_bilinear(
    values: ArrayLike, grid: DsmGrid, x: ArrayLike, y: ArrayLike, *, min_weight: float = 0.5
) -> FloatArray:
    """Bilinear samples of a grid at (x, y), nodata (NaN) kept out.

    Of the four cells around (x, y), those with a finite value are weighed bilinearly and the
    weights renormalized; the sample is NaN where their total weight is below ``min_weight``
    (0..1), where (x, y) lies outside the box of the cell centres, or is NaN.

    Args:
        values: (grid.height, grid.width), NaN where there is no value.
        grid: where the cells are (centre of cell (r, c) at x0 + c cell, y0 - r cell).
        x: X of the points, metres in the grid's frame (any shape).
        y: Y of the points, same shape.
        min_weight: smallest share of the bilinear support that must have data.

    Returns:
        float64 samples, the shape of ``x``.
    """
    v = np.asarray(values)
    if v.shape != (grid.height, grid.width):
        raise ValueError(f"values of shape {v.shape} on a grid of {grid.height} x {grid.width}")
    xa = np.asarray(x, dtype=float)
    ya = np.asarray(y, dtype=float)
    total, _, wsum, _ = bilinear_terms(v, grid, xa, ya, np.isfinite(v))
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(wsum) & (wsum >= min_weight - 1e-12) & (wsum > 0.0)
        return np.where(ok, total / np.where(ok, wsum, 1.0), np.nan)


def common_grid(grids: Sequence[DsmGrid], cell: float | None = None) -> DsmGrid:
    """The north-up grid covering every grid's cell centres, cell ``cell`` (default: finest).

    Centres on multiples of the cell (:meth:`DsmGrid.covering`), so grids made that way (as
    :func:`~parproj_ros.imaging.heights.make_dsm` makes them) share their lattice with it.
    """
    if not grids:
        raise ValueError("no grid to cover")
    size = min(g.cell for g in grids) if cell is None else float(cell)
    xmin = min(g.x0 for g in grids)
    xmax = max(g.x0 + (g.width - 1) * g.cell for g in grids)
    ymax = max(g.y0 for g in grids)
    ymin = min(g.y0 - (g.height - 1) * g.cell for g in grids)
    return DsmGrid.covering(xmin, xmax, ymin, ymax, size)


def block_means(heights: ArrayLike, grid: DsmGrid, k: int) -> tuple[Float32Array, DsmGrid]:
    """A DSM averaged over blocks of k x k cells (NaN holes left out), and its grid.

    A block is the mean of its cells with a height where they are at least a quarter of it,
    else NaN; the last row and column of blocks may hold fewer cells. The blocks' grid: cell
    ``k grid.cell``, its first centre the centre of the first block.
    """
    z = np.asarray(heights, dtype=np.float32)
    rows, cols = -(-z.shape[0] // k), -(-z.shape[1] // k)
    pad = np.full((rows * k, cols * k), np.nan, dtype=np.float32)
    pad[: z.shape[0], : z.shape[1]] = z
    blocks = pad.reshape(rows, k, cols, k)
    have = np.isfinite(blocks)
    n = have.sum(axis=(1, 3))
    total = np.where(have, blocks, np.float32(0.0)).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(4 * n >= k * k, total / np.maximum(n, 1), np.nan).astype(np.float32)
    half = 0.5 * (k - 1) * grid.cell
    coarse = DsmGrid(grid.x0 + half, grid.y0 - half, k * grid.cell, cols, rows)
    return mean, coarse


def on_grid(
    heights: ArrayLike, grid: DsmGrid, target: DsmGrid, *, min_weight: float = 0.5
) -> Float32Array:
    """A DSM resampled onto ``target`` (same frame): :func:`sample_bilinear` at its centres.

    Onto a target at least twice as coarse, the DSM is first averaged over blocks of
    ``floor(target.cell / grid.cell)`` cells (:func:`block_means`): a coarse cell is the mean of
    the heights in it, not the one fine cell under its centre (which, with a cell larger than
    the DSM, misses it altogether).
    """
    # floor of the ratio, a ratio within 1e-9 of a whole number taken as it (0.3 // 0.1 is 2.0)
    k = math.floor(target.cell / grid.cell + 1e-9) if grid.cell > 0 else 1
    if k >= 2:
        heights, grid = block_means(heights, grid, k)
    x, y = target.centres()
    return sample_bilinear(heights, grid, x, y, min_weight=min_weight).astype(np.float32)


def mutual_offsets(
    layers: Sequence[ArrayLike], *, min_cells: int = MIN_SHARED_CELLS
) -> tuple[FloatArray, NDArray[np.int64], FloatArray]:
    """Pairwise level offsets of DSMs on one grid.

    Returns:
        (median, cells, nmad), each (n, n): ``median[i, j]`` the median of layer i - layer j
        over the cells valid in both, metres (NaN with fewer than ``min_cells`` such cells;
        0 on the diagonal), ``cells[i, j]`` their number, ``nmad[i, j]`` 1.4826 median
        |d - median d|, metres.
    """
    arrs = [np.asarray(a, dtype=np.float32) for a in layers]
    n = len(arrs)
    med = np.full((n, n), np.nan)
    nmad = np.full((n, n), np.nan)
    cells = np.zeros((n, n), dtype=np.int64)
    for i in range(n):
        med[i, i] = 0.0
        nmad[i, i] = 0.0
        cells[i, i] = int(np.isfinite(arrs[i]).sum())
        for j in range(i + 1, n):
            d = (arrs[i] - arrs[j]).ravel()
            d = d[np.isfinite(d)].astype(float)
            cells[i, j] = cells[j, i] = d.size
            if d.size >= max(min_cells, 1):
                m = float(np.median(d))
                s = 1.4826 * float(np.median(np.abs(d - m)))
                med[i, j], med[j, i] = m, -m
                nmad[i, j] = nmad[j, i] = s
    return med, cells, nmad


def level_offsets(median: ArrayLike, cells: ArrayLike) -> FloatArray:
    """Per-layer offsets o (metres, sum 0) with o_i - o_j closest to ``median[i, j]``.

    Least squares over the pairs with a finite median, weighted by sqrt(shared cells); a layer
    with no such pair gets 0.
    """
    m = np.asarray(median, dtype=float)
    c = np.asarray(cells, dtype=float)
    n = m.shape[0]
    rows: list[FloatArray] = []
    rhs: list[float] = []
    for i in range(n):
        for j in range(i + 1, n):
            if math.isfinite(m[i, j]) and c[i, j] > 0:
                wt = math.sqrt(c[i, j])
                row = np.zeros(n)
                row[i], row[j] = wt, -wt
                rows.append(row)
                rhs.append(wt * m[i, j])
    if not rows:
        return np.zeros(n)
    scale = max(abs(r).max() for r in rows)
    rows.append(np.full(n, scale))  # sum o = 0
    rhs.append(0.0)
    sol, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    return np.asarray(sol, dtype=float)


#: Fixed-point rounds of :func:`reframe`, and the step (m) that ends them early.
REFRAME_ROUNDS = 6
REFRAME_TOL_M = 1e-5


def _median_z(heights: ArrayLike) -> float:
    z = np.asarray(heights, dtype=float)
    z = z[np.isfinite(z)]
    return float(np.median(z)) if z.size else 0.0


def frame_box(
    heights: ArrayLike, grid: DsmGrid, src: LocalTangentPlane, dst: LocalTangentPlane
) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) in ``dst`` of a ``src`` grid's outline, metres.

    The outline's cell corners are taken at the DSM's lowest and highest heights (a point's
    horizontal position in another tangent plane moves by about d / R per metre of height).
    """
    z = np.asarray(heights, dtype=float)
    zs = [float(np.nanmin(z)), float(np.nanmax(z))] if np.isfinite(z).any() else [0.0]
    half = 0.5 * grid.cell
    xa, xb = grid.x0 - half, grid.x0 + (grid.width - 1) * grid.cell + half
    ya, yb = grid.y0 + half, grid.y0 - (grid.height - 1) * grid.cell - half
    t = np.linspace(0.0, 1.0, 65)
    xs = np.concatenate([xa + (xb - xa) * t, xa + (xb - xa) * t, np.full(65, xa), np.full(65, xb)])
    ys = np.concatenate([np.full(65, ya), np.full(65, yb), ya + (yb - ya) * t, ya + (yb - ya) * t])
    px: list[FloatArray] = []
    py: list[FloatArray] = []
    for zz in zs:
        lon, lat, h = src.to_geodetic(xs, ys, zz)
        x, y, _ = dst.to_local(lon, lat, h)
        px.append(x)
        py.append(y)
    ax, ay = np.concatenate(px), np.concatenate(py)
    return float(ax.min()), float(ax.max()), float(ay.min()), float(ay.max())


def reframe(
    heights: ArrayLike,
    grid: DsmGrid,
    src: LocalTangentPlane,
    dst: LocalTangentPlane,
    target: DsmGrid,
    *,
    min_weight: float = 0.5,
) -> Float32Array:
    """A DSM of tangent plane ``src`` as heights Z of tangent plane ``dst`` on ``target``.

    For each target cell centre (x, y): the Z at which the vertical of ``dst`` through it meets
    the surface, by fixed-point iteration: (x, y, Z) -> geodetic -> ``src`` (xs, ys, zs);
    Z += Z_src(xs, ys) - zs (Z_src by :func:`sample_bilinear`). The two frames' verticals
    differ by about d / R (1.6e-4 rad at 1 km), so a few rounds reach 1e-5 m. NaN where the
    surface has no height.
    """
    z_src = np.asarray(heights, dtype=np.float32)
    x, y = target.centres()
    # start at the surface's median height, placed in dst at the source grid's centre
    xc = grid.x0 + 0.5 * (grid.width - 1) * grid.cell
    yc = grid.y0 - 0.5 * (grid.height - 1) * grid.cell
    lon, lat, h = src.to_geodetic(xc, yc, _median_z(z_src))
    _, _, zc = dst.to_local(lon, lat, h)
    z = np.full(x.shape, float(zc))
    for _ in range(REFRAME_ROUNDS):
        lon, lat, h = dst.to_geodetic(x, y, z)
        xs, ys, zs = src.to_local(lon, lat, h)
        dz = sample_bilinear(z_src, grid, xs, ys, min_weight=min_weight) - zs
        step = np.isfinite(dz)
        z = np.where(step, z + np.where(step, dz, 0.0), z)
        if not step.any() or float(np.max(np.abs(dz[step]))) < REFRAME_TOL_M:
            break
    lon, lat, h = dst.to_geodetic(x, y, z)
    xs, ys, zs = src.to_local(lon, lat, h)
    dz = sample_bilinear(z_src, grid, xs, ys, min_weight=min_weight) - zs
    return np.asarray(z + dz, dtype=np.float32)


@dataclass(frozen=True)
class FusedDsm:
    """A DSM fused from several pair DSMs on one grid.

    Attributes:
        heights: float32 (grid.height, grid.width), Z metres in the inputs' frame, NaN holes.
        count: uint8, samples kept per cell (0 for holes).
        spread: float32, max - min of the samples kept, metres (0 for one sample, NaN holes).
        grid: the common grid.
        offsets: metres subtracted from each input before fusion (0 without alignment).
        median_before: (n, n) median of input i - input j over shared cells, before
            alignment, metres (:func:`mutual_offsets`).
        median_after: the same after alignment (equal to ``median_before`` without it).
        shared_cells: (n, n) cells valid in both inputs.
        samples: uint8, inputs with a sample per cell (before rejection).
        split_cells: cells settled by the local consensus (two or more samples, none within
            the tolerance of their median).
    """

    heights: Float32Array
    count: NDArray[np.uint8]
    spread: Float32Array
    grid: DsmGrid
    offsets: FloatArray
    median_before: FloatArray
    median_after: FloatArray
    shared_cells: NDArray[np.int64]
    samples: NDArray[np.uint8]
    split_cells: int

    @property
    def completeness(self) -> float:
        """Share of the grid's cells with a fused height (0..1)."""
        return float(np.isfinite(self.heights).mean()) if self.heights.size else 0.0


def _consensus(
    fused: Float32Array, rows: NDArray[np.int64], cols: NDArray[np.int64]
) -> FloatArray:
    """Median of the finite fused heights in the window around each (row, col); NaN if none."""
    half = CONSENSUS_WINDOW // 2
    padded = np.pad(fused, half, constant_values=np.nan)
    win = np.stack(
        [
            padded[rows + half + dr, cols + half + dc]
            for dr in range(-half, half + 1)
            for dc in range(-half, half + 1)
        ],
        axis=1,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        return np.asarray(np.nanmedian(win, axis=1), dtype=float)


def fuse(
    dsms: Sequence[tuple[ArrayLike, DsmGrid]],
    *,
    grid: DsmGrid | None = None,
    cell: float | None = None,
    tolerance_m: float = TOLERANCE_M,
    align: bool = True,
    min_weight: float = 0.5,
    weights: Sequence[float] | None = None,
) -> FusedDsm:
    """Fuse the DSMs of one area (one object frame) into one DSM (module docstring).

    Args:
        dsms: (heights Z metres, NaN holes; grid) of each pair, all in the same frame.
        grid: the output grid (default :func:`common_grid` of the inputs at ``cell``).
        cell: output cell side, metres, when ``grid`` is not given (default: finest input).
        tolerance_m: samples farther than this from the per-cell median are rejected, metres.
        align: remove each input's level offset (:func:`level_offsets`) before combining.
        min_weight: see :func:`sample_bilinear`.
        weights: per input, the weight of its samples in the mean of the kept ones (default:
            equal). For pairs matched with one matcher, the height noise is the disparity
            noise (pixels, about the same in every pair) times the pair's metres per pixel of
            disparity ``a``: ``1 / a^2`` weighs each pair by its precision.

    Raises:
        ValueError: fewer than two DSMs, or a tolerance that is not > 0.
    """
    if len(dsms) < 2:
        raise ValueError(f"fusion needs two or more DSMs, got {len(dsms)}")
    if not (tolerance_m > 0 and math.isfinite(tolerance_m)):
        raise ValueError(f"tolerance_m must be a finite length > 0 m, got {tolerance_m}")
    if len(dsms) > 255:
        raise ValueError(f"at most 255 DSMs can be fused at once, got {len(dsms)}")
    out = grid or common_grid([g for _, g in dsms], cell)
    layers = [on_grid(h, g, out, min_weight=min_weight) for h, g in dsms]
    before, shared, _ = mutual_offsets(layers)
    offsets = level_offsets(before, shared) if align else np.zeros(len(layers))
    if align:
        layers = [a - np.float32(o) for a, o in zip(layers, offsets, strict=True)]
        after, _, _ = mutual_offsets(layers)
    else:
        after = before.copy()
    stack = np.stack(layers).astype(np.float32)  # (n, rows, cols)
    have = np.isfinite(stack)
    samples = have.sum(axis=0).astype(np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN cells
        med = np.nanmedian(stack, axis=0)
    keep = have & (np.abs(stack - med[None]) <= np.float32(tolerance_m))
    count = keep.sum(axis=0)
    if weights is None:
        w = np.ones(len(layers), dtype=np.float32)
    else:
        w = np.asarray(weights, dtype=np.float32)
        if w.shape != (len(layers),) or not np.all(np.isfinite(w) & (w > 0)):
            raise ValueError(f"weights must be {len(layers)} finite values > 0, got {weights}")
    wk = np.where(keep, w[:, None, None], np.float32(0.0))
    kept = np.where(keep, stack, np.float32(0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        total = wk.sum(axis=0)
        fused = np.where(
            count > 0, (wk * kept).sum(axis=0) / np.where(count > 0, total, 1), np.nan
        )
    fused = fused.astype(np.float32)
    hi = np.where(keep, stack, -np.inf).max(axis=0)
    lo = np.where(keep, stack, np.inf).min(axis=0)
    spread = np.where(count > 0, hi - lo, np.nan).astype(np.float32)
    split = (samples >= 2) & (count == 0)
    rows, cols = np.nonzero(split)
    if rows.size:
        ref = _consensus(fused, rows, cols)
        vals = stack[:, rows, cols].astype(float)  # (n, k)
        dist = np.where(np.isfinite(vals), np.abs(vals - ref[None]), np.inf)
        pick = np.argmin(dist, axis=0)
        chosen = vals[pick, np.arange(rows.size)]
        good = np.isfinite(ref) & (dist[pick, np.arange(rows.size)] <= 2.0 * tolerance_m)
        fused[rows[good], cols[good]] = chosen[good]
        count[rows[good], cols[good]] = 1
        spread[rows[good], cols[good]] = 0.0
    return FusedDsm(
        heights=fused,
        count=count.astype(np.uint8),
        spread=spread,
        grid=out,
        offsets=np.asarray(offsets, dtype=float),
        median_before=before,
        median_after=after,
        shared_cells=shared,
        samples=samples,
        split_cells=int(rows.size),
    )
