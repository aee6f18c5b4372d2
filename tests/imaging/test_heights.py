"""Heights, DSM and ortho-image of a normalized pair (imaging/heights.py), ROS-free.

The end-to-end tests build a simulated pair as tests/core/test_pipeline.py does: the ikonos_agile
geometry (scaled down to 384 x 384 px scenes) rendered through the rigorous pushbroom model
over the scenario's procedural terrain, fed to a Pipeline without DDS; the terrain gives the
true height of every DSM cell. Tolerances come from the pair's geometry: one pixel of
x-parallax is |a| metres of height (``height_per_disparity_px``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from testkit.scenes import feed, nav_events, small_scenario, strip_events

from parproj_ros.core.pipeline import PairResult, Pipeline
from parproj_ros.geometry import AffineModel
from parproj_ros.imaging.dense import DenseStatus, disparity_range, match_pair, refine_range
from parproj_ros.imaging.heights import (
    DsmGrid,
    GroundMapping,
    dsm_errors,
    heights_from_disparity,
    make_dsm,
    orthoimage,
)
from parproj_ros.imaging.resample import OutputGrid
from parproj_ros.sim.scenarios import SCENARIOS, Scenario
from parproj_ros.sim.simulate import render_scene
from parproj_ros.sim.terrain import Terrain, procedural_terrain

SIZE = 384  # lines and detectors of each scene (the scenario has 768)
MARGIN_PX = 8  # cells whose ground is this close to an image edge are not evaluated


@dataclasses.dataclass
class Sim:
    scn: Scenario
    terrain: Terrain
    scenes: list[np.ndarray]
    pair: PairResult
    left: GroundMapping
    right: GroundMapping


def small_ikonos() -> Scenario:
    return small_scenario("ikonos_agile", SIZE)


@pytest.fixture(scope="module")
def sim() -> Sim:
    scn = small_ikonos()
    terrain = procedural_terrain(
        scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
    )
    scenes = [
        render_scene(scn.model(i), terrain, 0, SIZE, dtype=np.uint16, workers=2)
        for i in range(len(scn.scenes))
    ]
    pipe = Pipeline(scn.pipeline_config(tie_points=False, streaming=False))
    out = feed(pipe, nav_events(scn) + strip_events(scn, scenes))
    assert out.issues == []
    (pair,) = out.pairs
    left = GroundMapping(pair.left_grid, pair.normalization.left, pair.left.affine)
    right = GroundMapping(pair.right_grid, pair.normalization.right, pair.right.affine)
    for side, ref in (("left", left), ("right", right)):
        got = GroundMapping.of_pair(pair, side)  # type: ignore[arg-type]
        assert got.grid == ref.grid and got.affine == ref.affine
        assert np.array_equal(got.to_normalized, ref.to_normalized)
    return Sim(scn, terrain, scenes, pair, left, right)


def true_heights_of_left_pixels(sim: Sim, step: int = 4) -> np.ndarray:
    """Terrain heights seen by a grid of left normalized pixels (fixed point in Z)."""
    img = sim.pair.left_image
    assert img is not None
    cc, rr = np.meshgrid(np.arange(0, img.shape[1], step), np.arange(0, img.shape[0], step))
    z = np.zeros(cc.shape)
    for _ in range(8):
        x, y = sim.left.pixel_to_ground(cc, rr, z)
        z = sim.terrain.height(x, y)
    return z


def seen_by(mapping: GroundMapping, image: np.ndarray, x: Any, y: Any, z: Any) -> np.ndarray:
    """Ground points that project into ``image`` (with data), MARGIN_PX from its edges."""
    c, r = mapping.ground_to_pixel(x, y, z)
    h, w = image.shape
    m = MARGIN_PX
    ok = (c >= m) & (c <= w - 1 - m) & (r >= m) & (r <= h - 1 - m)
    ci = np.clip(np.rint(c).astype(int), 0, w - 1)
    ri = np.clip(np.rint(r).astype(int), 0, h - 1)
    return ok & (image[ri, ci] != 0)


@pytest.fixture(scope="module")
def matched(sim: Sim) -> dict[str, Any]:
    p = sim.pair
    assert p.left_image is not None and p.right_image is not None
    z = true_heights_of_left_pixels(sim)
    rng = disparity_range(p.height_per_disparity_px, p.height_offset_m, (z.min(), z.max()))
    res = match_pair(p.left_image, p.right_image, d_range=rng)
    return {"res": res, "z_range": (float(z.min()), float(z.max()))}


# ---- the mapping --------------------------------------------------------------------------------


def test_ground_mapping_round_trip_and_equation_2(sim: Sim) -> None:
    rng = np.random.default_rng(0)
    col, row = rng.uniform(0, 400, 50), rng.uniform(0, 380, 50)
    z = rng.uniform(-100, 300, 50)
    x, y = sim.left.pixel_to_ground(col, row, z)
    c2, r2 = sim.left.ground_to_pixel(x, y, z)
    np.testing.assert_allclose(c2, col, atol=1e-6)
    np.testing.assert_allclose(r2, row, atol=1e-6)
    # The same point through the normalization's own object projection (paper 2 Eq 8).
    nl, _ = sim.pair.normalization.project_object(np.column_stack([x, y, z]))
    g = sim.pair.left_grid
    np.testing.assert_allclose((nl[:, 0] - g.x_origin) / g.pixel, col, atol=1e-3)
    np.testing.assert_allclose((nl[:, 1] - g.y_origin) / g.pixel, row, atol=1e-3)


def test_disparity_of_a_ground_point_gives_its_height(sim: Sim) -> None:
    """Project object points into both normalized images: Z = a (col_l - col_r) + b."""
    rng = np.random.default_rng(1)
    pts = rng.uniform([-150, -150, -200], [150, 150, 250], (40, 3))
    cl, rl = sim.left.ground_to_pixel(*pts.T)
    cr, rr = sim.right.ground_to_pixel(*pts.T)
    np.testing.assert_allclose(rl, rr, atol=1e-6)  # epipolar: same row
    p = sim.pair
    z = heights_from_disparity(cl - cr, p.height_per_disparity_px, p.height_offset_m)
    np.testing.assert_allclose(z, pts[:, 2], atol=1e-3)
    assert z.dtype == np.float32


def test_ground_sample_distance(sim: Sim) -> None:
    # IKONOS-like: 12 um pixels, c = 10 m, 680 km: 0.82 m at nadir, more off nadir.
    assert 0.8 < sim.left.ground_sample_distance < 1.0


# ---- gridding and errors (synthetic numbers) ----------------------------------------------------


def identity_mapping(pixel: float = 1.0) -> GroundMapping:
    """X = col * pixel, Y = -row * pixel, independent of Z (a vertical view)."""
    grid = OutputGrid(pixel, 0.0, 0.0, 100, 100)
    flip = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # normalized y = -Y
    affine = AffineModel.from_array([1, 0, 0, 0, 0, 1, 0, 0])
    return GroundMapping(grid, flip, affine)


def test_dsm_of_a_plane_and_its_grid() -> None:
    m = identity_mapping()
    rr, cc = np.mgrid[0:50, 0:60].astype(float)
    disp = (0.1 * cc + 0.05 * rr).astype(np.float32)  # Z = 2 d + 10
    disp[10:14, 20:30] = np.nan
    dsm = make_dsm(disp, 2.0, 10.0, m)
    assert dsm.grid == DsmGrid(0.0, 0.0, 1.0, 60, 50)
    x, y = dsm.grid.centres()
    np.testing.assert_allclose(x[0, :3], [0, 1, 2])
    np.testing.assert_allclose(y[:3, 0], [0, -1, -2])
    ok = np.isfinite(dsm.heights)
    assert (~ok).sum() == 40 and not ok[10:14, 20:30].any()
    np.testing.assert_allclose(dsm.heights[ok], (2 * disp + 10)[ok], atol=1e-4)
    assert np.all(dsm.count[ok] == 1) and not dsm.filled.any()
    filled = make_dsm(disp, 2.0, 10.0, m, fill="nearest", max_fill_cells=1.0)
    assert filled.filled.sum() == 2 * 10 + 2 * 2  # the hole's 1-cell border
    assert np.isfinite(filled.heights[filled.filled]).all()


def test_dsm_mean_and_median_of_cells() -> None:
    m = identity_mapping(0.5)  # 4 pixels per 1 m cell
    disp = np.full((4, 4), 1.0, dtype=np.float32)
    disp[0, 0] = 41.0  # an outlier in the first cell
    grid = DsmGrid(0.25, -0.25, 1.0, 2, 2)
    mean = make_dsm(disp, 1.0, 0.0, m, grid=grid)
    med = make_dsm(disp, 1.0, 0.0, m, grid=grid, reducer="median")
    assert mean.count.tolist() == [[4, 4], [4, 4]]
    assert mean.heights[0, 0] == pytest.approx(11.0) and med.heights[0, 0] == pytest.approx(1.0)
    assert med.heights[1, 1] == pytest.approx(1.0)


def test_interpolated_cells_take_the_height_at_their_centre() -> None:
    """A slanted plane seen with pixels 0.3 / 0.2 cell off the cell centres: "mean" gives the
    height of the point in the cell, "interpolated" the plane's height at the centre."""
    grid = OutputGrid(1.0, 0.3, -0.2, 100, 100)  # pixel (c, r) at X = c + 0.3, Y = -r + 0.2
    flip = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    m = GroundMapping(grid, flip, AffineModel.from_array([1, 0, 0, 0, 0, 1, 0, 0]))
    rr, cc = np.mgrid[0:50, 0:60].astype(float)
    disp = (0.5 * cc + 0.25 * rr).astype(np.float32)  # Z = 2 d + 10 = 10 + X - 0.3 + ...
    cells = DsmGrid(0.0, 0.0, 1.0, 60, 50)
    mean = make_dsm(disp, 2.0, 10.0, m, grid=cells)
    interp = make_dsm(disp, 2.0, 10.0, m, grid=cells, reducer="interpolated")
    x, y = cells.centres()
    plane = 10.0 + (x - 0.3) - 0.5 * (y - 0.2)  # 2 (0.5 c + 0.25 r) + 10 at the centre
    inner = np.zeros(plane.shape, dtype=bool)
    inner[2:-2, 2:-2] = True
    assert np.isfinite(interp.heights[inner]).all()
    # remap's weights are in 1/32 px: 1.5 m per px of slope, within 0.05 m
    assert np.abs(interp.heights[inner] - plane[inner]).max() < 0.05
    assert np.abs(mean.heights[inner] - plane[inner]).min() > 0.15  # 0.3 - 0.5 x 0.2 m off
    assert np.array_equal(np.isfinite(mean.heights), np.isfinite(interp.heights))


