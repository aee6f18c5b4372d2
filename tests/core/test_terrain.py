"""The terrain measured from the pair itself (core/terrain.py, issue 24 item 1).

Unit tests of the measurement, then the pipeline on a bag whose prior height range holds far
more than the ground (airborne_foreaft: 500 m prior for 8 m of relief) and on the real Ventoux
pair imported without a DEM (the virtual GCP span the RPC's 1,062 m of height, the ground lies
500 m below the frame's origin).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from testkit.paths import BAGS, DATA

from parproj_ros.core.results import Outputs
from parproj_ros.core.terrain import (
    MIN_TERRAIN_POINTS,
    TERRAIN_PAD_PX,
    TERRAIN_PAD_SHARE,
    Terrain,
    TerrainSource,
    reduce_image,
    terrain_from_heights,
)
from parproj_ros.imaging.dense import DenseStatus
from parproj_ros.imaging.resample import OutputGrid

PRIOR = Terrain(-500.0, 500.0, TerrainSource.PRIOR)


def test_percentiles_and_margin() -> None:
    """1st / 99th percentiles, widened by 20 % of their span (>= 4 px of x-parallax)."""
    rng = np.random.default_rng(1)
    z = rng.uniform(100.0, 300.0, 5000)
    z[:10] = 5000.0  # 0.2 % gross errors: beyond the 99th percentile
    t = terrain_from_heights(z, PRIOR, metres_per_px=1.2)
    lo, hi = np.percentile(z, [1.0, 99.0])
    assert t.source == TerrainSource.TIE_POINTS and t.points == 5000
    assert t.measured_m == pytest.approx((lo, hi))
    pad = TERRAIN_PAD_SHARE * (hi - lo)
    assert t.range_m == pytest.approx((lo - pad, hi + pad))
    assert 55.0 < t.low_m < 70.0 and 330.0 < t.high_m < 345.0  # 100..300 m widened by 40 m
    # A flat ground: the margin is the matching noise's, 4 px of x-parallax either way.
    flat = terrain_from_heights(np.full(100, 50.0), PRIOR, metres_per_px=-0.25)
    assert flat.range_m == pytest.approx((50.0 - TERRAIN_PAD_PX * 0.25, 50.0 + 1.0))


def test_too_few_points_keep_the_prior() -> None:
    z = np.linspace(0.0, 10.0, MIN_TERRAIN_POINTS - 1)
    assert terrain_from_heights(z, PRIOR, metres_per_px=1.0) is PRIOR
    z = np.r_[np.linspace(0.0, 10.0, MIN_TERRAIN_POINTS - 1), np.nan, np.inf]
    assert terrain_from_heights(z, PRIOR, metres_per_px=1.0) is PRIOR


def test_reduced_image_keeps_its_grid() -> None:
    """Each reduced pixel is the mean of its block, at the block's centre; blocks with no-data
    are no-data."""
    cols = np.arange(103, dtype=np.float32)
    img = np.tile(10.0 + cols, (41, 1)).astype(np.float32)
    img[0, 5] = 0.0
    grid = OutputGrid(0.5, 100.0, -20.0, 103, 41)
    small, g = reduce_image(img, grid, 4, 0.0)
    assert small.shape == (10, 25) and (g.width, g.height) == (25, 10)
    assert g.pixel == 2.0
    # value = 10 + full column; the full column of a reduced centre is (x - x0) / pixel
    full_col = (g.x_origin + g.pixel * np.arange(25) - grid.x_origin) / grid.pixel
    np.testing.assert_allclose(small[1], 10.0 + full_col, atol=1e-4)
    assert small[0, 1] == 0.0 and small[0, 0] != 0.0  # block (0, 1) holds pixel (0, 5)


def _heights(out: Outputs, keep: list[object]) -> None:
    keep += out.heights
    keep += out.issues


@pytest.mark.ros
@pytest.mark.slow
def test_airborne_pair_gets_heights_from_its_tie_points(tmp_path: Path) -> None:
    """500 m of prior height range needs 4,600 px of disparity on a 768-px image: no heights
    from the prior; the terrain measured from the pair gives them, as accurate as the
    scenario's terrain allows (NMAD within one pixel of x-parallax, >= 95 % complete)."""
    from parproj_ros.apps.process import process_bag
    from parproj_ros.eval.heights import dsm_accuracy, scenario_terrain

    got: dict[str, list[object]] = {}
    for terrain in ("prior", "tie_points"):
        kept: list[object] = []
        process_bag(
            BAGS / "airborne_foreaft",
            tmp_path / terrain,
            progress=False,
            overrides={"heights": True, "terrain": terrain},
            on_outputs=lambda out, k=kept: _heights(out, k),
        )
        got[terrain] = kept
    (prior,) = [h for h in got["prior"] if hasattr(h, "dsm")]
    assert prior.status == DenseStatus.RANGE_TOO_WIDE  # type: ignore[attr-defined]
    (h,) = [h for h in got["tie_points"] if hasattr(h, "dsm")]
    assert h.ok and h.terrain is not None  # type: ignore[attr-defined]
    t = h.terrain  # type: ignore[attr-defined]
    assert t.source == TerrainSource.TIE_POINTS and t.points >= 100
    truth = scenario_terrain("airborne_foreaft")
    assert truth is not None
    dsm = h.dsm  # type: ignore[attr-defined]
    acc = dsm_accuracy(dsm.heights, dsm.grid, truth, filled=dsm.filled)
    px = abs(h.height_per_disparity_px)  # type: ignore[attr-defined]
    assert acc["nmad"] <= px and acc["completeness"] >= 0.95, acc
    # The ground of the DSM's footprint lies within the measured terrain.
    x, y = dsm.grid.centres()
    z = np.asarray(truth(x, y))[np.isfinite(dsm.heights)]
    inside = (z >= t.low_m) & (z <= t.high_m)
    assert inside.mean() >= 0.995, (t, np.percentile(z, [0, 1, 99, 100]))
    assert t.high_m - t.low_m < 0.1 * 1000.0  # far narrower than the prior's 1,000 m


