"""``parproj simulate``: simulated scenarios rendered into input bags."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ...io.files import (
    InputError,
    check_output,
    number,
    staged_output,
)
from .common import bags_dir, shown


def run(args: argparse.Namespace) -> int:
    """``parproj simulate``: render scenarios into bags."""
    from ...sim.recording import record_scenario
    from ...sim.scenarios import SCENARIOS

    names = list(SCENARIOS) if args.scenario == ["all"] else list(dict.fromkeys(args.scenario))
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        raise InputError(unknown[0], f"unknown scenario; known: {', '.join(SCENARIOS)}, all")
    outs = [check_output(Path(args.output) / n, force=args.force) for n in names]
    args.outputs = outs
    for name, out in zip(names, outs, strict=True):
        with staged_output(out, force=args.force) as work:
            record_scenario(
                SCENARIOS[name](),
                work,
                progress=not args.quiet,
                noise_px=args.noise_px,
                log=shown(work, out),
            )
    return 0


def add_parser(sub: Any) -> None:
    """Add ``parproj simulate`` to the sub-command parsers ``sub``."""
    p = sub.add_parser("simulate", help="render simulated scenarios into bags (MCAP)")
    p.add_argument("scenario", nargs="+", help="scenario names, or 'all'")
    p.add_argument("-o", "--output", default=str(bags_dir()), help="folder for the bags")
    p.add_argument(
        "--noise-px",
        type=number(0.0, 1e3),
        default=None,
        help="GCP measurement noise, px (default: the scenario's)",
    )
    p.add_argument("--force", action="store_true", help="replace existing bags")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)
