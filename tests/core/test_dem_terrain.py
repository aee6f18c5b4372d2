"""A DEM's heights as a pair's terrain (core/dem_terrain.py; issue 24, What to build 1 and 3).

- the conversion: a DEM's ellipsoidal height at a point's own lon/lat into the object Z of a
  tangent plane, with the plane's curvature: a flat DEM (h constant above WGS84) against the
  osculating sphere of the normal section through the origin (Euler's radius in the point's
  azimuth), exact to e^2 d^3 / R^2 (6e-5 m at 7 km), where ignoring the curvature errs by
  d^2 / 2R (3.9 m at the corners of a 10 km square); and the Ventoux import's virtual GCP
  (rays of the RPCs meeting the SRTM crop + 50 m, then geodetic -> ENU) lying on the DEM
  surface as this module places it (the import stops at 1 mm in height);
- the rule: the DEM's span joined with the tie points' (their hull), the DEM's alone instead
  of the prior, the disagreement said;
- the pipeline (no ROS): the small ikonos_agile pair of tests/core/test_heights_step.py with
  its own terrain as the DEM (the frame taken as a tangent plane: the DEM surface is the
  terrain Z = T(X, Y) exactly), a DEM elsewhere (ERROR naming it, the pair still made), a
  ``map`` frame (a WARN once), a DEM that fails (ERROR, the pair still made).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from numpy.typing import ArrayLike
from testkit.paths import DATA
from testkit.rasters import srtm_crop_geotiff
from testkit.scenes import feed, nav_events, rendered, small_scenario, strip_events

from parproj_ros.core.dem_terrain import (
    DEM_PAD_M,
    DEM_PAD_SHARE,
    FOOTPRINT_GRID,
    DemTerrain,
    surface_z,
)
from parproj_ros.core.frames import frame_id_of, tangent_plane
from parproj_ros.core.pipeline import Pipeline
from parproj_ros.core.results import Level
from parproj_ros.core.terrain import (
    DISAGREE_M,
    Terrain,
    TerrainSource,
    disagreement,
    with_dem,
)
from parproj_ros.geometry.geodesy import WGS84_A, WGS84_F, LocalTangentPlane

#: The Ventoux bag's object frame (bags/README.md).
VENTOUX = LocalTangentPlane(44.2069738, 5.1950231, 519.80)


class FlatDem:
    """A DEM of one ellipsoidal height everywhere (or nowhere: ``cover`` False)."""

    name = label = "flat.tif"
    reference = "ellipsoidal heights"

    def __init__(self, h: float, cover: bool = True) -> None:
        self.h, self.cover = h, cover

    def __call__(self, lon: ArrayLike, lat: ArrayLike) -> Any:
        shape = np.broadcast(np.asarray(lon), np.asarray(lat)).shape
        return np.full(shape, self.h if self.cover else np.nan)

    def gap_error(self, lon: ArrayLike, lat: ArrayLike, what: str) -> str | None:
        if self.cover:
            return None
        return f"{self.name}: the DEM gives heights at 0 % of {what} (needed: lon ..)"


def _euler_sphere_z(plane: LocalTangentPlane, x: Any, y: Any, h: float) -> Any:
    """Z of the point at horizontal (x, y) and ellipsoidal height h on the osculating sphere of
    the normal section through the origin in the point's azimuth (Euler's radius)."""
    e2 = WGS84_F * (2.0 - WGS84_F)
    s = math.sin(math.radians(plane.lat0))
    n = WGS84_A / math.sqrt(1.0 - e2 * s * s)
    m = n * (1.0 - e2) / (1.0 - e2 * s * s)
    az = np.arctan2(x, y)
    r = 1.0 / (np.cos(az) ** 2 / m + np.sin(az) ** 2 / n)
    return np.sqrt((r + h) ** 2 - np.hypot(x, y) ** 2) - (r + plane.h0)


def test_a_flat_dem_is_curved_in_the_tangent_plane() -> None:
    h = 600.0  # ellipsoidal; the plane's origin is at 519.80 m
    d = 5000.0  # the corners of a 10 km square, and points between
    x = np.array([d, -d, d, -d, 0.0, 0.0, 1000.0, 3000.0, -250.0])
    y = np.array([d, d, -d, -d, 0.0, d, 0.0, -2000.0, 125.0])
    z = surface_z(VENTOUX, FlatDem(h), x, y, 0.0)
    expected = _euler_sphere_z(VENTOUX, x, y, h)
    assert np.abs(z - expected).max() < 1e-3  # the sphere's own error: 6e-5 m at 7 km
    drop = h - VENTOUX.h0 - z
    assert drop[:4] == pytest.approx(3.92, abs=0.01)  # d^2 / 2R at 7.07 km: not negligible
    assert drop[4] == pytest.approx(0.0, abs=1e-6)
    # and the point found has the DEM's height at its own lon/lat
    _, _, hh = VENTOUX.to_geodetic(x, y, z)
    assert np.abs(hh - h).max() < 1e-4


def test_the_import_virtual_gcp_lie_on_the_dem_surface(tmp_path: Any) -> None:
    """The Ventoux import's ground points (RPC rays meeting the DEM, scene_import._ground)
    converted to the import's frame: the DEM surface of this module passes through them."""
    from parproj_ros.io.dem import load_dem
    from parproj_ros.io.scene_import import _grid, _ground, load_image, make_frame

    dem = load_dem(srtm_crop_geotiff(tmp_path / "srtm.tif"), geoid=50.0)
    img = load_image(DATA / "left_image.tif", "left")
    plane = make_frame(img, dem)
    assert frame_id_of(plane) == "enu_wgs84:lat=44.2069738,lon=5.1950231,h=519.80"
    line, sample = _grid(img, 7, 7)
    geo = _ground(img, line, sample, dem, np.zeros(line.shape))
    x, y, z = plane.to_local(geo[:, 0], geo[:, 1], geo[:, 2])
    ours = surface_z(plane, dem, x, y, 0.0)
    assert np.isfinite(ours).all() and np.ptp(z) > 20.0  # sloping ground: a real test
    assert np.abs(ours - z).max() < 2e-3, np.abs(ours - z).max()


