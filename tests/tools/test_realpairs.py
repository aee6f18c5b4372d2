"""The real-pair benchmark (`python -m tools.bench.realpairs`): its scoring and report, tiny.

The full run (import, process, dsm, fuse on the Marseille triplet and Ventoux) takes minutes
and is the benchmark itself; here: the scoring of a DSM against two references on one grid and
one footprint, the markdown it prints, and the timing hook of the heights step. Speed is
measured by the benchmark, never asserted here.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from pyproj import CRS

from parproj_ros.eval.dsm_compare import MapDsm
from parproj_ros.imaging.heights import DsmGrid
from tools.bench import realpairs
from tools.bench.realpairs import CASES, markdown, score

UTM31 = CRS.from_epsg(32631)


def test_score_on_one_grid_and_footprint() -> None:
    rng = np.random.default_rng(5)
    grid = DsmGrid(698000.25, 4793000.25, 0.5, 120, 100)
    e, n = grid.centres()
    ground = (150.0 + 0.02 * (e - 698000.0) + np.sin(n / 7.0)).astype(np.float32)
    s2p = ground.copy()
    s2p[rng.random(s2p.shape) < 0.1] = np.nan  # s2p's scattered empty cells
    cars = (ground + 0.1 + rng.normal(0, 0.05, ground.shape)).astype(np.float32)
    ours = ground + np.float32(0.3)
    ours[:, :30] = np.nan  # a quarter of the grid without heights
    # cars on a grid 3 cells west and 2 north of s2p's: resampled onto s2p's lattice
    cars_grid = DsmGrid(grid.x0 - 1.5, grid.y0 + 1.0, 0.5, 120, 100)
    cars_on = np.full_like(cars, np.nan)
    cars_on[2:, 3:] = cars[:-2, :-3]
    refs = {
        "s2p": MapDsm(s2p, grid, UTM31, "s2p_x"),
        "cars": MapDsm(cars_on, cars_grid, UTM31, "cars_x"),
    }
    rows = score(MapDsm(ours, grid, UTM31, "ours"), refs, [], label="ours")
    by = {(r["dsm"], r["vs"]): r for r in rows}
    assert set(by) == {("ours", "s2p_x"), ("ours", "cars_x"), ("s2p_x (reference)", "cars_x")}
    # one footprint for all rows: the cells of the first reference (no images given)
    fp = int(np.isfinite(s2p).sum())
    assert {r["footprint_cells"] for r in rows} == {fp}
    assert by["ours", "s2p_x"]["median"] == pytest.approx(0.3, abs=1e-4)
    assert by["ours", "s2p_x"]["nmad"] < 1e-4
    assert abs(by["ours", "s2p_x"]["shift_e_m"]) < 1e-3  # same surface, same place
    assert by["ours", "s2p_x"]["completeness"] == pytest.approx(0.75, abs=0.02)
    assert by["ours", "cars_x"]["median"] == pytest.approx(0.2, abs=0.01)
    assert by["ours", "cars_x"]["nmad"] == pytest.approx(0.05, abs=0.01)
    assert by["s2p_x (reference)", "cars_x"]["median"] == pytest.approx(-0.1, abs=0.01)
    assert by["s2p_x (reference)", "cars_x"]["completeness"] == 1.0
    # cars misses the first 2 rows and 3 columns of s2p's grid (its own grid is shifted)
    missing = 1.0 - by["ours", "cars_x"]["reference_completeness"]
    assert missing == pytest.approx((2 * 120 + 3 * 100 - 6) / 12000, abs=0.01)

    doc = {
        "git": {"commit": "abc1234", "uncommitted_files": 2},
        "date": "today",
        "machine": "x",
        "cases": [
            {
                "case": "marseille_12",
                "rows": rows,
                "seconds": {"import": 1.0, "process": 2.0, "dsm": 3.0},
                "speed": {"heights_s_per_mpx": 1.5, "sgbm_s_per_mpx": 0.5, "ratio": 3.0},
            }
        ],
    }
    text = markdown(doc)
    assert "commit abc1234 + 2 uncommitted files" in text
    assert "| marseille_12 | ours | s2p_x | +0.30 | 0.00 |" in text
    assert "| marseille_12 | 1.0 | 2.0 | 3.0 | - | 1.50 | 0.50 | 3.00 |" in text


def test_cases_name_existing_data() -> None:
    """Every case's images and references are in ../shared/data (README of the data)."""
    for case in CASES.values():
        for p in case.images:
            assert p.is_file(), p
        for refs in case.refs.values():
            for p in refs.values():
                assert p.is_file(), p
        for imgs in case.footprints.values():
            assert set(imgs) <= set(case.images)
    assert set(CASES["marseille_123"].refs) == {
        "img_01+img_02",
        "img_01+img_03",
        "img_02+img_03",
        "fused",
    }


