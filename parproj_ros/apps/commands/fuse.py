"""``parproj fuse``: the pair DSMs of one area fused into one DSM (GeoTIFF, count, spread)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from ...io.files import check_output, input_path, number, staged_output
from .common import FORCE_HELP, report


def run(args: argparse.Namespace) -> int:
    """Fuse the DSMs of the bags; print the pairs' offsets and the fused DSM's figures."""
    from ..fuse import NotEnoughDsmsError, export_fused, fuse_bags, offsets_table

    args.inputs = list(args.output_bags)
    bags = [input_path(b, "bag") for b in args.output_bags]
    out = check_output(args.output, inputs=bags, force=args.force, kind="folder")
    args.outputs = [out]
    try:
        res = fuse_bags(
            bags,
            tolerance_m=args.tolerance_m,
            align=not args.no_align,
            cell_m=args.cell_m or None,
            weigh=not args.equal_weights,
        )
    except NotEnoughDsmsError as err:
        print(f"parproj fuse: {err}", file=sys.stderr)
        return 1
    if res.fused.completeness == 0.0:
        print(
            "parproj fuse: the fused DSM has no cell with a height (the inputs do not overlap "
            "or are empty): check each pair with parproj dsm",
            file=sys.stderr,
        )
        return 1
    with staged_output(out, force=args.force, kind="folder") as work:
        doc = export_fused(res, work, target=args.target)
        (work / "fuse.json").write_text(json.dumps(doc, indent=1, default=float))
    doc["output"] = str(out)

    def show(d: dict[str, Any]) -> None:
        names = d["inputs"]
        for note in d.get("notes", []):
            print(note)
        print(f"{len(names)} DSMs in frame {d['frame_id']}:")
        for n, c, w in zip(names, d["input_completeness"], d["weights"], strict=True):
            print(f"  {n}: {100 * c:.1f} % of the fused grid, weight {w:.2f}")
        print("level offsets before fusion (median of row - column over shared cells, m):")
        for line in offsets_table(names, d["median_before_m"]):
            print("  " + line)
        after = [abs(v) for row in d["median_after_m"] for v in row if v is not None]
        if d["aligned"] and after:
            offs = ", ".join(f"{n} {o:+.2f}" for n, o in zip(names, d["offsets_m"], strict=True))
            print(f"removed (m): {offs}; after: largest |median| {max(after):.2f} m")
        elif d["aligned"]:
            print("levels kept as they are: no two DSMs share a cell to measure an offset on")
        else:
            print("levels kept as they are (--no-align)")
        counts = " / ".join(str(k) for k in d["cells_by_count"])
        sp = d["spread_median_m"]
        print(
            f"fused: {d['cells'][0]} x {d['cells'][1]} cells of {d['cell_size_m']:.3g} m, "
            f"{d['crs']}; {100 * d['completeness']:.1f} % of its frame grid with a height; "
            f"cells with 1..{len(names)} samples kept: {counts}"
            + (f"; median spread {sp:.2f} m" if sp is not None else "")
        )
        print(f"-> {out}")

    report(args.json, doc, show)
    return 0


def add_parser(sub: Any) -> None:
    """Add ``parproj fuse`` to the sub-command parsers ``sub``."""
    p = sub.add_parser(
        "fuse",
        help="fuse the pair DSMs of one area (output bags of process --heights) into one DSM",
    )
    p.add_argument(
        "output_bags",
        nargs="+",
        help="output bag(s) with a dsm topic, of one area (DSMs of other tangent-plane frames "
        "are brought into the first one's)",
    )
    p.add_argument("-o", "--output", required=True, help="folder to create")
    p.add_argument(
        "--tolerance-m",
        type=number(0.0, 1000.0, lo_open=True),
        default=3.0,
        help="samples farther than this from a cell's median are rejected [m]; default 3.0",
    )
    p.add_argument(
        "--no-align",
        action="store_true",
        help="keep each pair's height level (default: remove the pairs' mutual median offsets)",
    )
    p.add_argument(
        "--equal-weights",
        action="store_true",
        help="average the kept samples with equal weights (default: each pair weighs 1 / a^2, "
        "a its metres of height per pixel of disparity)",
    )
    p.add_argument(
        "--cell-m",
        type=number(0.0, 10000.0),
        default=0.0,
        help="fused cell side; 0 = the finest input's [m]",
    )
    p.add_argument(
        "--target",
        choices=["utm", "local"],
        default="utm",
        help="CRS of a real area's DSM: its UTM zone, or a local transverse Mercator",
    )
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.set_defaults(func=run)
