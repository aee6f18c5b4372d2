"""Sub-pixel refinement of the dense matcher (imaging/dense.py, ``SgbmParams.subpixel``).

OpenCV's SGBM interpolates its disparities with a parabola through three aggregated costs,
which pulls them towards whole pixels ("pixel-locking"): the error depends on the true
disparity's fractional part. ``subpixel="gradient"`` refines them on the images
(``_refine_subpixel``). The pairs here are made as in test_dense.py: a band-limited random
texture seen by the right image displaced by a known disparity field (smooth, a steep plane,
a step), so that every pixel's error is known.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import pytest

from parproj_ros.imaging.dense import DenseStatus, SgbmParams, match_pair

H, W = 240, 320
Field = Callable[[np.ndarray, np.ndarray], np.ndarray]


def make_pair(field: Field, seed: int = 0, pad: int = 40) -> tuple[np.ndarray, ...]:
    """(left uint16, right uint16, true left disparity px) with right(c - d(c)) = left(c)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 2047, (H, W + 2 * pad)).astype(np.float32), (0, 0), 1)
    tex = cv2.normalize(tex, None, 50, 2000, cv2.NORM_MINMAX)
    rr, cc = np.mgrid[0:H, 0 : W + 2 * pad].astype(np.float64)
    d = field(rr, cc - pad)
    rr, cr = np.mgrid[0:H, 0:W].astype(np.float64)
    cl = cr + d[:, pad : pad + W]
    for _ in range(30):  # the left column a right pixel sees: cl = cr + d(cl)
        cl = cr + cv2.remap(
            d.astype(np.float32), (cl + pad).astype(np.float32), rr.astype(np.float32),
            cv2.INTER_LINEAR,
        )  # fmt: skip
    right = cv2.remap(tex, (cl + pad).astype(np.float32), rr.astype(np.float32), cv2.INTER_CUBIC)
    to16 = lambda a: np.clip(np.rint(a), 1, 2047).astype(np.uint16)  # noqa: E731
    return to16(tex[:, pad : pad + W]), to16(right), d[:, pad : pad + W]