def test_heights_hook_times_and_restores() -> None:
    from parproj_ros.core.heights import HeightsStage

    original = HeightsStage.__call__
    times: list[float] = []

    out: Any = SimpleNamespace(pairs=[1])  # no blocks, no issues: the step raises
    with realpairs._timed_heights(times):
        assert HeightsStage.__call__ is not original
        with pytest.raises(AttributeError):  # the real step runs (and fails on this fake)
            HeightsStage.__call__(HeightsStage.__new__(HeightsStage), out)
    assert HeightsStage.__call__ is original
    assert len(times) == 1 and times[0] >= 0.0


def test_captured_steps_are_timed_again_on_their_inputs(monkeypatch: pytest.MonkeyPatch) -> None:
    from parproj_ros.core import heights as core_heights

    original = core_heights.measure_heights
    seen: list[tuple[Any, ...]] = []

    def fake(*args: Any) -> str:  # the step as the stage calls it (module global)
        seen.append(args)
        return "done"

    monkeypatch.setattr(core_heights, "measure_heights", fake)
    calls: list[tuple[Any, ...]] = []
    with realpairs._captured_steps(calls):
        assert core_heights.measure_heights("pair", "l", "r") == "done"
    assert core_heights.measure_heights is fake and calls == [("pair", "l", "r")]
    seen.clear()
    bares: list[Any] = []
    t, b = realpairs.step_best_s(calls, lambda pair: bares.append(pair) or 0.25, repeat=3)
    assert seen == [("pair", "l", "r")] * 3 and bares == ["pair"] * 3
    assert math.isfinite(t) and t >= 0.0 and b == 0.25
    assert math.isnan(realpairs.step_best_s(calls, None, repeat=1)[1])
    assert original is not fake


def test_bare_sgbm_time_is_finite() -> None:
    rng = np.random.default_rng(0)
    left = rng.integers(1, 2000, (64, 96)).astype(np.uint16)
    right = np.roll(left, -4, axis=1)
    t = realpairs.bare_sgbm_s(left, right, (-8, 8))
    assert math.isfinite(t) and t > 0


