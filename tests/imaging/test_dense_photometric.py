"""The dense matcher's photometric check (imaging/dense.py, ``SgbmParams.min_ncc``).

After the sub-pixel step, each valid pixel's window is correlated with the right image
resampled at its disparities (``_window_ncc``); below ``min_ncc`` the pixel is rejected. The
pairs are made as in test_dense_subpixel.py: a band-limited random texture (Gaussian blur of
1 px) seen by the right image displaced by a known disparity field, so that the correlation
of a right match is known to be near 1 (only the linear resampling's error) and that of a
wrong one near 0 (the texture's autocorrelation at a lag of 4 px is exp(-4^2 / 4) = 0.02,
its Gaussian blur of 1 px seen twice).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_dense_subpixel import INNER, H, W, make_pair, smooth

from parproj_ros.imaging.dense import (
    DenseStatus,
    SgbmParams,
    _window_ncc,
    match_pair,
    to_uint8,
)


def stretched(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both images to 8 bits over one range (the matcher's own stretch is per image)."""
    lo, hi = (float(v) for v in np.percentile(left, (0.5, 99.5)))
    return to_uint8(left, lo, hi), to_uint8(right, lo, hi)


def test_the_correlation_is_near_1_at_the_true_disparities_and_near_0_off_them() -> None:
    left, right, truth = make_pair(smooth)
    l8, r8 = stretched(left, right)
    cols = slice(0, W)
    good = _window_ncc(l8, r8, truth.astype(np.float32), cols, 0, 1.5)[INNER]
    bad = _window_ncc(l8, r8, (truth + 4.0).astype(np.float32), cols, 0, 1.5)[INNER]
    print(f"NCC at the truth: median {np.median(good):.4f}, 0.1 % {np.percentile(good, 0.1):.3f}")
    print(f"4 px off: median {np.median(bad):+.3f}, 99.9 % {np.percentile(bad, 99.9):.3f}")
    # at the truth only the linear resampling of a texture blurred by 1 px differs
    assert np.median(good) > 0.98
    assert np.percentile(good, 0.1) > 0.9
    # 4 px off, the texture is uncorrelated: the window's own spread (some 10-30
    # independent samples under a Gaussian of 1.5 px: +-0.2-0.3) around 0, a little below
    # (the window's mean removed, the texture anti-correlates at a lag of a few pixels:
    # -0.12 here); 0.7 is some 2.7 of those spreads above: < 1 % above it
    assert abs(float(np.median(bad))) < 0.2
    assert np.mean(bad < 0.7) > 0.99


def test_a_faint_window_passes_and_invalid_pixels_have_none() -> None:
    """Noise of 1 DN on a flat area: no correlation, but a difference below ncc_noise_dn."""
    rng = np.random.default_rng(3)
    l8 = np.clip(100 + rng.normal(0, 1, (64, 96)), 0, 255).astype(np.uint8)
    r8 = np.clip(100 + rng.normal(0, 1, (64, 96)), 0, 255).astype(np.uint8)
    disp = np.full(l8.shape, 2.0, dtype=np.float32)
    disp[:, :10] = np.nan
    cols = slice(0, 96)
    raw = _window_ncc(l8, r8, disp, cols, 0, 1.5)
    kept = _window_ncc(l8, r8, disp, cols, 0, 1.5, noise_dn=4.0)
    assert np.all(np.isnan(raw[:, :10])) and np.all(np.isnan(kept[:, :10]))
    inner = (slice(8, -8), slice(18, -8))
    # the difference has a standard deviation of sqrt(2) DN (1.5 with rounding) < 4 DN
    assert np.median(np.abs(raw[inner])) < 0.3
    assert np.all(kept[inner] == 1.0)


