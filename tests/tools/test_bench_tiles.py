"""The tiles' profile of the benchmark (`python -m tools.bench.dsm`, issue 26) at a small size.

Speed is measured by the benchmark, never asserted here: the test checks that the stages add
up to the CPU measured and that the module's functions are put back.
"""

from __future__ import annotations

from dataclasses import replace

import pytest

from tools.bench.config import QUICK


def test_tile_stages_add_up_and_leave_the_module_as_it_was() -> None:
    from parproj_ros.core import tiles as core_tiles
    from tools.bench.dsm import TILE_STAGES, tile_stages

    before = {name: getattr(core_tiles, name) for name, _ in TILE_STAGES}
    small = replace(QUICK, lines=1024, detectors=512, strip_lines=128)
    res = tile_stages(small, -2, log=lambda _: None)
    assert {name: getattr(core_tiles, name) for name, _ in TILE_STAGES} == before
    # 512 normalized columns reduced by 4: 128, one span of QUICKLOOK_TILE_COLS
    assert res["tiles"] == res["tiles_ok"] == 1
    assert sum(res["stages"].values()) == pytest.approx(res["cpu_s"], abs=1e-9)
    assert res["stages"]["match_pair"] > 0 and res["stages"]["reduce blocks"] > 0
    assert res["sensor_s"] == pytest.approx(1024 / 6500.0)
    assert res["cpu_per_sensor_s"] == pytest.approx(res["cpu_s"] / res["sensor_s"])
