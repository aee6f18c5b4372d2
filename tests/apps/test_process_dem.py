"""``parproj process --dem`` (issue 24, What to build 3 and 1): the DEM's heights as the terrain.

The Ventoux bag (bags/ventoux: imported with the SRTM tile + 50 m, its frame the tangent plane
``enu_wgs84:lat=44.2069738,lon=5.1950231,h=519.80``) processed with the SRTM crop of
tests/data/ventoux written as a GeoTIFF (testkit.rasters.srtm_crop_geotiff). Expected figures
come from the crop itself, independently of the pipeline's sampling: its heights (+ 50 m, in the
object frame) over the DSM's cells with a height (ground both images see and that matched:
inside the pair's ground) and over the DSM's whole grid (the left image's footprint beyond the
pair's ground), up to the pair-ground sampling (its grid's node spacing, 500 px x 0.5 m / 30,
times the crop's steepest slope).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from testkit.cli import run
from testkit.paths import BAGS
from testkit.rasters import pair_ground_slack, srtm_crop_geotiff, srtm_crop_z

from parproj_ros.core.dem_terrain import DEM_PAD_M, DEM_PAD_SHARE
from parproj_ros.core.terrain import TerrainSource

pytestmark = pytest.mark.ros  # bags

BAG = BAGS / "ventoux"
FRAME = "enu_wgs84:lat=44.2069738,lon=5.1950231,h=519.80"


@pytest.fixture(scope="module")
def dems(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("dems")
    return {
        "here": srtm_crop_geotiff(root / "N44E005_crop.tif"),
        "elsewhere": srtm_crop_geotiff(root / "N44E010_crop.tif", shift_lon_deg=5.0),
    }


def _process(dem: Path, tmp: Path, **overrides: Any) -> dict[str, Any]:
    from parproj_ros.apps.process import process_bag
    from parproj_ros.io.dem import load_dem

    kept: list[Any] = []
    process_bag(
        BAG,
        tmp,
        progress=False,
        overrides={"heights": True, **overrides},
        dem=load_dem(dem, geoid=50.0),
        on_outputs=kept.append,
    )
    (pair,) = [p for o in kept for p in o.pairs]
    (res,) = [h for o in kept for h in o.heights]
    return {"pair": pair, "heights": res, "issues": [i for o in kept for i in o.issues]}


def test_the_dem_span_joins_the_tie_points(dems: dict[str, Path], tmp_path: Path) -> None:
    got = _process(dems["here"], tmp_path / "out")
    t = got["pair"].terrain
    assert t.source == TerrainSource.DEM_TIE_POINTS and t.points >= 100
    lo, hi = t.dem_m
    dsm = got["heights"].dsm
    x, y = dsm.grid.centres()
    ok = np.isfinite(dsm.heights)
    inside, around = srtm_crop_z(FRAME, x[ok], y[ok]), srtm_crop_z(FRAME, x.ravel(), y.ravel())
    eps = pair_ground_slack()
    print(
        f"DEM {lo:.2f}..{hi:.2f} m; tie points {t.measured_m}; SRTM over the DSM's cells "
        f"{inside.min():.2f}..{inside.max():.2f}, its grid {np.nanmin(around):.2f}.."
        f"{np.nanmax(around):.2f} m; slack {eps:.2f} m"
    )
    assert lo <= inside.min() + eps and hi >= inside.max() - eps
    assert lo >= np.nanmin(around) - eps and hi <= np.nanmax(around) + eps
    # The hull: both spans, each with its margin, are searched.
    tlo, thi = t.measured_m
    assert t.low_m <= min(lo - DEM_PAD_M, tlo) and t.high_m >= max(hi + DEM_PAD_M, thi)
    assert got["heights"].ok and got["heights"].terrain == t
    (line,) = [i for i in got["issues"] if i.message.startswith("terrain ")]
    assert "from the DEM N44E005_crop.tif, geoid undulation 50 m (its heights" in line.message
    assert f"and {t.points} tie points" in line.message


def test_terrain_prior_with_a_dem_searches_the_dem(dems: dict[str, Path], capsys: Any) -> None:
    """Through the command: the DSM message says "dem" and holds the DEM's span + margin."""
    from parproj_ros.ros.bag import BagReader

    out = Path(str(dems["here"].parent)) / "out_prior"
    argv = ["process", str(BAG), "-o", str(out), "-q", "--heights", "--terrain", "prior"]
    code, _, err = run([*argv, "--dem", str(dems["here"]), "--geoid-undulation", "50"], capsys)
    assert code == 0, err
    (m,) = [x.msg for x in BagReader(out).messages(topics=["dsm"])]
    assert m.terrain_source == "dem" and m.terrain_points == 0
    # the DEM's span over the pair's ground, said on /diagnostics, widened by its margin
    said = next(s for s in err.splitlines() if "[ok] pair left+right: terrain " in s)
    lo, hi = (float(v) for v in said.split("ground: ")[1].split(" m")[0].split(".."))
    pad = max(DEM_PAD_SHARE * (hi - lo), DEM_PAD_M)
    assert m.terrain_min_m == pytest.approx(lo - pad, abs=0.6)  # the line's metres rounded
    assert m.terrain_max_m == pytest.approx(hi + pad, abs=0.6)
    assert 60.0 < m.terrain_max_m - m.terrain_min_m < 100.0  # not the GCP's 200 m + span


def test_a_dem_elsewhere_is_named_and_the_pair_comes(
    dems: dict[str, Path], tmp_path: Path, capsys: Any
) -> None:
    out = tmp_path / "out"
    argv = [
        "process",
        str(BAG),
        "-o",
        str(out),
        "-q",
        "--heights",
        "--dem",
        str(dems["elsewhere"]),
    ]
    code, stdout, err = run(argv, capsys)
    assert code == 0 and "1 pairs" in stdout, err
    (line,) = [s for s in err.splitlines() if s.startswith("[error]")]
    assert f"{dems['elsewhere']}: the DEM gives heights at 0 % of pair left+right's ground" in line
    assert "(needed: lon 5.19" in line and "the DEM covers lon 10.1" in line, line
    assert "the DEM is not used for this pair" in line
    from parproj_ros.ros.bag import BagReader

    (m,) = [x.msg for x in BagReader(out).messages(topics=["dsm"])]
    assert m.terrain_source == "tie_points"


def test_an_unreadable_dem_is_refused(tmp_path: Path, capsys: Any) -> None:
    bad = tmp_path / "N44E005.hgt"
    bad.write_bytes(b"not a tile")
    argv = ["process", str(BAG), "-o", str(tmp_path / "o"), "-q", "--dem", str(bad)]
    code, _, err = run(argv, capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{bad}: GDAL cannot read it as a raster" in err
    assert not (tmp_path / "o").exists()
    code, _, err = run(
        ["process", str(BAG), "-o", str(tmp_path / "o"), "--geoid", "egm2008"], capsys
    )
    assert code == 2 and "--geoid: describes the DEM's heights: give --dem too" in err, err
