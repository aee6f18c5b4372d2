"""The reduced pass that guides the matching (imaging/dense.CoarseGuide), ROS-free.

The pair: a band-limited random texture; the left image's columns < 480 at disparity 4 px,
the others at 60 px (a step, with the occlusion it makes in between), and a 24 x 24 px patch of
its own texture at 20 px inside the far part: 40 px off its surroundings, and 6 x 6 pixels at
the guide's 1/4 scale, where SGM smooths it away. Every pixel's true disparity
``col_left - col_right`` is known.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pytest

from parproj_ros.imaging import dense
from parproj_ros.imaging.dense import CoarseGuide, DenseStatus, match_pair

H, W = 256, 960
STEP = 480  # first left column at 60 px
PATCH = (slice(100, 124), slice(800, 824))
SEARCH = (0, 70)


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.2)
    return ((t - t.min()) / (t.max() - t.min()) * 3000 + 500).astype(np.uint16)


@pytest.fixture(scope="module")
def scene() -> dict[str, Any]:
    rng = np.random.default_rng(3)
    t = _texture(rng, H, W + 100)
    left = t[:, :W].copy()
    truth = np.where(np.arange(W) < STEP, 4.0, 60.0)[None, :].repeat(H, 0)
    right = np.empty_like(left)
    for x in range(W):  # right column x shows the left column x + d of its part
        right[:, x] = t[:, x + 4] if x + 4 < STEP else t[:, x + 60]
    patch = _texture(rng, 24, 24)
    left[PATCH] = patch
    right[PATCH[0], PATCH[1].start - 20 : PATCH[1].stop - 20] = patch
    truth[PATCH] = 20.0
    return {"left": left, "right": right, "truth": truth}


def _match(scene: dict[str, Any], guide: CoarseGuide | None, spy: list[int] | None = None) -> Any:
    original = dense.sgbm_matcher

    def counting(params: Any, dmin: int, ndisp: int) -> Any:
        if spy is not None:
            spy.append(ndisp)
        return original(params, dmin, ndisp)

    dense.sgbm_matcher = counting  # type: ignore[assignment]
    try:
        return match_pair(scene["left"], scene["right"], d_range=SEARCH, guide=guide)
    finally:
        dense.sgbm_matcher = original


def test_narrowed_tiles_search_what_the_reduced_pass_found(scene: dict[str, Any]) -> None:
    """Tiles of one part search 32 disparities instead of 80, with the same disparities."""
    whole = _match(scene, None)
    searched: list[int] = []
    narrow = _match(scene, CoarseGuide(ranges=True), searched)
    assert whole.status == narrow.status == DenseStatus.OK
    # the pair's matcher (80), the reduced pass (80 / 4 -> 32), then one per tile: three of
    # 320 x 256 px; the outer ones search 4 +- 12 and 60 +- 12 px (32), the one over the
    # step the whole 80
    assert searched == [80, 32, 32, 80, 32]
    truth = scene["truth"]
    for res in (whole, narrow):
        d = res.disparity
        rows = np.r_[0:96, 128:H]  # away from the patch
        for part in (slice(20, 470), slice(500, 940)):
            ok = np.isfinite(d[rows, part])
            err = np.abs(d[rows, part] - truth[rows, part])[ok]
            assert ok.mean() > 0.85 and np.percentile(err, 99.5) <= 0.1, ok.mean()
            assert (err > 1.0).mean() < 0.002, (err > 1.0).sum()
    both = np.isfinite(whole.disparity) & np.isfinite(narrow.disparity)
    same = np.abs(whole.disparity - narrow.disparity)[both] <= 1.0 / 16.0  # SGBM's step
    assert same.mean() >= 0.99


def test_what_the_reduced_pass_missed(scene: dict[str, Any]) -> None:
    """The patch at 20 px: found with the pair's range, mostly kept by the support rule (its
    centre is 3 reduced pixels from the reduced pass's valid pixels: lost), lost by the
    narrowed ranges (its tile searches 60 +- 12 px): never given a wrong disparity."""
    shares = {}
    for name, guide in (
        ("none", None),
        ("support", CoarseGuide()),
        ("ranges", CoarseGuide(ranges=True)),
    ):
        d = _match(scene, guide).disparity[PATCH]
        inner = d[2:-2, 2:-2]  # away from the patch's border (blocks straddling it)
        ok = np.isfinite(inner)
        assert np.all(np.abs(inner[ok] - 20.0) <= 0.25), name
        shares[name] = float(ok.mean())
    assert shares["none"] >= 0.95
    assert 0.5 <= shares["support"] < shares["none"]
    assert shares["ranges"] <= 0.05


def test_the_support_rule_keeps_only_pixels_near_a_reduced_match(scene: dict[str, Any]) -> None:
    """Every pixel taken has a valid reduced pixel within one reduced pixel of its own; the
    others are counted as no_match."""
    guide = CoarseGuide()
    plain = _match(scene, None)
    res = _match(scene, guide)
    coarse = dense._coarse_disparity(
        scene["left"], scene["right"], (0, 79), guide.scale, 0.0, (None, None), None
    )
    assert coarse is not None
    near = cv2.dilate(np.isfinite(coarse).view(np.uint8), np.ones((3, 3), np.uint8)) != 0
    rows = np.minimum(np.arange(H) // 4, near.shape[0] - 1)
    cols = np.minimum(np.arange(W) // 4, near.shape[1] - 1)
    supported = near[rows[:, None], cols[None, :]]
    valid = np.isfinite(res.disparity)
    assert not np.any(valid & ~supported)
    dropped = np.isfinite(plain.disparity) & ~supported
    assert dropped.sum() > 0
    assert res.counts["no_match"] - plain.counts["no_match"] == int(dropped.sum())
    assert res.counts["valid"] == plain.counts["valid"] - int(dropped.sum())


def test_a_guide_on_a_pair_the_reduced_pass_cannot_match_changes_nothing() -> None:
    """A range as wide as the reduced image: no reduced pass, the caller's tiles as before."""
    rng = np.random.default_rng(1)
    t = _texture(rng, 96, 160)
    left, right = t[:, 8:].copy(), t[:, :-8].copy()
    plain = match_pair(left, right, d_range=(-60, 60))
    guided = match_pair(left, right, d_range=(-60, 60), guide=CoarseGuide(ranges=True))
    np.testing.assert_array_equal(plain.disparity, guided.disparity)


@pytest.mark.parametrize(
    "kwargs",
    [{"scale": 1}, {"tile_px": 8}, {"overlap_px": -1}, {"min_cells": 0}, {"margin_px": -1.0}],
)
def test_bad_guides_are_refused(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match=r"CoarseGuide|margin_px"):
        CoarseGuide(**kwargs)
