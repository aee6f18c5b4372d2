"""Tie points between the ORIGINAL images of an import, the terrain they measure, RPC biases.

What ``parproj import`` does with them (:func:`measure`), before any virtual point is made:

1. **Features.** Each image is read tile by tile (:func:`features`: memory bounded by one
   tile), at reduced resolution when it is large (GDAL average decimation by an integer factor
   so that its longer side is at most :data:`MAX_SIDE` pixels), stretched to 8 bits (1st-99th
   percentiles), and SIFT key points are detected on it (at most :data:`MAX_FEATURES`, no-data
   masked). Key point positions are scaled back to full-resolution
   pixels of the image (this project's convention, (0, 0) = centre of the first pixel).
2. **Matches**, per pair of images whose footprints overlap: nearest neighbours of the
   descriptors with Lowe's ratio test (:data:`RATIO`), then an RPC-consistency check instead of
   a fundamental matrix (a pushbroom pair has none): each match is triangulated through both
   RPCs (:func:`parproj_ros.rpc.adjust.pair_heights`: the height at which the left point's
   ray projects closest to the right point) and kept if its height lies within the RPC's
   validity span (``height_off +- 1.1 height_scale``) and its distance across the epipolar
   curve (the y-parallax, a few pixels of RPC bias at most, the same for all matches) is within
   max(4 robust sigmas, 1 px) of the median.
3. **Tracks.** Since every pair is matched on the same key points, the matches chain into tie
   points seen in several views (union-find; a chain holding two key points of one image is
   dropped).
4. **Bias adjustment** (with three or more views, unless turned off): one image-space bias per
   view from the tracks (:func:`parproj_ros.rpc.adjust.adjust_biases`, gauge "mean"); the
   importer then uses the corrected RPCs for everything (virtual points, frame, truth points).
5. **Terrain.** The heights of the pairs' matches (triangulated through the corrected RPCs):
   1st / 99th percentiles, plus :func:`padded_range`'s margin; a robust height range is only
   trusted with at least :data:`MIN_TIE_POINTS` matches.

Units: pixels, metres (ellipsoidal heights), degrees.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..imaging.matching import stretch_limits, to_uint8
from ..rpc.adjust import (
    BiasAdjustment,
    adjust_biases,
    apply_biases,
    pair_heights,
    robust_range,
)
from . import raster
from .scene_import import ImportedImage

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Longest side of the image SIFT runs on, pixels (larger images are decimated).
MAX_SIDE = 2048
#: Most SIFT key points per image.
MAX_FEATURES = 6000
#: Side of the tiles SIFT runs on, reduced pixels, and their overlap border.
TILE = 512
TILE_MARGIN = 24
#: Lowe's ratio test.
RATIO = 0.75
#: Fewest consistent matches for a measured terrain range.
MIN_TIE_POINTS = 50
#: Height percentiles of the measured terrain.
PERCENTILES = (1.0, 99.0)
#: Margin added on each side of the measured percentiles: this share of their span ...
MARGIN_SHARE = 0.2
#: ... but at least this, metres.
MIN_MARGIN_M = 25.0
#: Smallest span of the virtual points' heights, metres (the model's height terms need one).
MIN_SPAN_M = 100.0
#: Most tie points the adjustment uses (a bias is a mean: 1500 points of 0.3 px make it good
#: to 0.01 px; more only cost time).
ADJUST_MOST = 1500
#: Refinement at full resolution of tie points found at reduced resolution: half template
#: size (px), smallest correlation peak, most tie points refined.
REFINE_HALF = 10
REFINE_MIN_CORR = 0.8
REFINE_MOST = 2000
#: Rejection of matches across the epipolar curve: robust sigmas, and floor in pixels.
EPIPOLAR_SIGMA = 4.0
EPIPOLAR_FLOOR_PX = 1.0


@dataclass
class Features:
    """SIFT key points of one image.

    Attributes:
        points: (n, 2) (line, sample) full-resolution pixels.
        descriptors: (n, 128) float32.
        factor: decimation factor the detection ran at (1 = full resolution).

    """

    points: FloatArray
    descriptors: NDArray[np.float32]
    factor: int


def read_reduced(
    img: ImportedImage,
    factor: int,
    window: tuple[int, int, int, int] | None = None,
) -> NDArray[np.float32]:
    """A window of one band, GDAL-averaged by ``factor`` (float32; masked pixels 0).

    Args:
        img: the image.
        factor: decimation factor (1 = full resolution).
        window: (row0, col0, rows, cols) in full-resolution pixels; None: the whole image.

    Raises:
        SceneImportError: GDAL cannot read the band.

    """
    from rasterio.enums import Resampling
    from rasterio.errors import RasterioError
    from rasterio.windows import Window

    r0, c0, nr, nc = window if window is not None else (0, 0, img.lines, img.samples)
    shape = (max(1, nr // factor), max(1, nc // factor))
    win = Window(c0, r0, shape[1] * factor, shape[0] * factor)
    with raster._env(), raster._open(img.path) as src:
        try:
            data = src.read(img.band, window=win, out_shape=shape, resampling=Resampling.average)
            mask = src.read_masks(img.band, window=win, out_shape=shape) == 0
        except RasterioError as err:
            raise raster.SceneImportError(
                f"{img.path}: GDAL cannot read band {img.band} for tie points: "
                f"{str(err).splitlines()[0][:160]}"
            ) from None
    a = np.asarray(data, dtype=np.float32)
    a[mask | ~np.isfinite(a)] = 0.0
    return a


def features(img: ImportedImage, max_side: int = MAX_SIDE) -> Features:
    """SIFT key points of an image (module docstring, step 1), tile by tile.

    The image is decimated by k = ceil(longest side / max_side) and cut into tiles of
    :data:`TILE` reduced pixels (plus a :data:`TILE_MARGIN` border, key points kept in the
    core only), each read from the file alone: memory is bounded by one tile's SIFT pyramid,
    whatever the raster's size. Each tile may keep its share (by area) of :data:`MAX_FEATURES`,
    so that the key points spread over the image. The 8-bit stretch (1st-99th percentiles)
    is that of a decimated read of the whole image (at most 512 px a side).
    """
    k = max(1, math.ceil(max(img.lines, img.samples) / max_side))
    overview = read_reduced(img, max(k, math.ceil(max(img.lines, img.samples) / 512)))
    limits = stretch_limits(overview, 0.0)
    del overview
    rl, rs = img.lines // k, img.samples // k  # reduced size
    pts: list[FloatArray] = []
    descs: list[NDArray[np.float32]] = []
    for t0 in range(0, rl, TILE):
        for u0 in range(0, rs, TILE):
            a0, b0 = max(0, t0 - TILE_MARGIN), max(0, u0 - TILE_MARGIN)
            a1, b1 = min(rl, t0 + TILE + TILE_MARGIN), min(rs, u0 + TILE + TILE_MARGIN)
            tile = read_reduced(img, k, (a0 * k, b0 * k, (a1 - a0) * k, (b1 - b0) * k))
            u8 = to_uint8(tile, 0.0, limits)
            if (u8 > 0).mean() < 0.05:
                continue
            share = min(TILE, rl - t0) * min(TILE, rs - u0) / (rl * rs)
            sift = cv2.SIFT.create(nfeatures=max(50, round(MAX_FEATURES * share)))
            kp, desc = sift.detectAndCompute(u8, (u8 > 0).astype(np.uint8))
            if desc is None or not kp:
                continue
            xy = np.array([p.pt for p in kp], dtype=np.float64)  # reduced (col, row)
            xy += np.array([b0, a0], dtype=np.float64)
            core = (
                (xy[:, 1] >= t0 - 0.5)
                & (xy[:, 1] < t0 + TILE - 0.5)
                & (xy[:, 0] >= u0 - 0.5)
                & (xy[:, 0] < u0 + TILE - 0.5)
            )
            # a reduced pixel centre c covers full pixels k c .. k c + k - 1: centre k c + (k-1)/2
            pts.append(np.stack([xy[core, 1], xy[core, 0]], axis=-1) * k + (k - 1) / 2.0)
            descs.append(np.asarray(desc, dtype=np.float32)[core])
    if not pts:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32), k)
    return Features(np.concatenate(pts), np.concatenate(descs), k)


def ratio_matches(a: Features, b: Features, ratio: float = RATIO) -> tuple[IntArray, IntArray]:
    """Indices (ia, ib) of mutual-consistent matches passing Lowe's ratio test."""
    if len(a.points) < 2 or len(b.points) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # approximate nearest neighbours (FLANN k-d trees): exact search costs ~1 s per 6000^2
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    knn = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    ia, ib = [], []
    for m in knn:
        if len(m) == 2 and m[0].distance < ratio * m[1].distance:
            ia.append(m[0].queryIdx)
            ib.append(m[0].trainIdx)
    ia_a, ib_a = np.array(ia, dtype=np.int64), np.array(ib, dtype=np.int64)
    # several left key points on one right one are ambiguous: drop them all
    uniq, counts = np.unique(ib_a, return_counts=True)
    single = np.isin(ib_a, uniq[counts == 1])
    return ia_a[single], ib_a[single]


