"""``parproj fuse``: the DSMs of several pairs of one area fused into one DSM, as GeoTIFF.

Reads every ``dsm`` ElevationGrid of the output bags given (``parproj process --heights`` on a
bag of three or more images imported with ``--pairs all``, or several bags of one area; DSMs
of different tangent-plane frames, pairs imported one by one, are brought exactly into the
first one's frame, :func:`parproj_ros.imaging.fusion.reframe`), measures the pairs' mutual
level offsets, and fuses them (:func:`parproj_ros.imaging.fusion.fuse`: per cell the mean of
the samples within a tolerance of their median, after removing each pair's level offset).
Writes, on the grid of a pair's DSM export (:mod:`parproj_ros.io.geotiff`: the UTM zone of a
tangent-plane frame with WGS84 ellipsoidal heights, or the frame as it is):

* ``fused_dsm.tif``: the fused heights (float32, NaN holes);
* ``fused_count.tif``: samples kept per cell (uint8, 0 = none);
* ``fused_spread.tif``: max - min of the samples kept, metres (float32, NaN holes; 0 where
  one sample was kept: the count layer tells);

each with a band description and unit saying what it holds, and tags naming the software and
the fused pairs (``PARPROJ_INPUTS``);
* ``fuse.json``: the inputs, offsets before and after, and the figures printed;
* ``bag/``: the fused DSM as a ``dsm`` ElevationGrid (pair id ``fused``), as a pair's DSM is
  published: ``parproj dsm DIR/bag -o ...`` exports it like one.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..core import contract
from ..core.heights import MAX_CELLS_PER_GSD
from ..imaging.fusion import TOLERANCE_M, FusedDsm, frame_box, fuse, reframe, sample_bilinear
from ..imaging.heights import DsmGrid
from ..io.files import InputError
from ..io.geotiff import frame_of, write_dsm_geotiff, write_like
from ..ros.bag import BagError, BagReader
from ..ros.conversions import array_to_image, elevation_grid_from_msg, stamp_to_ns
from .export import provenance

__all__ = [
    "FuseResult",
    "NotEnoughDsmsError",
    "PairDsm",
    "export_fused",
    "fuse_bags",
    "read_dsms",
    "write_fused_bag",
]


class NotEnoughDsmsError(Exception):
    """Fewer than two DSMs to fuse (exit 1: nothing to fuse, not bad input)."""


@dataclass(frozen=True)
class FuseResult:
    """The fused DSM and what it was made from.

    Attributes:
        fused: the fusion (heights, count, spread, grid, offsets).
        frame_id: the object frame of the inputs and of ``fused``.
        names: the inputs' pair ids (with the bag's name when several bags are given).
        completeness: each input's share of the fused grid's cells with a height (0..1).
        weights: each input's weight in the mean (1 / a^2, or 1 each).
        notes: what was done besides the fusion (frames converted).
        stamp_ns: the latest input DSM's stamp, nanoseconds (the fused DSM's).
        aligned: the pairs' level offsets were removed (not ``--no-align``).
    """

    fused: FusedDsm
    frame_id: str
    names: list[str]
    completeness: list[float]
    weights: list[float]
    notes: list[str]
    stamp_ns: int = 0
    aligned: bool = True


@dataclass(frozen=True)
class PairDsm:
    """One ``dsm`` ElevationGrid of an output bag.

    Attributes:
        name: the pair id (``<bag>:<pair id>`` when several bags are read).
        frame_id: its object frame.
        heights: Z metres in the frame, float32, NaN holes.
        grid: its cells.
        a: the pair's metres of height per pixel of disparity (``height_per_disparity_px``).
        stamp_ns: the message's stamp, nanoseconds.
    """

    name: str
    frame_id: str
    heights: Any
    grid: DsmGrid
    a: float
    stamp_ns: int


def read_dsms(bags: Sequence[Path]) -> list[PairDsm]:
    """Every ``dsm`` of the bags, in their order.

    Raises:
        BagError: a bag without a ``dsm`` topic.
    """
    out: list[PairDsm] = []
    labels = [b.name for b in bags]
    if len(set(labels)) < len(labels):  # out/, out/, out/ of three folders: name the folders
        labels = [f"{b.resolve().parent.name}/{b.name}" for b in bags]
    for bag, label in zip(bags, labels, strict=True):
        reader = BagReader(bag)
        if contract.DSM not in reader.topics():
            raise BagError("no dsm topic: process the bag with --heights", bag)
        if not reader.recovery.complete:
            warnings.warn(
                f"{bag}: {reader.recovery.describe()}; the DSMs complete in it are used",
                stacklevel=2,
            )
        for item in reader.messages(topics=[contract.DSM]):
            m = item.msg
            heights, grid, _ = elevation_grid_from_msg(m)
            name = str(m.pair_id) or f"dsm_{len(out)}"
            if len(bags) > 1:
                name = f"{label}:{name}"
            out.append(
                PairDsm(
                    name,
                    str(m.header.frame_id),
                    np.asarray(heights, np.float32),
                    grid,
                    float(m.height_per_disparity_px),
                    stamp_to_ns(m.header.stamp),
                )
            )
    return out


def fuse_bags(
    bags: Sequence[Path],
    *,
    tolerance_m: float = TOLERANCE_M,
    align: bool = True,
    cell_m: float | None = None,
    frame_id: str | None = None,
    weigh: bool = True,
) -> FuseResult:
    """Fuse the DSMs of ``bags`` (module docstring).

    Args:
        bags: output bags.
        tolerance_m: see :func:`parproj_ros.imaging.fusion.fuse`.
        align: remove each pair's level offset first.
        cell_m: output cell side, metres (default: the finest input's).
        frame_id: the frame to take for DSMs labelled with one that is not a tangent plane
            (an imported pair processed before its frame travelled to the outputs: ``map``).
        weigh: weigh each pair's samples by 1 / a^2 (``a``: its metres of height per pixel of
            disparity; the matching noise in pixels being alike, its height noise is
            proportional to ``a``); equal weights otherwise or where an ``a`` is unusable.

    Raises:
        NotEnoughDsmsError: fewer than two DSMs in the bags.
        InputError: DSMs of different frames.
    """
    dsms = read_dsms(bags)
    for i, d in enumerate(dsms):
        for e in dsms[:i]:
            if (
                e.frame_id == d.frame_id
                and e.grid == d.grid
                and e.heights.shape == d.heights.shape
                and np.array_equal(e.heights, d.heights, equal_nan=True)
            ):
                warnings.warn(
                    f"{d.name} is the same DSM as {e.name} (same frame, grid and heights: one "
                    "bag given twice, or a copy): it is fused with itself, which adds nothing",
                    stacklevel=2,
                )
    if len(dsms) < 2:
        found = ", ".join(d.name for d in dsms) or "none"
        cut = [str(b) for b in bags if not BagReader(b).recovery.complete]
        advice = (
            f"{', '.join(cut)} cut off or damaged (note above): copy it again, or process its "
            "input again with --heights"
            if cut
            else "fuse needs the DSMs of two or more pairs of one area: import three or more "
            "images with --pairs all, then process --heights"
        )
        raise NotEnoughDsmsError(
            f"fewer than two DSMs to fuse (found {len(dsms)}: {found}) in "
            f"{', '.join(str(b) for b in bags)}; {advice}"
        )
    finest = min(d.grid.cell for d in dsms)
    if cell_m is not None and cell_m * MAX_CELLS_PER_GSD < finest:
        raise InputError(
            "--cell-m",
            f"{cell_m:g} m is {finest / cell_m:.3g} times finer than the finest input DSM's "
            f"cell ({finest:.3g} m): a grid of {(finest / cell_m) ** 2:.3g} times its cells, "
            "interpolated between them (no detail gained); give 0 (the finest input's cell) "
            f"or at least {finest / MAX_CELLS_PER_GSD:.3g} m",
        )
    small = min(dsms, key=lambda d: min(d.grid.width, d.grid.height) * d.grid.cell)
    side = min(small.grid.width, small.grid.height) * small.grid.cell
    if cell_m is not None and cell_m > side / 2:
        raise InputError(
            "--cell-m",
            f"{cell_m:g} m cells are too coarse for {small.name} (its grid spans "
            f"{small.grid.width * small.grid.cell:.0f} x {small.grid.height * small.grid.cell:.0f}"
            f" m): fewer than 2 x 2 of them would hold its heights; give at most "
            f"{math.floor(5 * side) / 10:g} m "
            "(or 0: the finest input's cell)",
        )
    frames = []
    for d in dsms:
        f = d.frame_id
        frames.append(frame_id if frame_id is not None and frame_of(f) is None else f)
    planes = [frame_of(f) for f in frames]
    inputs = [(d.heights, d.grid) for d in dsms]
    grid: DsmGrid | None = None
    notes: list[str] = []
    if len(set(frames)) > 1:
        if any(p is None for p in planes):
            listed = "; ".join(f"{d.name} in {f!r}" for d, f in zip(dsms, frames, strict=True))
            raise InputError(
                str(bags[0]),
                f"DSMs of different object frames cannot be fused ({listed}): only tangent "
                "planes on WGS84 (imported pairs) can be brought into one frame",
            )
        dst = planes[0]
        assert dst is not None
        cell = cell_m or min(g.cell for _, g in inputs)
        boxes = [frame_box(h, g, p, dst) for (h, g), p in zip(inputs, planes, strict=True) if p]
        grid = DsmGrid.covering(
            min(b[0] for b in boxes),
            max(b[1] for b in boxes),
            min(b[2] for b in boxes),
            max(b[3] for b in boxes),
            cell,
        )
        moved = []
        for (h, g), f, p in zip(inputs, frames, planes, strict=True):
            if f != frames[0] and p is not None:
                moved.append((reframe(h, g, p, dst, grid), grid))
            else:
                moved.append((h, g))
        inputs = moved
        notes.append(
            f"DSMs of {len(set(frames))} object frames: all brought into {frames[0]} "
            "(exact conversion through WGS84)"
        )
    a = np.array([abs(d.a) for d in dsms])
    weights = (
        [float(v) for v in 1.0 / a**2] if weigh and np.all(np.isfinite(a) & (a > 0)) else None
    )
    fused = fuse(inputs, tolerance_m=tolerance_m, align=align, cell=cell_m, grid=grid,
                 weights=weights)  # fmt: skip
    x, y = fused.grid.centres()
    comp = [float(np.isfinite(sample_bilinear(h, g, x, y)).mean()) for h, g in inputs]
    names = [d.name for d in dsms]
    stamp = max(d.stamp_ns for d in dsms)
    return FuseResult(
        fused, frames[0], names, comp, weights or [1.0] * len(dsms), notes, stamp, align
    )


def _matrix(m: Any) -> list[list[float | None]]:
    return [[None if not math.isfinite(v) else round(float(v), 3) for v in row] for row in m]


def _layers_on_export(
    dsm_path: Path,
    layers: dict[str, tuple[Any, float, str, str]],
    grid: DsmGrid,
    frame_id: str,
    tags: dict[str, str] | None = None,
) -> None:
    """Write frame-grid layers on the grid of the DSM GeoTIFF just written, nearest cell.

    Each map cell with a height h in ``dsm_path`` takes the layer's value at the frame (x, y)
    of its (lon, lat, h) (the point of the fused surface it shows, as
    :func:`~parproj_ros.io.geotiff.write_ortho_geotiff` finds it, without its iteration: the
    heights are already there); nodata where h has none. A frame without geodetic anchor:
    the layers as they are (same grid). ``layers``: file name -> (array, nodata, what it
    holds, unit); ``tags``: dataset tags of every layer.
    """
    import rasterio

    with rasterio.open(dsm_path) as src:
        h = src.read(1).astype(float)
        transform = src.transform
        crs = src.crs
    frame = frame_of(frame_id)
    if frame is None or crs is None:
        rows = cols = None
    else:
        from pyproj import CRS, Transformer

        cols_m, rows_m = np.meshgrid(np.arange(h.shape[1]) + 0.5, np.arange(h.shape[0]) + 0.5)
        e = transform.c + transform.a * cols_m
        n = transform.f + transform.e * rows_m
        to_ll = Transformer.from_crs(CRS.from_wkt(crs.to_wkt()), CRS.from_epsg(4326),
                                     always_xy=True)  # fmt: skip
        lon, lat = to_ll.transform(e, n)
        ok = np.isfinite(h)
        x, y, _ = frame.to_local(lon, lat, np.where(ok, h, frame.h0))
        rows, cols = grid.index(x, y)
        ok &= (rows >= 0) & (rows < grid.height) & (cols >= 0) & (cols < grid.width)
        rows = np.where(ok, rows, -1)
        cols = np.where(ok, cols, -1)
    for name, (values, nodata, what, unit) in layers.items():
        v = np.asarray(values)
        if rows is None or cols is None:
            out = v
        else:
            good = rows >= 0
            out = np.full(h.shape, nodata, dtype=v.dtype)
            out[good] = v[rows[good], cols[good]]
        # a COG on the DSM file's grid and CRS, like the DSM
        write_like(
            dsm_path.with_name(name),
            dsm_path,
            out,
            nodata=nodata,
            description=f"parproj_ros fused DSM: {what}",
            unit=unit,
            tags={**(tags or {}), "PARPROJ_SOURCE_FRAME": frame_id},
        )


#: Pair id of the fused DSM's ElevationGrid.
FUSED_ID = "fused"


def write_fused_bag(res: FuseResult, path: Path) -> None:
    """The fused DSM as a ``dsm`` parproj_msgs/ElevationGrid in a bag, like a pair's DSM.

    ``parproj dsm`` exports it like a pair's (``fused_dsm.tif``); the pair fields that do not
    apply to a fusion (disparity range, matched share, height relation, terrain searched) stay
    0 / empty; ``filled_cells`` 0, ``completeness`` the share of cells with a height.
    """
    from parproj_msgs.msg import ElevationGrid
    from sensor_msgs.msg import Image

    from ..ros.bag import BagWriter
    from ..ros.conversions import ns_to_stamp

    f = res.fused
    m = ElevationGrid()
    ns_to_stamp(res.stamp_ns, m.header.stamp)
    m.header.frame_id = res.frame_id
    m.pair_id = FUSED_ID
    m.x0, m.y0, m.cell_size = float(f.grid.x0), float(f.grid.y0), float(f.grid.cell)
    m.heights = array_to_image(
        np.ascontiguousarray(f.heights, dtype=np.float32),
        Image(),
        frame_id=res.frame_id,
        stamp_ns=res.stamp_ns,
    )
    m.completeness = float(f.completeness)
    with BagWriter(path) as bw:
        bw.add_topics([contract.topic(contract.DSM)])
        bw.write(contract.DSM, m, res.stamp_ns)


def export_fused(
    res: FuseResult, folder: Path, *, target: Literal["utm", "local"] = "utm"
) -> dict[str, Any]:
    """Write the fused DSM, count and spread GeoTIFFs into ``folder``; the report as a dict."""
    f = res.fused
    made_by = {
        **provenance(FUSED_ID),
        "PARPROJ_INPUTS": ", ".join(res.names),
        "PARPROJ_OFFSETS_REMOVED_M": ", ".join(f"{o:+.3f}" for o in f.offsets)
        if res.aligned
        else "none (--no-align)",
    }
    crs, out = write_dsm_geotiff(
        folder / "fused_dsm.tif",
        f.heights,
        f.grid,
        res.frame_id,
        target=target,
        tags={**made_by, "PARPROJ_LAYERS": "fused_count.tif, fused_spread.tif"},
    )
    write_fused_bag(res, folder / "bag")
    _layers_on_export(
        folder / "fused_dsm.tif",
        {
            "fused_count.tif": (
                f.count,
                0,
                "count of pair DSM samples kept in the cell (0: no height)",
                "",
            ),
            "fused_spread.tif": (
                f.spread,
                float("nan"),
                "spread (max - min) of the samples kept, metres (0 where one was kept)",
                "m",
            ),
        },
        f.grid,
        res.frame_id,
        made_by,
    )
    n = len(res.names)
    valid = f.count > 0
    hist = [int((f.count == k).sum()) for k in range(1, n + 1)]
    spread = f.spread[valid & (f.count > 1)]
    return {
        "inputs": res.names,
        "frame_id": res.frame_id,
        "crs": None if crs is None else crs.name,
        "epsg": None if crs is None else crs.to_epsg(),
        "cells": [out.width, out.height],
        "cell_size_m": out.cell,
        "frame_grid": {
            "x0": f.grid.x0,
            "y0": f.grid.y0,
            "cell": f.grid.cell,
            "width": f.grid.width,
            "height": f.grid.height,
        },
        "input_completeness": res.completeness,
        "weights": [w / max(res.weights) for w in res.weights],
        "notes": res.notes,
        "completeness": f.completeness,
        "cells_by_count": hist,
        "spread_median_m": float(np.median(spread)) if spread.size else None,
        "split_cells": f.split_cells,
        "aligned": res.aligned,
        "offsets_m": [round(float(o), 3) for o in f.offsets],
        "median_before_m": _matrix(f.median_before),
        "median_after_m": _matrix(f.median_after),
        "shared_cells": f.shared_cells.tolist(),
        "files": ["fused_dsm.tif", "fused_count.tif", "fused_spread.tif", "fuse.json", "bag"],
    }


def offsets_table(names: Sequence[str], median: Sequence[Sequence[float | None]]) -> list[str]:
    """Lines of a matrix of level offsets (row - column, metres) for a person."""
    w = max(8, *(len(n) for n in names))
    lines = [" " * w + "".join(f" {n:>{w}s}" for n in names)]
    for name, row in zip(names, median, strict=True):
        cells = "".join(f" {'-':>{w}s}" if v is None else f" {v:+{w}.2f}" for v in row)
        lines.append(f"{name:>{w}s}{cells}")
    return lines
