"""The heights step of a pair (core/heights.py): DSM accuracy on a simulated pair, bad cases.

The ikonos_agile geometry at 384 x 384 px scenes, rendered through the rigorous model over its
terrain and normalized by the Pipeline without DDS (as tests/imaging/test_heights.py); the
terrain gives the true height of every DSM cell. One pixel of x-parallax is |a| metres
(``height_per_disparity_px``): the DSM's robust error (NMAD) must stay within it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from testkit.scenes import feed, nav_events, rendered, small_scenario, strip_events

from parproj_ros.core.heights import HeightsOptions, measure_heights
from parproj_ros.core.pipeline import Pipeline
from parproj_ros.core.results import Level
from parproj_ros.eval.heights import dsm_accuracy, hillshade
from parproj_ros.imaging.dense import DenseStatus


@pytest.fixture(scope="module")
def pair() -> dict[str, Any]:
    scn = small_scenario("ikonos_agile", 384)
    terrain, scenes = rendered(scn)
    pipe = Pipeline(scn.pipeline_config(tie_points=False, streaming=False))
    out = feed(pipe, nav_events(scn) + strip_events(scn, scenes))
    (p,) = out.pairs
    return {"pair": p, "terrain": terrain}


def test_dsm_of_a_simulated_pair_within_one_pixel_of_parallax(pair: dict[str, Any]) -> None:
    p, terrain = pair["pair"], pair["terrain"]
    z = (terrain.min_height, terrain.max_height)
    res, issues = measure_heights(p, p.left_image, p.right_image, z)
    assert res.ok, res.message
    assert [i.level for i in issues] == [Level.OK]
    a = abs(p.height_per_disparity_px)
    acc = dsm_accuracy(res.dsm.heights, res.dsm.grid, terrain.height, res.dsm.filled)
    print(f"|a| {a:.3f} m/px: {acc}")
    assert acc["nmad"] <= a
    assert abs(acc["mean"]) <= a / 2
    assert acc["completeness"] >= 0.95
    # the height image is a d + b of the disparity, pixel for pixel
    valid = np.isfinite(res.disparity)
    assert np.allclose(
        res.height[valid], p.height_per_disparity_px * res.disparity[valid] + p.height_offset_m
    )
    # the ortho-image has data where the DSM has a height, and nodata elsewhere
    assert np.all(res.ortho[~np.isfinite(res.dsm.heights)] == 0)
    assert (res.ortho[np.isfinite(res.dsm.heights)] > 0).mean() > 0.99
    shade = hillshade(res.dsm.heights, res.dsm.grid.cell)
    assert shade.dtype == np.uint8 and shade[np.isfinite(res.dsm.heights)].std() > 5


def test_the_cell_follows_the_option(pair: dict[str, Any]) -> None:
    p, terrain = pair["pair"], pair["terrain"]
    z = (terrain.min_height, terrain.max_height)
    res, _ = measure_heights(p, p.left_image, p.right_image, z, HeightsOptions(cell_m=2.0))
    assert res.ok and res.dsm.grid.cell == 2.0


def test_subpixel_refinement_by_default_lowers_the_dsm_error(pair: dict[str, Any]) -> None:
    """The default sub-pixel refinement ("gradient") against SGBM's own ("sgbm").

    On this pair: NMAD against the terrain 0.107 against 0.158 m (|a| 1.19 m/px).
    """
    p, terrain = pair["pair"], pair["terrain"]
    z = (terrain.min_height, terrain.max_height)
    assert HeightsOptions().subpixel == "gradient"
    acc = {}
    for sp in ("sgbm", "gradient"):
        opt = HeightsOptions(subpixel=sp)
        res, _ = measure_heights(p, p.left_image, p.right_image, z, opt)
        assert res.ok, res.message
        acc[sp] = dsm_accuracy(res.dsm.heights, res.dsm.grid, terrain.height, res.dsm.filled)
    print({k: {n: round(v, 4) for n, v in a.items()} for k, a in acc.items()})
    a = abs(p.height_per_disparity_px)
    assert acc["gradient"]["nmad"] < 0.8 * acc["sgbm"]["nmad"]
    assert acc["gradient"]["nmad"] <= a / 8
    assert acc["gradient"]["rms"] <= acc["sgbm"]["rms"] * 1.01
    # the refinement moves disparities, it does not add or remove cells
    assert abs(acc["gradient"]["completeness"] - acc["sgbm"]["completeness"]) < 0.005


def test_inverted_x_parallax_sign_gives_the_same_heights(pair: dict[str, Any]) -> None:
    """Both images mirrored and a -> -a: the disparities change sign, the heights do not."""
    p, terrain = pair["pair"], pair["terrain"]
    z = (terrain.min_height, terrain.max_height)
    ref, _ = measure_heights(p, p.left_image, p.right_image, z)
    flipped = dataclasses.replace(p, height_per_disparity_px=-p.height_per_disparity_px)
    res, _ = measure_heights(
        flipped, np.ascontiguousarray(p.left_image[:, ::-1]),
        np.ascontiguousarray(p.right_image[:, ::-1]), z,
    )  # fmt: skip
    assert res.status == DenseStatus.OK, res.message
    both = np.isfinite(ref.height) & np.isfinite(res.height[:, ::-1])
    assert both.mean() > 0.8
    diff = np.abs(ref.height[both] - res.height[:, ::-1][both])
    assert np.median(diff) < abs(p.height_per_disparity_px) / 4


@pytest.mark.parametrize(
    ("case", "status"),
    [
        ("textureless", DenseStatus.TEXTURELESS),
        ("saturated", DenseStatus.TEXTURELESS),
        ("nodata", DenseStatus.NO_OVERLAP),
        ("wide_range", DenseStatus.RANGE_TOO_WIDE),
        ("no_relation", DenseStatus.NO_MATCH),
    ],
)
def test_bad_cases_get_a_status_and_a_warning(
    pair: dict[str, Any], case: str, status: DenseStatus
) -> None:
    p, terrain = pair["pair"], pair["terrain"]
    left, right = p.left_image, p.right_image
    z = (terrain.min_height, terrain.max_height)
    if case == "textureless":
        left, right = np.full_like(left, 700), np.full_like(right, 700)
    elif case == "saturated":
        left, right = np.full_like(left, 65535), np.full_like(right, 65535)
    elif case == "nodata":
        left, right = np.zeros_like(left), np.zeros_like(right)
    elif case == "wide_range":
        z = (-1.0e5, 1.0e5)
    elif case == "no_relation":
        p = dataclasses.replace(p, height_per_disparity_px=0.0)
    res, issues = measure_heights(p, left, right, z)
    assert res.status == status, res.message
    assert not res.ok and res.dsm is None and res.ortho is None
    assert np.isnan(res.height).all()
    (iss,) = issues
    assert iss.level == Level.WARN and str(status) in iss.message


def test_terrain_not_measured_keeps_the_prior_with_a_warn(pair: dict[str, Any]) -> None:
    """Images without texture give no tie points: the heights searched stay the pair's own
    (its GCP's), and a WARN says so and what to try; measured on the real images instead."""
    from parproj_ros.core.heights import HeightsStage
    from parproj_ros.core.terrain import Terrain, TerrainSource

    p = pair["pair"]
    gcp = Terrain(-40.0, 140.0, TerrainSource.GCP)
    p = dataclasses.replace(p, terrain=gcp)
    stage = HeightsStage(HeightsOptions(measure_terrain=True))
    flat = np.full_like(p.left_image, 1000)
    terrain, issues = stage.pair_terrain(p, flat, flat)
    assert terrain is gcp
    (warn,) = issues
    assert warn.level == Level.WARN and warn.where == f"pair {p.pair_id}"
    assert "too few tie points agree to measure the terrain" in warn.message
    assert "terrain -40..140 m from the pair's GCP" in warn.message
    assert "give a DEM at import, or set z_avg / height_range" in warn.message
    measured, issues = stage.pair_terrain(p, p.left_image, p.right_image)
    assert issues == [] and measured.source == TerrainSource.TIE_POINTS
    # the measured terrain holds the pair's ground: searching it gives the full DSM
    res, _ = measure_heights(p, p.left_image, p.right_image, measured)
    assert res.ok and res.terrain is measured
    acc = dsm_accuracy(res.dsm.heights, res.dsm.grid, pair["terrain"].height, res.dsm.filled)
    assert acc["nmad"] <= abs(p.height_per_disparity_px) and acc["completeness"] >= 0.95, acc
    # not asked: the pair's own, without a word
    assert HeightsStage(HeightsOptions()).pair_terrain(p, flat, flat) == (gcp, [])
