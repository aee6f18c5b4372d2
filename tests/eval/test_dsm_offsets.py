"""Mutual offsets of pair DSMs (parproj_ros/eval/dsm_offsets.py) on DSMs of a known surface.

Three ElevationGrid messages of one plane-plus-waves surface on different grids (cell corners
shifted by fractions of a cell, 0.5 m and 0.6 m cells), each raised by its own constant and with
holes: the medians of A - B must be the constants' differences (bilinear sampling of a smooth
surface: its error is below 1 cm here), the cells those valid in both.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from parproj_ros.eval.dsm_offsets import format_offsets, pair_offsets
from parproj_ros.imaging.fusion import sample_bilinear
from parproj_ros.imaging.heights import DsmGrid

FRAME = "enu_wgs84:lat=43.2617452,lon=5.4429476,h=189.84"
#: Constant raise of each DSM, metres.
LEVELS = {"1+2": 0.0, "1+3": 2.37, "2+3": 4.86}


def _surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.05 * x - 0.02 * y + 3.0 * np.sin(x / 15.0) * np.cos(y / 20.0)


def _dsm(x0: float, y0: float, cell: float, n: int, seed: int) -> tuple[np.ndarray, DsmGrid]:
    grid = DsmGrid(x0, y0, cell, n, n)
    x, y = grid.centres()
    z = _surface(x, y).astype(np.float32)
    rng = np.random.default_rng(seed)
    z[rng.uniform(size=z.shape) < 0.2] = np.nan  # scattered holes
    return z, grid


def test_sample_bilinear_exact_on_a_plane() -> None:
    grid = DsmGrid(0.0, 10.0, 0.5, 21, 21)
    x, y = grid.centres()
    z = 2.0 * x - 3.0 * y + 1.0
    px, py = np.array([0.1, 3.33, 9.9, -1.0]), np.array([9.7, 5.55, 0.2, 5.0])
    got = sample_bilinear(z, grid, px, py, min_weight=1.0)  # as dsm_offsets samples
    assert np.allclose(got[:3], 2.0 * px[:3] - 3.0 * py[:3] + 1.0, atol=1e-9)
    assert np.isnan(got[3])  # outside the grid
    z[10, 10] = np.nan
    assert np.isnan(sample_bilinear(z, grid, np.array([5.2]), np.array([4.8]), min_weight=1.0)[0])


@pytest.mark.ros
def test_pair_offsets_of_a_bag(tmp_path: Path) -> None:
    from parproj_msgs.msg import ElevationGrid
    from sensor_msgs.msg import Image

    from parproj_ros.ros.bag import BagWriter
    from parproj_ros.ros.conversions import array_to_image

    grids = {
        "1+2": _dsm(0.0, 200.0, 0.5, 400, 1),
        "1+3": _dsm(0.23, 199.61, 0.5, 380, 2),
        "2+3": _dsm(-3.1, 201.2, 0.6, 330, 3),
    }
    with BagWriter(tmp_path / "out") as bw:
        bw.add_topic("dsm", "parproj_msgs/msg/ElevationGrid", "transient_local")
        for k, (pair, (z, g)) in enumerate(grids.items()):
            m = ElevationGrid()
            m.header.frame_id = FRAME
            m.pair_id = pair
            m.x0, m.y0, m.cell_size = g.x0, g.y0, g.cell
            z = z + np.float32(LEVELS[pair])
            m.heights = array_to_image(z, Image(), frame_id=FRAME, stamp_ns=1000 + k)
            bw.write("dsm", m, 1000 + k)
    rows = pair_offsets(tmp_path / "out")
    print(format_offsets(rows))
    assert [(r["a"], r["b"]) for r in rows] == [("1+2", "1+3"), ("1+2", "2+3"), ("1+3", "2+3")]
    for r in rows:
        assert r["median"] == pytest.approx(LEVELS[r["a"]] - LEVELS[r["b"]], abs=0.01)
        assert r["nmad"] < 0.02
        # A's valid cells (80 %) over the common area whose 4 neighbours in B are valid (0.8^4):
        # about 0.33 of the common cells
        assert 0.3 * 400 * 330 < r["cells"] < 0.8 * 400 * 400
    with pytest.raises(ValueError, match=r"no DSM of \['9\+9'\]"):
        pair_offsets(tmp_path / "out", ["1+2", "9+9"])
