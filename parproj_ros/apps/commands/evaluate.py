"""``parproj evaluate``: the normalized pairs of an output bag against truth."""

from __future__ import annotations

import argparse
import contextlib
import warnings
from typing import Any

from ...io.files import (
    check_output,
    input_path,
    staged_output,
)
from .common import report


def run(args: argparse.Namespace) -> int:
    """``parproj evaluate``: y-parallax, x-parallax linearity and object errors of an output."""
    from ...eval.evaluate import evaluate_bag, print_evaluation
    from ...ros.inputs import check_output_bag, check_truth_bag

    args.inputs = [args.output_bag, args.truth]
    out_bag = input_path(args.output_bag, "bag")
    truth = input_path(args.truth, "bag") if args.truth else None
    plots = None
    if args.plots:
        plots = check_output(args.plots, inputs=[out_bag, truth], force=args.force, kind="folder")
    args.outputs = [plots]
    check_output_bag(out_bag)
    if truth is not None:
        check_truth_bag(truth)
    with contextlib.ExitStack() as stack:
        work = (
            stack.enter_context(staged_output(plots, force=args.force, kind="folder"))
            if plots
            else None
        )
        res = evaluate_bag(out_bag, truth, plots=work, matching=not args.no_matching)
    if truth is None and res["truth_points"] == 0 and res["pair_count"] > 0:
        warnings.warn(
            f"{out_bag}: it holds no truth points, so there are no geometric figures: they "
            "are in the input bag parproj process read (the import's, or the recording's): "
            "give it with --truth BAG",
            stacklevel=1,
        )
    report(args.json, res, print_evaluation)
    return 0 if res["pair_count"] > 0 else 1


def add_parser(sub: Any) -> None:
    """Add ``parproj evaluate`` to the sub-command parsers ``sub``."""
    p = sub.add_parser("evaluate", help="evaluate the normalized pairs of an output bag")
    p.add_argument("output_bag")
    p.add_argument("--truth", help="bag with truth/points: the input bag parproj process read")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--plots", help="folder to create for PNG plots and images")
    p.add_argument("--force", action="store_true", help="replace an existing --plots folder")
    p.add_argument("--no-matching", action="store_true", help="skip image matching")
    p.set_defaults(func=run)
