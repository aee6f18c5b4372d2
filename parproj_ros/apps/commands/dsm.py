"""``parproj dsm``: the DSMs of an output bag as GeoTIFF (UTM), ortho-images and plots."""

from __future__ import annotations

import argparse
import json
from typing import Any

from ...io.dem import add_dem_arguments
from ...io.files import check_output, input_path, staged_output
from .common import FORCE_HELP, report


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
    dem = dem_from_args(args)
    with staged_output(out, force=args.force, kind="folder") as work:
        rows = export_dsms(bag, work, target=args.target, truth=truth, dem=dem)
        if dem is not None:
            dem.check_usage("the DSMs' cells")
        (work / "dsm.json").write_text(json.dumps(rows, indent=1, default=float))

    def show(res: dict[str, Any]) -> None:
        for r in res["pairs"]:
            t = r.get("against_truth")
            err = (
                f"; against truth NMAD {t['nmad']:.3f} m, rms {t['rms']:.3f} m, "
                f"{100 * t['completeness']:.1f} % complete"
                if t
                else ""
            )
            print(f"{r['pair_id']}: {r['cells'][0]} x {r['cells'][1]} cells, {r['crs']}{err}")
        print(f"-> {out}")

    report(args.json, {"pairs": rows, "output": str(out)}, show)
    return 0 if rows else 1


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
        default="utm",
        help="CRS of a real pair's DSM: its UTM zone, or a local transverse Mercator",
    )
    p.add_argument("--scenario", help="simulated bag: the scenario whose terrain is the truth")
    add_dem_arguments(p, "real pair: the (coarse) truth")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.set_defaults(func=run)