def occluded_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[slice, slice]]:
    """A smooth pair whose right image shows another texture in a 48 x 48 px patch.

    The left pixels whose partners fall into the patch have no true match there (as in an
    occlusion, or a change between the two dates).
    """
    left, right, truth = make_pair(smooth)
    other, _, _ = make_pair(smooth, seed=7)
    patch = (slice(96, 144), slice(136, 184))
    right = right.copy()
    right[patch] = other[patch]
    return left, right, truth, patch


def test_the_check_rejects_a_patch_without_partner_and_little_else() -> None:
    left, right, truth, (pr, pc) = occluded_pair()
    rng = (int(np.floor(truth.min())) - 4, int(np.ceil(truth.max())) + 4)
    # SGBM's own uniqueness and speckle tests off, so that it gives the patch disparities
    # (its uniqueness test alone rejects 99.9 % of them here; not so the blunders at the
    # simulated bags' occlusions, docs/heights.md run 6)
    kw = {"lr_check": "none", "uniqueness_ratio": 0, "speckle_window": 0}
    off = match_pair(left, right, d_range=rng, params=SgbmParams(**kw))  # type: ignore[arg-type]
    on = match_pair(left, right, d_range=rng, params=SgbmParams(**kw, min_ncc=0.7))  # type: ignore[arg-type]
    assert off.status == DenseStatus.OK and on.status == DenseStatus.OK
    # the left pixels whose partner (x - d) lies in the patch, 6 px (the block, the window)
    # inside its edges; and those whose partner is 12 px or more outside it
    rows, cols = np.mgrid[0:H, 0:W]
    xr = cols - truth
    inside = (rows >= pr.start + 6) & (rows < pr.stop - 6)
    inside &= (xr >= pc.start + 6) & (xr < pc.stop - 6)
    outside = (rows < pr.start - 12) | (rows >= pr.stop + 12)
    outside |= (xr < pc.start - 12) | (xr >= pc.stop + 12)
    inner = np.zeros(truth.shape, dtype=bool)
    inner[INNER] = True
    outside &= inner
    v_off, v_on = np.isfinite(off.disparity), np.isfinite(on.disparity)
    blunder = v_off & inside & (np.abs(off.disparity - truth) > 1.0)
    print(
        f"in the patch: {v_off[inside].mean():.3f} valid without the check, "
        f"{v_on[inside].mean():.3f} with; blunders kept {np.sum(blunder & v_on)} of "
        f"{blunder.sum()}; outside: {v_off[outside].mean():.4f} -> {v_on[outside].mean():.4f}"
    )
    # SGBM gives most of them a (wrong) disparity
    assert blunder.sum() > 0.5 * inside.sum()
    # The check rejects most of those blunders: 70 % here. Not all: the disparity SGBM
    # picks is the best match of the 32 searched, whose correlation is the highest of 32
    # draws, not that of one uncorrelated lag (< 0.7 for 99.6 %, the first test).
    assert np.sum(blunder & ~v_on) > 0.6 * blunder.sum()
    # It costs less than 0.5 % of the pixels away from the patch.
    assert v_on[outside].mean() > v_off[outside].mean() - 0.005
    # Which disparities it keeps, it keeps as they were.
    both = v_on & v_off
    assert np.array_equal(on.disparity[both], off.disparity[both])
    # The rejected pixels are counted as left-right failures.
    rejected = int(np.sum(v_off & ~v_on))
    assert on.counts["lr_failure"] - off.counts["lr_failure"] == rejected


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="min_ncc"):
        SgbmParams(min_ncc=1.5)
    with pytest.raises(ValueError, match="ncc_sigma_px"):
        SgbmParams(min_ncc=0.7, ncc_sigma_px=0.0)
    # a correlation is never below -1: the check then rejects nothing and changes nothing
    left, right, _ = make_pair(smooth, seed=1)
    a = match_pair(left, right, d_range=(0, 24))
    b = match_pair(left, right, d_range=(0, 24), params=SgbmParams(min_ncc=-1.0))
    assert np.array_equal(a.disparity, b.disparity, equal_nan=True)
    assert a.counts == b.counts
