"""Step 8 (heights on): the DSMs of overlapping pairs fused into one (issue 24, item 4).

Pairs of one area (three or more views of one place: ``parproj import A B C --pairs all``, or a
node fed with repeated passes) each give a DSM in the one object frame. Every time a pair's DSM
is made, the stage fuses it with the DSMs kept of the earlier pairs whose ground overlaps it
(:func:`~parproj_ros.imaging.fusion.fuse`: per cell the weighted mean of the samples within a
tolerance of their median, after removing each pair's level offset; weights ``1 / a^2``, ``a``
the pair's metres of height per pixel of disparity, so that each pair counts by its
precision), and the fused DSM is published (topic ``dsm_fused``) like a pair's DSM, with the
pairs' mutual level offsets before and after on ``/diagnostics``. A multi-view adjustment at
import (``docs/multiview.md``) leaves those offsets near zero; without it, the alignment
removes them as s2p does.

Memory: the kept DSMs are bounded by ``heights_fuse_mb`` (the oldest are dropped first; a DSM
larger than the budget is not kept, and nothing is fused with it). Nothing here imports ROS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..imaging.fusion import fuse
from ..imaging.heights import Dsm, DsmGrid
from .results import FusedResult, Issue, Level, Outputs

#: Share of the smaller DSM's area two DSMs must share to be fused.
MIN_SHARED_AREA = 0.1


@dataclass(frozen=True)
class _Kept:
    pair_id: str
    stamp_ns: int
    dsm: Dsm
    metres_per_px: float

    @property
    def nbytes(self) -> int:
        return int(self.dsm.heights.nbytes)


def _box(g: DsmGrid) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) of a grid's cells (their outer edges), metres."""
    half = 0.5 * g.cell
    return (
        g.x0 - half,
        g.x0 + (g.width - 0.5) * g.cell,
        g.y0 - (g.height - 0.5) * g.cell,
        g.y0 + half,
    )


def shared_area(a: DsmGrid, b: DsmGrid) -> float:
    """Share of the smaller grid's area that the other grid covers too (0..1)."""
    ax0, ax1, ay0, ay1 = _box(a)
    bx0, bx1, by0, by1 = _box(b)
    w = max(0.0, min(ax1, bx1) - max(ax0, bx0))
    h = max(0.0, min(ay1, by1) - max(ay0, by0))
    small = min((ax1 - ax0) * (ay1 - ay0), (bx1 - bx0) * (by1 - by0))
    return w * h / small if small > 0 else 0.0


class FusionStage:
    """Fuses each new pair DSM with the kept DSMs of the pairs it overlaps (module docstring).

    Args:
        budget_mb: most megabytes of kept DSM heights (0: no fusion).
        tolerance_m: samples farther than this from a cell's median are rejected, metres.
    """

    def __init__(self, budget_mb: float, tolerance_m: float = 3.0) -> None:
        self.budget_bytes = int(budget_mb * 1e6)
        self.tolerance_m = tolerance_m
        self._kept: list[_Kept] = []

    def __call__(self, out: Outputs) -> Outputs:
        """Add the fused DSMs of the pairs whose DSM ``out`` holds (and their issues), in place."""
        for h in out.heights:
            if not h.ok or h.dsm is None:
                continue
            new = _Kept(h.pair_id, h.stamp_ns, h.dsm, abs(h.height_per_disparity_px))
            group = [
                k for k in self._kept if shared_area(k.dsm.grid, new.dsm.grid) >= MIN_SHARED_AREA
            ]
            self._keep(new)
            if not group:
                continue
            group.append(new)
            fused = fuse(
                [(k.dsm.heights, k.dsm.grid) for k in group],
                cell=new.dsm.grid.cell,
                tolerance_m=self.tolerance_m,
                weights=[1.0 / max(k.metres_per_px, 1e-9) ** 2 for k in group],
            )
            res = FusedResult(tuple(k.pair_id for k in group), new.stamp_ns, fused)
            out.fused.append(res)
            out.issues.append(Issue(Level.OK, res.name, self._describe(res)))
        return out

    def _keep(self, new: _Kept) -> None:
        if new.nbytes > self.budget_bytes:
            return
        self._kept.append(new)
        while sum(k.nbytes for k in self._kept) > self.budget_bytes:
            self._kept.pop(0)

    @staticmethod
    def _describe(res: FusedResult) -> str:
        f = res.fused
        n = len(res.pair_ids)
        iu = np.triu_indices(n, 1)
        before = np.abs(f.median_before[iu])
        after = np.abs(f.median_after[iu])
        if not np.isfinite(before).any():
            return f"fused DSM of {n} pairs: they share no cell with a height"
        return (
            f"fused DSM of {n} pairs: {f.grid.width} x {f.grid.height} cells of "
            f"{f.grid.cell:.3g} m, {100 * f.completeness:.1f} % with a height; the pairs' "
            f"level offsets (median of A - B) up to {np.nanmax(before):.2f} m before, "
            f"{np.nanmax(after):.2f} m after alignment"
        )

    def forget(self) -> None:
        """Drop every kept DSM."""
        self._kept.clear()