@dataclass
class PairMatches:
    """Consistent matches of one pair (indices into each image's key points).

    Attributes:
        left: index of the left image (in the import's order).
        right: index of the right image.
        ia: key point indices in the left image.
        ib: key point indices in the right image.
        heights: triangulated heights through the RPCs (as given), metres.
        y_parallax_px: median distance across the epipolar curve, pixels.
        candidates: matches after the ratio test, before the RPC check.

    """

    left: int
    right: int
    ia: IntArray
    ib: IntArray
    heights: FloatArray
    y_parallax_px: float
    candidates: int


def rpc_check(
    left: ImportedImage,
    right: ImportedImage,
    pl: FloatArray,
    pr: FloatArray,
    floor_px: float = EPIPOLAR_FLOOR_PX,
) -> tuple[NDArray[np.bool_], FloatArray, FloatArray]:
    """(consistent mask, heights m, y-parallax px) of matches ``pl`` -> ``pr`` (step 2).

    ``floor_px``: floor of the rejection threshold across the epipolar curve, full-resolution
    pixels (key points found at a decimation k are good to about k / 3 px: k x the default).
    """
    r = left.rpc
    span = (r.height_off - 0.5 * abs(r.height_scale), r.height_off + 0.5 * abs(r.height_scale))
    h, across, _ = pair_heights(left.rpc, right.rpc, pl, pr, span)
    lo, hi = r.height_off - 1.1 * abs(r.height_scale), r.height_off + 1.1 * abs(r.height_scale)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(h) & np.isfinite(across) & (h >= lo) & (h <= hi)
    for _ in range(3):
        if not np.any(ok):
            break
        med = float(np.median(across[ok]))
        sigma = 1.4826 * float(np.median(np.abs(across[ok] - med)))
        with np.errstate(invalid="ignore"):
            ok = ok & (np.abs(across - med) <= max(EPIPOLAR_SIGMA * sigma, floor_px))
    return np.asarray(ok), h, across