def test_the_dem_and_the_tie_points_joined() -> None:
    dem = Terrain(-30.0, 60.0, TerrainSource.DEM, dem_m=(-10.0, 40.0), dem="a.tif, geoid 50 m")
    ties = Terrain(-20.0, 80.0, TerrainSource.TIE_POINTS, 300, (0.0, 60.0))
    prior = Terrain(-500.0, 500.0, TerrainSource.PRIOR)
    both = with_dem(dem, ties)
    assert (both.low_m, both.high_m, both.source) == (-30.0, 80.0, TerrainSource.DEM_TIE_POINTS)
    assert (both.points, both.measured_m, both.dem_m) == (300, (0.0, 60.0), (-10.0, 40.0))
    assert with_dem(dem, both) == both  # joined again: the same
    assert with_dem(dem, prior) is dem  # too few tie points: the DEM, not the prior
    assert with_dem(None, ties) is ties and with_dem(None, prior) is prior
    text = both.describe()
    assert text.startswith("terrain -30..80 m from the DEM a.tif, geoid 50 m"), text
    assert "(its heights over the pair's ground: -10..40 m)" in text and "300 tie points" in text
    assert dem.describe() == (
        "terrain -30..60 m from the DEM a.tif, geoid 50 m (its heights over the pair's "
        "ground: -10..40 m, plus a margin)"
    )
    assert disagreement(both) is None
    apart = with_dem(
        dem, Terrain(70.0, 130.0, TerrainSource.TIE_POINTS, 50, (40.0 + DISAGREE_M + 1, 110.0))
    )
    said = disagreement(apart)
    assert said is not None and "31 m above the DEM's" in said and "geoid_undulation" in said


# ---- the pipeline, without ROS ---------------------------------------------------------------


