"""Dense matching of a normalized (epipolar) stereo pair with OpenCV's semi-global matcher.

Convention (the pipeline's and OpenCV's): the disparity of a left pixel is
``d = col_left - col_right`` in normalized pixels, and the pair's own linear relation gives its
height, ``Z = a d + b`` (:attr:`parproj_ros.core.results.PairResult.height_per_disparity_px` ``a``,
metres per pixel, and ``height_offset_m`` ``b``, metres). ``a`` may be negative (an x-parallax
of inverted sign): the searched range is then simply the other way round.

:func:`match_pair` cuts the pair into tiles (row bands x column tiles) with overlaps, so that a
large pair (14k x 14k) is matched with bounded working memory; each tile is matched left to
right and, for the left-right consistency check, right to left (both images flipped
horizontally and swapped, which keeps OpenCV's convention and the disparity's sign). The
result is a float32 disparity map in the left normalized image's pixel grid, NaN where invalid
(no data, low texture, no unique match, left-right inconsistency).

With a :class:`CoarseGuide`, a pass on both images reduced 4 times comes first: a pixel with
no coarse match near it is not taken (where the reduced pass found nothing consistent, a match
is mostly a blunder), and, optionally, each tile of 256 px searches only the disparities the
coarse pass found around it, not the whole pair's range.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any, Literal, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from .threads import row_parts, run_parts, workers

__all__ = [
    "CoarseGuide",
    "DenseStatus",
    "DisparityResult",
    "SgbmParams",
    "disparity_range",
    "match_pair",
    "refine_range",
    "sgbm_matcher",
    "to_uint8",
]

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]
BoolArray = NDArray[np.bool_]
UInt8Array = NDArray[np.uint8]


class DenseStatus(StrEnum):
    """Outcome of :func:`match_pair` (a string in logs and messages)."""

    OK = "ok"
    #: The valid share is below ``min_valid_share`` and low texture is the main reason
    #: (uniform, smooth or saturated images).
    TEXTURELESS = "textureless"
    #: The valid share is below ``min_valid_share`` for another reason (no unique or no
    #: left-right consistent match).
    NO_MATCH = "no_match"
    #: The left or the right image has no data, or no row has data in both within the
    #: disparity range (nothing to match).
    NO_OVERLAP = "no_overlap"
    #: The disparity range is as wide as the image or wider than ``max_disparities``.
    RANGE_TOO_WIDE = "range_too_wide"


@dataclass(frozen=True)
class SgbmParams:
    """Settings of the semi-global matcher and of the validity checks.

    Attributes:
        block_size: matched block side, pixels (odd, >= 1).
        p1: SGM penalty of a 1-step disparity change (None: 8 * block_size^2).
        p2: SGM penalty of larger changes (None: 32 * block_size^2).
        uniqueness_ratio: OpenCV's uniquenessRatio, percent.
        speckle_window: largest speckle region removed, pixels (0: off).
        speckle_range: largest disparity change within a speckle region, pixels.
        mode: ``cv2.STEREO_SGBM_MODE_SGBM_3WAY`` (default, faster, less memory),
            ``cv2.STEREO_SGBM_MODE_SGBM`` or ``cv2.STEREO_SGBM_MODE_HH`` (8 paths, much more
            memory).
        lr_check: "flip" (default): a second, right-to-left SGBM pass on both images mirrored
            and swapped, and the left and right disparities compared (where they agree, the
            disparity is their mean); "reduced": the right-to-left pass on both images
            reduced by 2 (a quarter of the pixels, half the disparities: some 0.2 of a pass),
            its disparities interpolated back and compared, no mean (Marseille 1-2 against
            s2p: NMAD 0.926 against 0.918 m, 97.3 against 98.2 % complete; on the simulated
            bags more blunders kept: RMS against truth 2.11 against 1.25 m for ikonos_agile;
            docs/performance.md);
            "none": no check (half the time; only partners without
            data are rejected). OpenCV's own check
            (``disp12MaxDiff``) is not offered: it removed nothing here that the uniqueness
            test had not removed already.
        lr_rows: with "flip", the right-to-left pass matches every ``lr_rows``-th row of the
            mirrored windows (1: every row); each other row is checked against the
            disparities of the matched row above it. 2 (the default) halves the pass: the
            heights step 14-16 % less CPU on the Marseille pairs, NMAD against s2p 0.710 /
            0.415 / 0.737 m against 0.711 / 0.416 / 0.739 m with every row, 0.1-0.8 points
            less complete (98.0 / 96.7 / 98.5 %), RMS against truth on the simulated bags
            0.030 / 2.61 / 1.15 m against 0.033 / 2.52 / 1.25 m (airborne_foreaft,
            crab_foreaft, ikonos_agile; docs/performance.md). 3 and 4 cost Marseille 1-3 more
            completeness (95.0 and 92.4 %).
        lr_tolerance_px: largest |d_left - d_right| of the left-right check, pixels.
        min_texture_dn: smallest local standard deviation of the horizontal gradient
            (central difference) of the 8-bit left image over a (2 block_size + 1)^2 window,
            DN per pixel; below it a pixel is "low texture" (uniform, saturated, or a smooth
            ramp, which has variance but nothing to match along the epipolar line).
        stretch_percentiles: (low, high) percentiles of each image mapped to 0 and 255.
        max_disparities: widest accepted search range, pixels (memory and time bound).
        min_valid_share: below this share of valid pixels (of the left pixels with data) the
            status is not OK.
        subpixel: "sgbm": the sub-pixel disparities as OpenCV's SGBM gives them (a parabola
            through its aggregated costs: "pixel-locked", the fractional parts crowd
            towards whole pixels, 3.6 times as many within 1/16 px of one as uniform on the
            Marseille pair 1-2); "gradient": then refined on the images themselves
            (:func:`_refine_subpixel`, a Lucas-Kanade fit of the disparity in a Gaussian
            window: fractional parts uniform, on Marseille pair 1-2 NMAD against s2p 0.918 ->
            0.711 m, against CARS 1.047 -> 0.775 m; on the simulated bags NMAD against truth
            0.17 -> 0.14-0.15 m; some 0.05 s per Mpx; docs/heights.md).
        subpixel_sigma_px: standard deviation of the refinement's Gaussian window, pixels.
        subpixel_iterations: refinement steps (each re-samples the right image at the
            disparities of the previous one).
        subpixel_max_px: a refined disparity farther than this from SGBM's, pixels, is not
            taken (SGBM's stays: an edge, an occlusion, or too little texture to fit).
        min_ncc: the photometric check (None: off): after the sub-pixel step, a valid pixel
            whose left window and the right image resampled at the window's disparities
            correlate less than this (zero-mean normalized cross-correlation, Gaussian
            weights of ``ncc_sigma_px`` over the valid pixels) is rejected (counted as
            ``lr_failure``), unless the two windows differ by less than ``ncc_noise_dn``
            (a faint window: its correlation is low from noise alone). With
            ``lr_check="reduced"`` it removes the blunders the reduced check keeps, for some
            0.25 of a bare pass instead of the 1.07 of "flip"'s second pass
            (docs/heights.md, run 6).
        ncc_sigma_px: standard deviation of the photometric check's Gaussian window, pixels.
        ncc_noise_dn: windows whose difference (left minus right resampled, less its mean)
            has a standard deviation below this pass the photometric check, DN of the
            8-bit stretched images.
        scale: 1: SGBM on the full-resolution images; 2: SGBM on both images reduced by 2
            (2 x 2 means: a quarter of the pixels, half the disparities), its disparities
            (both passes of the left-right check) enlarged back to every pixel, checked
            there (texture, partners, left-right within ``lr_tolerance_px`` x 2), and refined
            at full resolution (``subpixel="gradient"``, within ``subpixel_max_px`` x 2; a
            pixel the refinement moves farther is dropped). Some 0.3 of a full-resolution
            pass instead of 1.6 for both passes (docs/performance.md).
    """

    block_size: int = 5
    p1: int | None = None
    p2: int | None = None
    uniqueness_ratio: int = 10
    speckle_window: int = 100
    speckle_range: int = 2
    mode: int = cv2.STEREO_SGBM_MODE_SGBM_3WAY
    lr_check: Literal["flip", "reduced", "none"] = "flip"
    lr_rows: int = 2
    lr_tolerance_px: float = 1.0
    min_texture_dn: float = 1.0
    stretch_percentiles: tuple[float, float] = (0.5, 99.5)
    max_disparities: int = 1024
    min_valid_share: float = 0.2
    subpixel: Literal["sgbm", "gradient"] = "sgbm"
    subpixel_sigma_px: float = 2.5
    subpixel_iterations: int = 2
    subpixel_max_px: float = 0.5
    min_ncc: float | None = None
    ncc_sigma_px: float = 1.5
    ncc_noise_dn: float = 4.0
    scale: int = 1

    def __post_init__(self) -> None:
        if self.scale not in (1, 2):
            raise ValueError(f"scale must be 1 or 2, got {self.scale}")
        if self.scale == 2 and self.lr_check == "reduced":
            raise ValueError(
                "scale 2 matches at half resolution already: lr_check 'reduced' is for scale 1"
            )
        if self.lr_check not in ("flip", "reduced", "none"):
            raise ValueError(
                f"lr_check must be 'flip', 'reduced' or 'none', got {self.lr_check!r}"
            )
        if self.lr_rows < 1:
            raise ValueError(f"lr_rows must be >= 1, got {self.lr_rows}")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ValueError(f"block_size must be odd and >= 1, got {self.block_size}")
        if self.subpixel not in ("sgbm", "gradient"):
            raise ValueError(f"subpixel must be 'sgbm' or 'gradient', got {self.subpixel!r}")
        if not (self.subpixel_sigma_px > 0 and self.subpixel_iterations >= 1):
            raise ValueError(
                "subpixel_sigma_px must be > 0 px and subpixel_iterations >= 1, got "
                f"{self.subpixel_sigma_px}, {self.subpixel_iterations}"
            )
        if self.min_ncc is not None and not (
            -1.0 <= self.min_ncc <= 1.0 and self.ncc_sigma_px > 0 and self.ncc_noise_dn >= 0
        ):
            raise ValueError(
                "min_ncc must be within -1..1 (or None: no photometric check), ncc_sigma_px "
                f"> 0 px and ncc_noise_dn >= 0 DN, got {self.min_ncc}, {self.ncc_sigma_px}, "
                f"{self.ncc_noise_dn}"
            )
        lo, hi = self.stretch_percentiles
        if not 0.0 <= lo < hi <= 100.0:
            raise ValueError(f"stretch_percentiles must be 0 <= low < high <= 100, got {lo, hi}")


@dataclass(frozen=True)
class DisparityResult:
    """A dense disparity map of a normalized pair.

    Attributes:
        disparity: float32 (rows, cols) in the left normalized image's grid,
            ``col_left - col_right`` in pixels (1/16 px steps), NaN where invalid.
        status: overall outcome.
        d_range: (dmin, dmax) searched, pixels (inclusive).
        valid_share: valid pixels / left pixels with data (0 when there are none).
        counts: pixels per outcome: ``valid``, ``nodata`` (left no-data, or within half a
            block of it; at scale 2, of the half-resolution blocks), ``low_texture``,
            ``no_match`` (SGBM found no unique match), ``lr_failure`` (left-right check
            failed or the partner has no data).
        message: what happened, in words.
    """

    disparity: Float32Array
    status: DenseStatus
    d_range: tuple[int, int]
    valid_share: float
    counts: dict[str, int] = field(default_factory=dict)
    message: str = ""


@dataclass(frozen=True)
class CoarseGuide:
    """A pass on the pair reduced ``scale`` times guides the full-resolution matching.

    The reduced pass: both images reduced by area means (a reduced pixel with any no-data
    input has none), matched over the pair's range / ``scale`` with the same settings (SGBM's
    own sub-pixel, no speckle filter), left-right checked.

    The support rule (``support`` >= 0): a full-resolution pixel with no valid reduced pixel
    within ``support`` reduced pixels of its own is not taken (counted as ``no_match``). Where
    the reduced pass found nothing consistent (occlusions, the partner off the right image, no
    texture) a full-resolution match is mostly a blunder: on the simulated bags RMS against
    truth 0.030 / 2.61 / 1.15 -> 0.022 / 0.20 / 0.27 m (airborne_foreaft, crab_foreaft,
    ikonos_agile), on Marseille 2-3 RMS against s2p 1.79 -> 0.99 m; NMAD unchanged, about 1
    point less complete (docs/performance.md). Its cost: a feature smaller than some 3
    reduced pixels whose disparity stands out from its surroundings (a narrow tower) may be
    lost with the reduced pass's hole around it.

    Narrowed ranges (``ranges``): each tile of ``tile_px`` (overlap ``overlap_px``, instead of
    the caller's tiles) searches the disparities of the valid reduced pixels over it and one
    reduced pixel around it, widened by ``margin_px`` plus ``scale`` on both sides, within the
    pair's range; a tile over fewer than ``min_cells`` of them searches the pair's range.
    SGBM's time per pixel is about 22 ns plus 0.5 ns per disparity on 2 threads here: a tile
    searching 32 disparities instead of 160-224 costs a third. But a feature the reduced pass
    missed is then lost even where it is large enough to match at full resolution (a 24 px
    patch 40 px of disparity off its surroundings: 93 % matched with the pair's range, 5 %
    narrowed; ``tests/imaging/test_dense_guide.py``).

    Attributes:
        scale: reduction of the coarse pass (>= 2).
        support: reach of the support rule, reduced pixels (< 0: no rule).
        ranges: narrowed ranges per tile (above).
        tile_px: with ``ranges``, the tile side, pixels (tiles are equal, at most 1.25 times
            this).
        overlap_px: with ``ranges``, rows and columns matched around a tile and dropped,
            pixels.
        margin_px: with ``ranges``, added on both sides of a tile's reduced disparities,
            full-resolution pixels (``scale`` more is added for the reduced pixel's own
            uncertainty).
        min_cells: with ``ranges``, a tile over fewer valid reduced pixels searches the
            pair's range.
    """

    scale: int = 4
    support: int = 1
    ranges: bool = False
    tile_px: int = 256
    overlap_px: int = 16
    margin_px: float = 8.0
    min_cells: int = 16

    def __post_init__(self) -> None:
        if self.tile_px < 16 or self.overlap_px < 0 or self.scale < 2 or self.min_cells < 1:
            raise ValueError(
                "CoarseGuide needs tile_px >= 16 px, overlap_px >= 0 px, scale >= 2 and "
                f"min_cells >= 1, got {self.tile_px}, {self.overlap_px}, {self.scale}, "
                f"{self.min_cells}"
            )
        if not (math.isfinite(self.margin_px) and self.margin_px >= 0):
            raise ValueError(f"margin_px must be finite and >= 0 px, got {self.margin_px}")


def disparity_range(
    height_per_disparity_px: float,
    height_offset_m: float,
    z_range_m: tuple[float, float],
    margin_px: float = 8.0,
) -> tuple[int, int]:
    """Disparities (dmin, dmax), pixels, of heights in ``z_range_m`` plus a margin.

    ``d = (Z - b) / a`` for ``Z = a d + b``; with ``a < 0`` (inverted x-parallax) the lower
    height gives the higher disparity, so both ends are computed and sorted.

    Args:
        height_per_disparity_px: a, metres per pixel (non-zero, finite; either sign).
        height_offset_m: b, metres.
        z_range_m: (zmin, zmax) of the ground, metres (either order).
        margin_px: added on both sides, pixels (>= 0).

    Returns:
        (floor(dmin - margin), ceil(dmax + margin)), integer pixels, dmin <= dmax.

    Raises:
        ValueError: a is zero or not finite (no stereo base), or an input is not finite.
    """
    a, b = float(height_per_disparity_px), float(height_offset_m)
    if not (math.isfinite(a) and a != 0.0):
        raise ValueError(f"height per disparity must be finite and non-zero, got {a} m/px")
    z0, z1 = (float(z) for z in z_range_m)
    if not all(math.isfinite(v) for v in (b, z0, z1, margin_px)) or margin_px < 0:
        raise ValueError("height offset, height range and margin must be finite (margin >= 0)")
    d0, d1 = sorted(((z0 - b) / a, (z1 - b) / a))
    return math.floor(d0 - margin_px), math.ceil(d1 + margin_px)


def _valid_mask(image: NDArray[Any], nodata: float | None, mask: BoolArray | None) -> BoolArray:
    """True where ``image`` has data (not ``nodata``, and ``mask`` True when given)."""
    ok = np.ones(image.shape, dtype=bool) if nodata is None else image != nodata
    if image.dtype.kind == "f":
        ok &= np.isfinite(image)
    if mask is not None:
        ok &= mask.astype(bool)
    return ok


def to_uint8(image: NDArray[Any], low: float, high: float) -> UInt8Array:
    """Linear stretch of ``image`` mapping [low, high] DN to [0, 255] (clipped), uint8; NaN: 0."""
    scale = 255.0 / (high - low) if high > low else 0.0
    out = (image.astype(np.float32) - np.float32(low)) * np.float32(scale)
    if image.dtype.kind == "f":
        out = np.nan_to_num(out, nan=0.0, posinf=255.0, neginf=0.0)
    return cast("UInt8Array", np.clip(np.rint(out), 0, 255).astype(np.uint8))


def sgbm_matcher(params: SgbmParams, dmin: int, ndisp: int) -> cv2.StereoSGBM:
    """OpenCV's StereoSGBM with ``params``' settings: ``ndisp`` disparities from ``dmin``.

    The matcher of :func:`match_pair`, and the benchmarks' bare pass (tools/bench).
    """
    bs = params.block_size
    return cv2.StereoSGBM.create(
        minDisparity=dmin,
        numDisparities=ndisp,
        blockSize=bs,
        P1=params.p1 if params.p1 is not None else 8 * bs * bs,
        P2=params.p2 if params.p2 is not None else 32 * bs * bs,
        disp12MaxDiff=-1,
        preFilterCap=63,
        uniquenessRatio=params.uniqueness_ratio,
        speckleWindowSize=params.speckle_window,
        speckleRange=params.speckle_range,
        mode=params.mode,
    )


def _texture(image: UInt8Array, size: int) -> Float32Array:
    """Local variance of the horizontal gradient over size x size, (DN per pixel)^2.

    The gradient is the central difference; compare the result with the square of a
    standard deviation.
    """
    f = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    box = (size, size)
    m = cast("Float32Array", cv2.boxFilter(f, cv2.CV_32F, box, borderType=cv2.BORDER_REFLECT))
    var = cast("Float32Array", cv2.sqrBoxFilter(f, cv2.CV_32F, box, borderType=cv2.BORDER_REFLECT))
    m *= m
    var -= m
    return var


# Outcome codes of a pixel (their order is the order of precedence).
_VALID, _NODATA, _LOW_TEXTURE, _NO_MATCH, _LR = 0, 1, 2, 3, 4
_REASONS = ("valid", "nodata", "low_texture", "no_match", "lr_failure")


@dataclass(frozen=True)
class _Prepared:
    """Both original images, their masks and stretch limits, and the matcher's geometry.

    The right image is read ``shift`` columns to the left (``right'[x] = right[x - shift]``) so
    that the searched disparities ``d - shift``, from ``dmin`` (shifted) over ``ndisp`` values,
    are centred on 0 and ``pad`` columns on each side of a tile hold every partner.
    """

    left: NDArray[Any]
    right: NDArray[Any]
    left_mask: BoolArray | None
    right_mask: BoolArray | None
    nodata: float | None
    limits: tuple[tuple[float, float], tuple[float, float]]
    dmin: int
    ndisp: int
    pad: int
    shift: int

    def stretch(self, side: int, part: NDArray[Any]) -> UInt8Array:
        """``part`` of one image stretched to uint8 (:func:`to_uint8` with its limits).

        8- and 16-bit images go through a lookup table of every value (the same figures, a
        third of the time).
        """
        lo, hi = self.limits[side]
        if part.dtype in (np.uint8, np.uint16):
            lut = _stretch_table(part.dtype, lo, hi)
            return cast("UInt8Array", np.take(lut, part))
        return to_uint8(part, lo, hi)

    def window(
        self, side: int, rows: tuple[int, int], cols: tuple[int, int]
    ) -> tuple[UInt8Array, BoolArray]:
        """uint8 pixels and data mask of one image over rows x cols (outside: no data)."""
        img, mask = (self.left, self.left_mask) if side == 0 else (self.right, self.right_mask)
        r0, r1 = rows
        c0, c1 = cols
        a, b = max(0, c0), min(img.shape[1], c1)
        pix = np.zeros((r1 - r0, c1 - c0), dtype=np.uint8)
        ok = np.zeros((r1 - r0, c1 - c0), dtype=bool)
        if b > a:
            part = img[r0:r1, a:b]
            m = _valid_mask(part, self.nodata, None if mask is None else mask[r0:r1, a:b])
            inner = pix[:, a - c0 : b - c0]
            inner[...] = self.stretch(side, part)
            np.copyto(inner, 0, where=~m)
            ok[:, a - c0 : b - c0] = m
        return pix, ok


@functools.lru_cache(maxsize=8)
def _stretch_table(dtype: np.dtype[Any], low: float, high: float) -> UInt8Array:
    """:func:`to_uint8` of every value of an 8- or 16-bit ``dtype``, indexed by the value."""
    return to_uint8(np.arange(np.iinfo(dtype).max + 1, dtype=dtype), low, high)


def _average_with_partner(
    dl: Float32Array,
    xr: Float32Array,
    raw_r: NDArray[Any],
    ok: BoolArray,
    invalid: int,
    row0: int = 0,
) -> Float32Array:
    """The mean of each left disparity and its partner's right disparity, where both agree.

    The right disparity is interpolated linearly at the partner's position ``x - d`` (not
    taken at the nearest right pixel): two independent sub-pixel estimates of one parallax,
    whose mean halves the variance of the matching noise that is not common to both (on the
    Marseille pair 1-2 against s2p: NMAD 0.929 -> 0.918 m; with 8 paths 0.784 -> 0.774 m).
    Both right pixels around the partner must have a disparity. With ``cv2.remap`` (bilinear
    in 1/32 px steps; the two pixels' check as the nearest of a map of either having none),
    some 3 times faster than flat ``take``s.

    Args:
        dl: left disparities (rows, cols), pixels.
        xr: the partners' columns ``x - dl`` in the right window, pixels (same shape).
        raw_r: OpenCV's right disparities of the mirrored pass (16 x pixels) over the right
            window (window rows, window columns).
        ok: the left pixels whose partner passed the left-right check.
        invalid: OpenCV's code of a right pixel without disparity.
        row0: the window row of ``dl``'s first row.
    """
    src = raw_r[row0 : row0 + dl.shape[0]]
    yr = np.ascontiguousarray(
        np.broadcast_to(np.arange(dl.shape[0], dtype=np.float32)[:, None], dl.shape)
    )
    # none at a column or at the next one: the bilinear partner would use it
    none = (src == invalid).view(np.uint8)
    either = none.copy()
    either[:, :-1] |= none[:, 1:]
    # the nearest of x - 0.499 is floor(x) (x - dl is a whole 1/16 px)
    at = xr - np.float32(0.499)
    lost = cv2.remap(either, at, yr, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    partner = cast(
        "Float32Array",
        cv2.remap(
            src.astype(np.float32), xr, yr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        ),
    )
    partner *= np.float32(1.0 / 16.0)
    partner += dl
    partner *= np.float32(0.5)
    out: Float32Array = np.where(ok & (lost == 0), partner, dl)
    return out


def _half_search(dmin: int, ndisp: int) -> tuple[int, int]:
    """(dmin, ndisp) of the half-resolution search of a full-resolution one, half pixels."""
    lo = math.floor(dmin / 2) - 1
    hi = math.ceil((dmin + ndisp - 1) / 2) + 1
    return lo, max(16, math.ceil((hi - lo + 1) / 16) * 16)


def _matcher_of(params: SgbmParams, prep: _Prepared) -> cv2.StereoSGBM:
    """The matcher of a search (``prep``): at full resolution, or at half (``params.scale``).

    At half resolution the speckle filter's region is a quarter of the pixels and its range
    half the disparity.
    """
    if params.scale == 1:
        return sgbm_matcher(params, prep.dmin, prep.ndisp)
    lo, nd = _half_search(prep.dmin, prep.ndisp)
    half = replace(
        params,
        speckle_window=params.speckle_window // 4,
        speckle_range=max(1, params.speckle_range // 2),
    )
    return sgbm_matcher(half, lo, nd)


def _even_blocks(img: UInt8Array, origin: tuple[int, int]) -> tuple[UInt8Array, int, int]:
    """``img`` bordered so that its 2 x 2 blocks start at even image rows and columns.

    A row (column) before it where ``origin`` (its first pixel's row, column in the image) is
    odd, and one after where the bordered size is odd, repeated. Returns the bordered image and
    the rows and columns added before it (crop an enlargement with ``[pt : pt + rows, pl : pl
    + cols]``).
    """
    rows, cols = img.shape
    pt, pl = origin[0] % 2, origin[1] % 2
    eb, er = (pt + rows) % 2, (pl + cols) % 2
    if pt or pl or eb or er:
        img = cast("UInt8Array", cv2.copyMakeBorder(img, pt, eb, pl, er, cv2.BORDER_REPLICATE))
    return img, pt, pl


def _half_passes(
    lwin: UInt8Array,
    rwin: UInt8Array,
    matcher: cv2.StereoSGBM,
    params: SgbmParams,
    invalid: int,
    search: tuple[int, int],
    origin: tuple[int, int],
) -> tuple[NDArray[Any], NDArray[Any] | None]:
    """Both SGBM passes of a tile at half resolution, enlarged to the windows (OpenCV's units).

    The windows are reduced by 2 x 2 means in blocks at even image rows and columns (a row or
    column before the window and one after repeated where needed: tiles are reduced as the
    whole image), padded on both sides with the columns OpenCV leaves without a disparity (no
    data: zeros), matched left to right and, with ``lr_check`` "flip", right to left on both
    mirrored (every ``lr_rows``-th half row, from an even multiple of it in the image; the
    rows between take the matched row above, the first rows the one below); each map's
    disparities are doubled and enlarged back bilinearly, a pixel between half pixels of
    which one has none having none (``invalid``), as a pixel outside the full-resolution
    ``search`` (dmin, ndisp: the half-resolution one, whole multiples of 16, reaches farther).

    Args:
        lwin: the left window (uint8).
        rwin: the right window, the same shape.
        matcher: the half-resolution matcher (:func:`_matcher_of`).
        params: the settings.
        invalid: the full-resolution code of a pixel without disparity.
        search: the full-resolution search (dmin, ndisp), pixels.
        origin: (row, column) of the windows' first pixel in the left image.

    Returns:
        (left disparities, right disparities or None), int16, 16 x full-resolution pixels,
        the windows' shape.
    """
    rows, cols = lwin.shape
    (lb, pt, pl), (rb, _, _) = _even_blocks(lwin, origin), _even_blocks(rwin, origin)
    size = (lb.shape[1] // 2, lb.shape[0] // 2)
    l2, r2 = (
        cast("UInt8Array", cv2.resize(im, size, interpolation=cv2.INTER_AREA)) for im in (lb, rb)
    )
    lo, nd = _half_search(*search)  # the matcher's (only its compute is called: spies)
    left_pad, right_pad = max(lo + nd, 0), max(-lo, 0)
    none = (lo - 1) * 16  # OpenCV's code of a half pixel without disparity

    def run(a: UInt8Array, b: UInt8Array) -> NDArray[Any]:
        pa, pb = (
            cv2.copyMakeBorder(im, 0, 0, left_pad, right_pad, cv2.BORDER_CONSTANT, value=0)
            for im in (a, b)
        )
        return cast("NDArray[Any]", matcher.compute(pa, pb)[:, left_pad : left_pad + size[0]])

    def enlarge(raw: NDArray[Any]) -> NDArray[Any]:
        # bilinear, 2 x: every pixel between 4 half pixels, each weighted 1/16 .. 9/16, so a
        # pixel is valid where all 4 are (the enlarged validity is 255, not less)
        ok = (raw != none).view(np.uint8)
        full = (size[0] * 2, size[1] * 2)
        held = cv2.resize(ok * np.uint8(255), full, interpolation=cv2.INTER_LINEAR)
        doubled = raw * np.int16(2)
        doubled[ok == 0] = 0
        out = cast("NDArray[Any]", cv2.resize(doubled, full, interpolation=cv2.INTER_LINEAR))
        lo16, hi16 = 16 * search[0], 16 * (search[0] + search[1] - 1)
        out[(held != 255) | (out < lo16) | (out > hi16)] = invalid
        return out[pt : pt + rows, pl : pl + cols]

    raw_l = enlarge(run(l2, r2))
    if params.lr_check != "flip":
        return raw_l, None
    k = params.lr_rows
    first = -((origin[0] - pt) // 2) % k  # the half rows matched: multiples of k in the image
    # (a window of fewer half rows than that, with lr_rows over half a tile's rows: its last)
    first = min(first, l2.shape[0] - 1)
    flipped = [cast("UInt8Array", cv2.flip(im[first::k], 1)) for im in (r2, l2)]
    matched = cast("NDArray[Any]", cv2.flip(run(*flipped), 1))
    raw_r = np.empty_like(l2, dtype=matched.dtype)
    raw_r[first:] = np.repeat(matched, k, axis=0)[: l2.shape[0] - first]
    raw_r[:first] = matched[0]
    return raw_l, enlarge(raw_r)


def _half_reach(bad: UInt8Array, half: int, origin: tuple[int, int]) -> UInt8Array:
    """1 where a pixel's disparity at scale 2 comes from a block that reaches a ``bad`` pixel.

    :func:`_half_passes`' 2 x 2 blocks (at even image rows and columns, ``origin`` as there):
    a half pixel is bad where any of its 4 pixels is, its SGBM block (``half`` half pixels
    around it) where any half pixel of it is, and a pixel where any of the 4 half pixels its
    disparity is enlarged from is: some 2 ``half`` + 2 pixels of reach, not ``half``.

    Args:
        bad: 1 where a window has no data (uint8 0 / 1).
        half: half the block side, half pixels.
        origin: (row, column) of the window's first pixel in the left image.
    """
    rows, cols = bad.shape
    b, pt, pl = _even_blocks(bad, origin)
    h2, w2 = b.shape[0] // 2, b.shape[1] // 2
    # a block's mean of 0 / 255 is not 0 where any of its 4 is bad (numpy's max over the block
    # axes: the same, 14 times slower)
    small = cv2.resize(b * np.uint8(255), (w2, h2), interpolation=cv2.INTER_AREA)
    b2 = (small != 0).view(np.uint8)
    if half > 0:
        b2 = cv2.dilate(b2, np.ones((2 * half + 1, 2 * half + 1), np.uint8))
    # bilinear 2 x: each of the 4 half pixels weighs 1/16 .. 9/16, so > 0 where any is bad
    full = cv2.resize(b2 * np.uint8(255), (2 * w2, 2 * h2), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray((full[pt : pt + rows, pl : pl + cols] != 0).view(np.uint8))


def _match_tile(
    prep: _Prepared,
    matcher: cv2.StereoSGBM,
    params: SgbmParams,
    rows: tuple[int, int],
    cols: tuple[int, int],
) -> tuple[Float32Array, NDArray[np.uint8]]:
    """Disparity and outcome codes of left columns cols[0]:cols[1], rows rows[0]:rows[1].

    Both images are cut to the same extended column window (the tile plus ``pad`` on each
    side, no data outside the image), so that every searched partner is inside it. The
    checks run on the tile's own columns only, by row parts on a few threads
    (:mod:`.threads`); a partner is looked up in the right window with ``cv2.remap``
    (nearest: the same pixel as ``rint``; outside the window: no data).
    """
    a, b = cols
    ext = (a - prep.pad, b + prep.pad)
    lwin, lok = prep.window(0, rows, ext)
    rwin, rok = prep.window(1, rows, (ext[0] - prep.shift, ext[1] - prep.shift))
    invalid = (prep.dmin - 1) * 16
    s = slice(prep.pad, prep.pad + (b - a))
    raw_r: NDArray[Any] | None = None
    right_d = var = None
    raw_l: NDArray[Any]
    if params.scale == 2:
        raw_l, raw_r = _half_passes(
            lwin, rwin, matcher, params, invalid, (prep.dmin, prep.ndisp), (rows[0], ext[0])
        )
    else:
        raw_l = matcher.compute(lwin, rwin)
        if params.lr_check == "flip":
            # disparity of each right pixel u: its left partner is u + d (every k-th row
            # matched, each row between taking the matched row above it)
            k = params.lr_rows
            raw_r = cv2.flip(matcher.compute(cv2.flip(rwin[::k], 1), cv2.flip(lwin[::k], 1)), 1)
            if k > 1:
                raw_r = np.repeat(raw_r, k, axis=0)[: lwin.shape[0]]
        elif params.lr_check == "reduced":
            right_d = _reduced_right_pass(lwin, rwin, prep.dmin, prep.ndisp, params)
    tolerance = params.lr_tolerance_px * params.scale
    half = params.block_size // 2
    # No data, or a block that reaches into no data (at scale 2, the half-resolution blocks
    # its disparity is enlarged from).
    lbad = (~lok).view(np.uint8)
    rbad = (~rok).view(np.uint8)
    if params.scale == 2:
        lbad = _half_reach(lbad, half, (rows[0], ext[0]))
        rbad = _half_reach(rbad, half, (rows[0], ext[0]))
    elif half > 0:
        kernel = np.ones((2 * half + 1, 2 * half + 1), np.uint8)
        lbad = cast("UInt8Array", cv2.dilate(lbad, kernel))
        rbad = cast("UInt8Array", cv2.dilate(rbad, kernel))
    if params.min_texture_dn > 0:
        var = _texture(lwin, 2 * params.block_size + 1)
    disp = np.empty((lwin.shape[0], b - a), dtype=np.float32)
    code = np.empty(disp.shape, dtype=np.uint8)

    def checks(part: tuple[int, int]) -> None:
        r0, r1 = part
        dl = raw_l[r0:r1, s].astype(np.float32)
        dl *= np.float32(1.0 / 16.0)
        # The partner (the right pixel nearest to x - d) must have data and, with a check,
        # point back within tolerance.
        xr = np.arange(s.start, s.stop, dtype=np.float32)[None, :] - dl
        yr = np.broadcast_to(np.arange(r0, r1, dtype=np.float32)[:, None], xr.shape)
        yr = np.ascontiguousarray(yr)

        def partner(image: NDArray[Any], outside: float) -> NDArray[Any]:
            return cast(
                "NDArray[Any]",
                cv2.remap(
                    image,
                    xr,
                    yr,
                    cv2.INTER_NEAREST,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=outside,
                ),
            )

        lr_ok = partner(rbad, 1) == 0
        if raw_r is not None:
            back = partner(raw_r, invalid)
            diff = back.astype(np.float32)
            diff *= np.float32(1.0 / 16.0)
            diff -= dl
            lr_ok &= (back != invalid) & (np.abs(diff) <= tolerance)
            dl = _average_with_partner(dl, xr, raw_r, lr_ok, invalid, r0)
        elif right_d is not None:
            diff = partner(right_d, math.nan)  # NaN outside the window and where it has none
            diff -= dl
            lr_ok &= np.abs(diff) <= params.lr_tolerance_px  # False for NaN
        c = code[r0:r1]
        c[...] = _VALID
        c[~lr_ok] = _LR
        c[raw_l[r0:r1, s] == invalid] = _NO_MATCH
        if var is not None:
            c[var[r0:r1, s] < params.min_texture_dn**2] = _LOW_TEXTURE
        c[lbad[r0:r1, s] != 0] = _NODATA
        dl += np.float32(prep.shift)
        dl[c != _VALID] = np.nan
        disp[r0:r1] = dl

    run_parts(checks, row_parts(disp.shape[0], workers()))
    if params.subpixel == "gradient":
        refine = replace(params, subpixel_max_px=params.subpixel_max_px * params.scale)
        disp = _refine_subpixel(
            lwin,
            rwin,
            disp,
            s,
            prep.shift,
            refine,
            origin=(rows[0], a),
            drop_far=params.scale > 1,
        )
        code[np.isnan(disp) & (code == _VALID)] = _NO_MATCH
    if params.scale == 2 and params.speckle_window > 0:
        # the islands the checks left of a region (a half-resolution match they cut off at
        # its edge): the full-resolution pass's own speckle filter, on the checked map
        rel = (disp - np.float32(prep.shift)) * np.float32(16.0)
        fixed = np.where(np.isfinite(rel), np.rint(rel), -32768).astype(np.int16)
        cv2.filterSpeckles(fixed, -32768, params.speckle_window, 16 * params.speckle_range)
        gone = (fixed == -32768) & (code == _VALID)
        disp[gone] = np.nan
        code[gone] = _NO_MATCH
    if params.min_ncc is not None:
        ncc = _window_ncc(
            lwin, rwin, disp, s, prep.shift, params.ncc_sigma_px, params.ncc_noise_dn
        )
        low = ncc < np.float32(params.min_ncc)  # False where NaN (invalid pixels)
        disp[low] = np.nan
        code[low] = _LR
    return disp, code


def _window_ncc(
    lwin: UInt8Array,
    rwin: UInt8Array,
    disp: Float32Array,
    s: slice,
    shift: int,
    sigma: float,
    noise_dn: float = 0.0,
) -> Float32Array:
    """Correlation of each valid left pixel's window with the right image at its disparities.

    The zero-mean normalized cross-correlation of the left window and the right window
    resampled (linearly) at each pixel's own disparity, with Gaussian weights (standard
    deviation ``sigma``, pixels) over the valid pixels only: 1 for a perfect match up to
    gain and offset, near 0 or below for a mismatch (an occlusion, a blunder). Where the
    windows' difference (less its mean) has a standard deviation below ``noise_dn``, 1: a
    faint window (shadow, water) whose correlation is low from noise alone. By strips of
    rows on threads, as :func:`_refine_subpixel`.

    Args:
        lwin: the left window (uint8, the matcher's input).
        rwin: the right window, read ``shift`` columns to the left.
        disp: disparities of the tile's columns ``s`` of the windows (NaN: invalid), pixels.
        s: the tile's columns in the windows.
        shift: the right window's shift, pixels.
        sigma: the window's standard deviation, pixels.
        noise_dn: the faint windows' limit, DN.

    Returns:
        The correlation, the shape of ``disp`` (NaN where ``disp`` is).
    """
    k = 2 * math.ceil(3.0 * sigma) + 1
    rows = disp.shape[0]
    valid = np.isfinite(disp)
    x = np.arange(s.start, s.stop, dtype=np.float32)[None, :]
    halo = k // 2 + 1
    out = np.empty(disp.shape, dtype=np.float32)
    rimg = rwin.astype(np.float32)

    def filt(a: Float32Array) -> Float32Array:
        return cast(
            "Float32Array", cv2.GaussianBlur(a, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
        )

    def part(span: tuple[int, int]) -> None:
        r0, r1 = span
        ra, rb = max(0, r0 - halo), min(rows, r1 + halo)
        w = valid[ra:rb].astype(np.float32)
        d = disp[ra:rb] - np.float32(shift)
        np.nan_to_num(d, copy=False, nan=0.0)
        xr = x - d
        yr = np.ascontiguousarray(
            np.broadcast_to(np.arange(ra, rb, dtype=np.float32)[:, None], d.shape)
        )
        rp = cast(
            "Float32Array",
            cv2.remap(rimg, xr, yr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
        )
        lp = lwin[ra:rb, s].astype(np.float32)
        lp *= w
        rp *= w
        n = filt(w)
        np.maximum(n, np.float32(1e-6), out=n)
        inv_n = np.reciprocal(n)
        ml = filt(lp) * inv_n
        mr = filt(rp) * inv_n
        slr = filt(lp * rp) * inv_n  # the weights are 0 or 1: w^2 = w
        slr -= ml * mr
        sll = filt(lp * lp) * inv_n
        sll -= ml * ml
        srr = filt(rp * rp) * inv_n
        srr -= mr * mr
        # the variance of the difference, sll + srr - 2 slr: below noise^2, a faint window
        dvar = sll + srr
        dvar -= 2.0 * slr
        faint = dvar < np.float32(noise_dn * noise_dn)
        sll *= srr
        np.maximum(sll, np.float32(1e-6), out=sll)
        slr /= np.sqrt(sll)
        slr[faint] = 1.0
        out[r0:r1] = slr[r0 - ra : r1 - ra]

    run_parts(part, row_parts(rows, max(workers(), rows // 256), min_rows=32))
    out[~valid] = np.nan
    return out


#: How the gradient fit resamples the right image and its gradient. Bilinear resampling moves
#: the fit's fixed point towards whole pixels (on a band-limited texture shifted by 8.3 and
#: 14.7 px: +0.035 and -0.035 px, the steps oscillating around it); bicubic leaves none
#: (0.000 px), for some 20 ms more of CPU on the Marseille pair 1-2 (1.2 Mpx).
_FIT_INTERPOLATION = cv2.INTER_CUBIC


def _refine_subpixel(
    lwin: UInt8Array,
    rwin: UInt8Array,
    disp: Float32Array,
    s: slice,
    shift: int,
    params: SgbmParams,
    *,
    origin: tuple[int, int] = (0, 0),
    drop_far: bool = False,
) -> Float32Array:
    """A tile's disparities refined on its images by a windowed 1-D gradient fit, pixels.

    SGBM's sub-pixel step (a parabola through three aggregated costs) pulls disparities
    towards whole pixels. Here, for every valid left pixel p, the disparity D common to a
    Gaussian window around it (standard deviation ``subpixel_sigma_px``) is fitted to the
    images: with each pixel q's current disparity d_q, the right image at q - D is, to first
    order, ``R(q - d_q) + (d_q - D) g_q`` (g: the right image's horizontal gradient there), so
    ``e_q = R(q - d_q) - L(q) + d_q g_q = D g_q + c`` (c: a brightness offset of the window),
    a straight line in g fitted by weighted least squares (Gaussian filters of e, g, e g,
    g^2). The fit holds at the centroid of its weights ``g (g - mean g)``, not at p: it is
    moved back along the fitted disparities' gradient (with Gaussian weights of standard
    deviation s, ``sum w (q - p) f = s^2 d/dp sum w f``: derivatives of the same filtered
    sums), which keeps slopes unbiased. Repeated ``subpixel_iterations`` times; where the
    window's gradient varies too little (variance < 1 DN^2 per px^2) the disparity stays,
    and where the result moves more than ``subpixel_max_px`` from the matcher's, the
    matcher's is kept (``drop_far``: the pixel is dropped, NaN).

    The window's sums are smooth (a Gaussian of 2.5 px), so they are taken on a grid of half
    the resolution: the products e, g, e g, g^2 of every pixel are reduced by 2 x 2 means
    (blocks at even image rows and columns, whatever the tile: tiles join as the whole image)
    and filtered there with the Gaussian that makes up the window (the window's variance less
    the means' 1/4 px^2), the fit and its centroid solved there, and the fitted disparities
    enlarged back (bilinear; where the fit holds on only some of the half pixels around a
    pixel, a blend with its own disparity). A quarter of the filtering and solving: on the
    Marseille pair 1-2, 51 instead of 90 ms of CPU. The right image and its gradient are
    resampled bicubically at each pixel's disparity (:data:`_FIT_INTERPOLATION`: bilinear
    biases the fit towards whole pixels). Against s2p on Marseille 1-2 / 1-3 / 2-3 NMAD
    0.710 / 0.415 / 0.737 -> 0.694 / 0.393 / 0.707 m, against truth crab_foreaft 0.154 ->
    0.132 m, ikonos_agile 0.141 -> 0.129 m (docs/performance.md).
    By strips of rows on threads (each with the rows its filters reach).

    Args:
        lwin: the left window (uint8, the matcher's input).
        rwin: the right window, read ``shift`` columns to the left.
        disp: disparities of the tile's columns ``s`` of the windows (NaN: invalid), pixels.
        s: the tile's columns in the windows.
        shift: the right window's shift, pixels.
        params: ``subpixel_*`` settings.
        origin: (row, column) of ``disp[0, 0]`` in the whole image, pixels (the 2 x 2 blocks
            start at its even rows and columns).
        drop_far: a pixel whose fit moves farther than ``subpixel_max_px`` is dropped (NaN)
            instead of keeping the matcher's disparity.

    Returns:
        The refined disparities, the shape of ``disp`` (NaN where it is, and where dropped).
    """
    sigma = float(params.subpixel_sigma_px)
    # the half grid's Gaussian, in half pixels: the window less the 2 x 2 means' variance
    sh = math.sqrt(max(sigma * sigma - 0.25, 0.0625)) / 2.0
    k = 2 * math.ceil(3.0 * sh) + 1
    s2 = np.float32((sigma / 2.0) ** 2)  # the window's variance, half pixels^2
    rimg = rwin.astype(np.float32)
    gx = cv2.Sobel(rimg, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    lt = lwin[:, s]
    rows, cols = disp.shape
    # whole 2 x 2 blocks at even image columns: pl columns before the tile's, the last repeated
    pl = origin[1] % 2
    ec = pl + cols + (pl + cols) % 2
    x = np.arange(s.start - pl, s.start - pl + ec, dtype=np.float32)[None, :]
    valid = np.isfinite(disp)
    d0 = disp - np.float32(shift)
    np.nan_to_num(d0, copy=False, nan=0.0)
    out = np.empty_like(d0)
    halo = 2 * (params.subpixel_iterations * (k // 2 + 2) + 2)
    one = np.float32(1.0)

    def filt(a: Float32Array) -> Float32Array:
        return cast(
            "Float32Array",
            cv2.GaussianBlur(a, (k, k), sh, borderType=cv2.BORDER_CONSTANT),
        )

    def half(a: Float32Array, size: tuple[int, int]) -> Float32Array:
        return filt(cast("Float32Array", cv2.resize(a, size, interpolation=cv2.INTER_AREA)))

    def dx(a: Float32Array) -> Float32Array:
        return cast("Float32Array", cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=1, scale=0.5))

    def dy(a: Float32Array) -> Float32Array:
        return cast("Float32Array", cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=1, scale=0.5))

    def even(a: NDArray[Any], r0: int, r1: int, pt: int, er: int) -> Float32Array:
        """Rows r0:r1 of ``a`` as float32 (er, ec) from row pt and column pl, edges repeated."""
        b = np.empty((er, ec), dtype=np.float32)
        b[pt : pt + r1 - r0, pl : pl + cols] = a[r0:r1]
        if pl:
            b[:, 0] = b[:, 1]
        if ec > pl + cols:
            b[:, -1] = b[:, -2]
        if pt:
            b[0] = b[1]
        if er > pt + r1 - r0:
            b[-1] = b[-2]
        return b

    def part(span: tuple[int, int]) -> None:
        r0, r1 = span
        ra, rb = max(0, r0 - halo), min(rows, r1 + halo)
        pt = (origin[0] + ra) % 2  # a row before: the blocks start at even image rows
        er = pt + rb - ra + (pt + rb - ra) % 2
        size, full = (ec // 2, er // 2), (ec, er)
        lp = even(lt, ra, rb, pt, er)
        dp = even(d0, ra, rb, pt, er)
        wv = np.zeros((er, ec), dtype=np.float32)  # the repeated edges: no weight
        wv[pt : pt + rb - ra, pl : pl + cols] = valid[ra:rb]
        yr = np.ascontiguousarray(
            np.broadcast_to(np.arange(ra - pt, ra - pt + er, dtype=np.float32)[:, None], dp.shape)
        )
        n = half(wv, size)
        inv_n = np.maximum(n, np.float32(1e-6))
        np.reciprocal(inv_n, out=inv_n)
        floor = n + np.float32(1e-12)
        d = dp.copy()
        for _ in range(params.subpixel_iterations):
            xr = x - d
            e = cast(
                "Float32Array",
                cv2.remap(rimg, xr, yr, _FIT_INTERPOLATION, borderMode=cv2.BORDER_REPLICATE),
            )
            g = cast(
                "Float32Array",
                cv2.remap(gx, xr, yr, _FIT_INTERPOLATION, borderMode=cv2.BORDER_REPLICATE),
            )
            # e = R(x - d) - L(x) + d g: the right image at the common disparity D of a
            # window is R(x - d) + (d - D) g, so e = D g + (brightness offset): a line fit
            e -= lp
            e += d * g
            e *= wv
            g *= wv
            se, sg = half(e, size), half(g, size)
            e *= g
            seg = half(e, size)
            g *= g
            sgg = half(g, size)
            mg = sg * inv_n
            num = seg - se * mg
            den = sgg - sg * mg
            # fitted where the variance of g over the window is > 1 (DN / px)^2
            okf = (den > n).astype(np.float32)
            inv_den = okf / np.maximum(den, floor)  # 0 where not fitted
            fit = num * inv_den
            # the weights' centroid, relative to the pixel, and the fit moved back from it
            cx = (dx(sgg) - mg * dx(sg)) * inv_den
            cy = (dy(sgg) - mg * dy(sg)) * inv_den
            corr = dx(fit) * cx
            corr += dy(fit) * cy
            corr *= s2
            np.clip(corr, -0.5, 0.5, out=corr)
            fit -= corr
            fit *= okf
            # back to every pixel: the fit where the half pixels around it are fitted, its
            # own disparity where none is, a blend between
            new = cast("Float32Array", cv2.resize(fit, full, interpolation=cv2.INTER_LINEAR))
            held = cast("Float32Array", cv2.resize(okf, full, interpolation=cv2.INTER_LINEAR))
            held -= one
            held *= d
            new -= held
            d = new
        far = np.abs(d - dp) > params.subpixel_max_px
        d[far] = np.nan if drop_far else dp[far]
        out[r0:r1] = d[pt + r0 - ra : pt + r1 - ra, pl : pl + cols]

    # strips of some 256 rows (their arrays stay in the caches: 20 % less CPU than 2 halves)
    run_parts(part, row_parts(rows, max(workers(), rows // 256), min_rows=32))
    out += np.float32(shift)
    out[~valid] = np.nan
    return out


def _reduced_right_pass(
    lwin: UInt8Array, rwin: UInt8Array, dmin: int, ndisp: int, params: SgbmParams
) -> Float32Array:
    """Disparities of the right window's pixels from a pass at half resolution, pixels.

    Both windows are mirrored and swapped (as the "flip" check does), cut to even sizes,
    reduced by 2 x 2 means, matched over the halved range, and the disparities (doubled)
    interpolated back onto the full-resolution right window (NaN where the reduced pass has
    none, or next to such a pixel).
    """
    rows, cols = lwin.shape
    hr, hc = rows // 2, cols // 2
    if hr < 1 or hc < 1:
        return np.full(lwin.shape, np.nan, dtype=np.float32)
    small = [
        cv2.resize(cv2.flip(img, 1)[: 2 * hr, : 2 * hc], (hc, hr), interpolation=cv2.INTER_AREA)
        for img in (rwin, lwin)
    ]
    lo = math.floor(dmin / 2) - 1
    hi = math.ceil((dmin + ndisp - 1) / 2) + 1
    nd = max(16, math.ceil((hi - lo + 1) / 16) * 16)
    # OpenCV leaves max(lo + nd, 0) columns on the left and max(-lo, 0) on the right without
    # a disparity: no-data columns on both sides keep them off the window
    left_pad, right_pad = max(lo + nd, 0), max(-lo, 0)
    small = [
        cv2.copyMakeBorder(im, 0, 0, left_pad, right_pad, cv2.BORDER_CONSTANT, value=0)
        for im in small
    ]
    raw = sgbm_matcher(params, lo, nd).compute(small[0], small[1])[:, left_pad : left_pad + hc]
    d = raw.astype(np.float32)
    d *= np.float32(2.0 / 16.0)
    d[raw == (lo - 1) * 16] = np.nan
    out = np.full(lwin.shape, np.nan, dtype=np.float32)
    # a reduced pixel is the mean of 2 x 2: its centre is full-resolution (2 j + 0.5), which
    # is where a 2x linear enlargement puts it; then mirrored back
    out[: 2 * hr, : 2 * hc] = cv2.resize(d, (2 * hc, 2 * hr), interpolation=cv2.INTER_LINEAR)
    return cast("Float32Array", cv2.flip(out, 1))


def _spans(n: int, tile: int) -> list[tuple[int, int]]:
    return [(s, min(n, s + tile)) for s in range(0, n, tile)]


def _balanced_spans(n: int, tile: int) -> list[tuple[int, int]]:
    """``n`` pixels cut into equal spans of at most 1.25 ``tile`` pixels.

    A 1,083 px side is one tile of 1,083, not 1,024 and a sliver of 59 that costs its whole
    overlap and padding.
    """
    k = max(1, math.ceil(n / (1.25 * tile)))
    edges = [round(i * n / k) for i in range(k + 1)]
    return list(itertools.pairwise(edges))


def match_pair(
    left: NDArray[Any],
    right: NDArray[Any],
    *,
    d_range: tuple[int, int],
    nodata: float | None = 0.0,
    left_mask: BoolArray | None = None,
    right_mask: BoolArray | None = None,
    tile_rows: int = 1024,
    tile_cols: int = 1024,
    overlap: int = 64,
    params: SgbmParams | None = None,
    guide: CoarseGuide | None = None,
) -> DisparityResult:
    """Dense disparity of a normalized pair (left grid), NaN where invalid.

    Args:
        left: left normalized image (rows, cols), uint8, uint16 or float32.
        right: right normalized image, same shape (same grid rows, as the pipeline makes them).
        d_range: (dmin, dmax) searched, pixels, from :func:`disparity_range` (either order);
            widened to a multiple of 16 disparities as SGBM needs.
        nodata: pixel value meaning "no data" in both images (None: every value is data).
        left_mask: optional bool (rows, cols), True where the left image has data.
        right_mask: same for the right image.
        tile_rows: rows of a tile, pixels (the image is cut into equal tiles of at most 1.25
            times this). The working memory is bounded by the tile, not the image: on a 4096 x
            4096 pair, 1024 px tiles took 144 MB besides the 64 MB result (one 4096 px tile:
            1.25 GB).
        tile_cols: columns of a tile, pixels.
        overlap: rows and columns matched around each tile and dropped, pixels; it lets the
            SGM paths settle so that tiles join without seams.
        params: matcher settings (default :class:`SgbmParams`).
        guide: a reduced pass first (:class:`CoarseGuide`): its support rule, and with its
            ``ranges`` each of its tiles (they replace ``tile_rows``, ``tile_cols`` and
            ``overlap``) searching what the reduced pass found there. When the reduced pair
            does not match, as without a guide.

    Returns:
        The disparity map, its status and the count of pixels per outcome. Bad inputs
        (textureless or saturated images, a range wider than the image, no data) give a
        status other than OK and an all-NaN (or mostly NaN) map, never an exception.

    Raises:
        ValueError: the images are not 2-D arrays of the same shape, or a tile size is < 16.
    """
    p = params or SgbmParams()
    if left.ndim != 2 or left.shape != right.shape:
        raise ValueError(f"need two 2-D images of one shape, got {left.shape} and {right.shape}")
    if min(tile_rows, tile_cols) < 16 or overlap < 0:
        raise ValueError("tile sizes must be >= 16 px and the overlap >= 0 px")
    h, w = left.shape
    dmin, dmax = sorted(int(v) for v in d_range)
    ndisp, shift, pad = _search(dmin, dmax)
    rng = (dmin, dmin + ndisp - 1)
    # Data masks and stretch limits, one row band at a time (no full-size temporary).
    # Per row, the first and last column with data of each image (-1, -1: none).
    n_data = n_right = 0
    samples: tuple[list[NDArray[Any]], list[NDArray[Any]]] = ([], [])
    extent = np.full((2, 2, h), -1, dtype=np.int64)
    step = max(1, math.ceil(math.sqrt(h * w / 1_000_000)))
    for r0, r1 in _spans(h, tile_rows):
        for side, (img, mask) in enumerate(((left, left_mask), (right, right_mask))):
            ok = _valid_mask(img[r0:r1], nodata, None if mask is None else mask[r0:r1])
            if side == 0:
                n_data += int(ok.sum())
            else:
                n_right += int(ok.sum())
            has = ok.any(axis=1)
            extent[side, 0, r0:r1] = np.where(has, np.argmax(ok, axis=1), -1)
            extent[side, 1, r0:r1] = np.where(has, w - 1 - np.argmax(ok[:, ::-1], axis=1), -1)
            first = (-r0) % step
            sub = img[r0 + first : r1 : step, ::step][ok[first::step, ::step]]
            # 8- and 16-bit as they are: numpy's percentiles of them are those of their
            # float64 copies to the bit (b - a of two sorted values cannot wrap), faster
            keep = sub.dtype in (np.uint8, np.uint16)
            samples[side].append(sub if keep else sub.astype(np.float64))
    # A left column c can meet right columns c - dmax .. c - dmin.
    both = (extent[0, 0] >= 0) & (extent[1, 0] >= 0)
    meet = both & (extent[0, 0] <= extent[1, 1] + rng[1]) & (extent[0, 1] >= extent[1, 0] + dmin)

    def failed(status: DenseStatus, message: str, reason: str) -> DisparityResult:
        counts = dict.fromkeys(_REASONS, 0)
        counts["nodata"] = h * w - n_data
        counts[reason] += n_data
        nan_map = np.full((h, w), np.nan, dtype=np.float32)
        return DisparityResult(nan_map, status, rng, 0.0, counts, message)

    if n_data == 0 or n_right == 0:
        return failed(DenseStatus.NO_OVERLAP, "the left or the right image has no data", "nodata")
    if not meet.any():
        return failed(
            DenseStatus.NO_OVERLAP,
            f"no left pixel with data has a partner with data within disparities {rng}",
            "lr_failure",
        )
    if ndisp >= w or ndisp > p.max_disparities:
        return failed(
            DenseStatus.RANGE_TOO_WIDE,
            f"disparity range {rng} ({ndisp} px) is as wide as the image ({w} px) or wider "
            f"than max_disparities ({p.max_disparities}): narrow the height range",
            "no_match",
        )
    limits: list[tuple[float, float]] = []
    for side, name in enumerate(("left", "right")):
        vals = np.concatenate(samples[side])
        if vals.size == 0:  # data only off the subsample: use every valid pixel
            img, mask = (left, left_mask) if side == 0 else (right, right_mask)
            vals = img[_valid_mask(img, nodata, mask)].astype(np.float64)
        lo, hi = (float(v) for v in np.percentile(vals, p.stretch_percentiles))
        if not hi > lo:
            return failed(
                DenseStatus.TEXTURELESS,
                f"the {name} image is uniform (or saturated): {p.stretch_percentiles} "
                f"percentiles {lo:g}, {hi:g} DN",
                "low_texture",
            )
        limits.append((lo, hi))
    prep = _Prepared(
        left,
        right,
        left_mask,
        right_mask,
        nodata,
        (limits[0], limits[1]),
        dmin - shift,
        ndisp,
        pad,
        shift,
    )
    matcher = _matcher_of(p, prep)
    coarse = near = None
    if guide is not None:
        coarse = _coarse_disparity(
            left, right, rng, guide.scale, nodata, (left_mask, right_mask), p
        )
        if coarse is not None:  # else as without a guide
            near = _near(coarse, guide)
            if guide.ranges:
                tile_rows = tile_cols = guide.tile_px
                overlap = guide.overlap_px
    disp = np.full((h, w), np.nan, dtype=np.float32)
    counts = np.zeros(len(_REASONS), dtype=np.int64)
    for r0, r1 in _balanced_spans(h, tile_rows):
        ra, rb = max(0, r0 - overlap), min(h, r1 + overlap)
        for c0, c1 in _balanced_spans(w, tile_cols):
            ca, cb = max(0, c0 - overlap), min(w, c1 + overlap)
            local = None
            if coarse is not None and guide is not None and guide.ranges:
                local = _tile_range(coarse, guide, rng, (ra, rb), (ca, cb))
            if local is None:
                d, code = _match_tile(prep, matcher, p, (ra, rb), (ca, cb))
            else:
                tprep = _tile_prepared(prep, local)
                tmatcher = _matcher_of(p, tprep)
                d, code = _match_tile(tprep, tmatcher, p, (ra, rb), (ca, cb))
            if near is not None and guide is not None:
                lost = (code == _VALID) & ~_supported(near, guide.scale, (ra, rb), (ca, cb))
                d[lost] = np.nan
                code[lost] = _NO_MATCH
            sr, sc = slice(r0 - ra, r1 - ra), slice(c0 - ca, c1 - ca)
            disp[r0:r1, c0:c1] = d[sr, sc]
            counts += np.bincount(code[sr, sc].ravel(), minlength=len(_REASONS))
    named = {k: int(v) for k, v in zip(_REASONS, counts, strict=True)}
    share = named["valid"] / n_data
    if share >= p.min_valid_share:
        status, msg = DenseStatus.OK, f"{100 * share:.1f} % of the left pixels with data matched"
    else:
        worst = max(("low_texture", "no_match", "lr_failure"), key=lambda k: named[k])
        status = DenseStatus.TEXTURELESS if worst == "low_texture" else DenseStatus.NO_MATCH
        msg = (
            f"only {100 * share:.1f} % of the left pixels with data matched "
            f"(< {100 * p.min_valid_share:.0f} %); most failures: {worst}"
        )
    return DisparityResult(disp, status, rng, share, named, msg)


def _coarse_disparity(
    left: NDArray[Any],
    right: NDArray[Any],
    d_range: tuple[int, int],
    scale: int,
    nodata: float | None,
    masks: tuple[BoolArray | None, BoolArray | None],
    params: SgbmParams | None,
) -> Float32Array | None:
    """Disparities of the pair reduced ``scale`` times, reduced pixels (NaN: none), or None.

    Means of ``scale`` x ``scale`` blocks (:func:`_reduced`). Matched over ``d_range / scale``
    with ``params`` (no sub-pixel refinement, no speckle filter, and SGBM on the reduced pair
    itself: ``scale`` 1 whatever ``params.scale``); None when the reduced pair does not match
    (its status is not OK) or is smaller than a block.
    """
    lo, hi = d_range
    if min(left.shape) < scale:
        return None
    small = [
        _reduced(img, nodata, mask, scale) for img, mask in zip((left, right), masks, strict=True)
    ]
    p = replace(params or SgbmParams(), subpixel="sgbm", min_ncc=None, speckle_window=0, scale=1)
    res = match_pair(
        small[0],
        small[1],
        d_range=(math.floor(lo / scale), math.ceil(hi / scale)),
        nodata=None,
        params=p,
    )
    return res.disparity if res.status == DenseStatus.OK else None


def _reduced(
    image: NDArray[Any],
    nodata: float | None,
    mask: BoolArray | None,
    scale: int,
    band_rows: int = 256,
) -> Float32Array:
    """Means of the ``scale`` x ``scale`` blocks of ``image`` (float32), NaN: no data.

    A block with any pixel without data has none; the rows and columns past the last whole
    block are left out. By bands of about ``band_rows`` rows (no full-size float copy of a
    large image). The means are OpenCV's area reduction (``cv2.INTER_AREA`` at a whole
    factor: the block's mean), the blocks with no data those whose no-data share reduced the
    same way is not 0; some 10 times faster than numpy's mean over the block axes.
    """
    hr, wr = image.shape[0] // scale, image.shape[1] // scale
    out = np.empty((hr, wr), dtype=np.float32)
    step = max(1, band_rows // scale)
    checked = nodata is not None or mask is not None or image.dtype.kind == "f"
    for i in range(0, hr, step):
        j = min(hr, i + step)
        rows = slice(i * scale, j * scale)
        part = image[rows, : wr * scale]
        size = (wr, j - i)
        red = out[i:j]
        red[...] = cv2.resize(part.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        if checked:
            ok = _valid_mask(part, nodata, None if mask is None else mask[rows, : wr * scale])
            # 1 where no data: a block's mean of it is >= 1 / scale^2 > 0 when any is
            bad = cv2.resize((~ok).astype(np.float32), size, interpolation=cv2.INTER_AREA)
            red[bad > 0] = np.nan
    return out


def _near(coarse: Float32Array, opt: CoarseGuide) -> UInt8Array | None:
    """1 where a valid reduced pixel lies within ``opt.support`` reduced pixels (None: no rule)."""
    if opt.support < 0:
        return None
    k = 2 * opt.support + 1
    return cast(
        "UInt8Array", cv2.dilate(np.isfinite(coarse).view(np.uint8), np.ones((k, k), np.uint8))
    )


def _supported(
    near: UInt8Array, scale: int, rows: tuple[int, int], cols: tuple[int, int]
) -> BoolArray:
    """The support rule over the window rows x cols (full-resolution pixels).

    True where the pixel's reduced pixel (the last one for pixels past the last whole block) is
    near a valid reduced pixel (``near``, :func:`_near`).
    """
    r = np.minimum(np.arange(rows[0], rows[1]) // scale, near.shape[0] - 1)
    c = np.minimum(np.arange(cols[0], cols[1]) // scale, near.shape[1] - 1)
    # two takes, rows then columns: the same cells as near[r[:, None], c[None, :]], faster
    out: BoolArray = near.take(r, axis=0).take(c, axis=1) != 0
    return out


def _tile_range(
    coarse: Float32Array,
    opt: CoarseGuide,
    rng: tuple[int, int],
    rows: tuple[int, int],
    cols: tuple[int, int],
) -> tuple[int, int] | None:
    """The disparities a tile window rows x cols searches (:class:`CoarseGuide`), or None.

    None: too few valid reduced pixels over the window (it searches ``rng``).
    """
    s = opt.scale
    part = coarse[
        max(0, rows[0] // s - 1) : rows[1] // s + 2, max(0, cols[0] // s - 1) : cols[1] // s + 2
    ]
    v = part[np.isfinite(part)]
    if v.size < opt.min_cells:
        return None
    pad = opt.margin_px + s
    lo = max(rng[0], math.floor(float(v.min()) * s - pad))
    hi = min(rng[1], math.ceil(float(v.max()) * s + pad))
    return (lo, hi) if lo <= hi else None


def _search(dmin: int, dmax: int) -> tuple[int, int, int]:
    """(ndisp, shift, pad) of a search from ``dmin`` over at least ``dmax`` (:class:`_Prepared`).

    ``ndisp``: the disparities SGBM searches (a multiple of 16, at least 16); ``shift``: the
    right window's shift that centres them on 0; ``pad``: the columns each side of a tile that
    hold every partner. Pixels.
    """
    ndisp = max(16, math.ceil((dmax - dmin + 1) / 16.0) * 16)
    shift = dmin + ndisp // 2
    pad = max(abs(dmin - shift), abs(dmin + ndisp - 1 - shift)) + 1
    return ndisp, shift, pad


def _tile_prepared(prep: _Prepared, d_range: tuple[int, int]) -> _Prepared:
    """``prep`` for a tile searching ``d_range`` (pixels, inclusive): its own shift and pad."""
    dmin, dmax = d_range
    ndisp, shift, pad = _search(dmin, dmax)
    return replace(prep, dmin=dmin - shift, ndisp=ndisp, pad=pad, shift=shift)


def refine_range(
    left: NDArray[Any],
    right: NDArray[Any],
    *,
    d_range: tuple[int, int],
    scale: int = 4,
    nodata: float | None = 0.0,
    percentiles: tuple[float, float] = (0.5, 99.5),
    margin_px: float = 8.0,
    params: SgbmParams | None = None,
) -> tuple[int, int] | None:
    """A narrower disparity range from matching a ``scale`` times reduced pair over ``d_range``.

    For a pair whose height range (GCP, ``z_avg`` +- ``height_range``) gives a search range too
    wide to match at full resolution: both images are reduced by area averaging (a reduced
    pixel with any no-data input pixel has no data), matched over ``d_range / scale``, and the
    ``percentiles`` of the valid reduced disparities, times ``scale`` and widened by
    ``margin_px`` plus one reduced pixel, are returned (intersected with ``d_range``).

    Args:
        left: left normalized image.
        right: right normalized image (same shape).
        d_range: the wide range, pixels (either order).
        scale: reduction factor (>= 2).
        nodata: the images' no-data value (None: none).
        percentiles: of the reduced disparities kept, percent.
        margin_px: added on both sides, full-resolution pixels.
        params: matcher settings of the reduced matching.

    Returns:
        (dmin, dmax), full-resolution pixels, or None when the reduced pair does not match
        (its :class:`DenseStatus` is not OK): search the whole ``d_range`` or give up.
    """
    if scale < 2:
        raise ValueError(f"scale must be >= 2, got {scale}")
    lo, hi = sorted(int(v) for v in d_range)
    coarse = _coarse_disparity(left, right, (lo, hi), scale, nodata, (None, None), params)
    if coarse is None:
        return None
    d = coarse[np.isfinite(coarse)]
    p0, p1 = (float(v) for v in np.percentile(d, percentiles))
    pad = margin_px + scale
    out = (max(lo, math.floor(p0 * scale - pad)), min(hi, math.ceil(p1 * scale + pad)))
    return out if out[0] <= out[1] else None
