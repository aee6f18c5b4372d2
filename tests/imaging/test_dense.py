"""Dense matching of a normalized pair (imaging/dense.py), ROS-free.

The pairs here are made directly: a band-limited random texture seen by the left image as is
and by the right one displaced by a known smooth disparity field, so that every pixel's true
disparity ``col_left - col_right`` is known.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
import pytest

from parproj_ros.imaging.dense import (
    DenseStatus,
    SgbmParams,
    disparity_range,
    match_pair,
    refine_range,
    to_uint8,
)

H, W = 240, 320
SUBPIXEL = 1.0 / 16.0  # SGBM's disparity step, px


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Band-limited 11-bit texture (float), blurred so that it interpolates smoothly."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 2047, (h, w)).astype(np.float32), (0, 0), 1.0)
    return cv2.normalize(t, None, 50, 2000, cv2.NORM_MINMAX)


def true_disparity(h: int, w: int, base: float = 12.0) -> np.ndarray:
    """Smooth disparity field of the left pixels, px (base +- 6 px)."""
    rr, cc = np.mgrid[0:h, 0:w].astype(np.float64)
    return base + 6.0 * np.sin(cc / 70.0) * np.cos(rr / 55.0)


def make_pair(
    h: int = H, w: int = W, base: float = 12.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left uint16, right uint16, true left disparity px): right(c - d(c)) = left(c)."""
    pad = int(base) + 16
    tex = texture(h, w + 2 * pad, seed)
    d = true_disparity(h, w + 2 * pad, base)
    left = tex[:, pad : pad + w]
    # A right pixel cr sees the left column cl = cr + d(cl): solve by fixed-point iteration.
    rr, cr = np.mgrid[0:h, 0:w].astype(np.float64)
    cl = cr + base
    for _ in range(20):
        cl = cr + cv2.remap(
            d.astype(np.float32),
            (cl + pad).astype(np.float32),
            rr.astype(np.float32),
            cv2.INTER_LINEAR,
        )
    right = cv2.remap(tex, (cl + pad).astype(np.float32), rr.astype(np.float32), cv2.INTER_CUBIC)
    to16 = lambda a: np.clip(np.rint(a), 1, 2047).astype(np.uint16)  # noqa: E731
    return to16(left), to16(right), d[:, pad : pad + w]


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return make_pair()


def interior(shape: tuple[int, int], margin: int = 40) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    m[margin:-margin, margin:-margin] = True
    return m


# ---- disparity_range ----------------------------------------------------------------------------


def test_disparity_range_from_the_linear_relation() -> None:
    # Z = a d + b with a = 0.5 m/px, b = 100 m: Z 90..140 m is d -20..80 px, plus the margin.
    assert disparity_range(0.5, 100.0, (90.0, 140.0), 4.0) == (-24, 84)
    assert disparity_range(0.5, 100.0, (140.0, 90.0), 4.0) == (-24, 84)
    # Non-integer ends are widened outwards.
    assert disparity_range(0.3, 0.0, (-1.0, 1.0), 0.0) == (
        math.floor(-1 / 0.3),
        math.ceil(1 / 0.3),
    )


def test_disparity_range_inverted_sign() -> None:
    # An inverted x-parallax (a < 0): the lower ground has the larger disparity.
    assert disparity_range(-0.5, 100.0, (90.0, 140.0), 4.0) == (-84, 24)


@pytest.mark.parametrize("a", [0.0, float("nan"), float("inf")])
def test_disparity_range_without_base_raises(a: float) -> None:
    with pytest.raises(ValueError, match="non-zero"):
        disparity_range(a, 0.0, (0.0, 10.0))


# ---- accuracy -----------------------------------------------------------------------------------


