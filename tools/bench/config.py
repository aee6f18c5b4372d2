"""Sizes and limits of a benchmark run (full and quick), and its log."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

Log = Callable[[str], None]


@dataclass(frozen=True)
class BenchConfig:
    """Sizes and limits of one benchmark run.

    Attributes:
        name: "full" or "quick" (or a test's name).
        lines: lines per scene (micro-benchmark input and end-to-end scenes).
        detectors: detectors per line.
        pairs: stereo pairs sent through the live node.
        offline_pairs: stereo pairs run through ``process_bag``.
        strip_lines: lines per image message.
        map_coordinates_rows: output rows resampled with scipy (then scaled to the grid).
        repeats: timed repetitions of each micro-benchmark (the fastest is kept).
        scaling: (lines, detectors) sizes of the scaling table.
        nav_rate_hz: navigation samples per second.
        pairs_ahead: flow control: before sending the data of scene slot j, the publisher waits
            until pair j - 1 - pairs_ahead has been received (never when the node keeps up).
        inflight_strips: strips per view published before waiting for their acknowledgement.
        stall_s: give up when no pair arrives for this long, seconds.
        rss_cap_mb: the publisher also waits while the node's resident memory exceeds this, MB.
        kill_above_mb: the node is killed (and the live run ends) above this, MB: with the
            bench process, the run stays within about 10 GB.
        min_available_mb: ... or while the machine has less memory available than this, MB.
        check_fields: run the node with ROS_PYTHON_CHECK_FIELDS=1 (as the tests do) instead of
            as deployed.
        paced: the publisher waits for the node (``pairs_ahead``, ``inflight_strips``,
            ``rss_cap_mb``): the former flow-controlled mode, kept as a labelled option. By
            default (False) it is open-loop, as a real sensor: every message goes out at its
            sensor time whatever the node does.
        latency_limit_s: the keep-up target's bound on the latency from a pair's last strip to
            its StereoPair received, s.
        min_sustained: the keep-up target's bound on the real-time factor. Issue 11 asks for
            1.0; a node that keeps up scores 1 within the jitter of its first and last pair's
            latencies, which the factor divides by the time between them. Full run 0.995: 0.1
            s over its 21 s. 9 runs of 2e2b686-206430b, every pair at most 0.25 s late: 8 scored
            0.9988-1.0003, the 9th 0.992 (its last pair 0.23 s late, the others 0.04-0.07 s);
            the code before scored 1.02-1.08 only because its first pair was 1-2.5 s late.
            Quick run 0.95: its 4 scenes of 0.32 s each make the ratio of two time spans of
            about 1 s jitter by a few percent.
        passthrough_rates: sensor-rate multiples at which the pass-through node (the transport
            ceiling) is measured, open-loop.
        shm: run every process with the shared-memory profile config/fastdds_shm.xml.
        fast_repair: without ``shm``, run every process with config/fastdds_fast_repair.xml
            (default transports; reliable writers heartbeat every 100 ms instead of 3 s, as
            the README advises a sensor on UDP).
        memory_budget_mb: the node's memory_budget_mb (None: its default).
        image_compression: chunk compression of the offline output bag's image topics
            ("zstd", "lz4", "none"; None: the bag's zstd).
        live_rate: the live sensor's rate as a multiple of the IKONOS rate (2.0: the issue's
            stretch of 2x headroom); a node that keeps up still scores a real-time factor of 1.
        input_compression: chunk compression of the offline input bag: "none", what
            ``ros2 bag record`` writes by default and the only one that keeps up with the
            sensor's 360 MB/s on one core here (zstd writes 184 MB/s; README, "Recording large
            images"); "zstd" or "lz4" to measure what reading them costs.
        direct_output: the offline output bag (and the I/O bound's) written past the page
            cache (``process_bag``'s ``direct``, its default); False: through it.
        heights_repeats: timed runs of the heights step and of the bare SGBM pass on the
            benchmark's normalized pair (the fastest kept; :mod:`tools.bench.dsm`).
        heights_rows: the heights step and the bare pass on the central band of this many rows
            of the normalized pair (its full width; 0: the whole pair). The whole IKONOS-size
            pair (195 Mpx) took a peak RSS of 21.5 GB in the step.
        quicklook_factor: the node's ``heights_quicklook`` in the quick-look live run (-4:
            quick-look tiles at 1/4 instead of the full-resolution tiles; 4: alongside them).
    """

    name: str
    lines: int
    detectors: int
    pairs: int
    offline_pairs: int
    strip_lines: int
    map_coordinates_rows: int
    repeats: int
    scaling: tuple[tuple[int, int], ...]
    nav_rate_hz: float = 50.0
    pairs_ahead: int = 1
    inflight_strips: int = 4
    stall_s: float = 300.0
    rss_cap_mb: float = 6000.0
    kill_above_mb: float = 8500.0
    min_available_mb: float = 1500.0
    check_fields: bool = False
    paced: bool = False
    latency_limit_s: float = 2.0
    min_sustained: float = 0.95
    passthrough_rates: tuple[float, ...] = (1.0, 2.0)
    shm: bool = False
    fast_repair: bool = True
    memory_budget_mb: float | None = None
    image_compression: str | None = None
    input_compression: str = "none"
    live_rate: float = 1.0
    direct_output: bool = True
    heights_repeats: int = 2
    quicklook_factor: int = -4
    heights_rows: int = 0


FULL = BenchConfig(
    name="full",
    lines=14000,
    detectors=13816,
    pairs=10,
    offline_pairs=3,
    strip_lines=500,
    min_sustained=0.995,
    heights_repeats=1,
    heights_rows=4096,
    # 1/8 instead of the full resolution at the IKONOS width (1/4 took 1.6-1.9 CPU s of the
    # node per sensor s there; docs/quicklook_bench.md): the quick form keeps -4.
    quicklook_factor=-8,
    map_coordinates_rows=512,
    repeats=3,
    scaling=(
        (3500, 13816),
        (7000, 13816),
        (14000, 13816),
        (28000, 13816),
        (14000, 3454),
        (14000, 6908),
    ),
)

#: The quick run: the same line rate (6500 lines/s per view) on 2048-detector lines, so a
#: sensor of 2 x 6500 x 2048 x 2 bytes = 51 MB/s (a seventh of the IKONOS 360 MB/s), which the
#: node must keep up with open-loop like the full run; its latency bound is scaled with the
#: scene time (0.32 s against 2.15 s).
QUICK = BenchConfig(
    name="quick",
    lines=2048,
    detectors=2048,
    pairs=4,
    offline_pairs=2,
    strip_lines=256,
    map_coordinates_rows=256,
    repeats=7,
    scaling=((512, 2048), (1024, 2048), (2048, 2048), (2048, 512), (2048, 1024)),
    stall_s=60.0,
    rss_cap_mb=3000.0,
    kill_above_mb=4000.0,
    latency_limit_s=0.5,
)


def log_stderr(msg: str) -> None:
    """A progress line on stderr, with the time (the default ``log`` of every part)."""
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)
