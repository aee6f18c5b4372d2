"""Tie points between two normalized images: SIFT matches refined to sub-pixel by correlation.

The images are already close to epipolar, so a match is looked for in a window of the other
image at the same place (plus a disparity margin); every SIFT match is then refined by
normalized cross-correlation of a small patch with a parabola fit of the peak, which is
accurate to a few hundredths of a pixel on textured ground (SIFT positions alone are not).
Large images are sampled in a grid of windows, so the cost does not grow with the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Matches:
    """Conjugate points, (n,) arrays of pixel coordinates (col, row) in each image.

    Attributes:
        xl: left columns.
        yl: left rows.
        xr: right columns.
        yr: right rows.
        score: NCC peak of each match.
    """

    xl: FloatArray
    yl: FloatArray
    xr: FloatArray
    yr: FloatArray
    score: FloatArray

    def __len__(self) -> int:
        return int(self.xl.size)

    def subset(self, mask: NDArray[np.bool_]) -> Matches:
        """The matches where ``mask`` is True."""
        return Matches(
            self.xl[mask], self.yl[mask], self.xr[mask], self.yr[mask], self.score[mask]
        )


def stretch_limits(img: NDArray[np.generic], nodata: float) -> tuple[float, float]:
    """1st and 99th percentiles of the valid pixels, from a subsample of at most ~250k."""
    step = max(1, int(np.sqrt(img.size / 250_000)))
    a = np.asarray(img[::step, ::step], dtype=np.float32)
    v = a[np.isfinite(a) & (a != nodata)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [1.0, 99.0])
    return float(lo), float(hi)


def to_uint8(
    img: NDArray[np.generic], nodata: float = 0.0, limits: tuple[float, float] | None = None
) -> NDArray[np.uint8]:
    """Linear stretch of valid pixels to 1..255 between ``limits``; nodata becomes 0.

    ``limits`` defaults to the 1st and 99th percentiles (:func:`stretch_limits`).
    """
    lo, hi = limits if limits is not None else stretch_limits(img, nodata)
    a = np.asarray(img, dtype=np.float32)
    valid = np.isfinite(a) & (a != nodata)
    scaled = np.nan_to_num((a - lo) * (254.0 / max(hi - lo, 1e-12)) + 1.0)
    out: NDArray[np.uint8] = np.clip(scaled, 1, 255).astype(np.uint8)
    out[~valid] = 0
    return out


def _refine(
    lf: NDArray[np.generic],
    rf: NDArray[np.generic],
    nodata: float,
    xl: float,
    yl: float,
    xr: float,
    yr: float,
    half: int,
    search: int,
    min_corr: float,
) -> tuple[float, float, float] | None:
    cl, rl, cr, rr = round(xl), round(yl), round(xr), round(yr)
    if (
        min(cl, rl) < half
        or min(cr, rr) < half + search
        or rl + half >= lf.shape[0]
        or cl + half >= lf.shape[1]
        or rr + half + search >= rf.shape[0]
        or cr + half + search >= rf.shape[1]
    ):
        return None
    tpl = lf[rl - half : rl + half + 1, cl - half : cl + half + 1].astype(np.float32)
    win = rf[
        rr - half - search : rr + half + search + 1, cr - half - search : cr + half + search + 1
    ].astype(np.float32)
    if (
        (tpl == nodata).any()
        or (win == nodata).any()
        or not (np.isfinite(tpl).all() and np.isfinite(win).all())
        or tpl.std() == 0
    ):
        return None
    res = cv2.matchTemplate(win, tpl, cv2.TM_CCOEFF_NORMED)
    _, peak, _, (px, py) = cv2.minMaxLoc(res)
    if peak < min_corr or px in (0, res.shape[1] - 1) or py in (0, res.shape[0] - 1):
        return None

    def parabola(a: float, b: float, c: float) -> float:
        d = a - 2 * b + c
        return 0.0 if d == 0 else 0.5 * (a - c) / d

    dy = parabola(res[py - 1, px], res[py, px], res[py + 1, px])
    dx = parabola(res[py, px - 1], res[py, px], res[py, px + 1])
    # Position in the right image of the left pixel (cl, rl).
    return cr - search + px + dx, rr - search + py + dy, float(peak)


def match_normalized(
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    *,
    nodata: float = 0.0,
    window: int = 768,
    grid: int = 4,
    max_per_window: int = 150,
    half: int = 10,
    search: int = 3,
    min_corr: float = 0.85,
    max_y_px: float | None = 50.0,
    detector: str = "sift",
    whole: bool = False,
) -> Matches:
    """Tie points between two normalized images of equal size (pixels, sub-pixel refined).

    Args:
        left: left normalized image.
        right: right normalized image, same shape.
        nodata: value of pixels outside the scenes.
        window: side of the sampled windows, pixels (the whole image when smaller).
        grid: windows per side (grid x grid, spread over the image).
        max_per_window: best SIFT matches kept per window.
        half: half size of the correlation patch, pixels.
        search: correlation search radius around the SIFT position, pixels.
        min_corr: smallest accepted NCC peak.
        max_y_px: matches with a larger row difference are discarded (gross errors); None keeps
            all (images that are not yet epipolar).
        detector: "sift", or "orb" for key points independent of SIFT's (an evaluation that
            must not reuse the tie points).
        whole: one window over the whole image, whatever its shape (``window`` and ``grid``
            ignored): conjugate points may then lie anywhere along the rows (a small, reduced
            image whose disparities are not known yet).
    """
    h, w = left.shape
    lim_l, lim_r = stretch_limits(left, nodata), stretch_limits(right, nodata)
    feat: cv2.Feature2D
    if detector == "orb":
        feat = cv2.ORB.create(nfeatures=4 * max_per_window, fastThreshold=5)
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    else:
        feat = cv2.SIFT.create(nfeatures=4 * max_per_window)
        matcher = cv2.BFMatcher(cv2.NORM_L2)
    wr = wc = min(window, h, w)
    min_valid = 0.3  # share of a window with data in both images
    if whole:
        wr, wc, min_valid = h, w, 0.02
    r0s = np.unique(np.linspace(0, h - wr, grid).round().astype(int)) if h > wr else [0]
    c0s = np.unique(np.linspace(0, w - wc, grid).round().astype(int)) if w > wc else [0]
    out: list[tuple[float, float, float, float, float]] = []
    for r0 in r0s:
        for c0 in c0s:
            sl = np.s_[r0 : r0 + wr, c0 : c0 + wc]
            a, b = to_uint8(left[sl], nodata, lim_l), to_uint8(right[sl], nodata, lim_r)
            if (a > 0).mean() < min_valid or (b > 0).mean() < min_valid:
                continue
            ka, da = feat.detectAndCompute(a, (a > 0).astype(np.uint8))
            kb, db = feat.detectAndCompute(b, (b > 0).astype(np.uint8))
            if da is None or db is None or len(ka) < 2 or len(kb) < 2:
                continue
            pairs = matcher.knnMatch(da, db, k=2)
            good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
            good.sort(key=lambda m: m.distance)
            for m in good[:max_per_window]:
                xl, yl = ka[m.queryIdx].pt
                xr, yr = kb[m.trainIdx].pt
                if max_y_px is not None and abs(yl - yr) > max_y_px:
                    continue
                ref = _refine(
                    left, right, nodata, xl + c0, yl + r0, xr + c0, yr + r0, half, search, min_corr
                )
                if ref is not None:
                    out.append((float(round(xl + c0)), float(round(yl + r0)), *ref))
    arr = np.array(out, dtype=float).reshape(-1, 5)
    # One match per left pixel (windows may overlap).
    _, keep = np.unique(arr[:, :2], axis=0, return_index=True)
    arr = arr[np.sort(keep)]
    return Matches(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4])