def test_match_pair_recovers_the_disparity(pair: tuple[np.ndarray, ...]) -> None:
    left, right, truth = pair
    res = match_pair(left, right, d_range=(0, 24))
    assert res.status == DenseStatus.OK, res.message
    assert res.disparity.dtype == np.float32 and res.disparity.shape == left.shape
    inner = interior(left.shape)
    ok = inner & np.isfinite(res.disparity)
    assert ok.sum() >= 0.97 * inner.sum()
    err = res.disparity[ok] - truth[ok]
    # Sub-pixel: errors well below a pixel.
    assert np.median(np.abs(err)) < 0.2, np.median(np.abs(err))
    assert np.mean(np.abs(err) < 1.0) > 0.99
    # The left pass alone gives OpenCV's 1/16 px steps; the mean with the right pass (at the
    # partner) is closer to the truth.
    one = match_pair(left, right, d_range=(0, 24), params=SgbmParams(lr_check="none"))
    d1 = one.disparity[ok]
    assert np.array_equal(np.round(d1[np.isfinite(d1)] * 16) / 16, d1[np.isfinite(d1)])
    e1 = d1 - truth[ok]
    assert np.median(np.abs(err)) < 0.98 * np.nanmedian(np.abs(e1))  # 0.088 against 0.091 px
    assert sum(res.counts.values()) == left.size
    assert res.counts["valid"] == int(np.isfinite(res.disparity).sum())
    assert res.d_range[0] == 0 and (res.d_range[1] - res.d_range[0] + 1) % 16 == 0


def test_a_range_far_from_zero_is_searched_around_its_centre() -> None:
    """Disparities near 150 px: the right image is read shifted, the result is unchanged."""
    left, right, truth = make_pair(base=150.0, seed=3)
    res = match_pair(left, right, d_range=(138, 162))
    assert res.status == DenseStatus.OK, res.message
    ok = interior(left.shape) & np.isfinite(res.disparity)
    assert ok.sum() > 0.5 * interior(left.shape).sum()
    assert np.median(np.abs(res.disparity[ok] - truth[ok])) < 0.2


def test_tiled_equals_untiled_on_the_interior(pair: tuple[np.ndarray, ...]) -> None:
    left, right, _ = pair
    whole = match_pair(left, right, d_range=(0, 24), tile_rows=4096, tile_cols=4096)
    tiled = match_pair(left, right, d_range=(0, 24), tile_rows=64, tile_cols=96, overlap=48)
    inner = interior(left.shape, 16)
    a, b = whole.disparity[inner], tiled.disparity[inner]
    same_validity = np.isnan(a) == np.isnan(b)
    assert same_validity.mean() > 0.995, same_validity.mean()
    both = np.isfinite(a) & np.isfinite(b)
    close = np.abs(a[both] - b[both]) <= SUBPIXEL + 1e-6
    assert close.mean() > 0.995, close.mean()
    assert tiled.status == DenseStatus.OK


def test_inverted_sign_is_matched(pair: tuple[np.ndarray, ...]) -> None:
    """Both images mirrored: every disparity changes sign, as with a < 0."""
    left, right, truth = pair
    lo, hi = disparity_range(-0.5, 0.0, (0.0, 12.0), 0.0)  # a < 0: (-24, 0)
    res = match_pair(left[:, ::-1], right[:, ::-1], d_range=(lo, hi))
    assert res.status == DenseStatus.OK, res.message
    d = res.disparity[:, ::-1]
    ok = interior(left.shape) & np.isfinite(d)
    assert ok.sum() >= 0.95 * interior(left.shape).sum()
    assert np.median(np.abs(-d[ok] - truth[ok])) < 0.2


def test_left_right_check_rejects_what_the_right_image_does_not_show(
    pair: tuple[np.ndarray, ...],
) -> None:
    left, right, truth = pair
    right = right.copy()
    right[80:160, 120:200] = np.clip(texture(80, 80, seed=7), 1, 2047).astype(np.uint16)
    patch = (slice(90, 150), slice(145, 205))  # left pixels whose partners were replaced
    valid = {}
    maps = {}
    modes: tuple[tuple[Literal["flip", "reduced", "none"], int], ...] = (
        ("flip", 1),
        ("flip", 2),
        ("reduced", 1),
        ("none", 1),
    )
    for mode, rows in modes:
        params = SgbmParams(lr_check=mode, lr_rows=rows)
        res = match_pair(left, right, d_range=(0, 24), params=params)
        assert res.status == DenseStatus.OK
        name = f"{mode}{rows}" if mode == "flip" else mode
        valid[name] = np.isfinite(res.disparity[patch]).mean()
        maps[name] = res.disparity
        ok = interior(left.shape) & np.isfinite(res.disparity)
        ok[80:160, 110:215] = False
        assert np.median(np.abs(res.disparity[ok] - truth[ok])) < 0.2
    # the right pass on every row, or on every other row (each row between checked against
    # the row above it): both reject the pixels whose partners the right image lost
    for flip in ("flip1", "flip2"):
        assert valid[flip] < 0.2 and valid[flip] < 0.75 * valid["none"], valid
    # and elsewhere keep the same pixels; their disparities (the mean of the left one and its
    # partner's right one) differ by half the right ones' difference: at most one SGBM step
    # (1/16 px) in median, and under half a pixel almost everywhere
    a, b = maps["flip1"], maps["flip2"]
    inner = interior(left.shape)
    inner[80:160, 110:215] = False
    assert (np.isfinite(a[inner]) == np.isfinite(b[inner])).mean() > 0.99
    diff = np.abs(a - b)[inner & np.isfinite(a) & np.isfinite(b)]
    assert np.median(diff) <= 1 / 16 and (diff < 0.5).mean() > 0.99, np.median(diff)
    # the check on a right pass at half resolution rejects them as well
    assert valid["reduced"] < 0.2 and valid["reduced"] < 0.75 * valid["none"], valid
    with pytest.raises(ValueError, match="lr_check"):
        SgbmParams(lr_check="internal")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="lr_rows"):
        SgbmParams(lr_rows=0)


