"""Parts 1 and 4: the resampling micro-benchmark, its geometric error, its scaling."""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from parproj_ros.geometry import normalize_pair, parameters_from_navigation
from parproj_ros.geometry.epipolar import invert_affine_2x3
from parproj_ros.imaging.resample import (
    OutputGrid,
    SceneGeometry,
    footprint,
    native_pixel,
    resample,
)
from parproj_ros.sim.synthetic import (
    PRINCIPAL_DISTANCE_M,
    stereo_platform,
    texture_blocks,
)

from .config import BenchConfig, Log, log_stderr

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ResampleProblem:
    """A normalized pair's left-scene resampling problem.

    Attributes:
        geom: left scene geometry (exact map from normalized metres to line, sample).
        grid: output grid of lines x detectors pixels (width x height) at the native pixel,
            centred on the scene's footprint.
        lines: input lines.
        detectors: input detectors.
        base_to_height: stereo base-to-height ratio of the pair.
    """

    geom: SceneGeometry
    grid: OutputGrid
    lines: int
    detectors: int
    base_to_height: float


def resample_problem(lines: int, detectors: int) -> ResampleProblem:
    """Navigation-derived parameters of a fore/aft pair, its normalization, the left grid.

    Short scenes get a larger aft lag so that the base-to-height ratio stays above 0.005.
    """
    plat = stereo_platform(lines, detectors)
    nav = [
        parameters_from_navigation(
            plat.model(v, 0), line_mid=(lines - 1) / 2.0, z_avg=0.0, scene_lines=lines
        )
        for v in (0, 1)
    ]
    norm = normalize_pair(
        nav[0].affine, nav[1].affine, left_params=nav[0].params, right_params=nav[1].params
    )
    geom = SceneGeometry(nav[0].frame, norm.left, nav[0].psi, PRINCIPAL_DISTANCE_M)
    fp = footprint(geom, lines, detectors)
    pix = native_pixel(geom)
    cx = 0.5 * (fp[:, 0].min() + fp[:, 0].max())
    cy = 0.5 * (fp[:, 1].min() + fp[:, 1].max())
    grid = OutputGrid(
        pix, cx - pix * (lines - 1) / 2.0, cy - pix * (detectors - 1) / 2.0, lines, detectors
    )
    d1, d2 = nav[0].affine.direction, nav[1].affine.direction
    base = float(np.hypot(*(d1[:2] / d1[2] - d2[:2] / d2[2])))
    return ResampleProblem(geom, grid, lines, detectors, base)


def texture(lines: int, detectors: int, seed: int = 0, block: int = 512) -> NDArray[np.uint16]:
    """A lines x detectors uint16 scene: random 11-bit blocks, tiled and rolled (fast)."""
    blocks = texture_blocks(2, min(block, lines), detectors, seed)
    img = np.empty((lines, detectors), dtype=np.uint16)
    for i, r0 in enumerate(range(0, lines, block)):
        n = min(block, lines - r0)
        img[r0 : r0 + n] = np.roll(blocks[i % 2][:n], (i * 997) % detectors, axis=1)
    return img


def affine_part(pg: ResampleProblem) -> FloatArray:
    """2x3 map (col, row) -> (sample, line) of the exact map without the inverse PTP."""
    g, grid = pg.geom, pg.grid
    inv = invert_affine_2x3(g.to_normalized)
    p, x0, y0 = grid.pixel, grid.x_origin, grid.y_origin
    f = g.frame
    return np.array(
        [
            [
                inv[1, 0] * p / f.pixel_size,
                inv[1, 1] * p / f.pixel_size,
                (inv[1, 0] * x0 + inv[1, 1] * y0 + inv[1, 2]) / f.pixel_size + f.principal_point,
            ],
            [
                inv[0, 0] * p / f.x_per_line,
                inv[0, 1] * p / f.x_per_line,
                (inv[0, 0] * x0 + inv[0, 1] * y0 + inv[0, 2]) / f.x_per_line + f.line_mid,
            ],
        ]
    )


def exact_map(pg: ResampleProblem, r0: int, r1: int) -> tuple[FloatArray, FloatArray]:
    """Exact (line, sample) of output rows [r0, r1) (float64, (r1 - r0, width) each)."""
    grid = pg.grid
    xn = grid.x_origin + grid.pixel * np.arange(grid.width, dtype=float)
    yn = grid.y_origin + grid.pixel * np.arange(r0, r1, dtype=float)
    xg, yg = np.meshgrid(xn, yn)
    return pg.geom.normalized_to_image(xg, yg)


def _best(fn: Callable[[], object], repeats: int) -> float:
    """Fastest wall time of ``repeats`` calls, seconds."""
    best = math.inf
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _warp(image: Any, m: FloatArray, width: int, height: int) -> Any:
    return cv2.warpAffine(
        image,
        m,
        (width, height),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )


def _warp_tiled(
    image: NDArray[np.generic], m: FloatArray, width: int, height: int, tile: int = 512
) -> NDArray[np.generic]:
    """``_warp`` one tile x tile output block at a time (the source window stays in cache)."""
    out = np.empty((height, width), dtype=image.dtype)
    for r0 in range(0, height, tile):
        for c0 in range(0, width, tile):
            nr, nc = min(tile, height - r0), min(tile, width - c0)
            mt = m.copy()
            mt[:, 2] += m[:, 0] * c0 + m[:, 1] * r0
            out[r0 : r0 + nr, c0 : c0 + nc] = _warp(image, mt, nc, nr)
    return out


def geometric_error(
    pg: ResampleProblem, *, margin_px: float = 2.0, block: int = 256
) -> dict[str, Any]:
    """Error of ``resample`` (bilinear) against the exact map, source pixels.

    Two float32 sources hold their own sample and line coordinates; resampled, each output
    pixel holds the (sample, line) that ``resample`` read it from. Compared with
    ``SceneGeometry.normalized_to_image`` in float64 at every output pixel whose exact source
    position lies inside the scene at least ``margin_px`` from its border.

    Returns:
        max_px, rms_px: of the 2-D error length; max_sample_px, max_line_px: per axis; pixels:
        output pixels compared; affine_only_max_px: error of the affine part alone (what
        ``warpAffine`` without the PTP correction would make), on every 16th row and column.
    """
    lines, dets = pg.lines, pg.detectors
    outs = []
    for axis in (1, 0):
        n = dets if axis == 1 else lines
        ramp = np.arange(n, dtype=np.float32)
        src = np.ascontiguousarray(
            np.broadcast_to(ramp if axis == 1 else ramp[:, None], (lines, dets))
        )
        outs.append(resample(src, pg.geom, pg.grid, nodata=-1e6, interpolation=cv2.INTER_LINEAR))
        del src
    out_s, out_l = outs
    sq = 0.0
    count = 0
    emax = es = el = 0.0
    for r0 in range(0, pg.grid.height, block):
        r1 = min(pg.grid.height, r0 + block)
        line, sample = exact_map(pg, r0, r1)
        inside = (
            (line >= margin_px)
            & (line <= lines - 1 - margin_px)
            & (sample >= margin_px)
            & (sample <= dets - 1 - margin_px)
        )
        if not inside.any():
            continue
        ds = (out_s[r0:r1].astype(float) - sample)[inside]
        dl = (out_l[r0:r1].astype(float) - line)[inside]
        e2 = ds**2 + dl**2
        sq += float(e2.sum())
        count += int(e2.size)
        emax = max(emax, float(np.sqrt(e2.max())))
        es = max(es, float(np.abs(ds).max()))
        el = max(el, float(np.abs(dl).max()))
    del outs, out_s, out_l
    # The affine part alone, on a sparse grid.
    m = affine_part(pg)
    rows = np.arange(0, pg.grid.height, 16)
    cols = np.arange(0, pg.grid.width, 16)
    cg, rg = np.meshgrid(cols.astype(float), rows.astype(float))
    xn = pg.grid.x_origin + pg.grid.pixel * cg
    yn = pg.grid.y_origin + pg.grid.pixel * rg
    line, sample = pg.geom.normalized_to_image(xn, yn)
    inside = (line >= 0) & (line <= lines - 1) & (sample >= 0) & (sample <= dets - 1)
    a_s = m[0, 0] * cg + m[0, 1] * rg + m[0, 2]
    a_l = m[1, 0] * cg + m[1, 1] * rg + m[1, 2]
    aff = np.hypot(a_s - sample, a_l - line)[inside]
    return {
        "max_px": emax if count else None,
        "rms_px": math.sqrt(sq / count) if count else None,
        "max_sample_px": es if count else None,
        "max_line_px": el if count else None,
        "pixels": count,
        "margin_px": margin_px,
        "affine_only_max_px": float(aff.max()) if aff.size else None,
    }


