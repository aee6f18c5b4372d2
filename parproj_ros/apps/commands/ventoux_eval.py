"""``parproj ventoux-eval``: y-parallax against reference epipolar grids (OTB, shareloc)."""

from __future__ import annotations

import argparse
from typing import Any

from ...io.files import (
    input_path,
    integer,
)
from .common import check_tiff, report


def run(args: argparse.Namespace) -> int:
    """``parproj ventoux-eval``: y-parallax of matches, ours vs reference epipolar grids."""
    from ...eval.reference_grids import evaluate_against_grids, format_table
    from ...ros.inputs import check_output_bag

    args.inputs = [args.output_bag, args.left, args.right, args.grids, args.truth]
    check_output_bag(input_path(args.output_bag, "bag"))
    for f in (args.left, args.right):
        check_tiff(input_path(f, "file"))
    input_path(args.grids, "dir")
    if args.truth:
        input_path(args.truth, "bag")
    res = evaluate_against_grids(
        args.output_bag,
        args.left,
        args.right,
        args.grids,
        truth_bag=args.truth,
        pair_index=args.pair,
    )
    report(args.json, res, lambda r: print(format_table(r)))
    return 0 if res["methods"]["ours"].get("n", 0) > 0 else 1


def add_parser(sub: Any) -> None:
    """Add ``parproj ventoux-eval`` to the sub-command parsers ``sub``."""
    p = sub.add_parser(
        "ventoux-eval",
        help="y-parallax of image matches: published transforms vs reference epipolar grids",
    )
    p.add_argument("output_bag", help="output bag of parproj process (a stereo_pair)")
    p.add_argument("--left", required=True, help="original left image (the pair's left scene)")
    p.add_argument("--right", required=True, help="original right image")
    p.add_argument("--grids", required=True, help="folder of the reference grids (OTB, shareloc)")
    p.add_argument("--truth", help="the imported input bag: evaluate its RPC-exact truth points")
    p.add_argument(
        "--pair", type=integer(0, 10**6), default=0, help="which stereo_pair of the bag (from 0)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=run)
