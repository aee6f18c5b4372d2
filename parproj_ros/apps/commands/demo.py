"""``parproj demo``: the default bag through the live node, then the evaluation."""

from __future__ import annotations

import argparse
from typing import Any

from ...io.files import (
    check_output,
    input_path,
    number,
    staged_output,
)
from .common import FORCE_HELP, bags_dir


def run(args: argparse.Namespace) -> int:
    """``parproj demo``: the default bag through the live node; pair, anaglyph and evaluation."""
    from ...ros.inputs import check_input_bag
    from ..demo import run_demo

    args.inputs = [args.bag]
    bag = input_path(args.bag, "bag")
    out = check_output(args.output, inputs=[bag], force=args.force, kind="folder")
    args.outputs = [out]
    check_input_bag(bag)
    with staged_output(out, force=args.force, kind="folder") as work:
        code = run_demo(bag, work, rate=args.rate, progress=not args.quiet, shown_as=out)
    return code


def add_parser(sub: Any) -> None:
    """Add ``parproj demo`` to the sub-command parsers ``sub``."""
    p = sub.add_parser("demo", help="run the default bag through the live node")
    p.add_argument("--bag", default=str(bags_dir() / "ikonos_agile"))
    p.add_argument("-o", "--output", default="out/demo", help="folder to create for results")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.add_argument(
        "--rate", type=number(0.0, 1e6), default=20.0, help="replay speed factor (0 = unpaced)"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)
