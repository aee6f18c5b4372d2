"""``parproj segments``: a long RPC strip pair cut under model error bounds."""

from __future__ import annotations

import argparse
from pathlib import Path
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
    _check_two_scenes(input_path(args.left_rpc, "file"), input_path(args.right_rpc, "file"))
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


def _check_two_scenes(left: Path, right: Path) -> None:
    """Refuse one RPC given as both scenes (as ``import`` refuses one image as both).

    Raises:
        InputError: the two files hold the same RPC (offsets, scales and coefficients).
    """
    import numpy as np

    from ...io.files import InputError
    from ...io.raster import read_rpc_file

    a, b = read_rpc_file(left)[0], read_rpc_file(right)[0]
    keys = [
        f"{v}_{k}" for k in ("off", "scale") for v in ("line", "samp", "lat", "long", "height")
    ]
    if all(getattr(a, k) == getattr(b, k) for k in keys) and np.array_equal(
        a.coefficients, b.coefficients
    ):
        raise InputError(
            right, f"the same RPC as {left}: a stereo pair needs two scenes (no base here)"
        )


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
