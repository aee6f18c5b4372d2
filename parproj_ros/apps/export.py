"""``parproj dsm``: the DSMs of an output bag as GeoTIFF, with their ortho-images and plots.

For every ``dsm`` message (parproj_msgs/ElevationGrid) of an output bag (``parproj process``
with ``--heights``, or a recording of the node): ``<pair>_dsm.tif`` (float32, WGS84
ellipsoidal heights in the UTM zone of a real pair's frame, or the frame's Z with no CRS for a
simulated one, :mod:`parproj_ros.io.geotiff`), ``<pair>_ortho.tif`` (the same grid),
``<pair>_disparity.tif`` (the pair's disparity map in the left normalized grid, no
georeference), and the PNGs a person looks at (hillshade, disparity, ortho-image, and the
height error map when a true surface is given).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from ..eval.heights import (
    Surface,
    disparities_by_stamp,
    dsm_accuracy,
    enu_dem_surface,
    save_height_plots,
)
from ..io.files import InputError
from ..io.geotiff import frame_of, write_dsm_geotiff, write_ortho_geotiff, write_plain_tiff
from ..ros.bag import BagError, BagReader
from ..ros.conversions import elevation_grid_from_msg, stamp_to_ns
from ..rpc import HeightFunction


def export_dsms(
    out_bag: Path,
    folder: Path,
    *,
    target: Literal["utm", "local"] = "utm",
    truth: Surface | None = None,
    dem: HeightFunction | None = None,
    plots: bool = True,
) -> list[dict[str, Any]]:
    """Write the GeoTIFFs and plots of every DSM of ``out_bag`` into ``folder``; one row each.

    The truth for the error figures and map: ``truth`` (a surface in the DSM's frame), or
    ``dem`` (ellipsoidal heights by lon, lat) placed in each DSM's tangent-plane frame.

    Raises:
        BagError: the bag has no ``dsm`` topic (processed without heights).
        InputError: ``dem`` given for a DSM whose frame is not a tangent plane.
    """
    reader = BagReader(out_bag)
    if "dsm" not in reader.topics():
        raise BagError("no dsm topic: process the bag with --heights", out_bag)
    disparities = disparities_by_stamp(reader)
    rows: list[dict[str, Any]] = []
    for item in reader.messages(topics=["dsm"]):
        m = item.msg
        heights, grid, ortho = elevation_grid_from_msg(m)
        name = m.pair_id.replace("+", "_") or f"pair_{len(rows)}"
        frame = m.header.frame_id
        surface = truth
        if dem is not None:
            if frame_of(frame) is None:
                raise InputError(
                    "--dem", f"the DSM of {m.pair_id} is in {frame!r}, not a tangent plane"
                )
            surface = enu_dem_surface(frame, dem)
        crs, out_grid = write_dsm_geotiff(folder / f"{name}_dsm.tif", heights, grid, frame,
                                          target=target)  # fmt: skip
        files = [f"{name}_dsm.tif"]
        if ortho is not None:
            write_ortho_geotiff(
                folder / f"{name}_ortho.tif", ortho, grid, frame, heights=heights, target=target
            )
            files.append(f"{name}_ortho.tif")
        disp = disparities.get(stamp_to_ns(m.header.stamp))
        if disp is not None:
            write_plain_tiff(
                folder / f"{name}_disparity.tif",
                disp,
                nodata=float("nan"),
                description="disparity col_left - col_right, px, left normalized grid",
            )
            files.append(f"{name}_disparity.tif")
        row: dict[str, Any] = {
            "pair_id": m.pair_id,
            "crs": None if crs is None else crs.to_string(),
            "cells": [out_grid.width, out_grid.height],
            "cell_size_m": out_grid.cell,
            "files": files,
        }
        if surface is not None:
            row["against_truth"] = dsm_accuracy(heights, grid, surface)
        if plots:
            written = save_height_plots(
                folder, name, heights, grid, disparity=disp, truth=surface, ortho=ortho
            )
            files += [p.name for p in written]
        rows.append(row)
    return rows
