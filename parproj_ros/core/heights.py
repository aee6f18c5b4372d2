"""Heights of a normalized pair: disparity, height image, DSM and ortho-image (issue 12).

The step after normalization (and tie-point refinement) for one :class:`PairResult` with its
images: the disparity search range predicted from the pair's own linear relation
``Z = a (col_left - col_right) + b`` over the pair's height range (plus a margin, narrowed on a
reduced pair when it is wide), dense matching (:func:`~parproj_ros.imaging.dense.match_pair`:
semi-global matching, sub-pixel, left-right check, no-data / low texture masked), heights per
left normalized pixel, a DSM north-up in the object frame (cell = the ground sample distance of
the left normalized image unless set) and the left normalized image resampled onto it (the
ortho-image). A bad case (textureless or saturated images, a range wider than the image,
nodata-only overlap, no match) gives a :class:`HeightsResult` with that status and no DSM, and
an :class:`~.results.Issue` that says so; it never raises for image content.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from ..imaging.dense import (
    CoarseGuide,
    DenseStatus,
    DisparityResult,
    SgbmParams,
    disparity_range,
    match_pair,
    refine_range,
)
from ..imaging.heights import Dsm, GroundMapping, make_dsm, orthoimage
from .config import PipelineConfig
from .results import BlockResult, HeightsResult, HeightTile, Issue, Level, Outputs, PairResult
from .terrain import FROM_TIE_POINTS, Terrain, TerrainSource, measure_terrain, with_dem

if TYPE_CHECKING:
    from .dem_terrain import DemTerrain

Float32Array = NDArray[np.float32]

#: OpenCV SGBM mode of each ``heights_matcher``.
MATCHER_MODES = {
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "sgbm_8path": cv2.STEREO_SGBM_MODE_HH,
}

#: Search ranges wider than this share of the image width are first narrowed on a reduced pair.
REFINE_SHARE = 0.25

#: A DSM cell side below the ground sample distance divided by this is refused: each pixel
#: gives one point, so at most 1 cell in 10^2 = 100 could get a height (less than the 1 % of
#: cells ``parproj dsm`` exports), and the grid takes that many times the pixels' memory
#: (``heights_cell_m`` 0.0001 m on the Ventoux pair asked for 36.6 TiB).
MAX_CELLS_PER_GSD = 10.0


def cell_problem(cell_m: float, gsd_m: float) -> str | None:
    """Why a DSM cell side of ``cell_m`` metres cannot serve the pair; None when it can.

    ``gsd_m``: the pair's ground sample distance, metres; ``cell_m`` 0 means the GSD.
    """
    if cell_m <= 0 or not math.isfinite(gsd_m) or cell_m * MAX_CELLS_PER_GSD >= gsd_m:
        return None
    return (
        f"heights_cell_m {cell_m:g} m is {gsd_m / cell_m:.3g} times finer than the pair's "
        f"ground sample distance ({gsd_m:.3g} m): at most one cell in "
        f"{(gsd_m / cell_m) ** 2:.3g} could get a height (the disparity and height images are "
        f"kept); set heights_cell_m to 0 (the ground sample distance) or "
        f"at least {gsd_m / MAX_CELLS_PER_GSD:.3g} m"
    )


def coarse_cell_problem(dsm: Dsm, cell_m: float) -> str | None:
    """Why ``dsm`` is no DSM: fewer than 2 cells each way (a cell as large as the pair).

    None when it has at least 2 x 2 cells. ``cell_m``: the ``heights_cell_m`` asked, metres.
    """
    g = dsm.grid
    if g.width >= 2 and g.height >= 2:
        return None
    return (
        f"heights_cell_m {cell_m:g} m gives a DSM of {g.width} x {g.height} cells: a cell as "
        "large as the pair's ground leaves no relief to map (the disparity and height images "
        "are kept); set heights_cell_m to 0 (the ground sample distance) or a smaller cell"
    )


@dataclass(frozen=True)
class HeightsOptions:
    """How heights are made (node parameters ``heights_*``).

    Attributes:
        margin_px: added to both ends of the predicted disparity range, pixels.
        cell_m: DSM cell side, metres (0: the ground sample distance of the left image).
        fill: "none" (holes stay NaN) or "nearest" (holes up to ``max_fill_cells`` from a
            cell with points take its height, and are flagged).
        max_fill_cells: largest hole filled, in cells.
        tile_px: side of the matching tiles, pixels (memory: a few tiles at a time).
        nodata: pixel value meaning "no data" in the normalized images.
        measure_terrain: measure each pair's terrain from tie points between its normalized
            images when it does not come measured (parameter ``terrain`` "tie_points").
        prior_m: the heights assumed for a pair that carries none (``z_avg`` +-
            ``height_range``), metres.
        matcher: OpenCV's SGBM with 3 directions ("sgbm_3way") or 8 paths ("sgbm_8path").
        lr_check: the matcher's left-right check (:class:`SgbmParams`): "flip" (a
            right-to-left pass at full resolution, and the mean of both disparities),
            "reduced" (that pass at half resolution: the step 2.3-2.8x one bare SGBM pass
            instead of 3.3-3.8x, but more blunders kept on the simulated bags) or "none".
        reducer: how the DSM's cells take the points' heights (:func:`make_dsm`): "mean" or
            "median" (of the points in the cell), or "interpolated" (then the height image
            interpolated where the cell's centre projects: less NMAD and RMS on Marseille and
            the simulated bags, some 0.035 s per Mpx more). docs/performance.md has the
            figures of each.
        subpixel: the matcher's sub-pixel disparities (:class:`SgbmParams`): "gradient"
            (default: SGBM's refined on the images by a Lucas-Kanade fit in a Gaussian window
            of 2.5 px, which removes SGBM's pull towards whole pixels; NMAD against s2p on the
            Marseille pairs 1-2 / 1-3 / 2-3 0.711 / 0.416 / 0.739 m against 0.918 / 0.449 /
            0.873 with "sgbm", against truth on the simulated bags 0.012 / 0.154 / 0.142 m
            against 0.029 / 0.175 / 0.172 (run 5); since the fit's sums on a half grid and its
            bicubic resampling, 0.694 / 0.393 / 0.707 m and 0.011 / 0.132 / 0.129 m (run 10);
            some 0.06 s of CPU per Mpx) or "sgbm" (OpenCV's own). docs/heights.md and
            docs/performance.md have the figures.
        min_ncc: the matcher's photometric check (:class:`SgbmParams` ``min_ncc``; None:
            off): a pixel whose window correlates less than this with the right image at
            its disparities is rejected. With ``lr_check="reduced"`` and 0.7: the step 3.5x
            one bare SGBM pass instead of 4.3x (CPU, Marseille 1-2), crab_foreaft and
            ikonos_agile RMS against truth 1.61 / 1.00 m instead of 2.52 / 1.25 m,
            airborne_foreaft 0.058 m instead of 0.033 m, Marseille completeness 97.3 /
            95.0 / 97.9 % instead of 98.2 / 97.5 / 98.6 % (docs/heights.md, run 6).
        coarse: a matching pass at 1/4 scale first (:class:`CoarseGuide`):
            "support" (default): a pixel with no match of that pass within one reduced pixel
            is not taken (blunders: on the simulated bags RMS against truth 0.030 / 2.61 /
            1.15 -> 0.022 / 0.20 / 0.27 m, on Marseille 2-3 RMS against s2p 1.79 -> 0.99 m,
            the same NMAD, about 1 point less complete); "ranges": also each tile of 256 px
            searches only the disparities that pass found around it (10-30 % less CPU on
            ranges of 144-224 disparities, but a small feature the reduced pass missed is
            lost); "none": as before 2026-11-28. docs/performance.md has the figures.
        scale: the matching's resolution (:class:`SgbmParams` ``scale``): 1 (SGBM on the
            full-resolution images) or 2 (SGBM on both images reduced 2 x 2, its disparities
            checked and refined at full resolution: the step 1.4-1.7x faster on the Marseille
            pairs, NMAD against s2p 0.695 / 0.405 / 0.716 m against 0.694 / 0.393 / 0.707 m,
            97.2 / 94.0 / 97.6 % complete against 97.4 / 95.7 / 97.8 %; docs/performance.md).
        quicklook_only: streamed pairs get quick-look tiles only (``heights_quicklook`` < 0,
            core/tiles.py): no full-resolution heights for them (their blocks are not kept).
    """

    margin_px: float = 8.0
    cell_m: float = 0.0
    fill: Literal["none", "nearest"] = "nearest"
    max_fill_cells: float = 1.0
    tile_px: int = 1024
    nodata: float = 0.0
    measure_terrain: bool = False
    prior_m: tuple[float, float] = (-500.0, 500.0)
    matcher: Literal["sgbm_3way", "sgbm_8path"] = "sgbm_3way"
    lr_check: Literal["flip", "reduced", "none"] = "flip"
    reducer: Literal["mean", "median", "interpolated"] = "mean"
    subpixel: Literal["sgbm", "gradient"] = "gradient"
    min_ncc: float | None = None
    coarse: Literal["none", "support", "ranges"] = "support"
    scale: int = 1
    quicklook_only: bool = False


def coarse_guide(options: HeightsOptions) -> CoarseGuide | None:
    """The reduced pass of ``options.coarse`` (None for "none"), for the whole pair and tiles."""
    if options.coarse == "none":
        return None
    return CoarseGuide(ranges=options.coarse == "ranges")


def measure_heights(
    pair: PairResult,
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    z_range_m: tuple[float, float] | Terrain,
    options: HeightsOptions | None = None,
) -> tuple[HeightsResult, list[Issue]]:
    """Disparity, heights, DSM and ortho-image of a normalized pair (module docstring).

    Args:
        pair: the pair (its grids, normalization, A1..A8 and height relation).
        left: its left normalized image (rows, cols).
        right: its right normalized image (same rows; same shape as made by the pipeline).
        z_range_m: the heights the pair may hold (lowest, highest), metres, or its
            :class:`Terrain` (then kept in the result and named in the OK line).
        options: see :class:`HeightsOptions`.

    Returns:
        The result, and the issues to report (a WARN when there are no heights, an OK line
        with the figures otherwise).
    """
    opt = options or HeightsOptions()
    terrain = z_range_m if isinstance(z_range_m, Terrain) else None
    if isinstance(z_range_m, Terrain):
        z_range_m = z_range_m.range_m
    a, b = pair.height_per_disparity_px, pair.height_offset_m
    where = f"pair {pair.pair_id}"
    shape = left.shape[:2]
    empty = np.full(shape, np.nan, dtype=np.float32)

    def failed(
        status: DenseStatus, message: str, rng: tuple[int, int]
    ) -> tuple[HeightsResult, list[Issue]]:
        res = HeightsResult(
            pair.pair_id,
            pair.stamp_ns,
            status,
            message,
            rng,
            0.0,
            empty,
            empty,
            None,
            None,
            a,
            b,
            terrain=terrain,
        )
        return res, [Issue(Level.WARN, where, f"no heights ({status}): {message}")]

    if left.shape != right.shape:
        return failed(
            DenseStatus.NO_OVERLAP, f"images of shapes {left.shape} and {right.shape}", (0, 0)
        )
    try:
        lo, hi = disparity_range(a, b, z_range_m, margin_px=opt.margin_px)
    except ValueError as err:  # a = 0 or not finite: no height relation
        return failed(DenseStatus.NO_MATCH, str(err), (0, 0))
    rng = (math.floor(lo), math.ceil(hi))
    if rng[1] - rng[0] > REFINE_SHARE * shape[1]:
        narrowed = refine_range(left, right, d_range=rng, nodata=opt.nodata)
        if narrowed is not None:
            rng = narrowed
    tile = int(opt.tile_px)
    res: DisparityResult = match_pair(
        left,
        right,
        d_range=rng,
        nodata=opt.nodata,
        tile_rows=tile,
        tile_cols=tile,
        params=SgbmParams(
            mode=MATCHER_MODES[opt.matcher],
            lr_check=opt.lr_check,
            subpixel=opt.subpixel,
            min_ncc=opt.min_ncc,
            scale=opt.scale,
        ),
        guide=coarse_guide(opt),
    )
    if res.status != DenseStatus.OK:
        message = res.message
        width = res.d_range[1] - res.d_range[0]
        if res.status == DenseStatus.RANGE_TOO_WIDE and 4 * opt.margin_px >= width:
            # the margin is half the range or more: it, not the heights, made it too wide
            message += (
                f" (heights_margin_px {opt.margin_px:g} px adds {2 * opt.margin_px:g} px of "
                "it: lower heights_margin_px)"
            )
        return failed(res.status, message, res.d_range)
    height = (a * res.disparity + b).astype(np.float32)
    mapping = GroundMapping.of_pair(pair, "left")
    problem = cell_problem(opt.cell_m, mapping.ground_sample_distance)
    dsm = ortho = None
    if problem is None:
        dsm = make_dsm(
            res.disparity,
            a,
            b,
            mapping,
            cell=opt.cell_m or None,
            fill=opt.fill,
            max_fill_cells=opt.max_fill_cells,
            reducer=opt.reducer,
        )
        problem = coarse_cell_problem(dsm, opt.cell_m)
        if problem is None:
            ortho = orthoimage(left, dsm, mapping, nodata=opt.nodata)
        else:
            dsm = None
    out = HeightsResult(
        pair.pair_id,
        pair.stamp_ns,
        res.status,
        res.message if problem is None else problem,
        res.d_range,
        res.valid_share,
        res.disparity,
        height,
        dsm,
        ortho,
        a,
        b,
        opt.max_fill_cells if opt.fill == "nearest" and dsm is not None else 0.0,
        terrain,
    )
    if dsm is None:  # the disparity and height images are kept
        return out, [Issue(Level.WARN, where, f"no DSM: {problem}")]
    valid = np.isfinite(dsm.heights)
    searched = f"{terrain.describe()}: " if terrain is not None else ""
    text = (
        f"heights: {searched}disparity {res.d_range[0]}..{res.d_range[1]} px, "
        f"{100 * res.valid_share:.1f} % matched; DSM {dsm.grid.width} x {dsm.grid.height} cells "
        f"of {dsm.grid.cell:.3g} m, {100 * valid.mean():.1f} % with a height "
        f"({int(dsm.filled.sum())} filled)"
    )
    return out, [Issue(Level.OK, where, text)]


def options_of(config: PipelineConfig) -> HeightsOptions:
    """The heights options of a pipeline's settings.

    Its dense settings (the ``heights_*`` parameters), the no-data value, the terrain choice
    and the prior heights.
    """
    dense = config.dense
    return HeightsOptions(
        margin_px=dense.margin_px,
        cell_m=dense.cell_m,
        fill=dense.fill,
        max_fill_cells=dense.max_fill_cells,
        tile_px=dense.tile_px,
        matcher=dense.matcher,
        coarse=dense.coarse,
        scale=dense.scale,
        nodata=float(config.output.nodata),
        measure_terrain=config.ties.terrain == "tie_points",
        prior_m=config.orientation.prior_heights,
        quicklook_only=config.dense.quicklook < 0
        and config.stream.enabled
        and len(config.views) == 2
        and config.scenes.lines > 0,
    )


class HeightsStage:
    """The heights step on the pipeline's outputs: every finished pair gets its heights.

    A pair made whole carries its images; a streamed pair's images come as column blocks
    before its :class:`PairResult` (which then has none): the stage keeps the blocks of the
    pairs in progress (the whole normalized pair, as the unstreamed path holds it) and joins
    them when the pair is complete. A pair whose images are incomplete gets a WARN, no
    heights.

    The heights searched are the pair's :attr:`PairResult.terrain`; when it was not measured
    from the pair (a streamed pair, or tie points that did not refine a whole one) and
    ``options.measure_terrain`` is on, tie points between the pair's normalized images measure
    it here (:func:`pair_terrain`).

    Args:
        options: how heights are made.
    """

    def __init__(self, options: HeightsOptions) -> None:
        self.options = options
        #: The DEM of the pairs' terrain (:meth:`.pipeline.Pipeline.use_dem`), or None.
        self.dem: DemTerrain | None = None
        self._blocks: dict[tuple[str, str], list[BlockResult]] = {}
        #: The full-resolution streamed tiles of the pairs in progress (core/tiles.py), by pair.
        self._tiles: dict[str, list[HeightTile]] = {}
        #: Quick-look tiles with a DSM of the pairs in progress, by pair (quick-look only).
        self._quick: dict[str, int] = {}

    def __call__(self, out: Outputs) -> Outputs:
        """Add the heights (and their issues) of the pairs ``out`` completes, in place.

        A streamed pair whose full-resolution tiles all came (:attr:`Outputs.tiles`) gets its
        heights from them (:func:`heights_from_tiles`): it is not
        matched a second time.
        """
        for blk in out.blocks:
            self.keep(blk)
        for tile in out.tiles:
            if tile.factor == 1:
                self._tiles.setdefault(tile.pair_id, []).append(tile)
            elif tile.ok:
                self._quick[tile.pair_id] = self._quick.get(tile.pair_id, 0) + 1
        for pair in out.pairs:
            from_tiles = self._from_tiles(pair)
            if from_tiles is not None:
                self.forget(pair.pair_id)
                out.heights.append(from_tiles)
                continue
            if pair.left_image is None and self.options.quicklook_only:
                quick = self._quick.pop(pair.pair_id, 0)
                self.forget(pair.pair_id)
                out.issues.append(
                    Issue(
                        Level.OK,
                        f"pair {pair.pair_id}",
                        f"heights: its {quick} quick-look tiles stand for them "
                        "(heights_quicklook < 0): no full-resolution DSM",
                    )
                    if quick
                    else Issue(
                        Level.WARN,
                        f"pair {pair.pair_id}",
                        "no heights: quick-look tiles only (heights_quicklook < 0) and none "
                        "was made of this pair (shed under overload, or not matched: see the "
                        "tiles' lines on /diagnostics)",
                    )
                )
                continue
            images = self._images(pair)
            if images is None:
                out.issues.append(
                    Issue(
                        Level.WARN,
                        f"pair {pair.pair_id}",
                        "no heights: its normalized images are incomplete",
                    )
                )
                continue
            terrain, issues = self.pair_terrain(pair, *images)
            res, more = measure_heights(pair, *images, terrain, self.options)
            out.heights.append(res)
            out.issues += issues + more
        return out

    def pair_terrain(
        self, pair: PairResult, left: NDArray[np.generic], right: NDArray[np.generic]
    ) -> tuple[Terrain, list[Issue]]:
        """The terrain to search for ``pair`` (its own, or measured now), and its issues.

        A WARN when only the prior is known although a measurement was asked for. With a DEM
        (:attr:`dem`): a pair that comes without the DEM's heights (streamed) gets them now,
        and tie points measured now are joined with them (:func:`~.terrain.with_dem`); with
        too few tie points the DEM's heights are searched (OK, not WARN).
        """
        opt = self.options
        terrain = pair.terrain or Terrain(*opt.prior_m, TerrainSource.PRIOR)
        if terrain.source in FROM_TIE_POINTS:
            return terrain, []
        issues: list[Issue] = []
        if self.dem is not None and terrain.source != TerrainSource.DEM:
            k = pair.normalization.parallax_per_height
            dem = self.dem.pair_terrain(
                pair.pair_id,
                pair.left,
                pair.right,
                pair.normalization,
                z0=0.5 * (terrain.low_m + terrain.high_m),
                metres_per_px=pair.left_grid.pixel / k,
            )
            issues += self.dem.take_issues()
            terrain = dem or terrain
        if not opt.measure_terrain:
            return terrain, issues
        measured = measure_terrain(
            left,
            right,
            pair.left_grid,
            pair.right_grid,
            pair.normalization,
            terrain,
            nodata=opt.nodata,
        )
        dem_terrain = terrain if terrain.source == TerrainSource.DEM else None
        if measured.source == TerrainSource.TIE_POINTS:
            return with_dem(dem_terrain, measured), issues
        if dem_terrain is not None:
            return terrain, [
                *issues,
                Issue(
                    Level.OK,
                    f"pair {pair.pair_id}",
                    "too few tie points agree to measure the terrain from the pair: the heights "
                    f"searched are the DEM's, {terrain.describe()}",
                ),
            ]
        return terrain, [
            *issues,
            Issue(
                Level.WARN,
                f"pair {pair.pair_id}",
                "too few tie points agree to measure the terrain from the pair: the heights "
                f"searched are the prior, {terrain.describe()} (if the ground lies outside it, "
                "few pixels match: give a DEM at import, or set z_avg / height_range)",
            ),
        ]

    def keep(self, blk: BlockResult) -> None:
        """Keep a streamed block (its pixels as they are: pass a copy of a borrowed view).

        Not with quick-look tiles only: no full-resolution heights are made of them.
        """
        if not self.options.quicklook_only:
            self._blocks.setdefault((blk.pair_id, blk.side), []).append(blk)

    def _images(self, pair: PairResult) -> tuple[NDArray[np.generic], NDArray[np.generic]] | None:
        if pair.left_image is not None and pair.right_image is not None:
            return pair.left_image, pair.right_image
        sides = []
        for side, grid in (("left", pair.left_grid), ("right", pair.right_grid)):
            blocks = self._blocks.pop((pair.pair_id, side), [])
            if not blocks:
                return None
            img = np.zeros((grid.height, grid.width), dtype=blocks[0].image.dtype)
            covered = 0
            for b in blocks:
                img[:, b.col0 : b.col0 + b.image.shape[1]] = b.image
                covered += b.image.shape[1]
            if covered < grid.width:
                return None
            sides.append(img)
        return sides[0], sides[1]

    def _from_tiles(self, pair: PairResult) -> HeightsResult | None:
        """The heights of a streamed pair from its full-resolution tiles; None: not all came."""
        tiles = self._tiles.pop(pair.pair_id, [])
        if pair.left_image is not None or not tiles:
            return None
        opt = self.options
        fill = opt.max_fill_cells if opt.fill == "nearest" else 0.0
        return heights_from_tiles(tiles, max_fill_cells=fill, nodata=opt.nodata)

    def forget(self, pair_id: str) -> None:
        """Drop the blocks and tiles of a pair (done, or it will not complete)."""
        for side in ("left", "right"):
            self._blocks.pop((pair_id, side), None)
        self._tiles.pop(pair_id, None)
        self._quick.pop(pair_id, None)


def assemble_tiles(tiles: list[HeightTile]) -> Dsm | None:
    """The DSM of one pair's tiles on the pair's grid (cells of tiles not given: NaN)."""
    ok = [t for t in tiles if t.ok and t.dsm is not None and t.owned is not None]
    if not ok or ok[0].pair_grid is None:
        return None
    pg = ok[0].pair_grid
    heights = np.full((pg.height, pg.width), np.nan, dtype=np.float32)
    count = np.zeros(heights.shape, dtype=np.int32)
    filled = np.zeros(heights.shape, dtype=bool)
    for t in ok:
        assert t.dsm is not None and t.owned is not None
        g = t.dsm.grid
        r0 = round((pg.y0 - g.y0) / pg.cell)
        c0 = round((g.x0 - pg.x0) / pg.cell)
        rs, cs = slice(r0, r0 + g.height), slice(c0, c0 + g.width)
        np.copyto(heights[rs, cs], t.dsm.heights, where=t.owned)
        np.copyto(count[rs, cs], t.dsm.count, where=t.owned)
        np.copyto(filled[rs, cs], t.dsm.filled, where=t.owned)
    return Dsm(heights, pg, count, filled)


def heights_from_tiles(
    tiles: list[HeightTile], *, max_fill_cells: float = 0.0, nodata: float = 0.0
) -> HeightsResult | None:
    """A pair's :class:`HeightsResult` made of all its tiles (one level), without matching again.

    The disparity is the tiles' own columns side by side, the heights ``a d + b``, the DSM and
    ortho-image the tiles' owned cells on the pair's grid (:func:`assemble_tiles`). For a
    streamed pair this can stand for the whole-pair heights step, which would match the pair
    a second time. None: not every tile of the pair is given, or none has a DSM.

    Args:
        tiles: every tile of one pair at one level, any order.
        max_fill_cells: the fill applied (``heights_max_fill_cells`` with ``nearest``, else 0).
        nodata: the ortho-image's no-data value.
    """
    if not tiles:
        return None
    tiles = sorted(tiles, key=lambda t: t.index)
    first = tiles[0]
    if [t.index for t in tiles] != list(range(first.count)):
        return None
    dsm = assemble_tiles(tiles)
    if dsm is None:
        return None
    disparity = np.concatenate([t.disparity for t in tiles], axis=1)
    valid = sum(int(np.isfinite(t.disparity).sum()) for t in tiles)
    data = sum(np.isfinite(t.disparity).sum() / t.valid_share for t in tiles if t.valid_share > 0)
    a, b = first.height_per_disparity_px, first.height_offset_m
    ortho_t = next(t.ortho for t in tiles if t.ortho is not None)
    ortho = np.full(dsm.heights.shape, nodata, dtype=ortho_t.dtype)
    pg = dsm.grid
    for t in tiles:
        if t.ok and t.dsm is not None and t.owned is not None and t.ortho is not None:
            g = t.dsm.grid
            r0 = round((pg.y0 - g.y0) / pg.cell)
            c0 = round((g.x0 - pg.x0) / pg.cell)
            np.copyto(ortho[r0 : r0 + g.height, c0 : c0 + g.width], t.ortho, where=t.owned)
    bad = [t for t in tiles if not t.ok]
    status = DenseStatus.OK
    share = float(valid / data) if data > 0 else 0.0
    message = f"{100 * share:.1f} % of the left pixels with data matched, in {len(tiles)} tiles"
    if bad:
        message += f" ({len(bad)} without heights: {bad[0].message})"
    return HeightsResult(
        first.pair_id, first.stamp_ns, status, message, first.d_range, share,
        disparity.astype(np.float32), (a * disparity + b).astype(np.float32), dsm, ortho, a, b,
        max_fill_cells, first.terrain,
    )  # fmt: skip
