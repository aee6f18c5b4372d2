"""What the products of ``parproj dsm`` and ``parproj fuse`` say about themselves, read back as
a user reads them (rasterio tags, band descriptions and units; laspy's header).

Output bags built here: ``dsm`` ElevationGrids of the synthetic surface of
``tests/apps/test_dsm_export.py`` in the Marseille pair's tangent-plane frame, one with filled
cells (as ``parproj process`` reports them), two for the fusion (the second 0.4 m higher).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pytest
import rasterio

from parproj_ros import __version__
from parproj_ros.apps.cli import main
from parproj_ros.ros.bag import BagWriter
from parproj_ros.ros.conversions import array_to_image
from tests.apps.test_dsm_export import CELL, FID, FRAME, T0, surface

pytestmark = pytest.mark.ros  # bags (rclpy serialization) and messages

FILLED, MAX_FILL = 1234, 2.0
OFFSET_M = 0.4  # the second pair's level above the first's
TERRAIN = (-2.0, 60.0)  # terrain searched, Z m in the frame: holds the surface (12.8..50 m)


def bag(path: Path, pairs: list[tuple[str, Any]]) -> Path:
    """An output bag with one ``dsm`` per (pair id, heights), with filled-cell figures."""
    from parproj_msgs.msg import ElevationGrid
    from sensor_msgs.msg import Image

    with BagWriter(path) as bw:
        bw.add_topic("dsm", "parproj_msgs/msg/ElevationGrid", "reliable")
        for k, (pair, z) in enumerate(pairs):
            m = ElevationGrid()
            m.header.frame_id = FID
            m.header.stamp.sec = 1_700_000_000 + k
            m.pair_id = pair
            m.x0, m.y0, m.cell_size = -75.0, 60.0, CELL
            m.terrain_source, m.terrain_points = "tie_points", 381
            m.terrain_min_m, m.terrain_max_m = TERRAIN
            m.disparity_min, m.disparity_max, m.matched_share = -20, 35, 0.93
            m.filled_cells, m.max_fill_cells = FILLED, MAX_FILL
            m.heights = array_to_image(z.astype(np.float32), Image(), frame_id=FID, stamp_ns=T0)
            ortho = np.where(np.isfinite(z), 1000, 0).astype(np.uint16)
            m.ortho = array_to_image(ortho, Image(), frame_id=FID, stamp_ns=T0)
            bw.write("dsm", m, T0 + k)
    return path


def test_dsm_files_name_their_software_pair_and_filled_cells(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The DSM, the ortho-image and the LAS say what made them (software and version, the pair)
    and the DSM how many of its cells were filled, not measured (before: no software, no pair,
    the filled cells nowhere in the files or in dsm.json; the LAS said 'laspy 2.6.1')."""
    out = bag(tmp_path / "out", [("left+right", surface())])
    assert main(["dsm", str(out), "-o", str(tmp_path / "d"), "--las", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)["pairs"]
    assert row["filled_cells"] == FILLED
    software = f"parproj_ros {__version__}"
    with rasterio.open(tmp_path / "d" / "left_right_dsm.tif") as src:
        tags = src.tags()
    assert tags["TIFFTAG_SOFTWARE"] == software and tags["PARPROJ_PAIR_ID"] == "left+right"
    assert int(tags["PARPROJ_FILLED_CELLS"]) == FILLED
    assert f"at most {MAX_FILL:g} cell widths" in tags["PARPROJ_FILLED_NOTE"]
    with rasterio.open(tmp_path / "d" / "left_right_ortho.tif") as src:
        otags = src.tags()
    assert otags["TIFFTAG_SOFTWARE"] == software and otags["PARPROJ_PAIR_ID"] == "left+right"
    header = laspy.read(tmp_path / "d" / "left_right_dsm.las").header
    assert header.generating_software == software


def test_terrain_tags_relate_to_the_files_heights(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """PARPROJ_TERRAIN_MIN_M / MAX_M are Z in the object frame (here -2..60 m), next to heights
    above the ellipsoid (208..238 m): the note gives the ellipsoidal heights searched, h0 + Z
    (within 100 m of the origin the plane leaves the ellipsoid by < 1 mm), which hold the DSM's
    heights. Before, nothing in the file said the two were in different references."""
    out = bag(tmp_path / "out", [("left+right", surface())])
    assert main(["dsm", str(out), "-o", str(tmp_path / "d")]) == 0
    capsys.readouterr()
    with rasterio.open(tmp_path / "d" / "left_right_dsm.tif") as src:
        note = src.tags()["PARPROJ_TERRAIN_NOTE"]
        h = src.read(1, masked=True)
    lo, hi = (float(v) for v in note.split("about ")[1].split(" m above")[0].split(".."))
    assert lo == pytest.approx(FRAME.h0 + TERRAIN[0], abs=0.005)
    assert hi == pytest.approx(FRAME.h0 + TERRAIN[1], abs=0.005)
    assert lo < float(h.min()) and float(h.max()) < hi
    assert f"h0 {FRAME.h0:.2f} m" in note


def test_fused_layers_say_what_they_hold(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """fused_count.tif and fused_spread.tif: band descriptions that tell them apart and say
    what they hold, the spread in metres (unit "m"), tags naming the fused pairs and the
    offsets removed (the two pairs 0.4 m apart: +-0.2 m); before, both had the same generic
    description "fused DSM layer <file>" and no unit."""
    z = surface()
    out = bag(tmp_path / "out", [("a+b", z), ("a+c", z + np.float32(OFFSET_M))])
    assert main(["fuse", str(out), "-o", str(tmp_path / "f"), "--json"]) == 0
    capsys.readouterr()
    f = tmp_path / "f"
    with rasterio.open(f / "fused_dsm.tif") as src:
        tags = src.tags()
        valid = np.isfinite(src.read(1))
    assert tags["PARPROJ_PAIR_ID"] == "fused" and tags["PARPROJ_INPUTS"] == "a+b, a+c"
    offsets = [float(v) for v in tags["PARPROJ_OFFSETS_REMOVED_M"].split(",")]
    # float32 heights of about 20-40 m: the offset is exact to a few ulps (1e-5 m)
    assert offsets[1] - offsets[0] == pytest.approx(OFFSET_M, abs=2e-3)  # subtracted from each
    assert sum(offsets) == pytest.approx(0.0, abs=2e-3)
    with rasterio.open(f / "fused_count.tif") as src:
        count, count_desc, count_unit = src.read(1), src.descriptions[0], src.units[0]
        assert src.tags()["PARPROJ_INPUTS"] == "a+b, a+c" and src.nodata == 0
    with rasterio.open(f / "fused_spread.tif") as src:
        spread, spread_desc, spread_unit = src.read(1), src.descriptions[0], src.units[0]
        assert src.tags()["TIFFTAG_SOFTWARE"] == f"parproj_ros {__version__}"
    assert count_desc != spread_desc
    assert "count" in count_desc and "spread" in spread_desc and "metres" in spread_desc
    assert spread_unit == "m" and not count_unit
    # the layers themselves: both samples kept, and agreeing once the offset is removed
    assert np.all(count[valid] == 2) and np.all(count[~valid] == 0)
    assert float(np.nanmax(spread[valid])) < 1e-3


def test_fused_dsm_exported_by_dsm_gets_no_matching_figures(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``parproj dsm DIR/bag`` on parproj fuse's bag: the fused DSM has no disparity range,
    matched share or terrain search of its own (its ElevationGrid leaves them 0 / empty).
    Before, its GeoTIFF said PARPROJ_MATCHED_SHARE 0.0, PARPROJ_DISPARITY_RANGE_PX [0, 0] and
    terrain 0..0 m from 'unknown', as if no pixel had matched; now it names the software and
    the pair (fused) and gives no matching figures, in the tags and in dsm.json."""
    z = surface()
    out = bag(tmp_path / "out", [("a+b", z), ("a+c", z)])
    assert main(["fuse", str(out), "-o", str(tmp_path / "f")]) == 0
    capsys.readouterr()
    assert main(["dsm", str(tmp_path / "f" / "bag"), "-o", str(tmp_path / "d"), "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)["pairs"]
    assert row["status"] == "written" and "heights" not in row and "filled_cells" not in row
    with rasterio.open(tmp_path / "d" / "fused_dsm.tif") as src:
        tags = src.tags()
        valid = int(np.isfinite(src.read(1)).sum())
    assert tags["PARPROJ_PAIR_ID"] == "fused" and tags["TIFFTAG_SOFTWARE"].startswith("parproj")
    assert not {"PARPROJ_MATCHED_SHARE", "PARPROJ_DISPARITY_RANGE_PX"} & tags.keys()
    assert not [k for k in tags if k.startswith(("PARPROJ_TERRAIN", "PARPROJ_FILLED"))]
    assert valid > 0.9 * int(np.isfinite(z).sum())
