"""Step 8: each pair's DSM fused with those of the earlier pairs it overlaps (core/fusion.py).

Three DSMs of one surface (a tilted plane with a bump) on shifted grids, each with its own
level offset, noise, holes and blunders, as three pairs of a triplet give them; a fourth far
away. ROS-free: HeightsResult in, FusedResult and issues out.
"""

from __future__ import annotations

import numpy as np

from parproj_ros.core.fusion import FusionStage, shared_area
from parproj_ros.core.results import HeightsResult, Level, Outputs
from parproj_ros.imaging.dense import DenseStatus
from parproj_ros.imaging.heights import Dsm, DsmGrid

CELL = 0.5


def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 100.0 + 0.05 * x - 0.02 * y + 8.0 * np.exp(-((x - 10) ** 2 + y**2) / 200.0)


def pair_dsm(
    name: str, x0: float, offset: float, a: float, seed: int, *, size: int = 120
) -> HeightsResult:
    rng = np.random.default_rng(seed)
    grid = DsmGrid(x0, 30.0, CELL, size, size)
    x, y = grid.centres()
    z = surface(x, y) + offset + rng.normal(0.0, 0.2 * a, x.shape)
    z[rng.random(z.shape) < 0.1] = np.nan  # holes
    blunder = rng.random(z.shape) < 0.01
    z[blunder] += 25.0
    z = z.astype(np.float32)
    dsm = Dsm(z, grid, np.isfinite(z).astype(np.int32), np.zeros(z.shape, bool))
    empty = np.zeros((1, 1), np.float32)
    return HeightsResult(
        name, 1_000 + seed, DenseStatus.OK, "ok", (0, 1), 0.9, empty, empty, dsm, None, a, 0.0
    )


def errors(res: HeightsResult | np.ndarray, grid: DsmGrid) -> np.ndarray:
    x, y = grid.centres()
    z = res if isinstance(res, np.ndarray) else res.dsm.heights  # type: ignore[union-attr]
    return np.asarray(z - surface(x, y))


def test_three_pairs_fused_on_one_level() -> None:
    stage = FusionStage(budget_mb=64.0)
    pairs = [
        pair_dsm("a+b", -30.0, +2.4, 4.4, 1),
        pair_dsm("a+c", -25.0, 0.0, 2.2, 2),
        pair_dsm("b+c", -20.0, -2.4, 4.4, 3),
    ]
    outs = [stage(Outputs(heights=[p])) for p in pairs]
    assert outs[0].fused == []  # one DSM: nothing to fuse yet
    (two,) = outs[1].fused
    assert two.pair_ids == ("a+b", "a+c")
    (three,) = outs[2].fused
    assert three.pair_ids == ("a+b", "a+c", "b+c") and three.name == "fused:a+b,a+c,b+c"
    f = three.fused
    # the level offsets measured (median of A - B) before, and gone after alignment
    assert abs(f.median_before[0, 2] - 4.8) < 0.1 and abs(f.median_before[0, 1] - 2.4) < 0.1
    assert np.nanmax(np.abs(f.median_after)) < 0.1
    (issue,) = [i for i in outs[2].issues if i.where == three.name]
    assert issue.level == Level.OK and "fused DSM of 3 pairs" in issue.message
    # more complete than any pair, and no worse than the best (the a+c pair, a = 2.2 m) in
    # NMAD about the mean level, on the cells every pair covers
    fused_err = errors(f.heights, f.grid)
    best = next(p for p in pairs if p.pair_id == "a+c")
    bx = best.dsm.grid.centres()[0]
    inside = (f.grid.centres()[0] >= bx.min()) & (f.grid.centres()[0] <= bx.max() - 10)
    done = np.isfinite(f.heights) & inside
    assert done.sum() / inside.sum() > 0.99  # each pair 90 %: the others fill its holes
    e = fused_err[done]
    nmad = 1.4826 * np.median(np.abs(e - np.median(e)))
    eb = errors(best, best.dsm.grid)
    eb = eb[np.isfinite(eb)]
    assert nmad <= 1.4826 * np.median(np.abs(eb - np.median(eb)))
    assert np.mean(np.abs(e - np.median(e)) > 10) < 1e-3  # the 1 % blunders rejected


def test_far_pairs_and_the_budget() -> None:
    """A DSM elsewhere is fused with nothing; the budget drops the oldest DSMs."""
    stage = FusionStage(budget_mb=0.12)  # two 120 x 120 float32 DSMs (57.6 kB each)
    far = pair_dsm("x+y", 5000.0, 0.0, 4.4, 4)
    assert shared_area(far.dsm.grid, pair_dsm("a+b", -30.0, 0, 4.4, 1).dsm.grid) == 0.0
    assert stage(Outputs(heights=[pair_dsm("a+b", -30.0, 0.0, 4.4, 1)])).fused == []
    assert stage(Outputs(heights=[far])).fused == []  # elsewhere
    (f,) = stage(Outputs(heights=[pair_dsm("a+c", -25.0, 0.0, 2.2, 2)])).fused
    assert f.pair_ids == ("a+b", "a+c")  # then a+b is dropped: three exceed the budget
    (f,) = stage(Outputs(heights=[pair_dsm("b+c", -20.0, 0.0, 4.4, 3)])).fused
    assert f.pair_ids == ("a+c", "b+c")
    assert FusionStage(budget_mb=0.0)(Outputs(heights=[far, far])).fused == []
