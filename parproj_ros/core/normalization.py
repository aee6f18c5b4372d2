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

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry import DegenerateGeometryError, GeometryError, Normalization
from ..geometry import normalize_pair as normalize_affine_pair
from ..geometry.navigation import virtual_points
from ..geometry.segmentation import SideCamera, segment_pair
from ..imaging.resample import OutputGrid, SceneGeometry, footprint, native_pixel, resample
from .config import PipelineConfig
from .gcp_store import GcpStore
from .orientation import scene_from_gcp
from .results import Issue, Level, Method, Outputs, PairGeometry, SceneResult, YParallaxSource

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class NormalizedPair:
    """A pair's geometry and its two normalized images (output grid pixels, the scenes' dtype)."""

    geometry: PairGeometry
    left_image: NDArray[np.generic]
    right_image: NDArray[np.generic]


def interpolation_flag(config: PipelineConfig) -> int:
    """OpenCV interpolation flag of the configured interpolation."""
    return cv2.INTER_CUBIC if config.interpolation == "cubic" else cv2.INTER_LINEAR


def pair_geometry(
    left: SceneResult,
    right: SceneResult,
    lines: tuple[int, int],
    config: PipelineConfig,
    gcps: GcpStore,
) -> PairGeometry | Issue:
    """Normalization and output grids of a pair (scenes of ``lines`` lines each).

    An ERROR issue instead when the pair cannot be normalized: degenerate geometry, no overlap,
    or output images over ``max_output_pixels``.
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
    pix = config.output_pixel or min(native_pixel(gl), native_pixel(gr))
    y0 = max(fl[:, 1].min(), fr[:, 1].min())
    y1 = min(fl[:, 1].max(), fr[:, 1].max())
    if y1 <= y0:
        return Issue(
            Level.ERROR,
            f"pair {pair_id}",
            "the scenes do not overlap across the epipolar lines: pair skipped",
        )
    shift = norm.parallax_per_height * config.z_avg + norm.parallax_offset
    xo_l = min(fl[:, 0].min(), fr[:, 0].min() + shift)
    x1 = max(fl[:, 0].max(), fr[:, 0].max() + shift)
    if config.output_extent == "overlap":
        heights = pair_heights(left, right, config, gcps)
        span = overlap_columns(norm, fl, fr, shift, heights, config.z_avg)
        if span is None:
            return Issue(
                Level.ERROR,
                f"pair {pair_id}",
                "the scenes do not overlap along the epipolar lines at any height of the "
                "pair (output_extent overlap): pair skipped",
            )
        xo_l, x1 = max(xo_l, span[0]), min(x1, span[1])
    width = int(np.floor((x1 - xo_l) / pix)) + 1
    height = int(np.floor((y1 - y0) / pix)) + 1
    if width * height > config.max_output_pixels:
        return Issue(
            Level.ERROR,
            f"pair {pair_id}",
            f"normalized images would be {width} x {height} px (> max_output_pixels "
            f"{config.max_output_pixels}): pair skipped",
        )
    grid_l = OutputGrid(pix, xo_l, y0, width, height)
    grid_r = OutputGrid(pix, xo_l - shift, y0, width, height)
    return PairGeometry(pair_id, norm, gl, gr, grid_l, grid_r)


def pair_heights(
    left: SceneResult, right: SceneResult, config: PipelineConfig, gcps: GcpStore
) -> tuple[float, float]:
    """Heights (m) of the pair's ground: its GCP and check points, else z_avg +- height_range.

    With at least ``min_gcp`` points observed in either scene, their height span widened
    by 10 % of it (at least 1 m) on each side; otherwise ``z_avg`` +- ``height_range``.
    """
    z = gcps.heights((left.scene.scene_id, right.scene.scene_id))
    if z.size >= config.min_gcp:
        pad = max(0.1 * float(np.ptp(z)), 1.0)
        return float(z.min()) - pad, float(z.max()) + pad
    return config.z_avg - config.height_range, config.z_avg + config.height_range


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
    res: SceneResult, geom: SceneGeometry, grid: OutputGrid, config: PipelineConfig
) -> NDArray[np.generic]:
    """A whole scene resampled onto its normalized grid (``nodata`` outside it)."""
    return resample(
        res.scene.image,
        geom,
        grid,
        nodata=config.nodata,
        interpolation=interpolation_flag(config),
    )


def normalize_pair(
    left: SceneResult, right: SceneResult, config: PipelineConfig, gcps: GcpStore
) -> NormalizedPair | Issue:
    """A pair of whole scenes normalized: geometry (:func:`pair_geometry`), both resampled."""
    geo = pair_geometry(left, right, (left.scene.lines, right.scene.lines), config, gcps)
    if isinstance(geo, Issue):
        return geo
    img_l = resample_scene(left, geo.left_geom, geo.left_grid, config)
    img_r = resample_scene(right, geo.right_geom, geo.right_grid, config)
    return NormalizedPair(geo, img_l, img_r)


def y_parallax(
    left: SceneResult,
    right: SceneResult,
    gl: SceneGeometry,
    gr: SceneGeometry,
    gcps: GcpStore,
    config: PipelineConfig,
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
        z = config.z_avg
        h = config.height_range
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
    bound = config.segment_max_error_px
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
            overlap=config.segment_overlap,
            min_points=max(2 * config.min_gcp, 10),
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
            f"with {config.segment_overlap:.0%} overlap; largest segment error "
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
                    roll=config.gcp_roll,
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
