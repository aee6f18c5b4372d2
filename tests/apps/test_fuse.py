"""`parproj fuse`: the DSMs of output bags fused into one DSM with count and spread layers.

On the bundled airborne_foreaft bag (one pair): one DSM is refused with exit 1 and a line
saying what is missing; the same bag given twice fuses two identical DSMs: offsets 0, the
fused heights equal the pair's (the mean of two equal samples), count 2 where it has heights.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio

from parproj_ros.apps.cli import main
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.conversions import elevation_grid_from_msg
from tests.testkit.paths import BAGS

pytestmark = pytest.mark.ros  # bags (rclpy serialization) and messages


@pytest.fixture(scope="module")
def out_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fuse") / "out"
    assert (
        main(["process", str(BAGS / "airborne_foreaft"), "-o", str(out), "--heights", "-q"]) == 0
    )
    return out


def test_one_dsm_is_not_enough(
    out_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pair = next(i.msg.pair_id for i in BagReader(out_bag).messages(topics=["dsm"]))
    capsys.readouterr()
    assert main(["fuse", str(out_bag), "-o", str(tmp_path / "f")]) == 1
    err = capsys.readouterr().err
    assert f"fewer than two DSMs to fuse (found 1: {pair})" in err
    assert "--pairs all" in err
    assert not (tmp_path / "f").exists()


def test_two_equal_dsms_fuse_to_the_same_heights(
    out_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    msgs = [i.msg for i in BagReader(out_bag).messages(topics=["dsm"])]
    assert len(msgs) == 1
    pair = msgs[0].pair_id
    heights, grid, _ = elevation_grid_from_msg(msgs[0])
    dst = tmp_path / "f"
    capsys.readouterr()
    assert main(["fuse", str(out_bag), str(out_bag), "-o", str(dst), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    # two bags of one name: named with their folder
    label = f"{out_bag.parent.name}/out:{pair}"
    assert doc["inputs"] == [label, label]
    assert doc["median_before_m"] == [[0.0, 0.0], [0.0, 0.0]]
    assert doc["offsets_m"] == [0.0, 0.0]
    assert doc["weights"] == [1.0, 1.0]  # 1 / a^2 of one pair, twice
    valid = np.isfinite(heights)
    assert doc["cells_by_count"] == [0, int(valid.sum())]
    assert doc["completeness"] == pytest.approx(valid.mean())
    # a simulated frame ('map', no geodetic anchor): the grid written as it is
    assert doc["cells"] == [grid.width, grid.height]
    with rasterio.open(dst / "fused_dsm.tif") as src:
        fused = src.read(1)
    # the same values (to float rounding: the grid's cell centres resampled onto themselves)
    assert np.array_equal(np.isnan(fused), np.isnan(heights))
    assert np.allclose(fused, heights, rtol=1e-6, atol=1e-6, equal_nan=True)
    with rasterio.open(dst / "fused_count.tif") as src:
        assert np.array_equal(src.read(1), np.where(valid, 2, 0))
    with rasterio.open(dst / "fused_spread.tif") as src:
        spread = src.read(1)
    assert np.all(spread[valid] == 0.0) and np.all(np.isnan(spread[~valid]))


def test_fused_bag_exports_like_a_pair(
    out_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """DIR/bag holds the fused DSM as a 'dsm' ElevationGrid; parproj dsm exports it as a pair's."""
    dst = tmp_path / "f"
    assert main(["fuse", str(out_bag), str(out_bag), "-o", str(dst)]) == 0
    (m,) = [i.msg for i in BagReader(dst / "bag").messages(topics=["dsm"])]
    src = next(i.msg for i in BagReader(out_bag).messages(topics=["dsm"]))
    assert m.pair_id == "fused" and m.header.frame_id == src.header.frame_id
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (
        src.header.stamp.sec,
        src.header.stamp.nanosec,
    )
    heights, grid, ortho = elevation_grid_from_msg(m)
    src_heights, src_grid, _ = elevation_grid_from_msg(src)
    assert grid == src_grid  # the same DSM twice: its own grid, its own heights
    assert np.allclose(heights, src_heights, rtol=1e-6, atol=1e-6, equal_nan=True)
    with rasterio.open(dst / "fused_dsm.tif") as f:
        fused_tif = f.read(1)
    assert ortho is None and m.completeness == pytest.approx(np.isfinite(heights).mean())
    capsys.readouterr()
    assert main(["dsm", str(dst / "bag"), "-o", str(tmp_path / "d")]) == 0
    with rasterio.open(tmp_path / "d" / "fused_dsm.tif") as f:
        assert np.array_equal(f.read(1), fused_tif, equal_nan=True)