def tracks(feats: Sequence[Features], pairs: Sequence[PairMatches]) -> FloatArray:
    """(n, V, 2) (line, sample) of each chained tie point per view, NaN where not seen (step 3)."""
    offsets = np.cumsum([0] + [len(f.points) for f in feats])
    parent = np.arange(int(offsets[-1]))

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = int(parent[root])
        while parent[x] != root:
            parent[x], x = root, int(parent[x])
        return root

    used = np.zeros(int(offsets[-1]), dtype=bool)
    for pm in pairs:
        ga, gb = pm.ia + offsets[pm.left], pm.ib + offsets[pm.right]
        used[ga] = used[gb] = True
        for x, y in zip(ga.tolist(), gb.tolist(), strict=True):
            rx, ry = find(x), find(y)
            if rx != ry:
                parent[ry] = rx
    nodes = np.flatnonzero(used)
    roots = np.array([find(int(x)) for x in nodes], dtype=np.int64)
    view = np.searchsorted(offsets, nodes, side="right") - 1
    uniq, tid = np.unique(roots, return_inverse=True)
    nv = len(feats)
    obs = np.full((len(uniq), nv, 2), np.nan)
    hits = np.zeros((len(uniq), nv), dtype=np.int64)
    np.add.at(hits, (tid, view), 1)
    for node, t, v in zip(nodes.tolist(), tid.tolist(), view.tolist(), strict=True):
        obs[t, v] = feats[v].points[node - offsets[v]]
    conflict = np.any(hits > 1, axis=1)  # two key points of one image in one chain
    return np.asarray(obs[~conflict], dtype=np.float64)


