"""Streamed heights: DSM tiles of a pair while its normalized column blocks arrive (issue 26).

In along-track stereo the normalized columns run along track, so a span of left columns
[c0, c1) can be matched as soon as both sides hold its columns plus the disparity margin
(left column c meets right columns c - dmax .. c - dmin) and the matcher's overlap (SGM
paths settle over :data:`TILE_OVERLAP` columns). :class:`TileStage` takes each pair's
streamed blocks (:class:`~.results.BlockResult`, left and right, in order), keeps the columns
a later tile still needs (older ones are dropped), and emits a :class:`~.results.HeightTile`
for each span as soon as it is covered:

- the disparity range is fixed once per pair: from the terrain measured on the pair's first
  window (tie points, :func:`~.terrain.measure_terrain`, when ``terrain`` is ``tie_points``),
  else the prior (``z_avg`` +- ``height_range``); the tile says which;
- the stretch limits the matcher needs (percentiles of each image) come from the same first
  window and are kept for every tile of the pair (the images are stretched with them before
  :func:`~parproj_ros.imaging.dense.match_pair`, which then maps the window's own extremes,
  0 and 255 where both clipped ends occur, onto 0..255);
- each tile is matched on a window of both images (:func:`match_pair` over the span, its
  overlap and the disparity margin) and keeps its own columns only;
- the pair's DSM grid is fixed with the range (north-up, cells on multiples of the cell size,
  covering the left image at the terrain's lowest and highest heights); every cell belongs to
  the tile whose span holds the left column its centre maps to at the terrain's mid height,
  and is gridded (:func:`~parproj_ros.imaging.heights.make_dsm`) from the tile's points plus
  those of its overlap, so a cell on a border sees every point it would in the whole pair.

The tiles assembled (:func:`assemble_tiles`) are the pair's DSM within the matcher's noise,
without seams. The quick-look level (parameter ``heights_quicklook``: 1, 2, 3) is the same on
blocks reduced by 2, 4 or 8 (:func:`~.terrain.reduce_image`: block means, a reduced pixel touching
no-data has none). A pair whose stream breaks (its blocks stop: a scene ended short) ends with
the tiles made so far and an ERROR naming the pair, the tiles published and why.
"""

from __future__ import annotations

import math
import queue
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry import AffineModel, Normalization
from ..imaging.dense import (
    DenseStatus,
    SgbmParams,
    disparity_range,
    match_pair,
    to_uint8,
)
from ..imaging.heights import Dsm, DsmGrid, GroundMapping, make_dsm, orthoimage
from ..imaging.resample import OutputGrid, reduce_block
from .config import PipelineConfig
from .heights import (
    MATCHER_MODES,
    HeightsOptions,
    cell_problem,
    coarse_guide,
    options_of,
)
from .ledger import StreamPair
from .results import BlockResult, HeightTile, Issue, Level, Outputs, PairResult
from .terrain import Terrain, TerrainSource, measure_terrain, with_dem

Float32Array = NDArray[np.float32]

#: Columns of a tile's span, pixels of its level (one streamed block at full resolution).
TILE_COLS = 256
#: Columns matched on each side of a span and dropped: the SGM paths settle over them (the
#: overlap of :func:`match_pair`'s own tiles).
TILE_OVERLAP = 64
#: Columns both sides must hold before the terrain is measured on them (the first window).
FIRST_WINDOW_COLS = 256
#: Rows of a band of the first window whose terrain is measured (:func:`_window_terrain`) ...
TERRAIN_BAND_ROWS = 1024
#: ... and the most bands measured, spread over the rows.
TERRAIN_BANDS = 6
#: The quick-look reductions of ``heights_quicklook`` levels 1, 2, 3 (-1, -2, -3: instead of
#: the full resolution; 0: off).
QUICKLOOK_FACTORS = (2, 4, 8)
#: Columns of a quick-look tile's span, reduced pixels. Twice :data:`TILE_COLS`: a window
#: matches its span plus 2 x :data:`TILE_OVERLAP` and the disparity margin, so a 256-column
#: span matched 1.5 times its columns, a 512-column one 1.27 times (at 1/8, 512 reduced
#: columns are 4,096 lines, 0.63 s of the IKONOS line rate).
QUICKLOOK_TILE_COLS = 512
#: A tile whose valid disparities lie within a pixel of an end of the range it searched, for
#: this share of them or more, saw terrain beyond that end (SGBM piles such pixels at the end
#: or rejects them): the pair's range is widened there and the tile matched again. On the
#: airborne bag's tiles the share is 0.000-0.002; with the last tile's terrain moved 40 px
#: below the range measured on the first window, 0.227 (and half its pixels lost).
RANGE_EDGE_SHARE = 0.01
#: Widenings of one pair's range at most (each costs a tile matched again).
MAX_WIDENINGS = 4
#: OpenCV's threads while a :class:`TileThread` runs (``cv2.setNumThreads`` is process-wide).
#: The tile thread and the node's worker are already two compute threads on the machine's two
#: cores; OpenCV's own pool of two more on top spun for the cores: live at the IKONOS width
#: with the quick-look at 1/8 (2 pairs), node CPU 0.73-1.08 CPU s per sensor s and tile
#: latency max 1.47-2.86 s with OpenCV's 2 threads, 0.66-0.77 and 1.22-1.63 s with 1
#: (docs/quicklook_bench.md). A pair a node makes whole meanwhile matches on 1 thread too.
TILE_THREAD_OPENCV_THREADS = 1
#: The left-right check of the quick-look levels when the heights' own is "flip".
QUICKLOOK_LR_CHECK: Literal["flip", "reduced", "none"] = "reduced"


