"""``parproj dsm``: the DSMs of an output bag as GeoTIFF, with their ortho-images and plots.

For every ``dsm`` message (parproj_msgs/ElevationGrid) of an output bag (``parproj process``
with ``--heights``, or a recording of the node): ``<pair>_dsm.tif`` (a Cloud Optimized GeoTIFF,
float32: WGS84 ellipsoidal heights in the UTM zone of a real pair's frame with a 3-D CRS, or
heights above a geoid with a compound CRS, or the frame's Z with a local engineering CRS for a
simulated one, :mod:`parproj_ros.io.geotiff`), ``<pair>_ortho.tif`` (the same grid and CRS),
``<pair>_dsm.las`` / ``.laz`` on request (the DSM's cells as points, :mod:`parproj_ros.io.
pointcloud`), ``<pair>_disparity.tif`` (the pair's disparity map in the left normalized grid,
no georeference), and the PNGs a person looks at (hillshade, disparity, ortho-image, and the
height error map when a true surface is given).

A DSM with a height in fewer than :data:`MIN_VALID_FRACTION` of its cells is not exported: its
row says so (``status`` "empty"), and ``parproj dsm`` exits 1 with a line saying what to try.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .. import __version__
from ..core import contract
from ..eval.heights import (
    Surface,
    disparities_by_stamp,
    dsm_accuracy,
    enu_dem_surface,
    save_height_plots,
)
from ..io.files import InputError, file_stem
from ..io.geotiff import (
    Geoid,
    Ortho,
    frame_of,
    write_dsm_geotiff,
    write_plain_tiff,
)
from ..io.pointcloud import write_point_cloud
from ..ros.bag import BagReader
from ..ros.conversions import elevation_grid_from_msg, stamp_to_ns
from ..rpc import HeightFunction

#: A DSM with a height in fewer of its cells than this is reported and not exported.
MIN_VALID_FRACTION = 0.01


def heights_made(msg: Any) -> dict[str, Any]:
    """How a DSM's heights were made, from its ElevationGrid.

    The terrain searched (metres in the object frame) and where it came from, the disparity
    range (pixels) and the share of pixels matched.
    """
    return {
        "terrain_min_m": float(msg.terrain_min_m),
        "terrain_max_m": float(msg.terrain_max_m),
        "terrain_source": str(msg.terrain_source) or "unknown",
        "terrain_points": int(msg.terrain_points),
        "disparity_range_px": [int(msg.disparity_min), int(msg.disparity_max)],
        "matched_share": round(float(msg.matched_share), 4),
    }


def matched(msg: Any) -> bool:
    """Whether a DSM's ElevationGrid comes from matching one pair (its matching fields filled).

    A fused DSM (``parproj fuse``'s bag, the node's ``dsm_fused``) leaves them 0 / empty: its
    products get no matching figures (they would say 0 % matched, disparities 0..0).
    """
    return bool(
        float(msg.matched_share) > 0.0
        or int(msg.disparity_min) != int(msg.disparity_max)
        or str(msg.terrain_source)
    )


def provenance(pair_id: str) -> dict[str, str]:
    """Dataset tags naming what made a product: the software and its version, and the pair."""
    return {"TIFFTAG_SOFTWARE": f"parproj_ros {__version__}", "PARPROJ_PAIR_ID": pair_id}


class NoHeightsError(Exception):
    """The bag holds no DSM to export (no dsm topic, or no message on it): exit 1."""


def crs_text(crs: Any) -> str:
    """A CRS in a few words: ``EPSG:32631 + ellipsoidal height (WGS 84)`` and the like."""
    sub = list(crs.sub_crs_list) if crs.is_compound else [crs]
    horizontal = sub[0].to_2d() if len(sub[0].axis_info) == 3 else sub[0]
    code = horizontal.to_epsg()
    text = f"EPSG:{code}" if code else horizontal.name
    if crs.is_compound:
        vcode = sub[1].to_epsg()
        return f"{text} + {sub[1].name}" + (f" (EPSG:{vcode})" if vcode else "")
    if len(crs.axis_info) == 3:
        return f"{text} + ellipsoidal height (WGS 84)"
    return text


def export_dsms(
    out_bag: Path,
    folder: Path,
    *,
    target: Literal["utm", "local"] = "utm",
    truth: Surface | None = None,
    dem: HeightFunction | None = None,
    plots: bool = True,
    point_cloud: Literal["las", "laz"] | None = None,
    geoid: Geoid | None = None,
) -> list[dict[str, Any]]:
    """Write the GeoTIFFs and plots of every DSM of ``out_bag`` into ``folder``; one row each.

    The truth for the error figures and map: ``truth`` (a surface in the DSM's frame), or
    ``dem`` (ellipsoidal heights by lon, lat) placed in each DSM's tangent-plane frame.
    ``point_cloud``: also ``<pair>_dsm.las`` or ``.laz``. ``geoid``: heights written above it
    (:func:`parproj_ros.io.geotiff.write_dsm_geotiff`), not above the ellipsoid.

    Returns:
        One row per DSM message: ``status`` "written" (files, CRS, grid) or "empty" (fewer
        than :data:`MIN_VALID_FRACTION` of its cells with a height: nothing written).

    Raises:
        NoHeightsError: the bag has no ``dsm`` topic (processed without heights), or no message on
            it (no pair got heights); the message says what to try.
        InputError: ``dem`` or ``geoid`` given for a DSM whose frame is not a tangent plane.
    """
    reader = BagReader(out_bag)
    if contract.DSM not in reader.topics():
        strips = [t for t in reader.topics() if contract.view_of(t)]
        why = (
            "it is an input bag, of image strips: no outputs"
            if strips and contract.STEREO_PAIR not in reader.topics()
            else "processed without heights"
        )
        raise NoHeightsError(
            f"{out_bag}: no DSM: the bag has no dsm topic ({why}); make one with: parproj "
            "process INPUT_BAG -o OUT --heights, then parproj dsm OUT"
        )
    rec = reader.recovery
    if not rec.complete:
        warnings.warn(
            f"{out_bag}: {rec.describe()}; the DSMs complete in it are exported", stacklevel=2
        )
    disparities = disparities_by_stamp(reader)
    rows: list[dict[str, Any]] = []
    used: set[str] = set()
    for item in reader.messages(topics=[contract.DSM]):
        m = item.msg
        heights, grid, ortho = elevation_grid_from_msg(m)
        # the pair id as the bag gives it, made a safe file stem (never outside the folder),
        # distinct from the stems already written
        name = file_stem(m.pair_id) if m.pair_id else f"pair_{len(rows)}"
        base, k = name, 2
        while name in used:
            name, k = f"{base}_{k}", k + 1
        used.add(name)
        frame = m.header.frame_id
        try:
            plane = frame_of(frame)
        except ValueError as err:
            raise InputError(
                str(out_bag),
                f"the DSM of {m.pair_id} is in object frame {frame!r}, which cannot be placed "
                f"({err}): process its input again (parproj process --frame-id, or the node's "
                "frame_id parameter: a valid tangent plane, or none)",
            ) from None
        valid = float(np.isfinite(heights).mean()) if heights.size else 0.0
        row: dict[str, Any] = {"pair_id": m.pair_id, "frame_id": frame, "valid_fraction": valid}
        rows.append(row)
        if valid < MIN_VALID_FRACTION:
            row.update(status="empty", files=[])
            continue
        surface = truth
        for option, given in (("--dem", dem is not None), ("--heights-geoid", geoid is not None)):
            if given and plane is None:
                raise InputError(
                    option, f"the DSM of {m.pair_id} is in {frame!r}, not a tangent plane"
                )
        if truth is not None and plane is not None:
            raise InputError(
                "--scenario",
                f"the DSM of {m.pair_id} is in {frame!r}, a real pair's tangent plane on WGS84; "
                "a scenario's terrain is in a simulated bag's frame (map): compare a real pair "
                "with --dem",
            )
        if dem is not None:
            surface = enu_dem_surface(frame, dem)
        made_by = provenance(m.pair_id)
        tags = dict(made_by)
        if matched(m):
            made = heights_made(m)
            row["heights"] = made
            # cells of the DSM (its frame grid) filled from the nearest measured cell
            row["filled_cells"] = int(m.filled_cells)
            tags.update({f"PARPROJ_{k.upper()}": str(v) for k, v in made.items()})
            tags.update(
                PARPROJ_FILLED_CELLS=str(int(m.filled_cells)),
                PARPROJ_FILLED_NOTE="cells of the DSM's frame grid filled from the nearest "
                f"measured cell (at most {float(m.max_fill_cells):g} cell widths away): not "
                "measurements",
            )
            if plane is not None:  # the file's heights are not the frame's Z: say how they relate
                lo, hi = plane.h0 + made["terrain_min_m"], plane.h0 + made["terrain_max_m"]
                tags["PARPROJ_TERRAIN_NOTE"] = (
                    f"terrain searched {made['terrain_min_m']:.2f}..{made['terrain_max_m']:.2f} m "
                    f"in the object frame (Z above its tangent plane at h0 {plane.h0:.2f} m): "
                    f"about {lo:.2f}..{hi:.2f} m above the WGS84 ellipsoid"
                )
        with_ortho = (
            None if ortho is None else Ortho(folder / f"{name}_ortho.tif", ortho, tags=made_by)
        )
        crs, out_grid = write_dsm_geotiff(
            folder / f"{name}_dsm.tif",
            heights,
            grid,
            frame,
            target=target,
            geoid=geoid,
            tags=tags,
            ortho=with_ortho,  # on the same grid, from the same reprojection
        )
        files = [f"{name}_dsm.tif"]
        if ortho is not None:
            files.append(f"{name}_ortho.tif")
        if point_cloud is not None:
            cloud = f"{name}_dsm.{point_cloud}"
            row["points"] = write_point_cloud(folder / f"{name}_dsm.tif", folder / cloud)
            files.append(cloud)
        disp = disparities.get(stamp_to_ns(m.header.stamp))
        if disp is not None:
            write_plain_tiff(
                folder / f"{name}_disparity.tif",
                disp,
                nodata=float("nan"),
                description="disparity col_left - col_right, px, left normalized grid",
                unit="px",
                tags=made_by,
            )
            files.append(f"{name}_disparity.tif")
        row.update(
            status="written",
            crs=crs_text(crs),
            crs_wkt=crs.to_wkt(),
            cells=[out_grid.width, out_grid.height],
            cell_size_m=out_grid.cell,
            files=files,
        )
        if surface is not None:
            row["against_truth"] = dsm_accuracy(heights, grid, surface)
        if plots:
            written = save_height_plots(
                folder, name, heights, grid, disparity=disp, truth=surface, ortho=ortho
            )
            files += [p.name for p in written]
    if not rows and not rec.complete:
        raise NoHeightsError(
            f"{out_bag}: no DSM: no complete dsm message in the bag, which is "
            f"{rec.describe()}; copy it again, or run parproj process INPUT_BAG -o OUT "
            "--heights again"
        )
    if not rows:
        raise NoHeightsError(
            f"{out_bag}: no DSM: the dsm topic has no message (no pair got heights: the WARN "
            "lines of parproj process say why); try parproj process with --z-avg and "
            "--height-range around the ground, or, if no DEM was given, import with --dem"
        )
    return rows