def _strongest(obs: FloatArray, most: int) -> FloatArray:
    """At most ``most`` tie points: those seen in most views, in a seeded random order."""
    if obs.shape[0] <= most:
        return obs
    rng = np.random.default_rng(0)
    shuffled = obs[rng.permutation(obs.shape[0])]
    count = np.all(np.isfinite(shuffled), axis=2).sum(axis=1)
    return np.asarray(shuffled[np.argsort(-count, kind="stable")[:most]], dtype=np.float64)


def refine_tracks(
    images: Sequence[ImportedImage],
    obs: FloatArray,
    search_px: int,
    *,
    half: int = REFINE_HALF,
    min_corr: float = REFINE_MIN_CORR,
    most: int = REFINE_MOST,
) -> FloatArray:
    """Tie points found at reduced resolution, refined at full resolution by correlation.

    For each tie point (at most ``most``, the ones seen in most views first), a
    (2 half + 1)^2 px template of its first view, centred on the rounded key point, is searched
    within +- ``search_px`` px of the key point in every other view (normalized
    cross-correlation, sub-pixel by a parabola through the peak and its neighbours along each
    axis); an observation whose peak is below ``min_corr`` or on the search border is dropped.
    Windows are read from the files one by one (memory: one window).

    Returns:
        (m, V, 2) refined (line, sample), full-resolution pixels, NaN where not seen.

    """
    from rasterio.windows import Window

    seen = np.all(np.isfinite(obs), axis=2)
    order = np.argsort(-seen.sum(axis=1), kind="stable")[:most]
    sub = obs[order]
    out = np.full(sub.shape, np.nan)
    srcs = [raster._open(img.path) for img in images]
    try:
        with raster._env():

            def window(v: int, r: int, c: int, rad: int) -> NDArray[np.float32] | None:
                img = images[v]
                if r - rad < 0 or c - rad < 0 or r + rad >= img.lines or c + rad >= img.samples:
                    return None
                w = srcs[v].read(
                    img.band, window=Window(c - rad, r - rad, 2 * rad + 1, 2 * rad + 1)
                )
                a = np.asarray(w, dtype=np.float32)
                return None if not np.all(a != 0) else a

            for t in range(sub.shape[0]):
                views = np.flatnonzero(np.all(np.isfinite(sub[t]), axis=1))
                r0, c0 = (round(float(x)) for x in sub[t, views[0]])
                tpl = window(int(views[0]), r0, c0, half)
                if tpl is None or float(tpl.std()) == 0.0:
                    continue
                out[t, views[0]] = (r0, c0)
                for v in views[1:]:
                    r1, c1 = (round(float(x)) for x in sub[t, v])
                    win = window(int(v), r1, c1, half + search_px)
                    if win is None:
                        continue
                    res = cv2.matchTemplate(win, tpl, cv2.TM_CCOEFF_NORMED)
                    _, peak, _, (px, py) = cv2.minMaxLoc(res)
                    if (
                        peak < min_corr
                        or px in (0, res.shape[1] - 1)
                        or py in (0, res.shape[0] - 1)
                    ):
                        continue
                    dy = _parabola(res[py - 1, px], res[py, px], res[py + 1, px])
                    dx = _parabola(res[py, px - 1], res[py, px], res[py, px + 1])
                    out[t, v] = (r1 - search_px + py + dy, c1 - search_px + px + dx)
    finally:
        for src in srcs:
            src.close()
    keep = np.all(np.isfinite(out), axis=2).sum(axis=1) >= 2
    return np.asarray(out[keep], dtype=np.float64)


def _parabola(a: float, b: float, c: float) -> float:
    """Sub-pixel offset of the extremum of a parabola through (-1, a), (0, b), (1, c)."""
    d = a - 2.0 * b + c
    return 0.0 if d == 0 else 0.5 * (a - c) / d