def test_dsm_of_nothing() -> None:
    dsm = make_dsm(np.full((8, 8), np.nan, np.float32), 1.0, 0.0, identity_mapping())
    assert np.isnan(dsm.heights).all()


def test_dsm_errors_formulas() -> None:
    truth = np.zeros((2, 4))
    dsm = np.array([[1.0, -1.0, 2.0, np.nan], [0.0, 0.0, 0.0, 10.0]])
    mask = np.ones((2, 4), bool)
    mask[1, 3] = False
    e = dsm_errors(dsm, truth, mask)
    errs = np.array([1.0, -1.0, 2.0, 0.0, 0.0, 0.0])
    assert e["n"] == 6 and e["completeness"] == pytest.approx(6 / 7)
    assert e["rms"] == pytest.approx(np.sqrt(np.mean(errs**2)))
    assert e["nmad"] == pytest.approx(1.4826 * np.median(np.abs(errs - np.median(errs))))
    assert e["mean"] == pytest.approx(errs.mean())
    nothing = dsm_errors(np.full((2, 2), np.nan), np.zeros((2, 2)))
    assert nothing["completeness"] == 0.0 and np.isnan(nothing["nmad"])


# ---- the simulated pair -------------------------------------------------------------------------


def test_dense_matching_of_the_simulated_pair(sim: Sim, matched: dict[str, Any]) -> None:
    res = matched["res"]
    assert res.status == DenseStatus.OK, res.message
    assert res.valid_share > 0.85, res.counts