@pytest.mark.parametrize("rows", [1, 2, 3])
def test_the_right_pass_matches_every_lr_rows_th_row(
    pair: tuple[np.ndarray, ...], rows: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The left pass sees the whole window, the right-to-left pass 1 row in ``lr_rows``."""
    from parproj_ros.imaging import dense

    seen: list[tuple[int, ...]] = []
    made = dense.sgbm_matcher

    class Spy:
        def __init__(self, matcher: cv2.StereoSGBM) -> None:
            self.matcher = matcher

        def compute(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
            seen.append(a.shape)
            return self.matcher.compute(a, b)  # type: ignore[no-any-return]

    monkeypatch.setattr(dense, "sgbm_matcher", lambda *args: Spy(made(*args)))
    left, right, _ = pair
    res = match_pair(left, right, d_range=(0, 24), params=SgbmParams(lr_rows=rows))
    assert res.status == DenseStatus.OK
    (h, w), (hr, wr) = seen
    assert (h, w) == (left.shape[0], wr) and hr == math.ceil(h / rows)


def test_no_data_is_nan_and_counted(pair: tuple[np.ndarray, ...]) -> None:
    left, right, truth = pair
    left = left.copy()
    left[:, :100] = 0  # no data
    mask = np.ones(right.shape, dtype=bool)
    mask[150:, :] = False  # the right image's own mask
    res = match_pair(left, right, d_range=(0, 24), right_mask=mask)
    assert np.all(np.isnan(res.disparity[:, :100]))
    assert np.all(np.isnan(res.disparity[152:, :]))  # partner without data (half a block)
    assert res.counts["nodata"] >= 100 * H
    ok = np.isfinite(res.disparity)
    assert np.median(np.abs(res.disparity[ok] - truth[ok])) < 0.2


def test_uint8_and_float32_inputs(pair: tuple[np.ndarray, ...]) -> None:
    left, right, _ = pair
    ref = match_pair(left, right, d_range=(0, 24)).disparity
    for conv in (lambda a: to_uint8(a, 0, 2047), lambda a: a.astype(np.float32)):
        out = match_pair(conv(left), conv(right), d_range=(0, 24))
        assert out.status == DenseStatus.OK
        both = np.isfinite(ref) & np.isfinite(out.disparity)
        assert np.median(np.abs(ref[both] - out.disparity[both])) <= SUBPIXEL


def test_low_texture_regions_are_masked(pair: tuple[np.ndarray, ...]) -> None:
    left, right, _ = pair
    left, right = left.copy(), right.copy()
    left[60:180, 120:220] = 900
    right[60:180, 100:210] = 900
    res = match_pair(left, right, d_range=(0, 24))
    assert np.all(np.isnan(res.disparity[80:160, 140:200]))
    assert res.counts["low_texture"] > 50 * 80
    assert res.status == DenseStatus.OK


def test_refine_range_from_a_reduced_pair() -> None:
    """A +-150 px range (too wide for a 640 px image at 1:1) narrowed at 1:4 around the truth."""
    left, right, truth = make_pair(480, 640, base=40.0, seed=5)
    assert match_pair(left, right, d_range=(-400, 400)).status == DenseStatus.RANGE_TOO_WIDE
    rng = refine_range(left, right, d_range=(-150, 150), scale=4)
    assert rng is not None
    assert rng[0] <= truth.min() and rng[1] >= truth.max()
    assert rng[1] - rng[0] <= (truth.max() - truth.min()) + 2 * (8 + 4) + 8, rng
    res = match_pair(left, right, d_range=rng)
    ok = interior(left.shape) & np.isfinite(res.disparity)
    assert np.median(np.abs(res.disparity[ok] - truth[ok])) < 0.2
    flat = np.full((480, 640), 700, dtype=np.uint16)
    assert refine_range(flat, flat, d_range=(-150, 150)) is None


# ---- bad cases: a status, never an exception ----------------------------------------------------


def test_uniform_image_is_textureless() -> None:
    img = np.full((H, W), 700, dtype=np.uint16)
    res = match_pair(img, img, d_range=(0, 24))
    assert res.status == DenseStatus.TEXTURELESS
    assert np.all(np.isnan(res.disparity)) and res.valid_share == 0.0


def test_saturated_image_is_textureless(pair: tuple[np.ndarray, ...]) -> None:
    left, _, _ = pair
    sat = np.full((H, W), 2047, dtype=np.uint16)
    assert match_pair(left, sat, d_range=(0, 24)).status == DenseStatus.TEXTURELESS
    assert match_pair(sat, left, d_range=(0, 24)).status == DenseStatus.TEXTURELESS


def test_smooth_image_is_textureless() -> None:
    rr, cc = np.mgrid[0:H, 0:W]
    img = (500 + cc + 0.5 * rr).astype(np.uint16)  # a ramp: no texture at all
    res = match_pair(img, img, d_range=(0, 24))
    assert res.status == DenseStatus.TEXTURELESS, res.message
    assert res.counts["low_texture"] > 0.9 * img.size


def test_range_wider_than_the_image(pair: tuple[np.ndarray, ...]) -> None:
    left, right, _ = pair
    res = match_pair(left, right, d_range=(-200, 200))
    assert res.status == DenseStatus.RANGE_TOO_WIDE
    assert "narrow" in res.message and np.all(np.isnan(res.disparity))
    small = SgbmParams(max_disparities=16)
    assert match_pair(left, right, d_range=(0, 24), params=small).status == "range_too_wide"


def test_no_data_only(pair: tuple[np.ndarray, ...]) -> None:
    left, right, _ = pair
    empty = np.zeros_like(right)
    assert match_pair(left, empty, d_range=(0, 24)).status == DenseStatus.NO_OVERLAP
    assert match_pair(empty, right, d_range=(0, 24)).status == DenseStatus.NO_OVERLAP
    res = match_pair(left, right, d_range=(0, 24), left_mask=np.zeros(left.shape, bool))
    assert res.status == DenseStatus.NO_OVERLAP and res.counts["nodata"] == left.size


def test_data_that_do_not_overlap_within_the_range(pair: tuple[np.ndarray, ...]) -> None:
    left, right, _ = pair
    lcut, rcut = left.copy(), right.copy()
    lcut[:, 100:] = 0  # left data in columns 0..99
    rcut[:, :140] = 0  # right data in columns 140.. : disparities <= -41 would be needed
    res = match_pair(lcut, rcut, d_range=(0, 24))
    assert res.status == DenseStatus.NO_OVERLAP, res.message
    assert np.all(np.isnan(res.disparity))
    rcut[:, 60:140] = right[:, 60:140]  # now partners exist for left columns 60..99
    res = match_pair(lcut, rcut, d_range=(0, 24))
    assert res.status != DenseStatus.NO_OVERLAP and res.counts["valid"] > 0


def test_unrelated_images_do_not_match(pair: tuple[np.ndarray, ...]) -> None:
    left, _, _ = pair
    other = np.clip(texture(H, W, seed=99), 1, 2047).astype(np.uint16)
    res = match_pair(left, other, d_range=(0, 24))
    assert res.status == DenseStatus.NO_MATCH, res.message
    assert res.valid_share < 0.2


def test_bad_arguments_raise() -> None:
    img = np.ones((32, 32), dtype=np.uint8)
    with pytest.raises(ValueError, match="of one shape"):
        match_pair(img, img[:, :20], d_range=(0, 4))
    with pytest.raises(ValueError, match="tile"):
        match_pair(img, img, d_range=(0, 4), tile_rows=8)
    with pytest.raises(ValueError, match="odd"):
        SgbmParams(block_size=4)