def padded_range(lo: float, hi: float) -> tuple[float, float]:
    """The virtual points' height range from measured percentiles (lo, hi), metres.

    A margin of max(:data:`MARGIN_SHARE` x (hi - lo), :data:`MIN_MARGIN_M`) on each side (the
    percentiles leave the highest and lowest 1 % of the ground out, and a pair that was not
    matched may see a little more), then widened about its centre to at least
    :data:`MIN_SPAN_M`: the parallel-projection model has height terms, fitted from the spread
    of the virtual points' heights; exact RPC points make them well determined over 100 m, and
    the model error of a fit grows with its span, so a flat scene gets 100 m, not the RPC's
    several hundred.
    """
    m = max(MARGIN_SHARE * (hi - lo), MIN_MARGIN_M)
    a, b = lo - m, hi + m
    if b - a < MIN_SPAN_M:
        c = 0.5 * (a + b)
        a, b = c - 0.5 * MIN_SPAN_M, c + 0.5 * MIN_SPAN_M
    return a, b


@dataclass
class TieResult:
    """What :func:`measure` found.

    Attributes:
        pairs: per matched pair, its consistent matches.
        adjustment: the bias adjustment, or None (not asked, too few views or tie points).
        adjust_note: why there is no adjustment (empty when there is one).
        heights: triangulated heights of the pairs' consistent matches (through the corrected
            RPCs when adjusted), metres.
        measured: (p1, p99) of ``heights``, metres, or None with fewer than
            :data:`MIN_TIE_POINTS`.
        padded: the virtual points' range from ``measured`` (:func:`padded_range`), or None.
        seconds: wall time, s.
        rows: per pair, a summary for the import summary.
        observations: (n, V, 2) the chained tie points (:func:`tracks`), pixels, NaN where a
            view does not see one (empty unless the adjustment ran).
        lonlat: (n, 2) longitude, latitude of each of ``heights``' points (the left image's
            point localized at its height), degrees, NaN where that fails.

    """

    pairs: list[PairMatches] = field(default_factory=list)
    adjustment: BiasAdjustment | None = None
    adjust_note: str = ""
    heights: FloatArray = field(default_factory=lambda: np.zeros(0))
    measured: tuple[float, float] | None = None
    padded: tuple[float, float] | None = None
    seconds: float = 0.0
    rows: list[dict[str, Any]] = field(default_factory=list)
    observations: FloatArray = field(default_factory=lambda: np.zeros((0, 0, 2)))
    lonlat: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


def measure(
    images: Sequence[ImportedImage],
    pairs: Sequence[tuple[int, int]],
    *,
    adjust: bool,
    max_side: int = MAX_SIDE,
) -> TieResult:
    """Tie points, bias adjustment and terrain of the images (module docstring, steps 1-5).

    Args:
        images: the checked images (footprints known).
        pairs: (left, right) indices of the pairs to match (every overlapping pair is useful
            to the adjustment; the terrain comes from these pairs' matches).
        adjust: estimate per-view biases (needs three or more views with tracks).
        max_side: longest side SIFT runs on, pixels.

    Returns:
        The result (:class:`TieResult`); ``images`` are not changed.

    """
    t0 = time.perf_counter()
    feats = [features(img, max_side) for img in images]
    k = max(f.factor for f in feats)
    out = TieResult()
    for a, b in pairs:
        ia, ib = ratio_matches(feats[a], feats[b])
        pl, pr = feats[a].points[ia], feats[b].points[ib]
        ok, h, across = (
            rpc_check(images[a], images[b], pl, pr, EPIPOLAR_FLOOR_PX * k)
            if ia.size
            else (np.zeros(0, bool), np.zeros(0), np.zeros(0))
        )
        out.pairs.append(
            PairMatches(
                a,
                b,
                ia[ok],
                ib[ok],
                h[ok],
                float(np.median(across[ok])) if np.any(ok) else math.nan,
                int(ia.size),
            )
        )
    rpcs = [img.rpc for img in images]
    if adjust:
        if len(images) < 3:
            out.adjust_note = "two views cannot fix their relative bias"
        else:
            out.observations = _strongest(tracks(feats, out.pairs), ADJUST_MOST)
            if k > 1:  # key points of a decimated image: refine at full resolution
                out.observations = refine_tracks(images, out.observations, k + 2)
            try:
                out.adjustment = adjust_biases(
                    rpcs, out.observations, names=[img.scene_id for img in images]
                )
            except ValueError as err:
                out.adjust_note = str(err)
    if out.adjustment is not None:
        rpcs = apply_biases(rpcs, out.adjustment.biases)
    hs, lls = [], []
    for pm in out.pairs:
        if pm.ia.size == 0:
            continue
        left = rpcs[pm.left]
        span = (
            left.height_off - 0.5 * abs(left.height_scale),
            left.height_off + 0.5 * abs(left.height_scale),
        )
        h, _, _ = pair_heights(
            left, rpcs[pm.right], feats[pm.left].points[pm.ia], feats[pm.right].points[pm.ib],
            span,
        )  # fmt: skip
        pm.heights = h
        hs.append(h)
        pts = feats[pm.left].points[pm.ia]
        with np.errstate(invalid="ignore"):
            lon, lat = left.localize(pts[:, 0], pts[:, 1], h, outside="nan")
        lls.append(np.stack([lon, lat], axis=-1))
        lo, hi = robust_range(h, low=PERCENTILES[0], high=PERCENTILES[1])
        out.rows.append(
            {
                "left": images[pm.left].scene_id,
                "right": images[pm.right].scene_id,
                "candidates": pm.candidates,
                "consistent": int(pm.ia.size),
                "y_parallax_px": pm.y_parallax_px,
                "heights_p1_p99": [lo, hi],
            }
        )
    out.heights = np.concatenate(hs) if hs else np.zeros(0)
    out.lonlat = np.concatenate(lls) if lls else np.zeros((0, 2))
    n = int(np.isfinite(out.heights).sum())
    if n >= MIN_TIE_POINTS:
        out.measured = robust_range(out.heights, low=PERCENTILES[0], high=PERCENTILES[1])
        out.padded = padded_range(*out.measured)
    out.seconds = time.perf_counter() - t0
    return out