def test_dsm_accuracy_on_textured_terrain(sim: Sim, matched: dict[str, Any]) -> None:
    p = sim.pair
    a, b = p.height_per_disparity_px, p.height_offset_m
    assert p.left_image is not None and p.right_image is not None
    res = matched["res"]
    raw = make_dsm(res.disparity, a, b, sim.left)
    dsm = make_dsm(res.disparity, a, b, sim.left, fill="nearest", max_fill_cells=1.0)
    assert raw.grid == dsm.grid
    assert raw.grid.cell == pytest.approx(sim.left.ground_sample_distance)
    x, y = dsm.grid.centres()
    truth = sim.terrain.height(x, y)
    both = seen_by(sim.left, p.left_image, x, y, truth) & seen_by(
        sim.right, p.right_image, x, y, truth
    )
    assert both.sum() > 0.5 * both.size
    err_raw = dsm_errors(raw.heights, truth, both)
    err = dsm_errors(dsm.heights, truth, both)
    print(f"|a| = {abs(a):.3f} m/px, raw {err_raw}, filled 1 cell {err}")
    # One pixel of x-parallax is |a| metres: the DSM is better than that.
    assert err["nmad"] <= abs(a), err
    assert err_raw["nmad"] <= abs(a), err_raw
    assert abs(err["mean"]) <= 0.5 * abs(a), err
    # Cells of the size of a pixel: slopes facing away from a view leave one-cell gaps.
    assert err["completeness"] >= 0.95, err
    assert err_raw["completeness"] >= 0.90, err_raw