@dataclass(frozen=True)
class _Geometry:
    """What a pair's tiles need of its geometry, fixed at stream start (level's grids)."""

    pair_id: str
    normalization: Normalization
    left_affine: AffineModel
    left_grid: OutputGrid
    right_grid: OutputGrid
    stamp_ns: int
    #: From a stream under way (then its end before the last blocks is a break); False: from
    #: a finished pair's result.
    streamed: bool = True
    #: The DEM's heights over the pair's ground (source ``dem``: the pipeline's DEM, sampled
    #: when the stream began), or None: the tiles search the prior and the tie points'.
    dem_terrain: Terrain | None = None

    @property
    def height_relation(self) -> tuple[float, float]:
        """(a, b) of ``Z = a d + b`` on these grids (as :func:`~.publish.finish_pair`)."""
        n = self.normalization
        k = n.parallax_per_height
        a = self.left_grid.pixel / k
        b = (self.left_grid.x_origin - self.right_grid.x_origin - n.parallax_offset) / k
        return float(a), float(b)

    def mapping(self, col0: int = 0, cols: int | None = None) -> GroundMapping:
        """The left image's ground mapping, of columns col0 .. col0 + cols."""
        g = self.left_grid
        sub = OutputGrid(
            g.pixel, g.x_origin + col0 * g.pixel, g.y_origin, g.width if cols is None else cols,
            g.height,
        )  # fmt: skip
        return GroundMapping(sub, self.normalization.left, self.left_affine)


def _reduced(grid: OutputGrid, factor: int) -> OutputGrid:
    """``grid`` reduced by ``factor`` as :func:`reduce_image` reduces its image."""
    if factor == 1:
        return grid
    half = 0.5 * (factor - 1) * grid.pixel
    return OutputGrid(
        grid.pixel * factor,
        grid.x_origin + half,
        grid.y_origin + half,
        grid.width // factor,
        grid.height // factor,
    )


@dataclass
class _Side:
    """The columns of one side received so far, from ``start`` (older ones dropped)."""

    start: int = 0
    parts: list[NDArray[np.generic]] = field(default_factory=list)
    covered: int = 0
    done: bool = False
    blocks: int = 0

    def add(self, image: NDArray[np.generic]) -> None:
        self.parts.append(image)
        self.covered += image.shape[1]
        self.blocks += 1

    def columns(self, c0: int, c1: int) -> NDArray[np.generic]:
        """Columns c0 .. c1 (within start .. covered), as one array."""
        if len(self.parts) > 1:
            self.parts = [np.concatenate(self.parts, axis=1)]
        return self.parts[0][:, c0 - self.start : c1 - self.start]

    def drop_before(self, col: int) -> None:
        """Forget the columns before ``col``."""
        if col <= self.start or not self.parts:
            return
        whole = np.concatenate(self.parts, axis=1) if len(self.parts) > 1 else self.parts[0]
        cut = min(col, self.covered) - self.start
        self.parts = [np.ascontiguousarray(whole[:, cut:])]
        self.start += cut


@dataclass
class _PairTiles:
    """The tiling of one pair at one level."""

    geo: _Geometry
    spans: list[tuple[int, int]]
    sides: dict[str, _Side]
    terrain: Terrain | None = None
    d_range: tuple[int, int] | None = None
    stretch: tuple[tuple[float, float], tuple[float, float]] | None = None
    dsm_grid: DsmGrid | None = None
    next_tile: int = 0
    published: int = 0
    first_cols: int = 0
    #: Said in the pair's summary about its terrain (why no tie points were measured).
    note: str = ""
    #: (tile, requested range after it) of each widening of the range (:meth:`TileLevel._widen`).
    widened: list[tuple[int, tuple[int, int]]] = field(default_factory=list)
    #: The range fixed on the first window, before any widening.
    first_range: tuple[int, int] = (0, 0)
    issues: list[Issue] = field(default_factory=list)

    @property
    def width(self) -> int:
        return self.geo.left_grid.width

    def window(self, i: int) -> tuple[int, int]:
        """Columns of both images matched for tile ``i``: the span, overlap and margin."""
        assert self.d_range is not None
        c0, c1 = self.spans[i]
        dmin, dmax = self.d_range
        wa = max(0, c0 - TILE_OVERLAP - max(dmax, 0) - 1)
        wb = min(self.width, c1 + TILE_OVERLAP + max(-dmin, 0) + 1)
        # after a widening the columns before may be gone (never so with the first range)
        return max(wa, *(s.start for s in self.sides.values())), wb

    def covers(self, col: int) -> bool:
        """Whether both sides hold every column before ``col`` (or all they will)."""
        return all(s.covered >= min(col, self.width) or s.done for s in self.sides.values())


def _window_terrain(
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    geo: _Geometry,
    prior: Terrain,
    nodata: float,
) -> Terrain:
    """The terrain of a window of columns 0.. of both images, measured by row bands.

    :func:`measure_terrain` reduces an image until its longer side is 1,024 px: a window of a
    few hundred columns and a whole scene of rows (13,816 at IKONOS size) would keep some 20
    columns. So the window is cut into at most :data:`TERRAIN_BANDS` bands of
    :data:`TERRAIN_BAND_ROWS` rows spread over its rows, each measured at full resolution;
    the terrain is the hull of the bands' (the prior when no band measures one).
    """
    rows, cols = left.shape[:2]
    band = min(rows, TERRAIN_BAND_ROWS)
    count = min(TERRAIN_BANDS, math.ceil(rows / band))
    starts = sorted({round(i * (rows - band) / max(1, count - 1)) for i in range(count)})
    measured = []
    for r0 in starts:
        grids = [
            OutputGrid(g.pixel, g.x_origin, g.y_origin + r0 * g.pixel, cols, band)
            for g in (geo.left_grid, geo.right_grid)
        ]
        t = measure_terrain(
            left[r0 : r0 + band],
            right[r0 : r0 + band],
            grids[0],
            grids[1],
            geo.normalization,
            prior,
            nodata=nodata,
        )
        if t.source == TerrainSource.TIE_POINTS:
            measured.append(t)
    if not measured:
        return prior
    if len(measured) == 1:
        return measured[0]
    spans = [t.measured_m for t in measured if t.measured_m is not None]
    return Terrain(
        min(t.low_m for t in measured),
        max(t.high_m for t in measured),
        TerrainSource.TIE_POINTS,
        sum(t.points for t in measured),
        (min(lo for lo, _ in spans), max(hi for _, hi in spans)),
    )