@pytest.mark.ros
@pytest.mark.slow
def test_real_pair_without_dem(tmp_path: Path) -> None:
    """Ventoux imported without a DEM: the virtual GCP span the RPC's heights (over 1,000 m),
    so the prior disparity range is wider than the image. Measured from the pair: tie points
    refine it, the dense matcher finds heights, and the measured ground agrees with SRTM."""
    from parproj_ros.apps.importer import import_pair
    from parproj_ros.apps.process import process_bag
    from parproj_ros.io.dem import grid_height
    from parproj_ros.io.geotiff import frame_of

    images = [DATA / "left_image.tif", DATA / "right_image.tif"]
    import_pair(*images, tmp_path / "in", log=lambda _: None)
    kept: list[object] = []
    process_bag(
        tmp_path / "in",
        tmp_path / "out",
        progress=False,
        overrides={"heights": True},
        on_outputs=lambda out: _heights(out, kept),
    )
    (pair,) = [p for p in kept if hasattr(p, "dsm")]
    assert pair.ok, pair.message  # type: ignore[attr-defined]
    assert pair.valid_share >= 0.4  # type: ignore[attr-defined]
    t = pair.terrain  # type: ignore[attr-defined]
    assert t.source == TerrainSource.TIE_POINTS and t.points >= 100
    texts = [i.message for i in kept if hasattr(i, "where")]
    assert any("tie points:" in s and "inliers" in s for s in texts), texts
    # The measured ground against SRTM 3" (90 m cells, a coarse truth), in ellipsoidal
    # heights: the DSM cells' (X, Y, Z) through the object frame.
    dem = grid_height(
        np.loadtxt(DATA / "srtm_N44E005_crop.txt"),
        lat_max=45 - 927 / 1200,
        lon_min=5 + 206 / 1200,
        step_deg=1 / 1200,
        geoid_undulation=50.0,
    )
    frame = frame_of(_frame(tmp_path))
    assert frame is not None
    dsm = pair.dsm  # type: ignore[attr-defined]
    x, y = dsm.grid.centres()
    ok = np.isfinite(dsm.heights)
    lon, lat, h = frame.to_geodetic(x[ok], y[ok], dsm.heights[ok])
    lo, hi = t.measured_m
    assert hi - lo < 100.0  # the GCP span over 1,000 m (the RPC's height span)
    # Median of (DSM - SRTM): the trees and SRTM's smoothing, a few metres, not the 500 m
    # between the frame's origin and the ground.
    assert abs(float(np.median(h - np.asarray(dem(lon, lat))))) < 15.0


def _frame(root: Path) -> str:
    from parproj_ros.ros.bag import BagReader

    msg = next(BagReader(root / "in").messages(topics=["gcp"])).msg
    return str(msg.header.frame_id)