class TerrainDem:
    """The scenario's terrain as a DEM of the tangent plane ``plane`` (frame ``map`` taken as
    that plane): at (lon, lat) the ellipsoidal height whose object point lies on Z = T(X, Y)."""

    name = label = "terrain.tif"
    reference = "ellipsoidal heights"

    def __init__(self, terrain: Any, plane: LocalTangentPlane) -> None:
        self.terrain, self.plane, self.calls = terrain, plane, 0

    def __call__(self, lon: Any, lat: Any) -> Any:
        self.calls += 1
        lon, lat = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
        h = np.full(lon.shape, self.plane.h0)
        for _ in range(6):
            x, y, z = self.plane.to_local(lon, lat, h)
            h = h + (self.terrain.height(x, y) - z)
        return h

    def gap_error(self, lon: ArrayLike, lat: ArrayLike, what: str) -> str | None:
        return None


class FailingDem(FlatDem):
    def __call__(self, lon: ArrayLike, lat: ArrayLike) -> Any:
        raise OSError("read error on the DEM's file")


PLANE_ID = "enu_wgs84:lat=44.0000000,lon=5.0000000,h=0.00"


@pytest.fixture(scope="module")
def agile() -> dict[str, Any]:
    scn = small_scenario("ikonos_agile", 384)
    terrain, scenes = rendered(scn)
    return {"scn": scn, "terrain": terrain, "events": nav_events(scn) + strip_events(scn, scenes)}


def _run(agile: dict[str, Any], dem: Any, frame: str, **config: Any) -> Any:
    pipe = Pipeline(agile["scn"].pipeline_config(streaming=False, **config))
    pipe.use_dem(DemTerrain(dem, lambda: frame))
    return feed(pipe, agile["events"])


def test_the_pipeline_searches_the_dem_heights(agile: dict[str, Any]) -> None:
    """The terrain itself as the DEM: the pair's terrain holds its span over the pair's ground,
    and the heights step searches it (tie points off: the DEM's alone)."""
    terrain = agile["terrain"]
    dem = TerrainDem(terrain, tangent_plane(PLANE_ID))  # type: ignore[arg-type]
    out = _run(agile, dem, PLANE_ID, tie_points=False, terrain="prior", heights=True)
    (pair,) = out.pairs
    t = pair.terrain
    assert t.source == TerrainSource.DEM and dem.calls > 0
    lo, hi = t.dem_m
    # The span over the pair's ground, within the terrain's own, and holding the ground that
    # the DSM found (its cells with a height: the common ground matched), up to the sampling
    # of the footprint grid (its node spacing times the terrain's steepest slope).
    assert terrain.min_height - 1e-6 <= lo < hi <= terrain.max_height + 1e-6
    (res,) = out.heights
    assert res.ok and res.terrain == t, res.message
    x, y = res.dsm.grid.centres()
    ok = np.isfinite(res.dsm.heights)
    truth = terrain.height(x[ok], y[ok])
    spacing = 384 * res.dsm.grid.cell / (FOOTPRINT_GRID - 1)
    slope = terrain.max_slope
    eps = slope * spacing * math.sqrt(2.0)
    print(
        f"DEM span {lo:.2f}..{hi:.2f} m, DSM cells {truth.min():.2f}..{truth.max():.2f} m, "
        f"slack {eps:.2f} m"
    )
    assert lo <= truth.min() + eps and hi >= truth.max() - eps, (lo, hi, truth.min(), truth.max())
    pad = max(DEM_PAD_SHARE * (hi - lo), DEM_PAD_M, 4 * abs(pair.height_per_disparity_px))
    assert t.range_m == pytest.approx((lo - pad, hi + pad))
    said = [
        i for i in out.issues if i.where == f"pair {pair.pair_id}" and "from the DEM" in i.message
    ]
    assert said and said[0].level == Level.OK, [i.message for i in out.issues]
    assert "terrain.tif, ellipsoidal heights" in said[0].message


def test_a_dem_elsewhere_is_an_error_and_the_pair_comes(agile: dict[str, Any]) -> None:
    out = _run(agile, FlatDem(500.0, cover=False), PLANE_ID)
    (pair,) = out.pairs
    assert pair.terrain.source == TerrainSource.TIE_POINTS
    errors = [i for i in out.issues if i.level == Level.ERROR]
    assert len(errors) == 1 and errors[0].where == f"pair {pair.pair_id}", errors
    assert "flat.tif: the DEM gives heights at 0 %" in errors[0].message
    assert "the DEM is not used for this pair" in errors[0].message