def test_orthoimages_of_both_views_agree(sim: Sim, matched: dict[str, Any]) -> None:
    p = sim.pair
    assert p.left_image is not None and p.right_image is not None
    a, b = p.height_per_disparity_px, p.height_offset_m
    dsm = make_dsm(matched["res"].disparity, a, b, sim.left)
    lo = orthoimage(p.left_image, dsm, sim.left).astype(float)
    ro = orthoimage(p.right_image, dsm, sim.right).astype(float)
    # The left original scene through its own model (normalized -> inverse PTP -> frame).
    so = orthoimage(
        sim.scenes[0], dsm, sim.left, scene=p.left.geometry(p.normalization.left)
    ).astype(float)
    assert lo.shape == (dsm.grid.height, dsm.grid.width)
    assert np.all(lo[~np.isfinite(dsm.heights)] == 0)
    for other in (ro, so):
        both = (lo > 0) & (other > 0)
        assert both.sum() > 0.5 * lo.size
        ncc = np.corrcoef(lo[both], other[both])[0, 1]
        assert ncc > 0.9, ncc
    # A wrong height (100 m off) breaks the agreement of the two views.
    off = dataclasses.replace(dsm, heights=dsm.heights + np.float32(100.0))
    lo2 = orthoimage(p.left_image, off, sim.left).astype(float)
    ro2 = orthoimage(p.right_image, off, sim.right).astype(float)
    both = (lo2 > 0) & (ro2 > 0)
    assert np.corrcoef(lo2[both], ro2[both])[0, 1] < 0.5