def _pairs_text(images: Sequence[ImportedImage], pairs: Sequence[PairMatches]) -> str:
    used = [pm for pm in pairs if pm.ia.size]
    if not used:  # none matched: name the images searched, not "of 0 pairs ()"
        if len(images) == 2:
            return f"between {images[0].scene_id} and {images[1].scene_id}"
        return f"among the {len(images)} images"
    if len(used) == 1:
        return f"between {images[used[0].left].scene_id} and {images[used[0].right].scene_id}"
    names = ", ".join(f"{images[p.left].scene_id}:{images[p.right].scene_id}" for p in used)
    return f"of {len(used)} pairs ({names})"


#: Matches after the ratio test from which a pair's share agreeing with the RPCs is judged,
#: and the share under which the import warns (real Pléiades pairs: 96-99 %; the Ventoux pair
#: with its RPCs swapped: 13 of 506).
FEW_CONSISTENT_MIN = 100
FEW_CONSISTENT_SHARE = 0.25


def import_ties(
    images: Sequence[ImportedImage],
    heights: Any,
    *,
    measure_terrain: bool,
    adjust: bool | None,
    tie_points: bool = True,
    log: Callable[[str], None] = print,
) -> tuple[list[ImportedImage], Any, dict[str, Any]]:
    """The importer's use of :func:`measure`: corrected images, heights, a summary.

    Args:
        images: the checked images.
        heights: the prior: (hmin, hmax) metres (given, or the RPC span) or a DEM function.
        measure_terrain: replace the prior by the measured range (no ``--heights`` nor
            ``--dem`` given) when :data:`MIN_TIE_POINTS` matches agree.
        adjust: bias adjustment on / off; None: on with three or more images.
        tie_points: False: match nothing, keep the RPCs and the prior (one line says so).
        log: where the lines go (one per pair, one per adjusted view, one for the heights).

    Returns:
        (images, with the corrected RPCs when adjusted; the heights to use; a JSON-able
        summary: ``heights_source`` ("tie points", "RPC span", "given", "DEM"),
        ``heights_note`` (the line logged), ``pairs`` (per pair figures), ``adjustment``).

    """
    out_images = list(images)
    summary: dict[str, Any] = {}
    prior = "DEM" if callable(heights) else ("RPC span" if measure_terrain else "given")

    def prior_text() -> str:
        if callable(heights):
            return "heights from the DEM (--dem), +- the DEM margin"
        lo, hi = (float(v) for v in heights)
        return f"heights {lo:.0f}..{hi:.0f} m " + (
            "from the RPC span" if measure_terrain else "as given (--heights)"
        )

    if not tie_points:
        summary["heights_source"] = prior
        summary["heights_note"] = prior_text() + " (tie points not measured)"
        log(summary["heights_note"])
        return out_images, heights, summary
    do_adjust = len(images) >= 3 if adjust is None else adjust
    res = measure(images, overlapping_pairs(images), adjust=do_adjust)
    summary["pairs"] = res.rows
    summary["seconds"] = res.seconds
    for row in res.rows:
        lo, hi = row["heights_p1_p99"]
        log(
            f"tie points {row['left']}:{row['right']}: {row['candidates']} matched, "
            f"{row['consistent']} consistent with the RPCs (y-parallax {row['y_parallax_px']:+.2f}"
            f" px); heights (percentiles 1-99) {lo:.0f}..{hi:.0f} m"
        )
        cand, cons = int(row["candidates"]), int(row["consistent"])
        if cand >= FEW_CONSISTENT_MIN and cons < FEW_CONSISTENT_SHARE * cand:
            log(
                f"warning: only {cons} of the {cand} matches between {row['left']} and "
                f"{row['right']} agree with their RPCs (y-parallax {row['y_parallax_px']:+.2f} "
                "px; real pairs: over 90 %): the RPCs may not belong to these images (swapped "
                "--rpc-left / --rpc-right, or of another scene or crop?)"
            )
    a = res.adjustment
    if a is not None:
        views: dict[str, Any] = {}
        for v, img in enumerate(images):
            b = a.biases[v]
            views[img.scene_id] = {
                "bias_line_sample_px": [float(b[0]), float(b[1])],
                "rms_before_px": float(a.rms_before[v]),
                "rms_after_px": float(a.rms_after[v]),
                "observations": int(a.observations[v]),
            }
            log(
                f"RPC bias {img.scene_id}: line {b[0]:+.3f} px, sample {b[1]:+.3f} px; "
                f"residuals rms {a.rms_before[v]:.3f} -> {a.rms_after[v]:.3f} px "
                f"({a.observations[v]} observations)"
            )
        summary["adjustment"] = {
            "views": views,
            "tie_points": a.tracks,
            "in_three_or_more_views": a.multi_tracks,
            "gauge": str(a.gauge),
            "ground_shift_enu_m": [float(x) for x in a.shift_m],
        }
        log(
            f"RPC bias adjustment: {a.tracks} tie points ({a.multi_tracks} in 3+ views), "
            f"gauge: mean of the views; the tie points moved by "
            f"{', '.join(f'{x:+.2f}' for x in a.shift_m)} m (E, N, U)"
        )
        corrected = apply_biases([img.rpc for img in images], a.biases)
        out_images = [
            dataclasses.replace(img, rpc=r) for img, r in zip(images, corrected, strict=True)
        ]
    elif do_adjust or adjust:
        log(f"warning: no RPC bias adjustment: {res.adjust_note}")
    n = int(np.isfinite(res.heights).sum())
    where = _pairs_text(images, res.pairs)
    if measure_terrain and res.padded is not None and res.measured is not None:
        h: Any = res.padded
        summary["heights_source"] = "tie points"
        summary["heights_note"] = (
            f"heights {h[0]:.0f}..{h[1]:.0f} m from {n:,} tie points {where} (percentiles "
            f"1-99 {res.measured[0]:.0f}..{res.measured[1]:.0f} m, plus a margin)"
        )
    elif measure_terrain:
        h = heights
        summary["heights_source"] = prior
        summary["heights_note"] = (
            f"warning: {prior_text()}: only {n} tie points {where} ({MIN_TIE_POINTS} needed to "
            "measure the terrain); give --heights HMIN HMAX or --dem if the terrain lies "
            "elsewhere"
        )
    else:
        h = heights
        summary["heights_source"] = prior
        summary["heights_note"] = prior_text()
        if res.measured is not None:
            m0, m1 = res.measured
            summary["heights_note"] += f" (the tie points measure {m0:.0f}..{m1:.0f} m)"
            if not callable(heights) and (m0 < float(heights[0]) or m1 > float(heights[1])):
                summary["heights_note"] = (
                    "warning: " + summary["heights_note"] + ": the terrain reaches outside "
                    "the given heights; widen --heights or leave it out to use the measured ones"
                )
    if res.measured is not None:
        summary["measured_p1_p99"] = [float(x) for x in res.measured]
    summary["tie_points"] = n
    log(summary["heights_note"])
    if callable(heights):
        offset = dem_offset(heights, res)
        if offset is not None:
            summary["dem_offset_m"] = {"median": offset[0], "nmad": offset[1], "points": offset[2]}
            warning = dem_offset_warning(heights, offset)
            if warning:
                summary["dem_warning"] = warning
                log(warning)
    return out_images, h, summary


