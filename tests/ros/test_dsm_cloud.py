"""The DSM as sensor_msgs/PointCloud2 for viewers (issue 25, item 2): topics ``dsm_cloud`` and
``dsm_fused_cloud``, parameter ``dsm_cloud_step``.

The end-to-end check reads ``parproj process --heights``'s output bag with the independent
reader (mcap + mcap-ros2-support, not our BagReader nor rclpy): the cloud's points are the
ElevationGrid's cells at the cloud's decimation, x y from the grid's geometry, z the heights,
intensity the ortho-image, within float32 rounding.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from testkit.paths import BAGS

from parproj_ros.core import contract, params
from parproj_ros.imaging.heights import DsmGrid
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import msgtype_of

pytestmark = pytest.mark.ros  # message classes and bags

#: The console script installed next to the interpreter (.venv/bin/parproj).
PARPROJ = Path(sys.executable).with_name("parproj")
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def read_independently(bag: Path, topics: list[str]) -> dict[str, list[Any]]:
    """Each topic's messages decoded by mcap-ros2-support from the bag's schemas."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list[Any]] = {t: [] for t in topics}
    for path in sorted(bag.glob("*.mcap")):
        with path.open("rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for _, channel, _, msg in reader.iter_decoded_messages(topics=topics):
                out[channel.topic].append(msg)
    return out


def grid_arrays(m: Any) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
    """An ElevationGrid decoded independently -> (heights, ortho, (x0, y0, cell))."""
    h = m.heights
    assert h.encoding == "32FC1" and not h.is_bigendian
    heights = np.frombuffer(bytes(h.data), "<f4").reshape(h.height, h.step // 4)[:, : h.width]
    o = m.ortho
    dtype = {"mono8": "u1", "mono16": "<u2", "32FC1": "<f4"}[o.encoding]
    size = np.dtype(dtype).itemsize
    ortho = np.frombuffer(bytes(o.data), dtype).reshape(o.height, o.step // size)[:, : o.width]
    return heights, ortho, (m.x0, m.y0, m.cell_size)


def cloud_points(m: Any) -> np.ndarray:
    """A PointCloud2 decoded independently -> its points as a structured array (by fields)."""
    assert all(f.datatype == FLOAT32 and f.count == 1 for f in m.fields)
    dtype = np.dtype(
        {
            "names": [f.name for f in m.fields],
            "formats": ["<f4"] * len(m.fields),
            "offsets": [f.offset for f in m.fields],
            "itemsize": m.point_step,
        }
    )
    return np.frombuffer(bytes(m.data), dtype, count=m.width * m.height)


def expected_points(
    heights: np.ndarray, ortho: np.ndarray | None, geo: tuple[float, float, float], step: int
) -> dict[str, np.ndarray]:
    """The cells (i step, j step) with a height, row-major: x y z (intensity), float64."""
    x0, y0, cell = geo
    rows, cols = np.nonzero(np.isfinite(heights[::step, ::step]))
    r, c = rows * step, cols * step
    out = {"x": x0 + c * cell, "y": y0 - r * cell, "z": heights[r, c].astype(np.float64)}
    if ortho is not None:
        out["intensity"] = ortho[r, c].astype(np.float64)
    return out


def assert_cloud_is_grid(cloud: Any, expect: dict[str, np.ndarray]) -> None:
    """Layout, then every point against its cell within float32 rounding (half an ulp)."""
    n = expect["z"].size
    names = list(expect)
    assert [f.name for f in cloud.fields] == names
    assert [f.offset for f in cloud.fields] == [4 * i for i in range(len(names))]
    assert (cloud.height, cloud.width) == (1, n)
    assert cloud.point_step == 4 * len(names) and cloud.row_step == cloud.point_step * n
    assert cloud.is_dense and not cloud.is_bigendian
    assert len(cloud.data) == cloud.row_step
    pts = cloud_points(cloud)
    for name, want in expect.items():
        got = pts[name].astype(np.float64)
        half_ulp = np.spacing(np.abs(want).astype(np.float32)).astype(np.float64) / 2
        assert np.all(np.abs(got - want) <= half_ulp), name


# ---- the decimation ---------------------------------------------------------------------------


def test_cloud_step_auto_is_the_least_step_within_the_point_budget() -> None:
    """-1: the least s with ceil(rows/s) ceil(cols/s) <= DSM_CLOUD_POINTS; s itself else."""
    budget = params.DSM_CLOUD_POINTS

    def points(shape: tuple[int, int], s: int) -> int:
        return -(-shape[0] // s) * -(-shape[1] // s)

    # the demo pair's DSM, a full IKONOS-size one, sizes around the budget
    shapes = [(791, 787), (13336, 13816), (1, budget), (1, budget + 1), (1415, 1414), (3, 5)]
    for shape in shapes:
        s = conv.cloud_step(shape, -1)
        assert points(shape, s) <= budget, shape
        assert s == 1 or points(shape, s - 1) > budget, shape
    assert conv.cloud_step((791, 787), -1) == 1  # as the parameter's description says
    assert conv.cloud_step((13336, 13816), -1) == 10  # 1.84 M points (9: 2.28 M)
    assert conv.cloud_step((13336, 13816), 0) == 0
    assert conv.cloud_step((13336, 13816), 4) == 4
    assert params.default("dsm_cloud_step") == -1


@pytest.mark.parametrize("step", [1, 3, 7])
@pytest.mark.parametrize("ortho_dtype", [np.uint8, np.uint16, None])
def test_dsm_to_cloud_is_the_grid_at_the_step(step: int, ortho_dtype: type | None) -> None:
    """Holes left out, x y from the grid (x0 + col cell, y0 - row cell), z, intensity."""
    rng = np.random.default_rng(step)
    rows, cols = 23, 31
    heights = rng.normal(412.0, 30.0, (rows, cols)).astype(np.float32)
    heights[rng.random((rows, cols)) < 0.2] = np.nan
    heights[0, 0] = np.nan  # the first cell a hole
    top = 65535 if ortho_dtype is np.uint16 else 255
    ortho = None if ortho_dtype is None else rng.integers(0, top + 1, (rows, cols), ortho_dtype)
    grid = DsmGrid(-41.925, 4_812_345.5, 0.1083333, cols, rows)  # a UTM-like northing
    cloud = conv.dsm_to_cloud(heights, grid, ortho, step=step, frame_id="map", stamp_ns=7)
    assert msgtype_of(cloud) == contract.OUTPUT_TOPICS[contract.DSM_CLOUD]
    assert (cloud.header.frame_id, conv.stamp_to_ns(cloud.header.stamp)) == ("map", 7)
    expect = expected_points(heights, ortho, (grid.x0, grid.y0, grid.cell), step)
    assert 0 < expect["z"].size < (-(-rows // step)) * (-(-cols // step))
    assert_cloud_is_grid(cloud, expect)


def test_dsm_to_cloud_refuses_a_bad_step_or_ortho() -> None:
    heights = np.zeros((4, 5), np.float32)
    grid = DsmGrid(0.0, 0.0, 1.0, 5, 4)
    with pytest.raises(conv.ConversionError, match="step"):
        conv.dsm_to_cloud(heights, grid, None, step=0, frame_id="map", stamp_ns=0)
    with pytest.raises(conv.ConversionError, match="differ"):
        ortho = np.zeros((4, 4), np.uint8)
        conv.dsm_to_cloud(heights, grid, ortho, step=1, frame_id="map", stamp_ns=0)


def test_the_fused_dsm_cloud_and_step_0() -> None:
    """outputs_to_messages: dsm_fused_cloud (x y z) after dsm_fused; step 0 makes no cloud."""
    heights = np.arange(12, dtype=np.float32).reshape(3, 4)
    heights[1, 2] = np.nan
    grid = DsmGrid(10.0, 20.0, 2.0, 4, 3)
    fused = SimpleNamespace(
        name="fused:a,b",
        stamp_ns=5,
        fused=SimpleNamespace(grid=grid, heights=heights, completeness=11 / 12),
    )
    out = SimpleNamespace(scenes=[], blocks=[], pairs=[], heights=[], fused=[fused], issues=[])
    msgs = conv.outputs_to_messages(out, frame_id="map", stamp_ns=0)
    assert [t for t, _, _ in msgs] == [contract.DSM_FUSED, contract.DSM_FUSED_CLOUD]
    cloud = msgs[1][1]
    assert msgtype_of(cloud) == contract.OUTPUT_TOPICS[contract.DSM_FUSED_CLOUD]
    assert_cloud_is_grid(cloud, expected_points(heights, None, (10.0, 20.0, 2.0), 1))
    two = conv.outputs_to_messages(out, frame_id="map", stamp_ns=0, dsm_cloud_step=2)
    assert_cloud_is_grid(two[1][1], expected_points(heights, None, (10.0, 20.0, 2.0), 2))
    none = conv.outputs_to_messages(out, frame_id="map", stamp_ns=0, dsm_cloud_step=0)
    assert [t for t, _, _ in none] == [contract.DSM_FUSED]


# ---- end to end: parproj process, read back independently -----------------------------------


@pytest.mark.parametrize("option", [None, 3], ids=["default", "step3"])
def test_process_writes_the_cloud_of_the_dsm(tmp_path: Path, option: int | None) -> None:
    """``parproj process bags/airborne_foreaft --heights``: the bag's dsm_cloud is its dsm at
    the cloud's decimation (default -1: every cell of this 782 x 791 DSM; 3 when asked)."""
    out = tmp_path / "out"
    argv = [str(PARPROJ), "process", str(BAGS / "airborne_foreaft"), "-o", str(out), "--heights"]
    argv += ["-q"] + ([] if option is None else ["--dsm-cloud-step", str(option)])
    p = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    msgs = read_independently(out, [contract.DSM, contract.DSM_CLOUD])
    (grid_msg,), (cloud,) = msgs[contract.DSM], msgs[contract.DSM_CLOUD]
    heights, ortho, geo = grid_arrays(grid_msg)
    # the grid covers the valid points at their extreme heights: its size follows the
    # disparities by a cell or so (787 columns with SGBM's sub-pixel step, 786 refined; 782
    # since the reduced pass's support rule drops the edge's unsupported matches)
    assert heights.shape[0] == 791 and abs(heights.shape[1] - 782) <= 2, heights.shape

    def stamp(m: Any) -> tuple[str, int, int]:
        return (m.header.frame_id, m.header.stamp.sec, m.header.stamp.nanosec)

    assert stamp(cloud) == stamp(grid_msg)
    step = conv.cloud_step(
        heights.shape, params.default("dsm_cloud_step") if option is None else option
    )
    assert step == (1 if option is None else option)
    # the decimation as the cloud shows it: its smallest x spacing, in cells
    xs = np.unique(cloud_points(cloud)["x"].astype(np.float64))
    seen = round(float(np.min(np.diff(xs))) / geo[2])
    assert seen == step, f"cloud at step {seen}: the option did not reach outputs_to_messages"
    expect = expected_points(heights, ortho, geo, step)
    assert expect["z"].size > 0.9 * heights[::step, ::step].size  # 92.9 % of cells have a height
    assert_cloud_is_grid(cloud, expect)
