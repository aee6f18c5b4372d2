"""``parproj dsm``: an output bag's DSMs as COG (UTM + heights), ortho-images, points, plots.

Exit 1 when there is no DSM to export, or a DSM with almost no heights.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from typing import Any

from ...io.dem import add_dem_arguments
from ...io.files import check_output, input_path, staged_output
from .common import FORCE_HELP, report


def _check_scenario(bag: Any, name: str) -> None:
    """Refuse ``--scenario`` when the bag's pairs were not computed from its images.

    A real pair's frame (``enu_wgs84:``) is left to the export, which refuses it in words.
    """
    from ...core import contract
    from ...core.frames import FRAME_PREFIX
    from ...eval.evaluate import first_frame_id
    from ...eval.same_input import check_same_input, scenario_lines
    from ...ros.bag import BagReader

    frame = first_frame_id(BagReader(bag), contract.STEREO_PAIR) or ""
    if not frame.startswith(FRAME_PREFIX):
        check_same_input(bag, scenario_lines(name), option="--scenario", source=f"scenario {name}")


def run(args: argparse.Namespace) -> int:
    """Export every DSM of the bag; print one line per pair (or JSON)."""
    from ...eval.heights import scenario_terrain
    from ...io.dem import dem_from_args
    from ..export import export_dsms

    args.inputs = [args.output_bag, *(args.dem or [])]
    bag = input_path(args.output_bag, "bag")
    out = check_output(args.output, inputs=[bag], force=args.force, kind="folder")
    args.outputs = [out]
    truth = scenario_terrain(args.scenario) if args.scenario else None
    if args.scenario and truth is None:
        from ...io.files import InputError
        from ...sim.scenarios import SCENARIOS

        raise InputError("--scenario", f"unknown; known: {', '.join(SCENARIOS)}")
    if args.scenario:
        _check_scenario(bag, args.scenario)
    dem = dem_from_args(args)
    geoid = _heights_geoid(args.heights_geoid)
    from ..export import MIN_VALID_FRACTION, NoHeightsError

    try:
        with staged_output(out, force=args.force, kind="folder") as work:
            rows = export_dsms(
                bag,
                work,
                target=args.target or "utm",
                truth=truth,
                dem=dem,
                point_cloud=args.point_cloud,
                geoid=geoid,
            )
            if dem is not None:
                dem.check_usage("the DSMs' cells")
            (work / "dsm.json").write_text(json.dumps(rows, indent=1, default=float))
            if all(r["status"] == "empty" for r in rows):
                shutil.rmtree(work)  # nothing to give: no folder made
    except NoHeightsError as err:
        print(f"parproj dsm: {err}", file=sys.stderr)
        return 1
    from ...core.frames import FRAME_PREFIX

    local = sorted(
        {str(r["frame_id"]) for r in rows if not str(r["frame_id"]).startswith(FRAME_PREFIX)}
    )
    if args.target and local:
        print(
            f"parproj dsm: note: --target {args.target} applies to a real pair's tangent plane; "
            f"frame {', '.join(map(repr, local))} has no place on Earth (a simulated bag's): "
            "its DSMs are written in a local engineering CRS",
            file=sys.stderr,
        )
    empty = [r for r in rows if r["status"] == "empty"]
    for r in empty:
        print(
            f"parproj dsm: {r['pair_id']}: the DSM has a height in {100 * r['valid_fraction']:.2f}"
            f" % of its cells (< {100 * MIN_VALID_FRACTION:.0f} %): not exported; the pair "
            "matched almost nothing (see the heights line of parproj process); try parproj "
            "process with --z-avg and --height-range around the ground, or, if no DEM was given, "
            "import with --dem",
            file=sys.stderr,
        )

    def show(res: dict[str, Any]) -> None:
        for r in res["pairs"]:
            t = r.get("against_truth")
            err = (
                f"; against truth NMAD {t['nmad']:.3f} m, rms {t['rms']:.3f} m, "
                f"{100 * t['completeness']:.1f} % complete"
                if t
                else ""
            )
            if r["status"] == "written":
                print(
                    f"{r['pair_id']}: {r['cells'][0]} x {r['cells'][1]} cells, "
                    f"{100 * r['valid_fraction']:.1f} % with a height, {r['crs']}{err}"
                )
        if len(empty) < len(res["pairs"]):
            print(f"-> {out}")

    shown = [{k: v for k, v in r.items() if k != "crs_wkt"} for r in rows]
    report(args.json, {"pairs": shown, "output": str(out)}, show)
    return 1 if empty else 0


def _heights_geoid(model: str | None) -> Any:
    """(N(lon, lat), vertical EPSG) of ``--heights-geoid``; None for ellipsoidal heights."""
    if model is None:
        return None
    from ...io.dem import _geoid_sampler
    from ...io.geotiff import VERTICAL_EPSG

    return _geoid_sampler(model), VERTICAL_EPSG[model]


def add_parser(sub: Any) -> None:
    """Add ``parproj dsm`` to the sub-command parsers ``sub``."""
    p = sub.add_parser(
        "dsm", help="the DSMs of an output bag as GeoTIFF (UTM), ortho-images and plots"
    )
    p.add_argument("output_bag", help="output bag with a dsm topic (process --heights)")
    p.add_argument("-o", "--output", required=True, help="folder to create")
    p.add_argument(
        "--target",
        choices=["utm", "local"],
        default=None,
        help="CRS of a real pair's DSM: its UTM zone (default), or a local transverse Mercator",
    )
    p.add_argument("--scenario", help="simulated bag: the scenario whose terrain is the truth")
    add_dem_arguments(p, "real pair: the (coarse) truth")
    cloud = p.add_mutually_exclusive_group()
    cloud.add_argument(
        "--las",
        dest="point_cloud",
        action="store_const",
        const="las",
        help="also write each DSM's cells as a LAS 1.4 point cloud (<pair>_dsm.las, its CRS)",
    )
    cloud.add_argument(
        "--laz",
        dest="point_cloud",
        action="store_const",
        const="laz",
        help="the same, LAZ-compressed (<pair>_dsm.laz)",
    )
    p.add_argument(
        "--heights-geoid",
        choices=["egm2008"],
        help="real pair: write heights above this geoid (compound CRS, e.g. + EGM2008 height, "
        "EPSG:3855) instead of WGS84 ellipsoidal heights (3-D CRS, the default)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.set_defaults(func=run)