def dem_offset(dem: Callable[..., Any], res: TieResult) -> tuple[float, float, int] | None:
    """How far the tie points' heights lie from the DEM's at the same places, metres.

    The tie points' triangulated (ellipsoidal) heights less the DEM's (with its geoid) where
    each tie point lies (:attr:`TieResult.lonlat`): (median, NMAD, points compared), or None
    with fewer than :data:`MIN_TIE_POINTS` points where both have a height.
    """
    if res.lonlat.shape[0] != res.heights.size:
        return None
    ok = np.isfinite(res.heights) & np.isfinite(res.lonlat).all(axis=1)
    if int(ok.sum()) < MIN_TIE_POINTS:
        return None
    lon, lat = res.lonlat[ok, 0], res.lonlat[ok, 1]
    d = res.heights[ok] - np.asarray(dem(lon, lat), dtype=float)
    d = d[np.isfinite(d)]
    if d.size < MIN_TIE_POINTS:
        return None
    med = float(np.median(d))
    return med, float(1.4826 * np.median(np.abs(d - med))), int(d.size)


def dem_offset_warning(dem: Any, offset: tuple[float, float, int]) -> str | None:
    """A warning when the tie points lie over :data:`DISAGREE_M` from the DEM (else None).

    A median offset of tens of metres is a vertical reference other than the one given (an
    SRTM-like DEM above the geoid imported without ``--geoid``: some +50 m in southern
    France), or a DEM of another place or time; the virtual points then follow the DEM, not
    the terrain the images show.
    """
    from ..core.terrain import DISAGREE_M
    from .dem import DemHeights

    med, nmad, n = offset
    if abs(med) <= DISAGREE_M:
        return None
    where = "above" if med > 0 else "below"
    if not isinstance(dem, DemHeights):  # a height function of the API: no file, no options
        return (
            f"warning: the tie points lie {abs(med):.0f} m {where} the DEM's heights at the "
            f"same places (median of {n} points, NMAD {nmad:.1f} m; more than "
            f"{DISAGREE_M:.0f} m): check that they are ellipsoidal (WGS84), or the DEM is of "
            "another place or time. The virtual points follow the DEM"
        )
    advice = (
        "the DEM's heights above the geoid? give --geoid egm2008 (or --geoid-undulation N)"
        if med > 0 and dem.geoid in (None, 0.0)
        else "check its vertical reference (--geoid, --geoid-undulation, --dem-ellipsoidal)"
    )
    return (
        f"warning: the tie points lie {abs(med):.0f} m {where} the DEM {dem.label}, read with "
        f"{dem.reference}, at the same places (median of {n} points, NMAD {nmad:.1f} m; more "
        f"than {DISAGREE_M:.0f} m): "
        f"{advice}, or the DEM is of another place or time. The virtual points follow the DEM"
    )


def overlapping_pairs(images: Sequence[ImportedImage]) -> list[tuple[int, int]]:
    """Every (i, j), i < j, whose footprints (from the import checks) intersect."""
    from .scene_import import footprints_overlap

    return [
        (i, j)
        for i, j in itertools.combinations(range(len(images)), 2)
        if footprints_overlap(images[i], images[j])
    ]


__all__ = [
    "Features",
    "PairMatches",
    "TieResult",
    "dem_offset",
    "dem_offset_warning",
    "features",
    "import_ties",
    "measure",
    "overlapping_pairs",
    "padded_range",
    "ratio_matches",
    "rpc_check",
    "tracks",
]
