"""The whole benchmark: all parts, the summary first; and its command line."""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import sys
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from tools.harness import (
    cpu_busy_s,
    jsonable,
    machine_info,
    node_params_from_options,
    own_cpu_s,
    process_age_s,
)

from .config import FULL, QUICK, BenchConfig, Log, log_stderr
from .dds import bench_live, bench_transport
from .dsm import bench_heights_step, bench_quicklook
from .micro import bench_resample, bench_scaling
from .offline import bench_offline
from .report import format_markdown, format_text, summary_keys, targets

#: The line of bench/BENCHMARKS.md after which the report is written by hand (kept as it is).
HAND_WRITTEN = "<!-- hand-written below this line: bench/run.sh keeps it as it is -->"


def write_report(path: Path, report: str) -> None:
    """Write ``report`` to ``path``, keeping what follows :data:`HAND_WRITTEN` in the old file."""
    kept = ""
    if path.exists():
        old = path.read_text()
        if HAND_WRITTEN in old:
            kept = old[old.index(HAND_WRITTEN) :]
    path.write_text(report.rstrip("\n") + "\n\n" + kept if kept else report)


def run_bench(
    cfg: BenchConfig,
    *,
    workdir: Path | None = None,
    live: bool = True,
    offline: bool = True,
    scaling: bool = True,
    heights: bool = True,
    domain_id: int | None = None,
    py_spy: str | None = None,
    node_params: dict[str, Any] | None = None,
    log: Log = log_stderr,
) -> dict[str, Any]:
    """All parts of the benchmark; the flat summary keys first, then the details.

    ``heights``: the heights step against a bare SGBM pass on the benchmark's normalized pair
    and, with ``live``, the live run again with heights on and the quick-look
    (:mod:`tools.bench.dsm`).
    """
    t0 = time.perf_counter()
    busy0, own0 = cpu_busy_s(), own_cpu_s(children=True)
    res: dict[str, Any] = {
        "config": asdict(cfg),
        "machine": machine_info(),
        "micro": bench_resample(cfg, log),
    }
    gc.collect()
    if scaling:
        res["scaling"] = bench_scaling(cfg, log)
    gc.collect()
    if heights:
        res["heights_step"] = bench_heights_step(cfg, log, repeats=cfg.heights_repeats)
        gc.collect()
    tmp = None
    if workdir is None and (live or offline):
        tmp = tempfile.TemporaryDirectory(prefix="parproj_bench_")
        workdir = Path(tmp.name)
    try:
        if live and workdir is not None:
            res["transport"] = bench_transport(cfg, workdir / "transport", domain_id=domain_id,
                                               log=log)  # fmt: skip
            gc.collect()
            res["live"] = bench_live(
                cfg,
                workdir / "live",
                domain_id=domain_id,
                py_spy=py_spy,
                node_params=node_params,
                log=log,
            )
            gc.collect()
            res["quicklook"] = (
                bench_quicklook(
                    cfg,
                    workdir / "quicklook",
                    domain_id=domain_id,
                    node_params=node_params,
                    factor=cfg.quicklook_factor,
                    log=log,
                )
                if heights
                else {"available": False, "reason": "not run (--no-heights)"}
            )
            gc.collect()
        if offline and workdir is not None:
            (workdir / "offline").mkdir(parents=True, exist_ok=True)
            res["offline"] = bench_offline(
                cfg, workdir / "offline", node_params=node_params, log=log
            )
            gc.collect()
    finally:
        if tmp is not None:
            tmp.cleanup()
    res["bench_peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    res["machine"]["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    wall = time.perf_counter() - t0
    other = max(0.0, (cpu_busy_s() - busy0) - (own_cpu_s(children=True) - own0))
    res["machine"]["other_cpu_s"] = other
    res["machine"]["other_cpu_share"] = other / (wall * (os.cpu_count() or 1))
    res["elapsed_s"] = time.perf_counter() - t0
    out: dict[str, Any] = jsonable({**summary_keys(res), "elapsed_s": res["elapsed_s"], **res})
    return out


def run_and_report(
    quick: bool,
    *,
    json_out: bool,
    markdown: Path | None = None,
    include_quick: Path | None = None,
    workdir: Path | None = None,
    live: bool = True,
    offline: bool = True,
    heights: bool = True,
    domain_id: int | None = None,
    py_spy: str | None = None,
    pairs: int | None = None,
    check_fields: bool = False,
    node_params: dict[str, Any] | None = None,
    paced: bool = False,
    shm: bool = False,
    memory_budget_mb: float | None = None,
    image_compression: str | None = None,
    input_compression: str = "none",
    live_rate: float = 1.0,
    fast_repair: bool = True,
    direct_output: bool = True,
    quicklook_factor: int | None = None,
) -> dict[str, Any]:
    """What ``python -m tools.bench`` does: run, print (JSON or tables), write BENCHMARKS.md."""
    cfg = QUICK if quick else FULL
    if pairs is not None:
        cfg = replace(cfg, pairs=pairs)
    if check_fields:
        cfg = replace(cfg, check_fields=True)
    cfg = replace(
        cfg,
        paced=paced,
        shm=shm,
        fast_repair=fast_repair,
        memory_budget_mb=memory_budget_mb,
        image_compression=image_compression,
        input_compression=input_compression,
        live_rate=live_rate,
        direct_output=direct_output,
    )
    if quicklook_factor is not None:
        cfg = replace(cfg, quicklook_factor=quicklook_factor)
    res = run_bench(
        cfg,
        workdir=workdir,
        live=live,
        offline=offline,
        heights=heights,
        domain_id=domain_id,
        py_spy=py_spy,
        node_params=node_params,
    )
    res["process_elapsed_s"] = process_age_s()
    if quick:
        res["quick_elapsed_s"] = res["process_elapsed_s"]
    if include_quick is not None and include_quick.exists():
        q = json.loads(include_quick.read_text())
        res["quick"] = q
        res["quick_elapsed_s"] = q.get("elapsed_s")
    res["targets"] = targets(res)
    if markdown is not None:
        markdown.parent.mkdir(parents=True, exist_ok=True)
        write_report(markdown, format_markdown(res))
    if json_out:
        json.dump(res, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(format_text(res))
    return res


def build_parser() -> argparse.ArgumentParser:
    """The options of ``python -m tools.bench`` (those of the former ``parproj bench``)."""
    p = argparse.ArgumentParser(
        prog="python -m tools.bench",
        description="benchmark: resampler, live node over DDS, memory",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="2048 x 2048 scenes: 1-2 minutes (the heights part's second live run lasts as long "
        "as the node's backlog); under 20 s with --no-heights",
    )
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--markdown", help="write the report (bench/BENCHMARKS.md) to this file")
    p.add_argument("--include-quick", help="JSON of a --quick run to include in the report")
    p.add_argument("--workdir", help="folder for the node's files and bags (default: temporary)")
    p.add_argument("--pairs", type=int, default=None, help="pairs through the live node")
    p.add_argument("--no-live", action="store_true", help="skip the live node over DDS")
    p.add_argument("--no-offline", action="store_true", help="skip the offline process")
    p.add_argument(
        "--no-heights",
        action="store_true",
        help="skip the heights step against bare SGBM and the live quick-look run",
    )
    p.add_argument(
        "--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: the environment's)"
    )
    p.add_argument(
        "--check-fields",
        action="store_true",
        help="run the node with ROS_PYTHON_CHECK_FIELDS=1, as the tests do",
    )
    p.add_argument(
        "--node-param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra node parameter (YAML value), e.g. streaming=false; repeatable",
    )
    p.add_argument(
        "--paced",
        action="store_true",
        help="the publisher waits for the node (former flow control; labelled PACED in the "
        "report); default: open-loop at the sensor rate, as a real sensor",
    )
    p.add_argument(
        "--shm",
        action="store_true",
        help="run the node, the pass-through node and the publisher with the Fast DDS "
        "shared-memory profile config/fastdds_shm.xml",
    )
    p.add_argument(
        "--no-fast-repair",
        action="store_true",
        help="without --shm: Fast DDS's default heartbeat (3 s) instead of "
        "config/fastdds_fast_repair.xml (100 ms) in every process",
    )
    p.add_argument(
        "--memory-budget-mb",
        type=float,
        default=None,
        help="the node's memory_budget_mb (default: the node's default)",
    )
    p.add_argument(
        "--image-compression",
        choices=("zstd", "lz4", "none"),
        default=None,
        help="chunk compression of the offline output bag's image topics (default: zstd)",
    )
    p.add_argument(
        "--input-compression",
        choices=("zstd", "lz4", "none"),
        default="none",
        help="chunk compression of the offline input bag (default: none, what ros2 bag record "
        "writes by default)",
    )
    p.add_argument(
        "--live-rate",
        type=float,
        default=1.0,
        help="the live sensor at this multiple of the IKONOS rate (2: the 2x headroom stretch)",
    )
    p.add_argument(
        "--no-direct-output",
        action="store_true",
        help="write the offline output bag (and the I/O bound's) through the page cache "
        "(default: past it, as parproj process does)",
    )
    p.add_argument(
        "--quicklook-factor",
        type=int,
        default=None,
        help="the node's heights_quicklook in the quick-look live run (default -4: tiles at 1/4 "
        "instead of the full-resolution ones; 4: alongside them)",
    )
    p.add_argument("--py-spy", help="py-spy executable: sample the node during the live run")
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; 1 when the live run ended early, 2 on bad options."""
    args = build_parser().parse_args(argv)
    params = node_params_from_options(args.node_param)
    if params is None:
        return 2
    res = run_and_report(
        args.quick,
        json_out=args.json,
        markdown=Path(args.markdown) if args.markdown else None,
        include_quick=Path(args.include_quick) if args.include_quick else None,
        workdir=Path(args.workdir) if args.workdir else None,
        live=not args.no_live,
        offline=not args.no_offline,
        heights=not args.no_heights,
        domain_id=args.domain_id,
        py_spy=args.py_spy,
        pairs=args.pairs,
        check_fields=args.check_fields,
        node_params=params,
        paced=args.paced,
        shm=args.shm,
        fast_repair=not args.no_fast_repair,
        memory_budget_mb=args.memory_budget_mb,
        image_compression=args.image_compression,
        input_compression=args.input_compression,
        live_rate=args.live_rate,
        direct_output=not args.no_direct_output,
        quicklook_factor=args.quicklook_factor,
    )
    return 1 if (res.get("live") or {}).get("error") else 0
