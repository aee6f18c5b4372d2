"""Epipolar normalization of a pair of oriented scenes: paper 2 section 4 (Eq 8).

The two scenes' A1..A8 give the normalization (kappa_n, average scale and shift), each scene's
footprint on the normalized plane gives the common output grids (the overlap across the epipolar
lines, and along them the ground both scenes see over the pair's heights), and both scenes are
resampled onto them. A GCP pair whose affine model errs by more than ``segment_max_error_px`` is
first cut along track into segment pairs (paper 1 section 4's bound, per segment). The
y-parallax left is measured on GCP or on virtual points of the rigorous models. Normalized
coordinates are metres in the left image's plane; images are pixels of the output grid.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..geometry import DegenerateGeometryError, GeometryError, Normalization
from ..geometry import normalize_pair as normalize_affine_pair
from ..geometry.navigation import virtual_points
from ..geometry.segmentation import SideCamera, segment_pair
from ..imaging.resample import (
    OutputGrid,
    SceneGeometry,
    footprint,
    kernel_flag,
    native_pixel,
    resample,
)
from .config import OrientationSettings, OutputSettings, PipelineConfig
from .gcp_store import GcpStore
from .orientation import scene_from_gcp
from .results import Issue, Level, Method, Outputs, PairGeometry, SceneResult, YParallaxSource
from .terrain import (
    MEASURED,
    Terrain,
    TerrainSource,
    measure_terrain,
    reduction_factor,
    with_dem,
)

if TYPE_CHECKING:
    from .dem_terrain import DemTerrain

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class NormalizedPair:
    """A pair's geometry, its two normalized images and the terrain of its output extent.

    The images are in output grid pixels, of the scenes' dtype. ``dem_terrain``: the DEM's
    terrain of the pair (None: no DEM, or it could not give one), which the full-resolution tie
    points' terrain is joined with again (:func:`~.terrain.with_dem`).
    """

    geometry: PairGeometry
    left_image: NDArray[np.generic]
    right_image: NDArray[np.generic]
    terrain: Terrain
    dem_terrain: Terrain | None = None


def _output(settings: OutputSettings | PipelineConfig) -> OutputSettings:
    """The output settings (a whole config is accepted while its callers migrate)."""
    return settings.output if isinstance(settings, PipelineConfig) else settings


def _orientation(settings: OrientationSettings | PipelineConfig) -> OrientationSettings:
    """The orientation settings (a whole config is accepted while its callers migrate)."""
    return settings.orientation if isinstance(settings, PipelineConfig) else settings


def interpolation_flag(output: OutputSettings | PipelineConfig) -> int:
    """OpenCV interpolation flag of the configured interpolation (imaging/kernels.py's row)."""
    return kernel_flag(_output(output).interpolation)


@dataclass(frozen=True)
class PairFrame:
    """A pair's normalization and the two scenes' footprints on the normalized plane.

    Attributes:
        pair_id: "<left scene id>+<right scene id>".
        normalization: paper 2 Eq 8.
        left_geom: the left scene's geometry on the normalized plane.
        right_geom: the right scene's.
        left_footprint: the left scene's border in normalized metres, (n, 2).
        right_footprint: the right scene's, (n, 2).
        pixel: output pixel, normalized metres.
        rows: (lowest, highest) normalized y both scenes cover, metres.
        z_ref: the zero-disparity height of the output grids, metres (``z_avg``, or the
            middle of the measured terrain when ``z_avg`` lies outside it: :func:`pair_grids`).
    """

    pair_id: str
    normalization: Normalization
    left_geom: SceneGeometry
    right_geom: SceneGeometry
    left_footprint: FloatArray
    right_footprint: FloatArray
    pixel: float
    rows: tuple[float, float]
    z_ref: float

    @property
    def shift(self) -> float:
        """The right grid's x relative to the left one: ``k z_ref + offset``, metres."""
        n = self.normalization
        return float(n.parallax_per_height * self.z_ref + n.parallax_offset)

    def union_columns(self) -> tuple[float, float]:
        """Normalized x range (left image metres) of both footprints whole."""
        fl, fr, s = self.left_footprint, self.right_footprint, self.shift
        return min(fl[:, 0].min(), fr[:, 0].min() + s), max(fl[:, 0].max(), fr[:, 0].max() + s)


def pair_frame(
    left: SceneResult, right: SceneResult, lines: tuple[int, int], config: PipelineConfig
) -> PairFrame | Issue:
    """Normalization and footprints of a pair (scenes of ``lines`` lines each).

    An ERROR issue instead when the pair cannot be normalized: degenerate geometry, or no
    overlap across the epipolar lines.
    """
    pair_id = f"{left.scene.scene_id}+{right.scene.scene_id}"
    try:
        norm = normalize_affine_pair(
            left.affine, right.affine, left_params=left.params, right_params=right.params
        )
    except DegenerateGeometryError as err:
        return Issue(Level.ERROR, f"pair {pair_id}", f"{err}: pair skipped")
    gl = left.geometry(norm.left)
    gr = right.geometry(norm.right)
    fl = footprint(gl, lines[0], left.scene.detectors)
    fr = footprint(gr, lines[1], right.scene.detectors)
    pix = config.output.pixel_m or min(native_pixel(gl), native_pixel(gr))
    y0 = max(fl[:, 1].min(), fr[:, 1].min())
    y1 = min(fl[:, 1].max(), fr[:, 1].max())
    if y1 <= y0:
        return Issue(
            Level.ERROR,
            f"pair {pair_id}",
            "the scenes do not overlap across the epipolar lines: pair skipped",
        )
    z_avg = config.orientation.z_avg
    return PairFrame(pair_id, norm, gl, gr, fl, fr, pix, (float(y0), float(y1)), z_avg)


#: Fewest pixels a side of a pair's normalized images with ``output_pixel`` set: coarser
#: leaves nothing to match (tie points, dense heights).
MIN_OUTPUT_SIDE_PX = 16


def pair_grids(
    frame: PairFrame, output: OutputSettings, heights: tuple[float, float]
) -> PairGeometry | Issue:
    """The output grids of a pair: its rows, and its columns by ``output.extent``.

    ``heights`` (m): the pair's terrain, at which ``overlap`` keeps the columns both scenes
    see. An ERROR issue when no column is left, the images would exceed ``max_output_pixels``,
    or ``output_pixel`` makes them less than :data:`MIN_OUTPUT_SIDE_PX` a side. The
    zero-disparity height is ``frame.z_ref``.
    """
    norm, shift, pix = frame.normalization, frame.shift, frame.pixel
    xo_l, x1 = frame.union_columns()
    if output.extent == "overlap":
        span = overlap_columns(
            norm, frame.left_footprint, frame.right_footprint, shift, heights, frame.z_ref
        )
        if span is None:
            return Issue(
                Level.ERROR,
                f"pair {frame.pair_id}",
                "the scenes do not overlap along the epipolar lines at any height of the "
                f"pair ({heights[0]:.0f}..{heights[1]:.0f} m; output_extent overlap): pair "
                "skipped",
            )
        xo_l, x1 = max(xo_l, span[0]), min(x1, span[1])
    y0, y1 = frame.rows
    width = int(np.floor((x1 - xo_l) / pix)) + 1
    height = int(np.floor((y1 - y0) / pix)) + 1
    if width * height > output.max_pixels:
        return Issue(
            Level.ERROR,
            f"pair {frame.pair_id}",
            f"normalized images would be {width} x {height} px (> max_output_pixels "
            f"{output.max_pixels}): pair skipped",
        )
    if output.pixel_m > 0 and min(width, height) < MIN_OUTPUT_SIDE_PX:
        # else reported as scenes that see different ground (output_pixel 1: 1 x 1 px)
        return Issue(
            Level.ERROR,
            f"pair {frame.pair_id}",
            f"normalized images would be {width} x {height} px at output_pixel "
            f"{output.pixel_m:g} (< {MIN_OUTPUT_SIDE_PX} px a side: nothing to match): pair "
            "skipped; give a smaller output_pixel, or 0 for the scenes' own resolution",
        )
    grid_l = OutputGrid(pix, xo_l, y0, width, height)
    grid_r = OutputGrid(pix, xo_l - shift, y0, width, height)
    return PairGeometry(frame.pair_id, norm, frame.left_geom, frame.right_geom, grid_l, grid_r)


def pair_geometry(
    left: SceneResult,
    right: SceneResult,
    lines: tuple[int, int],
    config: PipelineConfig,
    gcps: GcpStore,
    dem: DemTerrain | None = None,
) -> tuple[PairGeometry, Terrain] | Issue:
    """Normalization and output grids of a pair before its pixels exist, and their heights.

    The heights its GCP (or the prior) give; with a DEM (``dem``, whose issues it keeps) the
    DEM's heights over the pair's ground instead, and the zero-disparity height at their
    middle, as :func:`normalize_pair` takes them for a whole pair without tie points. A
    streamed pair's geometry (its images are made block by block from it).

    Returns:
        (geometry, terrain), or an ERROR issue when the pair cannot be normalized:
        degenerate geometry, no overlap, or output images over ``max_output_pixels``.
    """
    frame = pair_frame(left, right, lines, config)
    if isinstance(frame, Issue):
        return frame
    terrain = pair_terrain(left, right, config.orientation, gcps)
    dem_terrain = _dem_terrain(dem, frame, left, right, terrain)
    if dem_terrain is not None:
        terrain = with_dem(dem_terrain, terrain)
        frame = replace(frame, z_ref=zero_disparity_height(config.orientation.z_avg, terrain))
    geo = pair_grids(frame, config.output, terrain.range_m)
    return geo if isinstance(geo, Issue) else (geo, terrain)


def _dem_terrain(
    dem: DemTerrain | None,
    frame: PairFrame,
    left: SceneResult,
    right: SceneResult,
    terrain: Terrain,
) -> Terrain | None:
    """The DEM's terrain of a pair (None without a DEM or when it cannot give it)."""
    if dem is None:
        return None
    k = frame.normalization.parallax_per_height
    return dem.pair_terrain(
        frame.pair_id,
        left,
        right,
        frame.normalization,
        z0=0.5 * (terrain.low_m + terrain.high_m),
        metres_per_px=frame.pixel / k,
    )


def pair_terrain(
    left: SceneResult,
    right: SceneResult,
    orientation: OrientationSettings | PipelineConfig,
    gcps: GcpStore,
) -> Terrain:
    """The heights the pipeline assumes for a pair: its GCP and check points, else the prior.

    With at least ``min_gcp`` points observed in either scene, their height span widened
    by 10 % of it (at least 1 m) on each side; otherwise ``z_avg`` +- ``height_range``.
    """
    settings = _orientation(orientation)
    z = gcps.heights((left.scene.scene_id, right.scene.scene_id))
    if z.size >= settings.min_gcp:
        pad = max(0.1 * float(np.ptp(z)), 1.0)
        return Terrain(float(z.min()) - pad, float(z.max()) + pad, TerrainSource.GCP)
    return Terrain(*settings.prior_heights, TerrainSource.PRIOR)


def pair_heights(
    left: SceneResult,
    right: SceneResult,
    orientation: OrientationSettings | PipelineConfig,
    gcps: GcpStore,
) -> tuple[float, float]:
    """(lowest, highest) height (m) of :func:`pair_terrain`."""
    return pair_terrain(left, right, orientation, gcps).range_m


def zero_disparity_height(z_avg: float, terrain: Terrain) -> float:
    """The zero-disparity height of a pair's grids: ``z_avg`` on a measured terrain holding it.

    Otherwise (the terrain measured elsewhere, by tie points or a DEM, e.g. an imported pair
    whose frame lies at the RPC's height offset, hundreds of metres above the ground) the middle
    of the measured terrain, to the metre: conjugate points then lie near the same column of
    both images, as a stereo user expects, and the images hold the same ground.
    """
    if terrain.source not in MEASURED or terrain.low_m <= z_avg <= terrain.high_m:
        return z_avg
    return float(round(0.5 * (terrain.low_m + terrain.high_m)))


#: Longest side of the reduced pair the terrain is first measured on, pixels.
PREPASS_PX = 1024


def terrain_prepass(
    frame: PairFrame, left: SceneResult, right: SceneResult, output: OutputSettings, prior: Terrain
) -> Terrain:
    """The pair's terrain measured on a reduced normalized pair covering both footprints whole.

    Both scenes are resampled at a reduced resolution (the longer side at most
    :data:`PREPASS_PX`) onto the union of their footprints, whatever heights are assumed, so
    that tie points are found even when the prior heights are far from the ground (an output
    extent chosen at them would hold little or no common ground); their heights give the terrain
    (:func:`~parproj_ros.core.terrain.measure_terrain`). ``prior`` when too few agree.
    """
    x0, x1 = frame.union_columns()
    y0, y1 = frame.rows
    full_w = int(np.floor((x1 - x0) / frame.pixel)) + 1
    full_h = int(np.floor((y1 - y0) / frame.pixel)) + 1
    f = reduction_factor(full_w, full_h, PREPASS_PX)
    pix = frame.pixel * f
    w, h = int(np.floor((x1 - x0) / pix)) + 1, int(np.floor((y1 - y0) / pix)) + 1
    grid_l = OutputGrid(pix, x0, y0, w, h)
    grid_r = OutputGrid(pix, x0 - frame.shift, y0, w, h)
    img_l = resample_scene(left, frame.left_geom, grid_l, output)
    img_r = resample_scene(right, frame.right_geom, grid_r, output)
    return measure_terrain(
        img_l, img_r, grid_l, grid_r, frame.normalization, prior, nodata=output.nodata
    )


def overlap_columns(
    norm: Normalization,
    fl: FloatArray,
    fr: FloatArray,
    shift: float,
    heights: tuple[float, float],
    z_avg: float,
) -> tuple[float, float] | None:
    """Normalized x range (left image metres) of the ground both scenes see (None: none).

    A point at height z is at x_l in the left image and at x_l - d, d = k (z - z_avg), in
    the right one (in the left image's x, the right grid being shifted by ``shift``). Over
    the pair's ``heights`` (m, :func:`pair_heights`) the left image needs the x_l in its
    footprint ``fl`` whose partner lies in the right footprint ``fr``, and the right image
    the converse; the range is the hull of both.
    """
    k = norm.parallax_per_height
    zlo, zhi = heights
    d = (k * (zlo - z_avg), k * (zhi - z_avg))
    dlo, dhi = min(d), max(d)
    l0, l1 = float(fl[:, 0].min()), float(fl[:, 0].max())
    r0, r1 = float(fr[:, 0].min()) + shift, float(fr[:, 0].max()) + shift
    lo = min(max(l0, r0 + dlo), max(r0, l0 - dhi))
    hi = max(min(l1, r1 + dhi), min(r1, l1 - dlo))
    return (lo, hi) if hi > lo else None


def resample_scene(
    res: SceneResult,
    geom: SceneGeometry,
    grid: OutputGrid,
    output: OutputSettings | PipelineConfig,
) -> NDArray[np.generic]:
    """A whole scene resampled onto its normalized grid (``nodata`` outside it)."""
    settings = _output(output)
    return resample(
        res.scene.image,
        geom,
        grid,
        nodata=settings.nodata,
        interpolation=interpolation_flag(settings),
    )


def normalize_pair(
    left: SceneResult,
    right: SceneResult,
    config: PipelineConfig,
    gcps: GcpStore,
    dem: DemTerrain | None = None,
) -> NormalizedPair | Issue:
    """A pair of whole scenes normalized: geometry (:func:`pair_geometry`), both resampled.

    With ``terrain`` "tie_points" the output extent is chosen at the terrain measured from the
    pair (:func:`terrain_prepass`), which :attr:`NormalizedPair.terrain` then holds; otherwise
    at the heights of its GCP or the prior (:func:`pair_terrain`). With a DEM (``dem``, whose
    issues it keeps), its heights over the pair's ground join the tie points' (their hull), or
    replace the prior (:func:`~.terrain.with_dem`).
    """
    frame = pair_frame(left, right, (left.scene.lines, right.scene.lines), config)
    if isinstance(frame, Issue):
        return frame
    terrain = pair_terrain(left, right, config.orientation, gcps)
    dem_terrain = _dem_terrain(dem, frame, left, right, terrain)
    if config.ties.terrain == "tie_points":
        terrain = terrain_prepass(frame, left, right, config.output, terrain)
    terrain = with_dem(dem_terrain, terrain)
    frame = replace(frame, z_ref=zero_disparity_height(config.orientation.z_avg, terrain))
    geo = pair_grids(frame, config.output, terrain.range_m)
    if isinstance(geo, Issue):
        return geo
    img_l = resample_scene(left, geo.left_geom, geo.left_grid, config.output)
    img_r = resample_scene(right, geo.right_geom, geo.right_grid, config.output)
    return NormalizedPair(geo, img_l, img_r, terrain, dem_terrain)


def y_parallax(
    left: SceneResult,
    right: SceneResult,
    gl: SceneGeometry,
    gr: SceneGeometry,
    gcps: GcpStore,
    orientation: OrientationSettings | PipelineConfig,
) -> tuple[FloatArray, YParallaxSource]:
    """Geometric y-parallax (px): GCP/check points, else virtual points of the models.

    Returns the y-parallaxes and their source.
    """
    ls_l, ls_r = gcps.common(left.scene.scene_id, right.scene.scene_id)
    pixel = left.camera.pixel_size
    if len(ls_l) >= 1:
        nl = gl.image_to_normalized(np.array(ls_l)[:, 0], np.array(ls_l)[:, 1])
        nr = gr.image_to_normalized(np.array(ls_r)[:, 0], np.array(ls_r)[:, 1])
        return (nl[:, 1] - nr[:, 1]) / pixel, YParallaxSource.GCP
    if left.model is not None and right.model is not None:
        z, h = _orientation(orientation).z_avg, _orientation(orientation).height_range
        obj = virtual_points(left.model, (0.0, left.scene.lines - 1.0), [z - h, z, z + h], grid=11)
        lr = right.model.project(obj)
        inside = (
            (lr[:, 0] >= 0)
            & (lr[:, 0] <= right.scene.lines - 1)
            & (lr[:, 1] >= 0)
            & (lr[:, 1] <= right.scene.detectors - 1)
        )
        if inside.sum() >= 1:
            ll = left.model.project(obj[inside])
            nl = gl.image_to_normalized(ll[:, 0], ll[:, 1])
            nr = gr.image_to_normalized(lr[inside, 0], lr[inside, 1])
            return (nl[:, 1] - nr[:, 1]) / pixel, YParallaxSource.VIRTUAL
    return np.zeros(0), YParallaxSource.NONE


def cut_into_segments(
    left: SceneResult,
    right: SceneResult,
    config: PipelineConfig,
    gcps: GcpStore,
    make_whole: Callable[[SceneResult, SceneResult], Outputs],
    keep: Collection[str] = (),
) -> tuple[Outputs, bool]:
    """Cut a GCP pair whose model error exceeds the bound into segment pairs (paper 1 Eq 8).

    Each segment pair is oriented from the GCP in it and made by ``make_whole``. Returns
    (outputs, cut): with ``cut`` the segments' scene results and pairs; otherwise the whole
    scenes are to be paired, and the outputs hold an issue when cutting was tried and did not
    help. The whole scenes' GCP observations are then forgotten (except in scenes in ``keep``).
    """
    out = Outputs()
    bound = config.segments.max_error_px
    whole = max(left.residual_max_px, right.residual_max_px)
    if (
        bound <= 0
        or whole <= bound
        or not (left.method.startswith("gcp") and right.method.startswith("gcp"))
        or left.scene.released
        or right.scene.released
    ):
        return out, False
    pair_id = f"pair {left.scene.scene_id}+{right.scene.scene_id}"
    # (GCP, check points) observed in each whole scene
    observed = {
        r.scene.scene_id: [gcps.observed(r.scene, check) for check in (False, True)]
        for r in (left, right)
    }
    (idl, xl, ll), (idr, xr, lr) = (observed[r.scene.scene_id][0] for r in (left, right))
    pos_r = {pid: k for k, pid in enumerate(idr)}
    common = [(k, pos_r[pid]) for k, pid in enumerate(idl) if pid in pos_r]
    ci = np.array(common, dtype=np.intp).reshape(-1, 2)

    def side(r: SceneResult) -> SideCamera:
        psi = None if r.method == Method.GCP_ROLL_ESTIMATED else r.psi
        return SideCamera(r.camera.principal_distance, r.camera.pixel_size, r.camera.pp, psi)

    try:
        seg = segment_pair(
            xl,
            ll,
            xr,
            lr,
            (ci[:, 0], ci[:, 1]),
            lines=(left.scene.lines, right.scene.lines),
            cameras=(side(left), side(right)),
            bound_px=bound,
            overlap=config.segments.overlap,
            min_points=max(2 * config.orientation.min_gcp, 10),
        )
    except GeometryError as err:
        seg = None
        why = str(err)
    if seg is None or seg.count == 1:
        why = seg.note if seg is not None else why
        out.issues.append(
            Issue(
                Level.WARN,
                pair_id,
                f"model error {whole:.3f} px > bound {bound:g} px "
                f"(segment_max_error_px), but cutting the scenes does not help: {why}; "
                "the whole scenes are paired",
            )
        )
        return out, False
    out.issues.append(
        Issue(
            Level.OK if seg.reached else Level.WARN,
            pair_id,
            f"model error {seg.whole_error_px[0]:.3f} / {seg.whole_error_px[1]:.3f} px "
            f"(left / right) > bound {bound:g} px: cut into {seg.count} segment pairs "
            f"with {config.segments.overlap:.0%} overlap; largest segment error "
            f"{seg.max_error_px:.3f} px, "
            + ("bound met" if seg.reached else f"bound NOT met ({seg.note})"),
        )
    )
    for k, (sl, sr) in enumerate(zip(seg.left, seg.right, strict=True)):
        parts = []
        for whole_res, fit in ((left, sl), (right, sr)):
            sc = whole_res.scene
            sub = replace(
                sc,
                scene_id=f"{sc.scene_id}.seg{k}",
                first_line_ns=sc.first_line_ns + round(fit.start * sc.line_period * 1e9),
                image=sc.image[fit.start : fit.stop],
                gaps=0,
            )
            for ids, _, ls in observed[sc.scene_id]:
                for pid, (ln, smp) in zip(ids, ls, strict=True):
                    if fit.start - 0.5 <= ln <= fit.stop - 0.5:
                        gcps.points[pid].observations[sub.scene_id] = (ln - fit.start, smp)
            try:
                res = scene_from_gcp(
                    sub,
                    whole_res.camera,
                    None,
                    gcps.for_scene(sub),
                    roll=config.orientation.gcp_roll,
                    reference=whole_res.params,
                )
            except GeometryError as err:  # the segmentation fitted it: not expected
                out.issues.append(Issue(Level.ERROR, pair_id, f"segment {k}: {err}: skipped"))
                break
            res = replace(
                res,
                model=None,  # the rigorous model counts lines of the whole scene
                segment_of=sc.scene_id,
                segment_first_line=fit.start,
                model_error_bound_px=bound,
                note=f"segment {k + 1} of {seg.count}, lines {fit.start}..{fit.stop - 1} "
                f"of {sc.scene_id}; {res.note}",
            )
            parts.append(res)
        else:
            out.scenes += parts
            out.extend(make_whole(parts[0], parts[1]))
    gcps.forget((left.scene.scene_id, right.scene.scene_id), keep)  # the segments' are gone
    return out, True