class HalfDem(FlatDem):
    """Heights on one side of a meridian only: part of the pair's ground."""

    def __init__(self, h: float, lon0: float) -> None:
        super().__init__(h)
        self.lon0 = lon0

    def __call__(self, lon: ArrayLike, lat: ArrayLike) -> Any:
        lon = np.asarray(lon, float)
        return np.where(lon > self.lon0, self.h, np.nan) + 0.0 * np.asarray(lat, float)

    def gap_error(self, lon: ArrayLike, lat: ArrayLike, what: str) -> str | None:
        share = float(np.isfinite(self(lon, lat)).mean())
        return None if share >= 0.9 else f"{self.name}: {100 * share:.0f} % of {what}"


def test_a_dem_over_part_of_the_pair_is_a_warning(agile: dict[str, Any]) -> None:
    """Under 90 % of the pair's ground but some: WARN (not ERROR), the pair without the DEM."""
    plane = tangent_plane(PLANE_ID)
    assert plane is not None
    pipe = Pipeline(agile["scn"].pipeline_config(streaming=False))
    seen = DemTerrain(FlatDem(0.0), lambda: PLANE_ID)
    pipe.use_dem(seen)
    out = feed(pipe, agile["events"])
    (pair,) = out.pairs
    # the meridian through the middle of the pair's ground
    from parproj_ros.core.dem_terrain import footprint_lonlat

    lon, _ = footprint_lonlat(pair.left, pair.right, pair.normalization, plane, z0=0.0)
    half = HalfDem(0.0, float(np.median(lon)))
    out = _run(agile, half, PLANE_ID)
    (pair,) = out.pairs
    assert pair.terrain.source == TerrainSource.TIE_POINTS
    (warn,) = [i for i in out.issues if "of pair" in i.message and "ground" in i.message]
    share = float(warn.message.split(": ")[1].split(" %")[0])
    assert warn.level == Level.WARN and 30.0 < share < 70.0, warn.message
    assert "the DEM is not used for this pair" in warn.message


def test_a_dem_in_a_map_frame_is_said_once(agile: dict[str, Any]) -> None:
    dem = FlatDem(500.0)
    pipe = Pipeline(agile["scn"].pipeline_config(streaming=False))
    terrains = DemTerrain(dem, lambda: "map")
    pipe.use_dem(terrains)
    out = feed(pipe, agile["events"])
    (pair,) = out.pairs
    assert pair.terrain.source == TerrainSource.TIE_POINTS
    warns = [i for i in out.issues if i.where == "dem"]
    assert len(warns) == 1 and warns[0].level == Level.WARN, warns
    assert "the DEM flat.tif is not used: the object frame 'map' has no place on Earth" in (
        warns[0].message
    )
    # a second pair in the same frame: not said again
    left, right = pair.left, pair.right
    assert (
        terrains.pair_terrain("b", left, right, pair.normalization, z0=0.0, metres_per_px=1.0)
        is None
    )
    assert terrains.take_issues() == []


def test_a_dem_that_fails_is_an_error_and_the_pair_comes(agile: dict[str, Any]) -> None:
    out = _run(agile, FailingDem(0.0), PLANE_ID)
    (pair,) = out.pairs
    assert pair.terrain.source == TerrainSource.TIE_POINTS
    (err,) = [i for i in out.issues if i.level == Level.ERROR]
    assert "the DEM flat.tif could not be sampled (OSError: read error" in err.message


# ---- a streamed pair (its extent and DSM tiles chosen when the stream begins) ---------------
# The airborne fore/aft bag (two views: it streams; tests/core/test_tiles.py), its frame taken
# as the tangent plane PLANE_ID and its scenario's terrain as the DEM.


@pytest.fixture(scope="module")
def airborne() -> dict[str, Any]:
    from parproj_ros.sim.scenarios import SCENARIOS
    from parproj_ros.sim.terrain import procedural_terrain

    scn = SCENARIOS["airborne_foreaft"]()
    terrain = procedural_terrain(
        scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
    )
    return {"terrain": terrain}