def test_done_when_verdicts() -> None:
    def row(dsm: str, vs: str, nmad: float, comp: float, median: float = 0.0) -> dict[str, Any]:
        return {"dsm": dsm, "vs": vs, "nmad": nmad, "completeness": comp, "median": median,
                "shift_e_m": 0.1, "shift_n_m": -0.1, "rms": 1.0, "p95_abs": 2.0, "cells": 9,
                "reference_completeness": 0.9}  # fmt: skip

    doc: dict[str, Any] = {
        "cases": [
            {
                "case": "marseille_12",
                "rows": [
                    row("left+right", "s2p_dsm_12", 0.70, 0.95),
                    row("left+right (GeoTIFF)", "s2p_dsm_12", 0.70, 0.94, 0.6),
                ],
                "speed": {"ratio": 2.0, "ratio_best": 1.2},
            },
            {
                "case": "marseille_123",
                "rows": [
                    row("fused", "s2p_dsm_123", 0.52, 0.99),
                    row("img_01+img_02", "s2p_dsm_123", 0.84, 0.987, -0.05),
                    row("img_01+img_03", "s2p_dsm_123", 0.57, 0.972, 0.60),
                    row("img_01+img_02", "s2p_dsm_12", 0.5, 0.999, 2.4),  # another reference
                ],
            },
        ]
    }
    doc["bags"] = [
        {"bag": "airborne_foreaft", "seconds": {"process": 1.0, "dsm": 2.0},
         "dsms": [{"pair_id": "l+r", "vs": "truth", "nmad": 0.03, "rms": 0.04,
                   "completeness": 0.968, "cells_with_height": 500}]},
        {"bag": "crab_foreaft", "seconds": {"process": 1.0}, "errors": {"dsm": "x"}},
    ]  # fmt: skip
    got = {crit: (value, met) for crit, value, _, met in realpairs.verdicts(doc)}
    assert got["bag airborne_foreaft: a DSM"] == ("1 DSM, 500 cells", True)
    assert got["bag crab_foreaft: a DSM"] == ("0 DSM, 0 cells", False)
    text = markdown(doc)
    assert "| airborne_foreaft | l+r | truth | 0.030 | 0.040 | 96.8 | 1.0 | 2.0 |" in text
    assert "| crab_foreaft | no DSM | - | - | - | - | 1.0 | - |" in text
    assert got["marseille_12: NMAD vs s2p"] == ("0.70 m", True)
    assert got["marseille_12: completeness"] == ("95.0 %", True)
    # median 0.6 m is off by more than 0.5 m; the 0.14 m shift is within half a cell
    assert got["marseille_12: GeoTIFF lands on s2p"] == ("median +0.60 m, shift 0.14 m", False)
    assert got["marseille_12: heights step (first call) / bare SGBM"] == ("2.00", False)
    assert got["marseille_12: heights step / bare SGBM (in turns, best of 5)"] == ("1.20", True)
    assert got["marseille_123: fused completeness vs best pair"] == ("99.0 %", True)
    assert got["marseille_123: fused NMAD vs best pair (s2p_dsm_123)"] == ("0.52 m", True)
    assert got["marseille_123: pair levels agree"] == ("0.65 m", False)
    assert "| marseille_12: completeness | 95.0 % | >= 90 % | yes |" in markdown(doc)


def test_step_parts_split_the_time_at_sgbm(monkeypatch: pytest.MonkeyPatch) -> None:
    """The step's time inside the matchers it builds and outside them, of its fastest run."""
    import time

    from parproj_ros.core import heights as core_heights
    from parproj_ros.imaging import dense

    rng = np.random.default_rng(1)
    left = rng.integers(0, 255, (96, 160)).astype(np.uint8)
    right = np.ascontiguousarray(np.roll(left, -3, axis=1))
    inside: list[float] = []
    original = dense.sgbm_matcher

    def step(*args: Any) -> None:
        matcher = dense.sgbm_matcher(dense.SgbmParams(), -8, 16)
        t0 = time.perf_counter()
        matcher.compute(left, right)
        inside.append(time.perf_counter() - t0)
        time.sleep(0.02)  # the rest of the step

    monkeypatch.setattr(core_heights, "measure_heights", step)
    in_sgbm, rest = realpairs.step_parts_s([("pair",)], repeat=3)
    assert dense.sgbm_matcher is original  # restored
    assert len(inside) == 3
    # the split of one of the runs: SGBM as the step itself timed it (+ the proxy's call)
    assert min(abs(in_sgbm - t) for t in inside) < 1e-3
    assert 0.02 <= rest < 0.02 + 0.05
    t16 = realpairs.narrowest_pass(left, right, (-40, 40))
    assert math.isfinite(t16) and t16 > 0