def _searched(a: float, b: float, terrain: Terrain, margin: float) -> int:
    """Disparities SGBM searches for ``terrain`` (a multiple of 16; 0 without a relation)."""
    try:
        d0, d1 = disparity_range(a, b, terrain.range_m, margin_px=margin)
    except ValueError:
        return 0
    return max(16, math.ceil((d1 - d0 + 1) / 16) * 16)


class TileLevel:
    """The tiles of streamed pairs at one level (full resolution, or reduced by ``factor``).

    Args:
        options: the heights options (margin, cell, fill, matcher, terrain measurement, prior).
        factor: 1 (full resolution), or 2, 4, 8 (quick-look).
        streams: the ledger's streams under way (:attr:`PairLedger.streams`, read live): a
            pair's geometry at its stream start, and whether its stream is still under way.
    """

    def __init__(
        self, options: HeightsOptions, factor: int, streams: Mapping[int, StreamPair]
    ) -> None:
        self.options = options
        self.factor = factor
        self.streams = streams
        self.pairs: dict[str, _PairTiles] = {}
        #: Shed (:meth:`TileStage.shed_quicklook`): no tiles for pairs that start meanwhile.
        self.shed = False
        #: Pairs this level makes no tiles of (shed while under way or at their start).
        self.off: set[str] = set()
        #: Issues of pairs turned off at their start, for the next :meth:`emit`.
        self.pending: list[Issue] = []
        #: Columns of a tile's span, pixels of the level.
        self.tile_cols = TILE_COLS if factor == 1 else QUICKLOOK_TILE_COLS
        # The quick-look's left-right check: "flip" (a second full pass) becomes "reduced"
        # (the right pass at half the level's resolution): at 1/8 of the benchmark's IKONOS
        # pair, match_pair 0.80 -> 0.55 s a pair; the DSM the same to a quarter of a reduced
        # pixel on 99.5 % of its cells, 0.6 % fewer cells (docs/quicklook_bench.md).
        lr_check = options.lr_check
        if factor > 1 and lr_check == "flip":
            lr_check = QUICKLOOK_LR_CHECK
        # The full resolution refines its sub-pixel disparities, and matches at the
        # resolution, as the whole-pair step does (HeightsOptions.subpixel, .scale), so that a
        # streamed pair's DSM is the step's; the quick-look keeps SGBM's own sub-pixel
        # disparities (its pixels are 2-8 times coarser, its CPU the limit) and its own
        # resolution.
        self.params = SgbmParams(
            mode=MATCHER_MODES[options.matcher],
            lr_check=lr_check,
            stretch_percentiles=(0, 100),
            subpixel=options.subpixel if factor == 1 else "sgbm",
            scale=options.scale if factor == 1 else 1,
        )
        # The full resolution is guided by a reduced pass as the whole-pair step is
        # (HeightsOptions.coarse); the quick-look, itself reduced, is not.
        self.guide = coarse_guide(options) if factor == 1 else None

    # ---- blocks in ----------------------------------------------------------------------
    def takes(self, pair_id: str) -> bool:
        """Whether this level would hold a block of ``pair_id`` (not shed, not off)."""
        return pair_id in self.pairs or not (pair_id in self.off or self.shed)

    def prepare(self, blk: BlockResult, *, borrowed: bool = False) -> NDArray[np.generic]:
        """A block's pixels as this level holds them: reduced, or a copy of borrowed ones."""
        if self.factor > 1:
            return reduce_block(blk.image, self.factor, self.options.nodata)
        return blk.image.copy() if borrowed else blk.image

    def keep(
        self,
        blk: BlockResult,
        geo: _Geometry | None,
        *,
        borrowed: bool = False,
        image: NDArray[np.generic] | None = None,
    ) -> None:
        """Hold a block's columns (reduced at the quick-look level); ``geo`` for a new pair.

        ``borrowed``: the block's pixels are valid during the call only (the full resolution
        then holds a copy; a quick-look level holds its reduction, a new array anyway).
        ``image``: the pixels already prepared (:meth:`prepare`), held as they are.
        """
        tiles = self.pairs.get(blk.pair_id)
        if tiles is None:
            if blk.pair_id in self.off or self.shed:
                self.off.add(blk.pair_id)
                return
            if geo is None:
                return
            g = replace(
                geo,
                left_grid=_reduced(geo.left_grid, self.factor),
                right_grid=_reduced(geo.right_grid, self.factor),
            )
            problem = cell_problem(
                self.options.cell_m * self.factor, g.mapping().ground_sample_distance
            )
            if problem is not None:  # a grid of holes, too large to hold: no tiles
                self.off.add(blk.pair_id)
                self.pending.append(
                    Issue(Level.WARN, f"pair {blk.pair_id}", f"no {self.label} tiles: {problem}")
                )
                return
            w = g.left_grid.width
            n = self.tile_cols
            spans = [(c, min(w, c + n)) for c in range(0, w, n)]
            if len(spans) > 1 and spans[-1][1] - spans[-1][0] < n // 4:
                spans[-2:] = [(spans[-2][0], w)]  # no sliver: it would cost a whole window
            tiles = _PairTiles(g, spans, {"left": _Side(), "right": _Side()})
            self.pairs[blk.pair_id] = tiles
        side = tiles.sides[blk.side]
        side.add(self.prepare(blk, borrowed=borrowed) if image is None else image)
        side.done = side.done or blk.last

    # ---- tiles out ----------------------------------------------------------------------
    def emit(self, out: Outputs, live: set[str] | None = None) -> None:
        """Append to ``out`` the tiles now covered, and end the pairs complete or broken.

        ``live``: the pairs whose streams are under way (default: read from the ledger's
        streams; another thread than the pipeline's is given them).
        """
        if live is None:
            live = {s.geometry.pair_id for s in self.streams.values()}
        out.issues += self.pending
        self.pending = []
        for pid in list(self.pairs):
            tiles = self.pairs[pid]
            while tiles.next_tile < len(tiles.spans):
                tile = self._next(tiles)
                if tile is None:
                    break
                out.tiles.append(tile)
                tiles.published += tile.ok
            out.issues += tiles.issues
            tiles.issues = []
            if tiles.next_tile == len(tiles.spans):
                out.issues.append(self._summary(tiles))
                del self.pairs[pid]
            elif (
                tiles.geo.streamed
                and pid not in live
                and not all(s.done for s in tiles.sides.values())
            ):
                out.issues.append(self._broken(tiles, out.issues))
                del self.pairs[pid]

    def _summary(self, tiles: _PairTiles) -> Issue:
        """The OK line of a pair whose tiles are all out."""
        assert tiles.terrain is not None and tiles.d_range is not None
        assert tiles.stretch is not None
        (l0, l1), (r0, r1) = tiles.stretch
        return Issue(
            Level.OK,
            f"pair {tiles.geo.pair_id}",
            f"{self.label} DSM tiles: {len(tiles.spans)} of {self.tile_cols} columns "
            f"({tiles.published} with heights); {tiles.terrain.describe()} on the first "
            f"{tiles.first_cols} columns{tiles.note}: disparity "
            f"{tiles.first_range[0]}..{tiles.first_range[1]} px"
            + "".join(
                f" (widened to {lo}..{hi} px at tile {i}: its disparities crowded an end)"
                for i, (lo, hi) in tiles.widened
            )
            + "; "
            f"stretch {l0:g}..{l1:g} (left), {r0:g}..{r1:g} (right) DN from the same window",
        )

    def _broken(self, tiles: _PairTiles, issues: list[Issue]) -> Issue:
        """The ERROR of a pair whose stream stopped before its last block."""
        pid = tiles.geo.pair_id
        why = next(
            (
                f"{i.where}: {i.message}"
                for i in issues
                if i.level == Level.ERROR and pid in i.message and "DSM tiles" not in i.message
            ),
            "its stream ended before the last blocks",
        )  # fmt: skip
        done = tiles.spans[tiles.next_tile - 1][1] if tiles.next_tile else 0
        got = ", ".join(f"{n} {s.blocks} blocks" for n, s in tiles.sides.items())
        return Issue(
            Level.ERROR,
            f"pair {pid}",
            f"{self.label} DSM tiles stopped after {tiles.next_tile} of {len(tiles.spans)} "
            f"({tiles.published} with heights; left columns 0..{done} of {tiles.width}; "
            f"received {got}): the stream broke ({why}). The tiles published stay valid; the "
            "rest of the pair has no heights",
        )

    @property
    def label(self) -> str:
        """The level in words: full-resolution, or quick-look (1/f)."""
        return "full-resolution" if self.factor == 1 else f"quick-look (1/{self.factor})"

    def _next(self, tiles: _PairTiles) -> HeightTile | None:
        """The pair's next tile if both sides now cover it, else None."""
        if tiles.d_range is None and not self._fix_range(tiles):
            return None
        i = tiles.next_tile
        wa, wb = tiles.window(i)
        if not tiles.covers(wb):
            return None
        wb = min([wb] + [s.covered for s in tiles.sides.values()])
        tile = self._match(tiles, i, wa, wb)
        if len(tiles.widened) < MAX_WIDENINGS and self._widen(tiles, tile):
            return self._next(tiles)  # the tile again on the wider range (once covered)
        tiles.next_tile += 1
        if tiles.next_tile < len(tiles.spans):
            nxt = tiles.window(tiles.next_tile)[0]
            for s in tiles.sides.values():
                s.drop_before(nxt)
        return tile

    def _widen(self, tiles: _PairTiles, tile: HeightTile) -> bool:
        """Widen the pair's range at an end that ``tile``'s disparities crowd (True if so).

        The range is measured once, on the pair's first window; terrain that later leaves it
        shows as disparities piled within a pixel of the searched range's end
        (:data:`RANGE_EDGE_SHARE`). That end moves out by half the searched width (16
        disparities at least): one more SGBM block of disparities for the tiles after.
        """
        assert tiles.d_range is not None
        d = tile.disparity
        if d is None:
            return False
        d = d[np.isfinite(d)]
        if d.size < 100:
            return False
        lo, hi = tile.d_range
        low = float(np.count_nonzero(d < lo + 1)) / d.size
        high = float(np.count_nonzero(d > hi - 1)) / d.size
        if max(low, high) < RANGE_EDGE_SHARE:
            return False
        step = max(16, (hi - lo + 1) // 2)
        dmin, dmax = tiles.d_range
        if low >= RANGE_EDGE_SHARE:
            dmin = min(dmin, lo - step)
        if high >= RANGE_EDGE_SHARE:
            dmax = max(dmax, hi + step)
        tiles.d_range = (dmin, dmax)
        tiles.widened.append((tile.index, (dmin, dmax)))
        return True

    def _fix_range(self, tiles: _PairTiles) -> bool:
        """Terrain, disparity range, stretch limits and DSM grid from the first window."""
        opt = self.options
        n = min(FIRST_WINDOW_COLS, tiles.width)
        if not tiles.covers(n):
            return False
        n = min(s.covered for s in tiles.sides.values())
        geo = tiles.geo
        left = tiles.sides["left"].columns(0, n)
        right = tiles.sides["right"].columns(0, n)
        # the DEM's heights (the stream's, sampled when it began) stand for the prior
        prior = geo.dem_terrain or Terrain(*opt.prior_m, TerrainSource.PRIOR)
        terrain = prior
        where = f"pair {geo.pair_id}"
        a, b = geo.height_relation
        margin = max(2.0, opt.margin_px / self.factor)
        known = "the DEM's heights" if geo.dem_terrain is not None else "the prior"
        if opt.measure_terrain and self.factor > 1 and _searched(a, b, prior, margin) <= 16:
            # The prior already needs no more than SGBM's fewest disparities: tie points
            # cannot narrow the search, and measured on the reduced window (its pixels
            # 388 m of height at 1/8 of the benchmark's pair, the terrain padded by 4 of
            # them) they would widen it: 0.42 s a pair and twice the matching at 1/8.
            tiles.note = f"; tie points not measured: {known} fit SGBM's 16 disparities"
        elif opt.measure_terrain:
            terrain = with_dem(
                geo.dem_terrain, _window_terrain(left, right, geo, prior, opt.nodata)
            )
            if terrain.source == TerrainSource.DEM:
                tiles.note = (
                    f"; too few tie points agree on the first {n} columns: the DEM's heights "
                    "are searched"
                )
            elif terrain.source not in (TerrainSource.TIE_POINTS, TerrainSource.DEM_TIE_POINTS):
                tiles.issues.append(
                    Issue(
                        Level.WARN,
                        where,
                        f"{self.label} tiles: too few tie points agree on the first {n} "
                        f"columns to measure the terrain: the heights searched are the prior, "
                        f"{terrain.describe()}",
                    )
                )
        try:
            rng = disparity_range(a, b, terrain.range_m, margin_px=margin)
        except ValueError:
            rng = (0, 0)
        tiles.terrain, tiles.d_range, tiles.first_cols = terrain, rng, n
        tiles.first_range = rng
        limits = []
        for img in (left, right):
            ok = img != opt.nodata
            vals = img[ok] if ok.any() else img.ravel()
            lo, hi = (float(v) for v in np.percentile(vals, SgbmParams().stretch_percentiles))
            limits.append((lo, hi))
        tiles.stretch = (limits[0], limits[1])
        # The pair's DSM grid: the left image's ground at the lowest and highest terrain.
        mapping = geo.mapping()
        cell = opt.cell_m * self.factor if opt.cell_m > 0 else mapping.ground_sample_distance
        g = geo.left_grid
        cc, rr, zz = np.meshgrid([0, g.width - 1], [0, g.height - 1], terrain.range_m)
        x, y = mapping.pixel_to_ground(cc, rr, zz)
        tiles.dsm_grid = DsmGrid.covering(x.min(), x.max(), y.min(), y.max(), cell)
        return True

    def _owner_col(
        self, tiles: _PairTiles, grid: DsmGrid, r0: int, c0: int
    ) -> NDArray[np.float64]:
        """Left column (level pixels) of each cell centre of ``grid`` at the terrain's mid height.

        ``grid`` is a sub-grid of the pair's, starting at its cell (r0, c0); computed from the
        pair grid's indices, so that every tile gets the same figure for a cell.
        """
        pg = tiles.dsm_grid
        assert pg is not None and tiles.terrain is not None
        rows = r0 + np.arange(grid.height, dtype=float)
        cols = c0 + np.arange(grid.width, dtype=float)
        x = pg.x0 + pg.cell * cols
        y = pg.y0 - pg.cell * rows
        zmid = 0.5 * sum(tiles.terrain.range_m)
        # The mapping is affine: col = kx X + ky Y + kz Z + k1, a term per column plus one
        # per row (one pass over the cells instead of some fifteen).
        m = tiles.geo.mapping()
        a, h, g = m.affine.matrix, m.to_normalized, m.grid
        k = (h[0, 0] * a[0] + h[0, 1] * a[1]) / g.pixel
        k1 = k[2] * zmid + k[3] + (h[0, 2] - g.x_origin) / g.pixel
        col: NDArray[np.float64] = (k[1] * y + k1)[:, None] + (k[0] * x)[None, :]
        return col

    def _match(self, tiles: _PairTiles, i: int, wa: int, wb: int) -> HeightTile:
        """Tile ``i``: match the window wa .. wb, keep the span, grid the cells it owns."""
        opt = self.options
        geo = tiles.geo
        c0, c1 = tiles.spans[i]
        assert tiles.d_range is not None and tiles.stretch is not None
        assert tiles.terrain is not None and tiles.dsm_grid is not None
        a, b = geo.height_relation
        left = tiles.sides["left"].columns(wa, wb)
        right = tiles.sides["right"].columns(wa, wb)
        masks = [(img != opt.nodata) for img in (left, right)]
        u8 = [to_uint8(img, *lim) for img, lim in zip((left, right), tiles.stretch, strict=True)]
        res = match_pair(
            u8[0],
            u8[1],
            d_range=tiles.d_range,
            nodata=None,
            left_mask=masks[0],
            right_mask=masks[1],
            # a quick-look window in one piece (at 1/8 of the IKONOS size, 1,740 x 650 px):
            # row tiles would add their overlap and their calls' fixed costs
            tile_rows=opt.tile_px if self.factor == 1 else max(opt.tile_px, left.shape[0]),
            tile_cols=max(16, wb - wa),
            overlap=TILE_OVERLAP,
            params=self.params,
            guide=self.guide,
        )
        own = res.disparity[:, c0 - wa : c1 - wa]
        has = masks[0][:, c0 - wa : c1 - wa]
        share = float(np.isfinite(own).sum() / max(1, int(has.sum())))
        base = HeightTile(
            geo.pair_id, i, len(tiles.spans), self.factor, c0, c1 - c0, res.status, res.message,
            res.d_range, share, np.ascontiguousarray(own), None, None, None, tiles.dsm_grid, a, b,
            tiles.terrain, tiles.stretch, geo.stamp_ns, i == len(tiles.spans) - 1,
        )  # fmt: skip
        if res.status not in (DenseStatus.OK, DenseStatus.NO_MATCH, DenseStatus.TEXTURELESS):
            tiles.issues.append(
                Issue(Level.WARN, f"pair {geo.pair_id}", f"{self.label} tile {i}: {res.message}")
            )
            return base
        if not np.isfinite(own).any():
            return replace(base, status=DenseStatus.NO_MATCH)
        # The points gridded: the span and its overlap (a border cell sees all its points).
        ga, gb = max(wa, c0 - TILE_OVERLAP), min(wb, c1 + TILE_OVERLAP)
        disp = res.disparity[:, ga - wa : gb - wa]
        dsm, owned = self._grid(tiles, i, disp, ga)
        if dsm is None or owned is None:
            return replace(base, status=DenseStatus.NO_MATCH, message="no cell owned")
        ortho = orthoimage(
            left[:, ga - wa : gb - wa], dsm, geo.mapping(ga, gb - ga), nodata=opt.nodata
        )
        return replace(base, status=DenseStatus.OK, dsm=dsm, owned=owned, ortho=ortho)

    def _grid(
        self, tiles: _PairTiles, i: int, disp: Float32Array, col0: int
    ) -> tuple[Dsm | None, NDArray[np.bool_] | None]:
        """The cells tile ``i`` owns, gridded from ``disp`` (left columns from ``col0``)."""
        opt = self.options
        geo = tiles.geo
        pg = tiles.dsm_grid
        assert pg is not None and tiles.terrain is not None
        c0, c1 = tiles.spans[i]
        last = len(tiles.spans) - 1
        lo = -math.inf if i == 0 else c0
        hi = math.inf if i == last else c1
        # The cells the tile may own: the ground of its columns (with its overlap, and to the
        # image's end for the first and last tile) at the terrain's extreme heights.
        g = geo.left_grid
        e = TILE_OVERLAP
        ca = -e if i == 0 else c0 - 2
        cb = g.width - 1 + e if i == last else c1 + 1
        mapping = geo.mapping()
        z_range = tiles.terrain.range_m
        if tiles.widened and tiles.d_range is not None:  # the heights the wider range reaches
            a, b = geo.height_relation
            z_ends = [a * d + b for d in tiles.d_range]
            z_range = (min(*z_range, *z_ends), max(*z_range, *z_ends))
        cc, rr, zz = np.meshgrid([ca, cb], [-e, g.height - 1 + e], z_range)
        x, y = mapping.pixel_to_ground(cc, rr, zz)
        pad = math.ceil(opt.max_fill_cells) + 2
        r_a, c_a = pg.index(np.array([x.max()]), np.array([y.max()]))
        r_b, c_b = pg.index(np.array([x.min()]), np.array([y.min()]))
        col_a, col_b = int(c_b[0]) - pad, int(c_a[0]) + pad
        row_a, row_b = int(r_a[0]) - pad, int(r_b[0]) + pad
        col_a, row_a = max(0, col_a), max(0, row_a)
        col_b, row_b = min(pg.width - 1, col_b), min(pg.height - 1, row_b)
        if col_b < col_a or row_b < row_a:
            return None, None
        box = DsmGrid(
            pg.x0 + col_a * pg.cell, pg.y0 - row_a * pg.cell, pg.cell,
            col_b - col_a + 1, row_b - row_a + 1,
        )  # fmt: skip
        a, b = geo.height_relation
        dsm = make_dsm(
            disp,
            a,
            b,
            geo.mapping(col0, disp.shape[1]),
            grid=box,
            reducer=opt.reducer,
            fill=opt.fill,
            max_fill_cells=opt.max_fill_cells,
        )
        col = self._owner_col(tiles, box, row_a, col_a)
        owned = (col >= lo) & (col < hi)
        if not owned.any():
            return None, None
        rows = np.flatnonzero(owned.any(axis=1))
        cols = np.flatnonzero(owned.any(axis=0))
        rs = slice(int(rows[0]), int(rows[-1]) + 1)
        cs = slice(int(cols[0]), int(cols[-1]) + 1)
        own = owned[rs, cs]
        heights = np.where(own, dsm.heights[rs, cs], np.float32(np.nan)).astype(np.float32)
        sub = DsmGrid(
            box.x0 + cs.start * box.cell, box.y0 - rs.start * box.cell, box.cell,
            own.shape[1], own.shape[0],
        )  # fmt: skip
        return (
            Dsm(heights, sub, np.where(own, dsm.count[rs, cs], 0), dsm.filled[rs, cs] & own),
            own,
        )


class TileStage:
    """Streamed DSM tiles of every streamed pair: full resolution and/or the quick-look.

    ``heights`` on and streaming: full-resolution tiles, plus quick-look tiles reduced by 2, 4
    or 8 when ``heights_quicklook`` is 1, 2 or 3; -1, -2 or -3: the quick-look tiles only (no
    full-resolution tiles). Feed it every streamed block (:meth:`keep`, a copy of a borrowed
    view) and call it on each of the pipeline's outputs (:meth:`__call__`): the tiles now
    covered come in :attr:`Outputs.tiles`.

    Args:
        config: the pipeline's settings.
        streams: the ledger's streams under way (:attr:`PairLedger.streams`, read live).
    """

    def __init__(self, config: PipelineConfig, streams: Mapping[int, StreamPair]) -> None:
        opt = options_of(config)
        q = int(config.dense.quicklook)
        if abs(q) > len(QUICKLOOK_FACTORS):
            raise ValueError(f"heights_quicklook = {q}: must be -3 .. 3 (a level, 2^|level|)")
        factors = ([] if q < 0 else [1]) + ([QUICKLOOK_FACTORS[abs(q) - 1]] if q else [])
        self.streams = streams
        self.levels = [TileLevel(opt, f, streams) for f in factors]
        #: Whether a quick-look level is made (the admission may shed it before pairs).
        self.quicklook = any(level.factor > 1 for level in self.levels)

    def held_bytes(self) -> int:
        """Bytes of the columns held for tiles still to come, every level and pair.

        Safe to call from another thread than the one feeding the stage (it reads copies of
        the lists; a part replaced meanwhile is counted or not).
        """
        total = 0
        for level in self.levels:
            for tiles in list(level.pairs.values()):
                for side in list(tiles.sides.values()):
                    total += sum(int(p.nbytes) for p in list(side.parts))
        return total

    @staticmethod
    def applies(config: PipelineConfig) -> bool:
        """Whether streamed pairs get tiles: heights on, and streaming possible."""
        return (
            config.dense.enabled
            and config.stream.enabled
            and not config.single_camera
            and config.scenes.lines > 0
        )

    @staticmethod
    def stream_geometry(s: StreamPair) -> _Geometry:
        """What the tiles need of a stream's geometry."""
        geo = s.geometry
        return _Geometry(
            geo.pair_id,
            geo.normalization,
            s.sides["left"].result.affine,
            geo.left_grid,
            geo.right_grid,
            s.stamp_ns,
            dem_terrain=s.terrain,
        )

    def _geometry(self, pair_id: str, pairs: list[PairResult]) -> _Geometry | None:
        for s in self.streams.values():
            if s.geometry.pair_id == pair_id:
                return self.stream_geometry(s)
        for p in pairs:  # the stream began and ended within one call
            if p.pair_id == pair_id:
                t = p.terrain
                dem = t if t is not None and t.source == TerrainSource.DEM else None
                return _Geometry(
                    pair_id,
                    p.normalization,
                    p.left.affine,
                    p.left_grid,
                    p.right_grid,
                    p.stamp_ns,
                    streamed=False,
                    dem_terrain=dem,
                )
        return None

    def shed_quicklook(self, shed: bool) -> list[Issue]:
        """Shed (True) or resume (False) the quick-look levels; what changed, in words.

        Shed: the quick-look tiles of the pairs under way stop (their columns are freed; the
        tiles published stay valid) and pairs that start meanwhile get none. Resumed: pairs
        whose first block comes from then on get their quick-look tiles again. The full
        resolution is never shed here (the admission sheds whole pairs).
        """
        issues: list[Issue] = []
        for level in self.levels:
            if level.factor == 1 or level.shed == shed:
                continue
            level.shed = shed
            if not shed:
                issues.append(
                    Issue(
                        Level.OK,
                        "heights",
                        f"{level.label} DSM tiles resumed, from the next pair that starts",
                    )
                )
                continue
            for pid, tiles in list(level.pairs.items()):
                issues.append(
                    Issue(
                        Level.WARN,
                        f"pair {pid}",
                        f"{level.label} DSM tiles shed after {tiles.next_tile} of "
                        f"{len(tiles.spans)} (the node's memory budget: the quick-look goes "
                        "before any pair); the tiles published stay valid",
                    )
                )
                level.off.add(pid)
                del level.pairs[pid]
        return issues

    def keep(
        self, blk: BlockResult, pairs: list[PairResult] | None = None, *, borrowed: bool = False
    ) -> None:
        """Hold a streamed block: its pixels as they are, or ``borrowed``.

        ``borrowed``: valid during the call only (e.g. the streamer's block sink's view); then
        only the full resolution copies them, the quick-look holds its reduction. A
        quick-look-only node need not copy a block for the tiles (at the IKONOS size, a 7 MB
        copy per block: 12 % of the pipeline thread's samples in the live run at 1/8).
        """
        geo: _Geometry | None = None
        for level in self.levels:
            if blk.pair_id not in level.pairs and geo is None:
                geo = self._geometry(blk.pair_id, pairs or [])
            level.keep(blk, geo, borrowed=borrowed)

    def keep_reduced(
        self,
        blk: BlockResult,
        reductions: list[NDArray[np.generic] | None],
        geo: _Geometry | None,
    ) -> None:
        """Hold a draft block's reductions, one per level as :attr:`levels` (None: none)."""
        for level, img in zip(self.levels, reductions, strict=True):
            if img is not None:
                level.keep(blk, geo, image=img)

    def __call__(self, out: Outputs, *, blocks: bool = True) -> Outputs:
        """Add to ``out`` the tiles now covered (``blocks``: hold ``out.blocks`` first)."""
        if blocks:
            for blk in out.blocks:
                self.keep(blk, out.pairs)
        for level in self.levels:
            level.emit(out)
        return out

    def close(self) -> None:
        """Nothing to stop (:class:`TileThread` has a thread)."""


class TileThread:
    """A :class:`TileStage` run on a thread of its own: the node's pipeline thread goes on.

    At the IKONOS rate the pipeline thread is the node's bottleneck: it takes the strips,
    waits for the render process block by block and, on the same thread, matched and gridded
    the tiles (0.5-0.7 s a pair at 1/8), while the render process stood idle. Here the
    blocks' columns (their quick-look reductions, or copies) are prepared on the caller's
    thread, as the borrowed pixels require, and handed with every call to a thread that
    holds them and makes the tiles (OpenCV's matcher, resize and remap give the GIL back).
    Each call of the pipeline collects the tiles and issues made since; a call that makes a
    streamed pair first waits for the thread to finish everything handed to it, so the
    pair's tiles all come before (or with) it, as in :class:`TileStage`. The same tiles as
    :class:`TileStage`, to the bit; only the call that returns them may be a later one.

    An exception in the thread is reported as an ERROR: the tiles of the pairs under way
    stop, later pairs get theirs. Same interface as :class:`TileStage`; :meth:`close` at the
    end.
    """

    def __init__(self, stage: TileStage) -> None:
        self.stage = stage
        self.levels = stage.levels
        self.quicklook = stage.quicklook
        self._queue: queue.Queue[tuple[str, Any] | None] = queue.Queue()
        self._done: list[Outputs] = []
        self._live: set[str] = set()  # the streams under way at the last call
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="parproj_tiles", daemon=True)
        # OpenCV's threads (process-wide), restored by close(): see TILE_THREAD_OPENCV_THREADS.
        self._opencv_threads = cv2.getNumThreads()
        cv2.setNumThreads(TILE_THREAD_OPENCV_THREADS)
        self._thread.start()

    def held_bytes(self) -> int:
        """Bytes of the columns held for tiles still to come (:meth:`TileStage.held_bytes`)."""
        return self.stage.held_bytes()

    def keep(
        self, blk: BlockResult, pairs: list[PairResult] | None = None, *, borrowed: bool = False
    ) -> None:
        """Prepare a streamed block's columns here and hand them to the thread."""
        images: list[NDArray[np.generic] | None] = [
            level.prepare(blk, borrowed=borrowed) if level.takes(blk.pair_id) else None
            for level in self.levels
        ]
        if all(img is None for img in images):
            return
        # The geometry only for a pair a level does not hold yet (as TileStage.keep): not per
        # block on the worker's path.
        new = any(blk.pair_id not in level.pairs for level in self.levels)
        geo = self.stage._geometry(blk.pair_id, pairs or []) if new else None
        self._queue.put(("keep", (replace(blk, image=blk.image[:, :0]), geo, images)))

    def keep_reduced(
        self,
        blk: BlockResult,
        reductions: list[NDArray[np.generic] | None],
        geo: _Geometry | None,
    ) -> None:
        """Hand a draft block's reductions to the thread (:meth:`TileStage.keep_reduced`)."""
        if all(img is None for img in reductions):
            return
        self._queue.put(("keep", (replace(blk, image=blk.image[:, :0]), geo, reductions)))

    def shed_quicklook(self, shed: bool) -> list[Issue]:
        """Shed or resume the quick-look levels (on the thread; what changed comes later)."""
        if any(level.factor > 1 and level.shed != shed for level in self.levels):
            self._queue.put(("shed", shed))
        return []

    def __call__(self, out: Outputs, *, blocks: bool = True) -> Outputs:
        """Add to ``out`` the tiles and issues made since the last call.

        ``blocks``: hand ``out.blocks`` to the thread first. When ``out`` holds pairs, or a
        stream ended since the last call (complete, or broken), wait until the thread has done
        all it was handed: the pairs' last tiles, or the status of a broken one.
        """
        if blocks:
            for blk in out.blocks:
                self.keep(blk, out.pairs)
        live = {s.geometry.pair_id for s in list(self.stage.streams.values())}
        ended = bool(self._live - live)
        self._live = live
        self._queue.put(("emit", live))
        if out.pairs or ended:
            self._queue.join()
        with self._lock:
            done, self._done = self._done, []
        for made in done:
            out.tiles += made.tiles
            out.issues += made.issues
        return out

    def _run(self) -> None:
        """The thread: hold blocks, make tiles, shed, in the order handed."""
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                made = Outputs()
                kind, arg = item
                if kind == "keep":
                    blk, geo, images = arg
                    for level, img in zip(self.levels, images, strict=True):
                        if img is not None:
                            level.keep(blk, geo, image=img)
                elif kind == "emit":
                    for level in self.levels:
                        level.emit(made, arg)
                else:
                    made.issues += self.stage.shed_quicklook(bool(arg))
            except Exception as err:  # a bug: say so, drop the pairs under way, go on
                pids = sorted({pid for level in self.levels for pid in level.pairs})
                for level in self.levels:
                    level.off.update(level.pairs)
                    level.pairs.clear()
                made = Outputs()
                made.issues.append(
                    Issue(
                        Level.ERROR,
                        "heights",
                        f"internal error making DSM tiles ({type(err).__name__}: {err}): the "
                        f"tiles of {', '.join(pids) or 'no pair'} stop there (those published "
                        "stay valid); later pairs get theirs",
                    )
                )
            finally:
                self._queue.task_done()
            if made.tiles or made.issues:
                with self._lock:
                    self._done.append(made)

    def close(self) -> None:
        """Stop the thread once it has done what it was handed (waits at most 30 s).

        OpenCV's thread count is set back to what it was.
        """
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join(timeout=30.0)
        cv2.setNumThreads(self._opencv_threads)


