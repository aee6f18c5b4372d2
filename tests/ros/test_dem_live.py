"""The node's DEM parameter over real DDS (issue 24, What to build 3 and 1).

parproj_node in its own process (localhost DDS) replaying bags/ventoux (imported with the SRTM
tile + 50 m; object frame ``enu_wgs84:lat=44.2069738,lon=5.1950231,h=519.80`` from its GCP),
with ``dem`` the SRTM crop of tests/data/ventoux as a GeoTIFF and ``geoid_undulation`` 50
(testkit.rasters.srtm_crop_geotiff); the outputs and /diagnostics recorded from the graph:

- the DEM where the pair is: the pair and its DSM published, the DSM's terrain source
  ``dem+tie_points``, its terrain holding the SRTM's heights over the DSM's cells (+ 50 m, in
  the object frame, up to the pair-ground sampling: tests/apps/test_process_dem.py), and an OK
  status naming the DEM file and its vertical reference;
- the same heights 5 degrees east (a DEM of another place): an ERROR status naming the file,
  the area needed and the area covered, and the pair and its DSM still published (terrain
  from the tie points);
- a streamed pair (bags/airborne_foreaft, 768-line scenes, its outputs labelled with the frame
  ``frame_id`` PLANE and its scenario's terrain as the DEM, testkit.rasters.terrain_geotiff):
  its DSM tiles and its DSM search the DEM's heights from the stream's start (terrain source
  ``dem+tie_points``, the DEM's span held), said once in an OK line naming the DEM;
- ``geoid_undulation`` 50 without ``dem``: a WARN saying it is ignored, the pair and its DSM
  published (terrain from the tie points);
- a DEM GDAL cannot read, two vertical references, a geoid without a DEM: the node does not
  start (exit 2, one line naming the parameter and the file).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from testkit.diagnostics import level, show
from testkit.live import thinned_navigation
from testkit.paths import BAGS
from testkit.rasters import pair_ground_slack, srtm_crop_geotiff, srtm_crop_z, terrain_geotiff

from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import ros_environment, run_through_node

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # live node over DDS (some 8 s a run)

BAG = BAGS / "ventoux"
FRAME = "enu_wgs84:lat=44.2069738,lon=5.1950231,h=519.80"


def _live(tmp: Path, dem: Path | None) -> dict[str, Any]:
    views = views_from_bag(BagReader(BAG))
    files = [] if dem is None else [str(dem)]
    params = node_parameters(views, heights=True, dem=files, geoid_undulation=50.0)
    run = run_through_node(BAG, tmp, params=params, log=lambda s: None, also=("dsm",))
    assert run.discovered and run.code == 0, run.log
    diags = [
        s
        for m in BagReader(run.output).messages(topics=["/diagnostics"])
        for s in m.msg.status
        if s.name != "parproj_node: summary"
    ]
    summary = {
        level(s)
        for m in BagReader(run.output).messages(topics=["/diagnostics"])
        for s in m.msg.status
        if s.name == "parproj_node: summary"
    }
    dsm = [m.msg for m in BagReader(run.output).messages(topics=["dsm"])]
    return {
        "counts": run.counts,
        "log": run.log,
        "diags": diags,
        "dsm": dsm,
        "summary_levels": summary,
    }


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    root = tmp_path_factory.mktemp("dem_live")
    here = srtm_crop_geotiff(root / "N44E005_crop.tif")
    elsewhere = srtm_crop_geotiff(root / "N44E010_crop.tif", shift_lon_deg=5.0)
    return {
        "here": {"dem": here, **_live(root / "here", here)},
        "elsewhere": {"dem": elsewhere, **_live(root / "elsewhere", elsewhere)},
        "none": _live(root / "none", None),
    }


def test_the_dem_is_the_terrain_source(runs: dict[str, dict[str, Any]]) -> None:
    from parproj_ros.core.dem_terrain import DEM_PAD_M
    from parproj_ros.ros.conversions import elevation_grid_from_msg

    got = runs["here"]
    c = got["counts"]
    assert c["stereo_pair"] == 1 and c["dsm"] == 1, got["log"]
    (m,) = got["dsm"]
    assert m.terrain_source == "dem+tie_points" and m.terrain_points >= 100, m
    # The terrain searched holds the SRTM's heights over the DSM's cells, with the DEM's margin.
    heights, grid, _ = elevation_grid_from_msg(m)
    x, y = grid.centres()
    ok = np.isfinite(heights)
    inside = srtm_crop_z(FRAME, x[ok], y[ok])
    eps = pair_ground_slack()
    assert m.terrain_min_m <= inside.min() + eps - DEM_PAD_M, (m.terrain_min_m, inside.min())
    assert m.terrain_max_m >= inside.max() - eps + DEM_PAD_M, (m.terrain_max_m, inside.max())
    said = [s for s in got["diags"] if "from the DEM N44E005_crop.tif" in s.message]
    assert said, show(got["diags"])
    assert said[0].name == "parproj_node: pair left+right" and level(said[0]) == 0
    assert "geoid undulation 50 m (its heights over the pair's ground:" in said[0].message
    assert not [s for s in got["diags"] if level(s) >= 2], show(got["diags"])
    assert f"dem {got['dem']} (geoid undulation 50 m)" in got["log"]


def test_a_dem_elsewhere_is_an_error_and_the_pair_comes(
    runs: dict[str, dict[str, Any]],
) -> None:
    got = runs["elsewhere"]
    c = got["counts"]
    assert c["stereo_pair"] == 1 and c["dsm"] == 1, got["log"]
    (m,) = got["dsm"]
    assert m.terrain_source == "tie_points", m
    errors = [s for s in got["diags"] if level(s) >= 2]
    assert len(errors) == 1, show(got["diags"])
    (e,) = errors
    assert e.name == "parproj_node: pair left+right"
    assert f"{got['dem']}: the DEM gives heights at 0 % of pair left+right's ground" in e.message
    assert "(needed: lon 5.19" in e.message and "the DEM covers lon 10.1" in e.message
    assert "the DEM is not used for this pair" in e.message


def test_an_undulation_without_a_dem_is_said_to_be_ignored(
    runs: dict[str, dict[str, Any]],
) -> None:
    got = runs["none"]
    c = got["counts"]
    assert c["stereo_pair"] == 1 and c["dsm"] == 1, got["log"]
    (m,) = got["dsm"]
    assert m.terrain_source == "tie_points", m
    # said once at start (logged; /diagnostics then has no subscriber yet), and a WARN is no
    # reason for an ERROR summary: the node runs as asked
    line = (
        "[WARN] [{}] [parproj_node]: parameter geoid_undulation: parameter geoid_undulation 50 m "
        "without parameter dem: ignored (it is added to a DEM's heights; give parameter dem"
    )
    head, tail = line.split("[{}]")
    assert any(ln.startswith(head) and tail in ln for ln in got["log"].splitlines()), got["log"]
    assert got["summary_levels"] == {0}, got["summary_levels"]
    assert not [s for s in got["diags"] if level(s) >= 2], show(got["diags"])


def _start(tmp: Path, params: dict[str, Any]) -> tuple[int, str]:
    """parproj_node started with ``params``: its exit code and what it printed."""
    pfile = tmp / "params.yaml"
    pfile.write_text(yaml.safe_dump({"parproj_node": {"ros__parameters": params}}))
    env = ros_environment(log_dir=tmp / "ros_log")
    argv = [
        sys.executable,
        "-m",
        "parproj_ros.ros.node",
        "--ros-args",
        "--params-file",
        str(pfile),
    ]
    r = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=60)
    return r.returncode, r.stdout + r.stderr


@pytest.mark.parametrize(
    "case",
    ["unreadable", "missing", "source gone", "two references", "geoid without dem"],
)
def test_a_dem_that_cannot_serve_refuses_the_start(case: str, tmp_path: Path) -> None:
    bad = tmp_path / "N44E005.hgt"
    bad.write_bytes(b"\0" * 100)
    vrt = tmp_path / "gone.vrt"  # opens (GDAL reads sources lazily); its data cannot be read
    vrt.write_text(
        '<VRTDataset rasterXSize="20" rasterYSize="20"><SRS>EPSG:4326</SRS>'
        "<GeoTransform>5.0, 0.001, 0.0, 44.3, 0.0, -0.001</GeoTransform>"
        '<VRTRasterBand dataType="Int16" band="1"><SimpleSource>'
        '<SourceFilename relativeToVRT="1">gone.tif</SourceFilename><SourceBand>1</SourceBand>'
        "</SimpleSource></VRTRasterBand></VRTDataset>"
    )
    params: dict[str, Any] = {
        "unreadable": {"dem": [str(bad)]},
        "source gone": {"dem": [str(vrt)]},
        "missing": {"dem": ["no_such_dem.tif"]},
        "two references": {"dem": [str(bad)], "geoid": "egm2008", "geoid_undulation": 50.0},
        "geoid without dem": {"dem_ellipsoidal": True},
    }[case]
    code, out = _start(tmp_path, params)
    lines = [s for s in out.splitlines() if s.startswith("parproj_node: cannot start")]
    assert code == 2 and len(lines) == 1, out
    want = {
        "unreadable": f"parameter dem: {bad}: GDAL cannot read it as a raster",
        "missing": "parameter dem: no_such_dem.tif (from the node's working folder, ",
        "source gone": f"parameter dem: {vrt}: cannot be read (",
        "two references": "parameter geoid_undulation: and parameter geoid both give the DEM's "
        "vertical reference",
        "geoid without dem": "parameter dem_ellipsoidal: describes the DEM's heights: give "
        "parameter dem too",
    }[case]
    assert want in lines[0], lines[0]
    assert "Traceback" not in out
    if case == "source gone":  # GDAL's words, not "Read failed. See previous exception"
        assert "gone.tif" in lines[0] and "See previous" not in lines[0], lines[0]


#: The frame the streamed bag's outputs are labelled with (a place on Earth for the DEM).
PLANE = "enu_wgs84:lat=44.0000000,lon=5.0000000,h=0.00"


def test_a_streamed_pair_and_its_tiles_search_the_dem(tmp_path: Path) -> None:
    from parproj_ros.sim.scenarios import SCENARIOS
    from parproj_ros.sim.terrain import procedural_terrain

    # a slow replay of the bag thinned as the tiles' live test replays it: the pair streams
    bag = thinned_navigation(BAGS / "airborne_foreaft", tmp_path / "input")
    scn = SCENARIOS["airborne_foreaft"]()
    terrain = procedural_terrain(
        scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
    )
    half = scn.terrain_extent_m / 2
    dem = terrain_geotiff(tmp_path / "terrain.tif", terrain.height, PLANE, half, 1.0)
    views = views_from_bag(BagReader(bag))
    params = node_parameters(
        views, heights=True, scene_lines=768, dem=[str(dem)], dem_ellipsoidal=True, frame_id=PLANE
    )
    run = run_through_node(
        bag,
        tmp_path,
        params=params,
        rate=0.2,
        max_gap_s=0.05,
        timeout_s=180.0,
        log=lambda s: None,
        also=("dsm",),
    )
    assert run.discovered and run.code == 0, run.log
    reader = BagReader(run.output)
    diags = [
        s
        for m in reader.messages(topics=["/diagnostics"])
        for s in m.msg.status
        if s.name != "parproj_node: summary"
    ]
    assert [s for s in diags if s.message.startswith("streaming: ")], show(diags)
    tiles = [m.msg for m in reader.messages(topics=["dsm_tile"])]
    (dsm,) = [m.msg for m in reader.messages(topics=["dsm"])]
    assert tiles, run.log
    lo, hi = terrain.min_height, terrain.max_height
    for m in [*tiles, dsm]:
        assert m.terrain_source == "dem+tie_points", (m.terrain_source, m.terrain_points)
        # the DEM's span over the pair's ground (within the scenario's) is searched
        assert m.terrain_min_m <= hi and m.terrain_max_m >= lo, (m.terrain_min_m, m.terrain_max_m)
    said = [s for s in diags if "from the DEM terrain.tif, ellipsoidal heights" in s.message]
    assert said and level(said[0]) == 0, show(diags)
    assert not [s for s in diags if level(s) >= 2], show(diags)
