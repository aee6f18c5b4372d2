"""``python -m tools.bench.batch``: ``parproj batch`` throughput with 1 and 2 Dask workers.

The same run measures, on ``--pairs`` copies of one synthetic fore/aft bag (the benchmark's
platform, ``--lines`` x ``--detectors`` scenes, one pair each):

1. ``process_bag`` + ``evaluate_bag`` called directly, one bag after the other in this process
   (what ``parproj process`` + ``parproj evaluate`` do): the baseline;
2. ``run_batch`` on a LocalCluster of one worker process: the batch path's overhead;
3. ``run_batch`` on two worker processes: the speed-up on this machine.

Prints a Markdown table (for bench/BENCHMARKS.md) and, with ``--json``, one JSON document.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from parproj_ros.sim.synthetic import stereo_platform

from .offline import write_input_bag


def _direct(bags: list[Path], out: Path) -> float:
    from parproj_ros.apps.process import process_bag
    from parproj_ros.eval.evaluate import evaluate_bag

    t = time.perf_counter()
    for b in bags:
        process_bag(b, out / b.name, progress=False)
        evaluate_bag(out / b.name, None, matching=False)
    return time.perf_counter() - t


def _batch(bags: list[Path], out: Path, workers: int) -> tuple[float, list[dict[str, Any]]]:
    from parproj_ros.apps.batch import find_inputs, run_batch

    res = run_batch(find_inputs(bags), out, workers=workers, progress=False, log=lambda _: None)
    bad = [r for r in res.rows if r["status"] != "done" or r.get("pairs") != 1]
    if bad:
        raise SystemExit(f"batch with {workers} workers: {bad}")
    return res.wall_s, res.rows


def main(argv: list[str] | None = None) -> int:
    """Run the three measurements; print the table."""
    ap = argparse.ArgumentParser(prog="python -m tools.bench.batch", description=__doc__)
    ap.add_argument("--pairs", type=int, default=8, help="bags of one pair each (default 8)")
    ap.add_argument("--lines", type=int, default=4096, help="scene lines (default 4096)")
    ap.add_argument("--detectors", type=int, default=4096, help="detectors (default 4096)")
    ap.add_argument("--strip-lines", type=int, default=256, help="lines per strip")
    ap.add_argument("--workdir", type=Path, default=None, help="scratch folder (default: tmp)")
    ap.add_argument("--json", action="store_true", help="print one JSON document as well")
    args = ap.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    work = args.workdir or Path(tempfile.mkdtemp(prefix="parproj_bench_batch_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        plat = stereo_platform(args.lines, args.detectors)
        first = work / "in" / "pair_00"
        t = time.perf_counter()
        write_input_bag(plat, 1, args.strip_lines, first, 50.0)
        print(f"input bag written in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        bags = [first]
        for k in range(1, args.pairs):
            bags.append(work / "in" / f"pair_{k:02d}")
            shutil.copytree(first, bags[-1])
        size_mb = sum(f.stat().st_size for f in first.iterdir()) / 1e6
        t_direct = _direct(bags, work / "direct")
        print(f"direct: {t_direct:.1f} s", file=sys.stderr)
        t1, rows1 = _batch(bags, work / "batch1", 1)
        print(f"batch, 1 worker: {t1:.1f} s", file=sys.stderr)
        t2, rows2 = _batch(bags, work / "batch2", 2)
        print(f"batch, 2 workers: {t2:.1f} s", file=sys.stderr)
        n = args.pairs
        result = {
            "pairs": n,
            "scene": f"{args.lines} x {args.detectors} uint16, 2 views",
            "bag_mb": size_mb,
            "cpus": os.cpu_count(),
            "direct_s": t_direct,
            "batch_1_worker_s": t1,
            "batch_2_workers_s": t2,
            "pairs_per_min": {
                "direct": 60 * n / t_direct,
                "batch_1": 60 * n / t1,
                "batch_2": 60 * n / t2,
            },
            "overhead_batch_1_vs_direct": t1 / t_direct - 1.0,
            "speedup_2_vs_1": t1 / t2,
            "peak_rss_mb_per_task": max(r["peak_rss_mb"] for r in rows1 + rows2),
        }
        ppm = result["pairs_per_min"]
        print(
            "| path | wall s | pairs/min | vs direct |\n|---|---|---|---|\n"
            f"| process + evaluate, one after another (baseline) | {t_direct:.1f} | "
            f"{ppm['direct']:.2f} | 1.00 |\n"
            f"| batch, 1 worker | {t1:.1f} | {ppm['batch_1']:.2f} | {t_direct / t1:.2f} |\n"
            f"| batch, 2 workers | {t2:.1f} | {ppm['batch_2']:.2f} | {t_direct / t2:.2f} |\n\n"
            f"{n} bags of one {result['scene']} pair ({size_mb:.0f} MB each); 2 workers give "
            f"{result['speedup_2_vs_1']:.2f}x one worker; the batch path costs "
            f"{100 * result['overhead_batch_1_vs_direct']:+.0f} % against the direct calls; "
            f"peak RSS of a task {result['peak_rss_mb_per_task']:.0f} MB."
        )
        if args.json:
            print(json.dumps(result, indent=1))
    finally:
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