def tiles_of_pair(
    config: PipelineConfig,
    pair: PairResult,
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    *,
    block_cols: int = TILE_COLS,
) -> list[tuple[int, HeightTile]]:
    """The tiles of a whole normalized pair fed as streamed blocks (benchmarks, tests).

    The images are cut into blocks of ``block_cols`` columns, fed left, right, left, ... to a
    :class:`TileStage` of ``config`` (its levels: ``heights_quicklook``), the stage called after
    each block as the pipeline calls it after each input. Returns (blocks fed so far, tile) in
    the order the tiles came.
    """
    stage = TileStage(config, {})
    got: list[tuple[int, HeightTile]] = []
    fed = 0
    width = left.shape[1]
    starts = list(range(0, width, block_cols))
    for i, c0 in enumerate(starts):
        for side, img, grid in (
            ("left", left, pair.left_grid),
            ("right", right, pair.right_grid),
        ):
            # a copy, as the pipeline keeps one of each block it publishes
            part = np.ascontiguousarray(img[:, c0 : c0 + block_cols])
            blk = BlockResult(
                pair.pair_id, side, i, c0, part, grid, pair.stamp_ns, i == len(starts) - 1
            )
            stage.keep(blk, [pair])
            fed += 1
            out = stage(Outputs(), blocks=False)
            got += [(fed, t) for t in out.tiles]
    return got
