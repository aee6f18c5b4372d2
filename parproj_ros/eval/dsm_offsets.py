"""Mutual height offsets of the pair DSMs of one output bag (issue 24: multi-view adjustment).

The pairs of a multi-view import (e.g. the Marseille triplet, pairs 1-2, 1-3, 2-3) give one DSM
each (topic ``dsm``, parproj_msgs/ElevationGrid), all in the import's object frame. If the views'
RPCs disagree along the epipolar lines, each pair's DSM sits at its own level: a nearly constant
offset between them (s2p and CARS: 2.4 m and 4.9 m on the triplet). :func:`pair_offsets` measures
it: for every two DSMs A and B, B is sampled at the centres of A's cells (bilinear, only where
the four surrounding cells of B have a height), and the statistics of A - B are taken over the
cells valid in both: median (the offset), NMAD (1.4826 median |d - median d|), and the count.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core import contract
from ..imaging.fusion import sample_bilinear
from ..imaging.heights import DsmGrid
from ..ros.bag import BagError, BagReader
from ..ros.conversions import elevation_grid_from_msg

FloatArray = NDArray[np.float64]


def dsm_difference(a: tuple[NDArray[Any], DsmGrid], b: tuple[NDArray[Any], DsmGrid]) -> FloatArray:
    """A - B at A's valid cell centres where B is valid too (metres, 1-D)."""
    ha, ga = a
    x, y = ga.centres()
    za = np.asarray(ha, dtype=np.float64)
    ok = np.isfinite(za)
    zb = sample_bilinear(b[0], b[1], x[ok], y[ok], min_weight=1.0)
    d = za[ok] - zb
    return np.asarray(d[np.isfinite(d)], dtype=np.float64)


def offset_stats(d: FloatArray) -> dict[str, float]:
    """cells, median, NMAD, RMS of differences d (metres)."""
    if d.size == 0:
        return {"cells": 0, "median": float("nan"), "nmad": float("nan"), "rms": float("nan")}
    med = float(np.median(d))
    return {
        "cells": int(d.size),
        "median": med,
        "nmad": float(1.4826 * np.median(np.abs(d - med))),
        "rms": float(np.sqrt(np.mean(d * d))),
    }


def read_dsms(bag: str | Path) -> dict[str, tuple[NDArray[Any], DsmGrid, str]]:
    """Pair id -> (heights, grid, frame_id) of every ``dsm`` message of an output bag.

    Raises:
        BagError: no ``dsm`` topic (the bag was processed without heights).

    """
    reader = BagReader(bag)
    if contract.DSM not in reader.topics():
        raise BagError("no dsm topic: process the bag with --heights", bag)
    out: dict[str, tuple[NDArray[Any], DsmGrid, str]] = {}
    for item in reader.messages(topics=[contract.DSM]):
        heights, grid, _ = elevation_grid_from_msg(item.msg)
        out[item.msg.pair_id or f"dsm_{len(out)}"] = (heights, grid, item.msg.header.frame_id)
    return out


def pair_offsets(bag: str | Path, pairs: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Every two pair DSMs of an output bag: the statistics of A - B (module docstring).

    Args:
        bag: an output bag of ``parproj process ... --heights``.
        pairs: pair ids to compare (default: all, in the bag's order).

    Returns:
        One row per (A, B): ``a``, ``b``, ``cells``, ``median``, ``nmad``, ``rms`` (metres),
        ``completeness_a``, ``completeness_b`` (share of each grid's cells with a height).

    Raises:
        BagError: no ``dsm`` topic.
        ValueError: DSMs in different object frames, or an unknown pair id.

    """
    dsms = read_dsms(bag)
    names = list(pairs) if pairs is not None else list(dsms)
    unknown = [n for n in names if n not in dsms]
    if unknown:
        raise ValueError(f"no DSM of {unknown} in {bag} (pairs: {list(dsms)})")
    frames = {dsms[n][2] for n in names}
    if len(frames) > 1:
        raise ValueError(f"the DSMs of {bag} are in different frames: {sorted(frames)}")
    rows = []
    for a, b in itertools.combinations(names, 2):
        ha, ga, _ = dsms[a]
        hb, gb, _ = dsms[b]
        row: dict[str, Any] = {"a": a, "b": b}
        row.update(offset_stats(dsm_difference((ha, ga), (hb, gb))))
        row["completeness_a"] = float(np.isfinite(ha).mean())
        row["completeness_b"] = float(np.isfinite(hb).mean())
        rows.append(row)
    return rows


def format_offsets(rows: Sequence[dict[str, Any]]) -> str:
    """The table of :func:`pair_offsets` as text (one line per two DSMs)."""
    lines = [f"{'A - B':<32} {'cells':>9} {'median m':>9} {'NMAD m':>7} {'RMS m':>7}"]
    for r in rows:
        lines.append(
            f"{r['a'] + ' - ' + r['b']:<32} {r['cells']:>9,} {r['median']:>+9.2f} "
            f"{r['nmad']:>7.2f} {r['rms']:>7.2f}"
        )
    return "\n".join(lines)


__all__ = ["dsm_difference", "format_offsets", "offset_stats", "pair_offsets", "read_dsms"]