@pytest.mark.slow
def test_full_size_pair_as_the_pipeline_would_call_it() -> None:
    """The recorded ikonos_agile geometry at full size (768 px scenes), its own height range.

    The pipeline's height range (z_avg +- height_range, 300 m) is 522 px of disparity:
    ``refine_range`` narrows it at 1:4 before matching at full resolution.
    """
    scn = dataclasses.replace(SCENARIOS["ikonos_agile"](), gcp=0, check=0)
    terrain = procedural_terrain(
        scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
    )
    scenes = [
        render_scene(scn.model(i), terrain, 0, sc.lines, dtype=np.uint16, workers=2)
        for i, sc in enumerate(scn.scenes)
    ]
    pipe = Pipeline(scn.pipeline_config(tie_points=False, streaming=False))
    (p,) = feed(pipe, nav_events(scn) + strip_events(scn, scenes)).pairs
    assert p.left_image is not None and p.right_image is not None
    a, b = p.height_per_disparity_px, p.height_offset_m
    wide = disparity_range(a, b, pipe.config.orientation.prior_heights)
    rng = refine_range(p.left_image, p.right_image, d_range=wide)
    assert rng is not None and rng[1] - rng[0] < 0.5 * (wide[1] - wide[0]), (wide, rng)
    res = match_pair(p.left_image, p.right_image, d_range=rng)
    assert res.status == DenseStatus.OK, res.message
    left, right = GroundMapping.of_pair(p), GroundMapping.of_pair(p, "right")
    dsm = make_dsm(res.disparity, a, b, left, fill="nearest", max_fill_cells=1.0)
    x, y = dsm.grid.centres()
    truth = terrain.height(x, y)
    both = seen_by(left, p.left_image, x, y, truth) & seen_by(right, p.right_image, x, y, truth)
    cl, _ = left.ground_to_pixel(x[both], y[both], truth[both])
    cr, _ = right.ground_to_pixel(x[both], y[both], truth[both])
    assert rng[0] <= (cl - cr).min() and (cl - cr).max() <= rng[1]  # the truth was searched
    err = dsm_errors(dsm.heights, truth, both)
    raw = dsm_errors(np.where(dsm.filled, np.nan, dsm.heights), truth, both)
    print(f"|a| = {abs(a):.3f} m/px, range {wide} -> {rng}, raw {raw}, filled 1 cell {err}")
    assert err["nmad"] <= abs(a) and raw["nmad"] <= abs(a), (raw, err)
    assert err["completeness"] >= 0.95 and raw["completeness"] >= 0.90, (raw, err)


@pytest.mark.parametrize("shape", [(60, 70), (1, 9), (5, 2), (2, 1)])
@pytest.mark.parametrize("max_cells", [1.0, 1.5, 2.0, 3.0, 4.0])
def test_nearest_fill_is_the_distance_transforms(max_cells: float, shape: tuple[int, int]) -> None:
    """The offsets (up to 3 cells) fill the cells the exact distance transform fills, each
    with the height of a cell at the smallest distance (ties: any of them); also on grids
    narrower than the offsets (shifted copies of the grid had failed there)."""
    from scipy.ndimage import distance_transform_edt

    from parproj_ros.imaging.heights import _fill_nearest

    rng = np.random.default_rng(3)
    h = rng.uniform(0.0, 100.0, shape).astype(np.float32)
    h[rng.random(h.shape) < 0.5] = np.nan
    h[20:30, 20:32] = np.nan  # a large hole: its middle stays empty
    h.flat[0] = 1.0  # at least one height
    holes = ~np.isfinite(h)
    dist = distance_transform_edt(holes)
    got = h.copy()
    filled = _fill_nearest(got, max_cells)
    assert np.array_equal(filled, holes & (dist <= max_cells))
    assert np.array_equal(got[~holes], h[~holes])
    known = np.argwhere(~holes)
    for i, j in np.argwhere(filled):
        d = np.hypot(*(known - (i, j)).T)
        near = known[np.isclose(d, d.min())]
        assert got[i, j] in {float(h[a, b]) for a, b in near}
