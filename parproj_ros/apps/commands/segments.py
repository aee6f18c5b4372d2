"""``parproj segments``: a long RPC strip pair cut under model error bounds."""

from __future__ import annotations

import argparse
from typing import Any

from ...io.files import (
    input_path,
    integer,
    number,
)
from .common import check_heights, check_rpc, report

#: Smallest height range of ``parproj segments``, m: the virtual GCP and check points need
#: relief to fix the model's height terms (A3, A7, roll); a flat set leaves them undetermined,
#: and check points at the same heights then cannot show it.
MIN_SEGMENT_HEIGHT_RANGE_M = 10.0


def run(args: argparse.Namespace) -> int:
    """``parproj segments``: a full-length RPC strip pair cut under model error bounds."""
    from ...eval.long_scene import format_table
    from ...eval.long_scene import run as run_segments

    args.inputs = [args.left_rpc, args.right_rpc]
    for f in args.inputs:
        check_rpc(input_path(f, "file"))
    check_heights("--heights", args.heights, MIN_SEGMENT_HEIGHT_RANGE_M)
    res = run_segments(
        args.left_rpc,
        args.right_rpc,
        width=args.width,
        heights=tuple(args.heights),
        bounds=tuple(args.bound or (1.0, 0.5, 0.3)),
        overlap=args.overlap,
    )
    report(args.json, res, lambda r: print(format_table(r)))
    return 0 if all(r["reached"] for r in res["runs"]) else 1


def add_parser(sub: Any) -> None:
    """Add ``parproj segments`` to the sub-command parsers ``sub``."""
    p = sub.add_parser(
        "segments",
        help="long scenes: cut a full-length RPC strip pair under model error bounds",
    )
    p.add_argument("left_rpc", help="RPC of the full left scene (.geom, _RPC.TXT, .RPB, XML, tif)")
    p.add_argument("right_rpc", help="RPC of the full right scene")
    p.add_argument(
        "--width",
        type=integer(2, 10**6),
        default=400,
        help="samples of the strips (default 400)",
    )
    p.add_argument(
        "--heights",
        type=number(-1e4, 1e5),
        nargs=2,
        default=[900.0, 1100.0],
        metavar=("LO", "HI"),
        help=f"height range, m (HI - LO >= {MIN_SEGMENT_HEIGHT_RANGE_M:g})",
    )
    p.add_argument(
        "--bound",
        type=number(0.0, 1e6, lo_open=True),
        action="append",
        help="model error bound, px (> 0; repeatable)",
    )
    p.add_argument(
        "--overlap", type=number(0.0, 0.5), default=0.1, help="segment overlap fraction (0-0.5)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=run, bound=None)