def smooth(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """12 +- 6 px, slopes up to 0.09 px per px."""
    return 12.0 + 6.0 * np.sin(c / 70.0) * np.cos(r / 55.0)


def steep(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """A plane rising 0.2 px of disparity per column."""
    return 4.0 + 0.2 * c + 0.0 * r


def step(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Two levels 6.4 px apart, the edge at column 160."""
    return np.where(c < 160, 8.3, 14.7) + 0.0 * r


INNER = (slice(30, -30), slice(60, -30))  # the right image holds every partner there


def both(field: Field) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(SGBM's disparities, the refined ones, the truth) of a pair made of ``field``."""
    left, right, truth = make_pair(field)
    rng = (int(np.floor(truth.min())) - 4, int(np.ceil(truth.max())) + 4)
    out = []
    for sp in ("sgbm", "gradient"):
        res = match_pair(left, right, d_range=rng, params=SgbmParams(subpixel=sp))
        assert res.status == DenseStatus.OK, res.message
        out.append(res.disparity)
    return out[0], out[1], truth


def locking(err: np.ndarray, truth: np.ndarray) -> float:
    """Spread (max - min) of the mean error over 8 bins of the truth's fractional part, px."""
    b = np.minimum(((truth - np.floor(truth)) * 8).astype(int), 7)
    means = [err[b == k].mean() for k in range(8)]
    return float(max(means) - min(means))


def test_refinement_removes_pixel_locking_on_a_smooth_field() -> None:
    sgbm, grad, truth = both(smooth)
    # the refinement changes values, not which pixels are valid
    assert np.array_equal(np.isnan(sgbm), np.isnan(grad))
    t = truth[INNER]
    e0, e1 = sgbm[INNER] - t, grad[INNER] - t
    ok = np.isfinite(e0)
    assert ok.mean() > 0.99
    e0, e1, t = e0[ok], e1[ok], t[ok]
    rms0, rms1 = (float(np.sqrt(np.mean(e**2))) for e in (e0, e1))
    lock0, lock1 = locking(e0, t), locking(e1, t)
    print(f"RMS {rms0:.4f} -> {rms1:.4f} px, locking {lock0:.4f} -> {lock1:.4f} px")
    # SGBM's error depends on the fractional part (0.21 px from bin to bin here) ...
    assert lock0 > 0.15
    # ... the refined one hardly (0.04), and it is a fifth of SGBM's (0.025 against 0.127)
    assert lock1 < 0.25 * lock0
    assert rms1 < 0.4 * rms0
    assert abs(float(np.median(e1))) < 0.02


def test_a_steep_slope_is_not_biased() -> None:
    """0.2 px of disparity per column: the window's fit is moved back to the pixel."""
    sgbm, grad, truth = both(steep)
    t = truth[INNER]
    e0, e1 = sgbm[INNER] - t, grad[INNER] - t
    ok = np.isfinite(e0)
    e0, e1 = e0[ok], e1[ok]
    rms0, rms1 = (float(np.sqrt(np.mean(e**2))) for e in (e0, e1))
    print(f"RMS {rms0:.4f} -> {rms1:.4f} px, median {np.median(e0):+.4f} -> {np.median(e1):+.4f}")
    assert rms1 < 0.6 * rms0  # 0.054 against 0.117 px
    assert abs(float(np.median(e1))) < 0.03


def test_an_edge_keeps_its_blunders_and_the_levels_their_accuracy() -> None:
    """A disparity step: away from it the refined levels are exact; at it, no new blunders."""
    sgbm, grad, truth = both(step)
    valid = np.isfinite(sgbm)
    # never farther than subpixel_max_px from SGBM's disparity
    assert np.nanmax(np.abs(grad - sgbm)) <= SgbmParams().subpixel_max_px + 1e-4
    cols = np.arange(W)[None, :]
    inner = np.zeros(truth.shape, dtype=bool)
    inner[INNER] = True
    far = inner & valid & (np.abs(cols - 160) > 10)
    rms0, rms1 = (float(np.sqrt(np.mean((d - truth)[far] ** 2))) for d in (sgbm, grad))
    print(f"RMS away from the edge {rms0:.4f} -> {rms1:.4f} px")
    assert rms1 < 0.05 < rms0
    near = inner & valid
    blunders = [int(np.sum(np.abs(d - truth)[near] > 1.0)) for d in (sgbm, grad)]
    print(f"errors > 1 px: {blunders}")
    assert blunders[1] <= blunders[0] + 0.001 * near.sum()


@pytest.mark.parametrize("level", [8.3, 14.7])
def test_the_fit_converges_to_the_true_disparity(level: float) -> None:
    """A constant disparity with a fractional part: the fit's steps converge on it.

    With the right image resampled bilinearly the steps settle 0.03-0.05 px off a fraction of
    .3 or .7 (the interpolation pulls the fit towards whole pixels); resampled bicubically, at
    the truth (0.000 px after 4 steps; 0.005 after the default 2).
    """
    left, right, truth = make_pair(lambda r, c: level + 0.0 * c)
    rng = (int(level) - 6, int(level) + 6)
    for steps, bound in ((2, 0.012), (4, 0.004)):
        p = SgbmParams(subpixel="gradient", subpixel_iterations=steps)
        res = match_pair(left, right, d_range=rng, params=p)
        err = (res.disparity - truth)[INNER]
        err = err[np.isfinite(err)]
        assert err.size > 0.99 * truth[INNER].size
        print(f"{level} px, {steps} steps: median {np.median(err):+.4f} px")
        assert abs(float(np.median(err))) < bound


def test_tiles_and_threads_do_not_change_the_refinement() -> None:
    """Row parts on threads (each with the rows its filters reach) and tiles join seamlessly."""
    left, right, _ = make_pair(smooth, seed=2)
    p = SgbmParams(subpixel="gradient")
    whole = match_pair(left, right, d_range=(0, 24), params=p).disparity
    n = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        one = match_pair(left, right, d_range=(0, 24), params=p).disparity
    finally:
        cv2.setNumThreads(n)
    assert np.array_equal(np.isnan(whole), np.isnan(one))
    assert np.nanmax(np.abs(whole - one)) < 1e-4
    tiled = match_pair(
        left, right, d_range=(0, 24), params=p, tile_rows=64, tile_cols=96, overlap=48
    ).disparity
    inner = np.zeros(left.shape, dtype=bool)
    inner[16:-16, 16:-16] = True
    ok = inner & np.isfinite(whole) & np.isfinite(tiled)
    assert ok.sum() > 0.99 * inner.sum()
    close = np.abs(whole[ok] - tiled[ok]) <= 0.02
    assert close.mean() > 0.995, close.mean()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"subpixel": "parabola"}, "subpixel must be"),
        ({"subpixel_sigma_px": 0.0}, "subpixel_sigma_px"),
        ({"subpixel_iterations": 0}, "subpixel_iterations"),
    ],
)
def test_bad_subpixel_settings_raise(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        SgbmParams(**kwargs)  # type: ignore[arg-type]
