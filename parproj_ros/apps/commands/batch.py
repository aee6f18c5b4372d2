"""``parproj batch``: bags, folders of bags and image-pair lists processed as tasks on Dask."""

from __future__ import annotations

import argparse
from typing import Any

from ...io.files import integer, number
from .process import add_parameter_options, overrides_from


def run(args: argparse.Namespace) -> int:
    """``parproj batch``: every input one task; a summary table, ``OUT/batch_summary.json``."""
    from ..batch import find_inputs, format_summary, run_batch

    args.inputs = list(args.inputs)
    inputs = find_inputs(args.inputs)
    args.outputs = [args.output]
    result = run_batch(
        inputs,
        args.output,
        scheduler=args.scheduler,
        workers=args.workers,
        worker_memory_mb=args.worker_memory_mb,
        overrides=overrides_from(args),
        force=args.force,
        retries=args.retries,
        progress=not args.quiet,
    )
    print(format_summary(result))
    short = any(r.get("warning") for r in result.rows)  # asked for DSMs, some missing
    return 1 if result.count("failed") or short else 0


def add_parser(sub: Any) -> None:
    """Add ``parproj batch`` to the sub-command parsers ``sub``."""
    from ..batch import WORKER_MEMORY_MB

    p = sub.add_parser(
        "batch",
        help="many bags or image pairs, each one task (import, process, evaluate) on Dask",
    )
    p.add_argument(
        "inputs",
        nargs="+",
        help="bags, folders of bags, or image-pair lists (.csv/.yaml: name,left,right,...)",
    )
    p.add_argument("-o", "--output", required=True, help="folder of the outputs (one per input)")
    p.add_argument(
        "--scheduler",
        help="address of a running Dask scheduler (tcp://host:8786); default: a local cluster",
    )
    p.add_argument(
        "--workers",
        type=integer(1, 1024),
        default=None,
        help="worker processes of the local cluster (default: one per core, within memory)",
    )
    p.add_argument(
        "--worker-memory-mb",
        type=number(256.0, 1e7),
        default=WORKER_MEMORY_MB,
        help=f"memory limit of each local worker, MiB (default {WORKER_MEMORY_MB})",
    )
    p.add_argument(
        "--retries",
        type=integer(0, 10),
        default=1,
        help="further attempts of a task that failed with an error (default 1)",
    )
    p.add_argument("--force", action="store_true", help="redo inputs whose outputs are up to date")
    p.add_argument("--no-gcp", action="store_true", help="ignore GCP (navigation only)")
    add_parameter_options(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