def bench_resample(cfg: BenchConfig, log: Log = log_stderr) -> dict[str, Any]:
    """Part 1: Mpx/s of resample, warpAffine, map_coordinates, copyto; geometric error."""
    from scipy import ndimage

    from parproj_ros.imaging import resample as resample_mod

    cv2.setNumThreads(2)
    t_all = time.perf_counter()
    pg = resample_problem(cfg.lines, cfg.detectors)
    grid = pg.grid
    px = grid.width * grid.height
    img = texture(cfg.lines, cfg.detectors)
    log(f"micro: {cfg.lines} x {cfg.detectors} uint16 -> {grid.width} x {grid.height}")

    linear: dict[str, Any] = {"nodata": 0.0, "interpolation": cv2.INTER_LINEAR}
    t_res = _best(partial(resample, img, pg.geom, grid, **linear), cfg.repeats)
    out = resample(img, pg.geom, grid, nodata=0.0, interpolation=cv2.INTER_LINEAR)
    inside = float((out != 0).mean())
    del out
    m = affine_part(pg)
    t_warp = _best(partial(_warp, img, m, grid.width, grid.height), cfg.repeats)
    t_tiled = _best(partial(_warp_tiled, img, m, grid.width, grid.height), cfg.repeats)
    # map_coordinates on a band of rows in the middle, map building included (and apart).
    rows = min(cfg.map_coordinates_rows, grid.height)
    r0 = (grid.height - rows) // 2
    t = time.perf_counter()
    line, sample = exact_map(pg, r0, r0 + rows)
    t_map = time.perf_counter() - t
    t = time.perf_counter()
    ndimage.map_coordinates(img, [line, sample], order=1, mode="constant", cval=0.0)
    t_mc = time.perf_counter() - t
    del line, sample
    scale = px / (rows * grid.width)
    src = np.ones((grid.height, grid.width), dtype=np.uint16)
    dst = np.zeros_like(src)
    t_copy = _best(partial(np.copyto, dst, src), max(3, cfg.repeats))
    del src, dst
    ref = getattr(resample_mod, "resample_remap", None)
    t_remap = None
    if ref is not None:
        t_remap = _best(partial(ref, img, pg.geom, grid, **linear), 1)
    del img
    gc.collect()
    log(f"micro: resample {t_res:.3f} s, warpAffine {t_warp:.3f} s; geometric error ...")
    err = geometric_error(pg)
    gc.collect()
    mpx = px / 1e6
    t_mc_full = (t_map + t_mc) * scale
    res = {
        "input": [cfg.lines, cfg.detectors],
        "output": [grid.width, grid.height],
        "output_inside_footprint": inside,
        "base_to_height": pg.base_to_height,
        "cv2_threads": cv2.getNumThreads(),
        "seconds": {
            "resample": t_res,
            "warpaffine": t_warp,
            "warpaffine_tiled": t_tiled,
            "map_coordinates": t_mc_full,
            "map_coordinates_interpolation_only": t_mc * scale,
            "copyto": t_copy,
            "resample_remap": t_remap,
        },
        "map_coordinates_rows": rows,
        "resample_mpx_s": mpx / t_res,
        "warpaffine_mpx_s": mpx / t_warp,
        "warpaffine_tiled_mpx_s": mpx / t_tiled,
        "map_coordinates_mpx_s": mpx / t_mc_full,
        "map_coordinates_interpolation_only_mpx_s": mpx / (t_mc * scale),
        "copyto_mpx_s": mpx / t_copy,
        "copyto_gb_s": 2 * 2 * px / t_copy / 1e9,
        "resample_remap_mpx_s": None if t_remap is None else mpx / t_remap,
        "resample_vs_warpaffine": t_res / t_warp,
        "resample_vs_warpaffine_tiled": t_res / t_tiled,
        "warpaffine_tiled_vs_warpaffine": t_tiled / t_warp,
        "map_coordinates_vs_warpaffine": t_mc_full / t_warp,
        "copyto_vs_warpaffine": t_copy / t_warp,
        "resample_remap_vs_warpaffine": None if t_remap is None else t_remap / t_warp,
        "geometric_error": err,
        "elapsed_s": time.perf_counter() - t_all,
    }
    return res


def bench_scaling(cfg: BenchConfig, log: Log = log_stderr) -> list[dict[str, Any]]:
    """Part 4: resample and warpAffine times over scene lengths and widths."""
    cv2.setNumThreads(2)
    rows = []
    for lines, dets in cfg.scaling:
        pg = resample_problem(lines, dets)
        img = texture(lines, dets, seed=1)
        g = pg.grid
        t_res = _best(partial(resample, img, pg.geom, pg.grid, nodata=0.0), cfg.repeats)
        m = affine_part(pg)
        t_warp = _best(partial(_warp, img, m, g.width, g.height), cfg.repeats)
        t_tiled = _best(partial(_warp_tiled, img, m, g.width, g.height), cfg.repeats)
        px = g.width * g.height
        rows.append(
            {
                "lines": lines,
                "detectors": dets,
                "mpx": px / 1e6,
                "resample_s": t_res,
                "warpaffine_s": t_warp,
                "warpaffine_tiled_s": t_tiled,
                "resample_mpx_s": px / 1e6 / t_res,
                "resample_ns_per_px": t_res / px * 1e9,
                "resample_vs_warpaffine": t_res / t_warp,
                "resample_vs_warpaffine_tiled": t_res / t_tiled,
            }
        )
        log(
            f"scaling: {lines} x {dets}: resample {t_res:.3f} s, warpAffine {t_warp:.3f} s, "
            f"tiled {t_tiled:.3f} s"
        )
        del img
        gc.collect()
    return rows
