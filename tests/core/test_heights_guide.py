"""The heights step's reduced pass (HeightsOptions.coarse) on the simulated bags, against truth.

``parproj process --heights`` on a bundled bag gives the step its inputs (captured); the step
again on them with each ``coarse`` setting, its DSM scored against the scenario's terrain. One
pixel of x-parallax is |a| metres (``height_per_disparity_px``, 1.19 m on both bags): without
the support rule the DSM keeps blunders (RMS 2.6 m on crab_foreaft, 1.15 m on ikonos_agile, 2
and 1 pixels, at an NMAD of 0.15 m); with it the RMS is within half a pixel.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
from testkit.paths import BAGS


def _steps(monkeypatch: pytest.MonkeyPatch) -> list[tuple[tuple[Any, ...], Any]]:
    """Every call of the heights step from now on: (its arguments, its result)."""
    from parproj_ros.core import heights as core_heights

    calls: list[tuple[tuple[Any, ...], Any]] = []
    step = core_heights.measure_heights

    def spy(*args: Any) -> Any:
        res = step(*args)
        calls.append((args, res))
        return res

    monkeypatch.setattr(core_heights, "measure_heights", spy)
    return calls


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("name", ["crab_foreaft", "ikonos_agile"])
def test_the_support_rule_removes_the_blunders(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from parproj_ros.apps.process import process_bag
    from parproj_ros.core import heights as core_heights
    from parproj_ros.eval.heights import dsm_accuracy, scenario_terrain

    step = core_heights.measure_heights
    calls = _steps(monkeypatch)
    process_bag(BAGS / name, tmp_path / "out", progress=False, overrides={"heights": True})
    ((args, _),) = calls
    pair, left, right, z, options = args
    assert options.coarse == "support"  # the default
    truth = scenario_terrain(name)
    assert truth is not None
    a = abs(pair.height_per_disparity_px)
    acc = {}
    for coarse in ("none", "support", "ranges"):
        res, _ = step(pair, left, right, z, dataclasses.replace(options, coarse=coarse))
        acc[coarse] = dsm_accuracy(res.dsm.heights, res.dsm.grid, truth, res.dsm.filled)
    print(name, f"|a| {a:.3f} m/px", acc)
    assert acc["none"]["rms"] > a / 2  # the blunders the rule is for
    for coarse in ("support", "ranges"):
        got = acc[coarse]
        assert got["rms"] <= a / 2, (coarse, got)
        assert got["nmad"] <= acc["none"]["nmad"] + 0.01 * a, (coarse, got)
        assert got["completeness"] >= 0.95, (coarse, got)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("coarse", ["none", "ranges"])
def test_the_heights_coarse_parameter_reaches_the_step(
    coarse: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``heights_coarse`` (node parameter, ``parproj process --heights-coarse``) is the step's
    ``HeightsOptions.coarse``: 'none' gives crab_foreaft's blunders back (RMS over half a pixel
    of x-parallax), 'ranges' keeps them out."""
    from parproj_ros.apps.cli import main as cli_main
    from parproj_ros.eval.heights import dsm_accuracy, scenario_terrain

    calls = _steps(monkeypatch)
    out = tmp_path / "out"
    argv = ["process", str(BAGS / "crab_foreaft"), "-o", str(out), "--heights", "-q"]
    assert cli_main([*argv, "--heights-coarse", coarse]) == 0
    ((args, (res, _)),) = calls
    pair, options = args[0], args[4]
    assert options.coarse == coarse
    truth = scenario_terrain("crab_foreaft")
    assert truth is not None
    acc = dsm_accuracy(res.dsm.heights, res.dsm.grid, truth, res.dsm.filled)
    a = abs(pair.height_per_disparity_px)
    assert (acc["rms"] > a / 2) == (coarse == "none"), acc


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("name", ["crab_foreaft", "ikonos_agile"])
def test_the_heights_scale_parameter_reaches_the_step(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``heights_scale`` 2 (``parproj process --heights-scale 2``): SGBM sees the pair reduced
    2 x 2, and the DSM keeps scale 1's accuracy against the truth (RMS within half a pixel of
    x-parallax, NMAD within a tenth of one of scale 1's, as complete to 2 points)."""
    from parproj_ros.apps.cli import main as cli_main
    from parproj_ros.core import heights as core_heights
    from parproj_ros.eval.heights import dsm_accuracy, scenario_terrain
    from parproj_ros.imaging import dense

    calls = _steps(monkeypatch)
    shapes: list[tuple[int, ...]] = []
    made = dense.sgbm_matcher

    class Spy:
        def __init__(self, matcher: Any) -> None:
            self.matcher = matcher

        def compute(self, a: Any, b: Any) -> Any:
            shapes.append(a.shape)
            return self.matcher.compute(a, b)

    monkeypatch.setattr(dense, "sgbm_matcher", lambda *args: Spy(made(*args)))
    argv = ["process", str(BAGS / name), "-o", str(tmp_path / "out"), "--heights", "-q"]
    assert cli_main([*argv, "--heights-scale", "2"]) == 0
    ((args, (res, _)),) = calls
    pair, left, right, z, options = args
    assert options.scale == 2
    # the passes at half resolution (the reduced guide's at a quarter): none at full
    assert shapes and max(s[0] for s in shapes) <= (left.shape[0] + 1) // 2
    truth = scenario_terrain(name)
    assert truth is not None
    a = abs(pair.height_per_disparity_px)
    acc = dsm_accuracy(res.dsm.heights, res.dsm.grid, truth, res.dsm.filled)
    monkeypatch.setattr(dense, "sgbm_matcher", made)
    full, _ = core_heights.measure_heights(
        pair, left, right, z, dataclasses.replace(options, scale=1)
    )
    ref = dsm_accuracy(full.dsm.heights, full.dsm.grid, truth, full.dsm.filled)
    print(name, f"|a| {a:.3f} m/px", "scale 2", acc, "scale 1", ref)
    assert acc["rms"] <= a / 2, acc
    assert acc["nmad"] <= ref["nmad"] + 0.1 * a, (acc, ref)
    assert acc["completeness"] >= ref["completeness"] - 0.02, (acc, ref)