def _streamed(dem: Any) -> Any:
    from testkit.paths import BAGS

    from parproj_ros.core.results import Outputs
    from parproj_ros.ros import conversions as conv
    from parproj_ros.ros.bag import BagReader
    from parproj_ros.ros.inputs import config_from_bag

    bag = BAGS / "airborne_foreaft"
    reader = BagReader(bag)
    cfg = config_from_bag(reader, scene_lines=768, heights=True)
    pipe = Pipeline(cfg)
    pipe.use_dem(DemTerrain(dem, lambda: PLANE_ID))
    out = Outputs()
    strips = {"left/image_strip": "left", "right/image_strip": "right"}
    for item in reader.messages(topics=["navigation", *strips]):
        if item.topic == "navigation":
            out.extend(pipe.add_navigation(conv.odometry_to_sample(item.msg)))
            continue
        stamp = conv.stamp_to_ns(item.msg.header.stamp)
        strip = conv.image_to_array(item.msg)
        out.extend(pipe.add_strip(strips[item.topic], stamp, item.msg.header.frame_id, strip))
    out.extend(pipe.flush())
    assert [i for i in out.issues if i.message.startswith("streaming: ")], [
        i.message for i in out.issues
    ]
    return out


@pytest.mark.ros  # reads a bag
def test_a_streamed_pair_searches_the_dem_from_its_start(airborne: dict[str, Any]) -> None:
    """The DEM's heights, sampled when the stream begins, are the streamed pair's extent and
    its tiles' search (joined with the first window's tie points), and the finished pair's
    terrain: the DEM sampled once for the pair (its problems said once)."""
    terrain = airborne["terrain"]
    dem = TerrainDem(terrain, tangent_plane(PLANE_ID))  # type: ignore[arg-type]
    out = _streamed(dem)
    (pair,) = out.pairs
    t = pair.terrain
    assert t.source in (TerrainSource.DEM, TerrainSource.DEM_TIE_POINTS), t
    lo, hi = t.dem_m
    assert terrain.min_height - 1e-6 <= lo < hi <= terrain.max_height + 1e-6
    said = [i for i in out.issues if i.where == f"pair {pair.pair_id}" and "DEM" in i.message]
    assert said, [i.message for i in out.issues]
    first = said[0]
    assert first.level == Level.OK and first.message.startswith("terrain "), first.message
    assert "from the DEM terrain.tif, ellipsoidal heights" in first.message
    full = [tile for tile in out.tiles if tile.factor == 1]
    assert full, "no tiles"
    for tile in full:
        assert tile.terrain is not None and tile.terrain.dem_m == (lo, hi), tile.terrain
        assert tile.terrain.low_m <= lo and tile.terrain.high_m >= hi
    (res,) = out.heights
    assert res.ok and res.dsm is not None, res.message
    calls = dem.calls
    again = DemTerrain(dem, lambda: PLANE_ID)
    k = pair.normalization.parallax_per_height
    args = (pair.pair_id, pair.left, pair.right, pair.normalization)
    z0 = 0.5 * (t.low_m + t.high_m)
    assert again.pair_terrain(*args, z0=z0, metres_per_px=pair.left_grid.pixel / k) is not None
    per_pair = dem.calls - calls  # what one pair's sampling costs
    assert calls == per_pair, (calls, per_pair)  # at the stream's start only: once


@pytest.mark.ros  # reads a bag
def test_a_streamed_pair_with_a_dem_elsewhere_is_one_error() -> None:
    out = _streamed(FlatDem(500.0, cover=False))
    (pair,) = out.pairs
    assert pair.terrain.source in (TerrainSource.TIE_POINTS, TerrainSource.PRIOR), pair.terrain
    errors = [i for i in out.issues if i.level == Level.ERROR]
    assert len(errors) == 1 and errors[0].where == f"pair {pair.pair_id}", errors
    assert "flat.tif: the DEM gives heights at 0 %" in errors[0].message
    assert out.tiles and all(
        tile.terrain is None or tile.terrain.dem_m is None for tile in out.tiles
    )
