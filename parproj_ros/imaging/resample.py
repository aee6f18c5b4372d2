"""Resampling scenes into the normalized (epipolar) geometry with OpenCV.

The map of an output pixel is exact: normalized pixel -> normalized metres -> inverse of the
scene's 2x3 normalization affine -> parallel scene coordinates (x, y') -> inverse PTP (Eq 7) ->
perspective y -> (line, sample) of the original scene. ``cv2.remap`` then interpolates with
the kernel the ``interpolation`` parameter names, a row of
:data:`parproj_ros.imaging.kernels.KERNELS` (its OpenCV flag: :func:`kernel_flag`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.epipolar import invert_affine_2x3
from ..geometry.navigation import SceneFrame
from ..geometry.ptp import ptp_inverse
from .encodings import DTYPE_ENCODINGS
from .kernels import kernel

FloatArray = NDArray[np.float64]

#: Supported pixel types (numpy dtype -> ROS encoding of a single-channel image).
ENCODINGS = DTYPE_ENCODINGS


def kernel_flag(name: str) -> int:
    """OpenCV interpolation flag of the kernel ``name`` (a row of ``imaging.kernels.KERNELS``).

    Raises:
        ValueError: not a kernel of the table (the known ones named).

    """
    return int(getattr(cv2, kernel(name).opencv))


@dataclass(frozen=True)
class SceneGeometry:
    """What the resampler needs to know of one original scene.

    Attributes:
        frame: image (line, sample) <-> scene metres (x, perspective y).
        to_normalized: 2x3 affine, parallel scene metres (x, y') -> normalized metres.
        psi: roll for the PTP correction, radians.
        principal_distance: c, metres.
    """

    frame: SceneFrame
    to_normalized: FloatArray
    psi: float
    principal_distance: float

    def normalized_to_image(self, xn: FloatArray, yn: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Normalized metres -> (line, sample) in the original scene (exact)."""
        inv = invert_affine_2x3(self.to_normalized)
        x = inv[0, 0] * xn + inv[0, 1] * yn + inv[0, 2]
        yp = inv[1, 0] * xn + inv[1, 1] * yn + inv[1, 2]
        y = ptp_inverse(yp, self.principal_distance, self.psi)
        ls = self.frame.to_image(x, y)
        return ls[..., 0], ls[..., 1]

    def image_to_normalized(self, line: FloatArray, sample: FloatArray) -> FloatArray:
        """(line, sample) -> normalized metres (..., 2) (exact; PTP applied)."""
        from ..geometry.ptp import ptp_forward

        xy = self.frame.to_scene(line, sample)
        xy[..., 1] = ptp_forward(xy[..., 1], self.principal_distance, self.psi)
        h = self.to_normalized
        return np.asarray(xy @ h[:, :2].T + h[:, 2], dtype=float)


@dataclass(frozen=True)
class OutputGrid:
    """Normalized image grid: ``col = (x_n - x_origin) / pixel``, same for rows with y.

    Attributes:
        pixel: normalized metres per output pixel.
        x_origin: normalized x (metres) at the centre of output column 0.
        y_origin: normalized y (metres) at the centre of output row 0.
        width: columns.
        height: rows.
    """

    pixel: float
    x_origin: float
    y_origin: float
    width: int
    height: int


def footprint(geom: SceneGeometry, lines: int, detectors: int, samples: int = 16) -> FloatArray:
    """Normalized metres of the scene border (4 * samples points, (n, 2))."""
    t = np.linspace(0.0, 1.0, samples)
    ll = np.concatenate(
        [t * (lines - 1), np.full_like(t, lines - 1.0), (1 - t) * (lines - 1), np.zeros_like(t)]
    )
    ss = np.concatenate(
        [
            np.zeros_like(t),
            t * (detectors - 1),
            np.full_like(t, detectors - 1.0),
            (1 - t) * (detectors - 1),
        ]
    )
    return geom.image_to_normalized(ll, ss)


def native_pixel(geom: SceneGeometry) -> float:
    """Smallest normalized length of one original pixel step (line or sample), metres."""
    h = geom.to_normalized
    return float(
        min(
            np.linalg.norm(h[:, 0]) * abs(geom.frame.x_per_line),
            np.linalg.norm(h[:, 1]) * geom.frame.pixel_size,
        )
    )


@dataclass(frozen=True)
class Tile:
    """One output tile and the affine map that stands for the exact one on it.

    Attributes:
        row0: first output row.
        col0: first output column.
        rows: tile height, pixels.
        cols: tile width, pixels.
        affine: 2x3, (col - col0, row - row0) -> (sample, line) of the source scene.
        max_error_px: largest distance between the affine and the exact map found on the
            tile's check grid, source pixels.
    """

    row0: int
    col0: int
    rows: int
    cols: int
    affine: FloatArray
    max_error_px: float


def _exact_map(
    geom: SceneGeometry, grid: OutputGrid, cols: FloatArray, rows: FloatArray
) -> tuple[FloatArray, FloatArray]:
    xn = grid.x_origin + grid.pixel * cols
    yn = grid.y_origin + grid.pixel * rows
    line, sample = geom.normalized_to_image(xn, yn)
    return sample, line


def _fit_tiles(
    geom: SceneGeometry,
    grid: OutputGrid,
    boxes: list[tuple[int, int, int, int]],
    check: int = 5,
) -> list[Tile]:
    """Least-squares affine of the exact map over a check x check grid of each tile.

    Vectorised: the exact map is evaluated for all tiles in one call, and tiles of the same
    size share one pseudo-inverse of their (identical) design matrix.
    """
    out: list[Tile] = []
    sizes: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for r0, c0, nr, nc in boxes:
        sizes.setdefault((nr, nc), []).append((r0, c0))
    u = np.linspace(0.0, 1.0, check)
    for (nr, nc), origins in sizes.items():
        cg, rg = np.meshgrid(u * (nc - 1.0), u * (nr - 1.0))
        design = np.column_stack([cg.ravel(), rg.ravel(), np.ones(cg.size)])
        pinv = np.linalg.pinv(design)  # (3, k)
        o = np.array(origins, dtype=float)  # (n, 2) as (r0, c0)
        cols = o[:, 1:2] + cg.ravel()[None, :]
        rows = o[:, 0:1] + rg.ravel()[None, :]
        sample, line = _exact_map(geom, grid, cols, rows)  # (n, k) each
        vals = np.stack([sample, line], axis=-1)  # (n, k, 2)
        coef = np.einsum("jk,nkc->njc", pinv, vals)  # (n, 3, 2)
        err = np.einsum("kj,njc->nkc", design, coef) - vals
        emax = np.hypot(err[..., 0], err[..., 1]).max(axis=1)
        affines = coef.transpose(0, 2, 1)  # (n, 2, 3): each tile's cf.T, a view of coef
        out.extend(
            Tile(r0, c0, nr, nc, aff, e)
            for (r0, c0), aff, e in zip(origins, affines, emax.tolist(), strict=True)
        )
    return out


def plan_tiles(
    geom: SceneGeometry,
    grid: OutputGrid,
    *,
    tile: int = 512,
    tolerance_px: float = 0.004,
    min_tile: int = 16,
    tile_rows: int | None = None,
) -> list[Tile]:
    """Cover the output grid with tiles on which an affine map is within ``tolerance_px``.

    The exact map is an affine map followed by the inverse PTP correction, a smooth 1-D
    function of one coordinate, so its deviation from the best affine fit grows with the square
    of the tile size: tiles that miss the tolerance are split in four until they meet it.
    Tiles are ``tile_rows`` (default ``tile``) rows by ``tile`` columns.
    """
    out: list[Tile] = []
    rows = tile if tile_rows is None else int(tile_rows)
    todo = [
        (r0, c0, min(rows, grid.height - r0), min(tile, grid.width - c0))
        for r0 in range(0, grid.height, rows)
        for c0 in range(0, grid.width, tile)
    ]
    while todo:
        split: list[tuple[int, int, int, int]] = []
        for t in _fit_tiles(geom, grid, todo):
            if t.max_error_px <= tolerance_px or max(t.rows, t.cols) <= min_tile:
                out.append(t)
                continue
            hr, hc = max(1, t.rows // 2), max(1, t.cols // 2)
            for rr0, rn in ((t.row0, hr), (t.row0 + hr, t.rows - hr)):
                for cc0, cn in ((t.col0, hc), (t.col0 + hc, t.cols - hc)):
                    if rn > 0 and cn > 0:
                        split.append((rr0, cc0, rn, cn))
        todo = split
    return out


def resample(
    image: NDArray[np.generic],
    geom: SceneGeometry,
    grid: OutputGrid,
    *,
    nodata: float = 0.0,
    interpolation: int = cv2.INTER_LINEAR,
    tile: int = 512,
    tolerance_px: float = 0.004,
    out: NDArray[np.generic] | None = None,
    row_offset: int = 0,
) -> NDArray[np.generic]:
    """Resample one original scene (lines, detectors) onto ``grid``; outside the scene: nodata.

    The output is cut into tiles on each of which the exact map (normalization affine, then
    inverse PTP) is replaced by its best affine fit, within ``tolerance_px`` source pixels
    (:func:`plan_tiles`); each tile is one ``cv2.warpAffine``, so no per-pixel map is built.
    The output dtype is the input's (uint8, uint16 or float32).

    ``out`` and ``row_offset`` let a caller fill rows [row_offset, row_offset + len(out)) of a
    larger grid (streaming); ``grid.height`` is then the full height.
    """
    if image.dtype not in ENCODINGS:
        raise ValueError(f"unsupported pixel type {image.dtype}; use uint8, uint16 or float32")
    if out is None:
        out = np.empty((grid.height - row_offset, grid.width), dtype=image.dtype)
    sub = OutputGrid(
        grid.pixel,
        grid.x_origin,
        grid.y_origin + row_offset * grid.pixel,
        grid.width,
        out.shape[0],
    )
    flags = interpolation | cv2.WARP_INVERSE_MAP
    for t in plan_tiles(geom, sub, tile=tile, tolerance_px=tolerance_px):
        m = t.affine.copy()
        out[t.row0 : t.row0 + t.rows, t.col0 : t.col0 + t.cols] = cv2.warpAffine(
            cast("NDArray[Any]", image),
            m,
            (t.cols, t.rows),
            flags=flags,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float(nodata),
        )
    return out


def resample_remap(
    image: NDArray[np.generic],
    geom: SceneGeometry,
    grid: OutputGrid,
    *,
    nodata: float = 0.0,
    interpolation: int = cv2.INTER_LINEAR,
    block_rows: int = 256,
) -> NDArray[np.generic]:
    """Reference resampler: the exact map built per pixel, then ``cv2.remap`` (slower).

    Kept to measure :func:`resample` against (geometric error and speed).
    """
    if image.dtype not in ENCODINGS:
        raise ValueError(f"unsupported pixel type {image.dtype}; use uint8, uint16 or float32")
    out = np.empty((grid.height, grid.width), dtype=image.dtype)
    cols = np.arange(grid.width, dtype=float)
    for r0 in range(0, grid.height, block_rows):
        r1 = min(grid.height, r0 + block_rows)
        cg, rg = np.meshgrid(cols, np.arange(r0, r1, dtype=float))
        sample, line = _exact_map(geom, grid, cg, rg)
        out[r0:r1] = cv2.remap(
            cast("NDArray[Any]", image),
            sample.astype(np.float32),
            line.astype(np.float32),
            interpolation,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float(nodata),
        )
    return out


def render_block(
    block: Any,
    data: NDArray[np.generic],
    first_line: int,
    grid: OutputGrid | None,
    *,
    nodata: float,
    interpolation: int,
    out: NDArray[np.generic] | None = None,
    stride: int = 1,
) -> NDArray[np.generic]:
    """Resample one column block from the retained lines ``data`` (line ``first_line`` first).

    ``block``: a streamed column block (``core.streaming``): its ``cols`` and ``tiles``.
    ``stride``: every ``stride``-th row and column only, each sampled at the centre of its
    ``stride`` x ``stride`` pixels (``height // stride`` x ``cols // stride``; the last rows
    and columns that do not fill a stride are dropped, as :func:`reduce_block` drops them).

    Into ``out`` (grid height x block columns, of the data's type, or the strided shape) when
    given, else a new array.
    """
    s = int(stride)
    if out is None:
        if grid is None:
            raise ValueError("render_block needs the grid or the output array")
        out = np.empty((grid.height // s, block.cols // s), dtype=data.dtype)
    src = cast("NDArray[Any]", data)
    flags = interpolation | cv2.WARP_INVERSE_MAP
    border = float(nodata)
    c = (s - 1) / 2.0  # a strided pixel's centre, full-resolution pixels from its first
    for t in block.tiles:
        m = t.affine.copy()
        m[1, 2] -= first_line
        tc = t.col0 - block.col0
        # The strided pixels whose centres lie on the tile.
        r0, r1 = math.ceil((t.row0 - c) / s), math.ceil((t.row0 + t.rows - c) / s)
        c0, c1 = math.ceil((tc - c) / s), math.ceil((tc + t.cols - c) / s)
        r0, r1, c0, c1 = max(r0, 0), min(r1, out.shape[0]), max(c0, 0), min(c1, out.shape[1])
        if r1 <= r0 or c1 <= c0:
            continue
        if s > 1:  # strided (X, Y) -> the tile's full-resolution (x, y) -> the source
            a = np.array([[s, 0.0, s * c0 + c - tc], [0.0, s, s * r0 + c - t.row0], [0, 0, 1]])
            m = m @ a
        dst = out[r0:r1, c0:c1]
        if dst.flags.c_contiguous:  # a tile as wide as the block: written in place
            cv2.warpAffine(
                src,
                m,
                (c1 - c0, r1 - r0),
                dst=cast("NDArray[Any]", dst),
                flags=flags,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=border,
            )
        else:
            dst[...] = cv2.warpAffine(
                src,
                m,
                (c1 - c0, r1 - r0),
                flags=flags,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=border,
            )
    return out


def reduce_block(image: NDArray[np.generic], factor: int, nodata: float) -> NDArray[np.generic]:
    """``image`` reduced by ``factor`` as ``core.terrain.reduce_image`` reduces it, faster.

    (Here, not in ``core.tiles``, so that the render process reduces draft blocks with only
    this module imported.)

    The same pixels to the bit (block means by ``cv2.INTER_AREA``; a reduced pixel whose block
    holds a no-data pixel is no-data; the last rows and columns that do not fill a block are
    dropped), but the no-data test costs one pass over the block when it has none (its
    minimum above ``nodata``, or no pixel equal to it), and otherwise one over the reduced
    rows that hold some: ``reduce_image`` built and reduced a float mask of every pixel
    (at the IKONOS size, 1.5 of the 3.4 CPU seconds of a pair's 1/8 tiles).
    """
    rows, cols = image.shape[0] // factor, image.shape[1] // factor
    full = np.asarray(image[: rows * factor, : cols * factor])
    small = cv2.resize(full, (cols, rows), interpolation=cv2.INTER_AREA)
    if full.size == 0 or float(full.min()) > nodata:
        return small
    try:
        # The reduced pixels holding no-data: the 255/0 mask's block means are > 0 exactly
        # there (the least, 255 / 64 at 8, rounds to 4). 2.6 ms a block of 256 x 14010 px
        # against 9.5 for the pass below: with draft blocks (nearest-neighbour sampling) a
        # simulated scene's zero DN reach most blocks.
        mask = cv2.compare(full, cast(Any, float(nodata)), cv2.CMP_EQ)
        small[cv2.resize(mask, (cols, rows), interpolation=cv2.INTER_AREA) > 0] = nodata
        return small
    except cv2.error:  # a type OpenCV does not compare
        pass
    bad = full == nodata
    band = bad.reshape(rows, factor * full.shape[1]).any(axis=1)
    if not band.any():
        return small
    hit = np.flatnonzero(band)
    blocks = bad.reshape(rows, factor, cols, factor)[hit].any(axis=(1, 3))
    sub = small[hit]
    sub[blocks] = nodata
    small[hit] = sub
    return small
