"""Part 3: the same acquisition through ``process_bag``, under cProfile."""

from __future__ import annotations

import cProfile
import gc
import pstats
import time
from pathlib import Path
from typing import Any

from parproj_ros.sim.synthetic import (
    T0_NS,
    VIEWS,
    Platform,
    StripMessages,
    acquisition,
    make_platform,
    nav_message,
)

from .config import BenchConfig, Log, log_stderr
from .dds import latency_stats


def write_input_bag(
    plat: Platform,
    pairs: int,
    strip_lines: int,
    path: Path,
    nav_hz: float,
    compression: str = "zstd",
) -> int:
    """The acquisition of ``pairs`` pairs as a bag (what ``parproj process`` reads); messages.

    ``compression``: the bag's chunk compression ("zstd", "lz4", "none").
    """
    from rclpy.serialization import serialize_message

    from parproj_ros.core import contract
    from parproj_ros.ros import conversions as conv
    from parproj_ros.ros.bag import BagWriter

    events = acquisition(plat, pairs, strip_lines, nav_hz)
    strips = StripMessages(plat, strip_lines)
    n = 0
    with BagWriter(path, compression=compression, overwrite=True) as bw:
        declared = [contract.NAVIGATION]  # an input bag without GCP and truth
        for v in plat.views:
            declared += [contract.strip_topic(v.name), contract.scanner_info_topic(v.name)]
        bw.add_topics(map(contract.topic, declared))
        t_first = T0_NS - 2_000_000_000
        for v in plat.views:
            info = conv.scanner_info_msg(v, stamp_ns=t_first)
            bw.write(contract.scanner_info_topic(v.name), info, t_first)
            n += 1
        for ev in events:
            log_ns = T0_NS + round(ev.due_s * 1e9)
            if ev.kind == "nav":
                bw.write(contract.NAVIGATION, nav_message(plat, ev.t_s), log_ns)
            else:
                data = serialize_message(strips.get(ev))
                bw.write_raw(contract.strip_topic(VIEWS[ev.view]), data, log_ns)
            n += 1
    return n


def _uncompressed_bytes(bag: Path) -> int:
    """Uncompressed size of a bag's chunks (its messages and their record headers), bytes.

    From the MCAP summaries: the bag is not read again.
    """
    from mcap.reader import SeekingReader

    total = 0
    for mcap_file in sorted(bag.glob("*.mcap")):
        with mcap_file.open("rb") as f:
            summary = SeekingReader(f).get_summary()
        total += sum(ci.uncompressed_size for ci in summary.chunk_indexes) if summary else 0
    return total


def io_bound(
    src: Path,
    out_bytes: int,
    path: Path,
    compression: str,
    keep_bytes: int = 0,
    direct: bool = True,
) -> dict[str, Any]:
    """The I/O alone, what ``parproj process`` cannot beat on this disk.

    Reads every message of the bag ``src`` and writes ``out_bytes`` of them (what
    ``process_bag`` wrote, uncompressed) to a bag at ``path``, chunk compression
    ``compression``; then deletes it. Memory is kept for reuse as ``process_bag`` keeps it
    (``keep_bytes`` of free heap: ``core/memory.tune_malloc``), and written as it writes
    (``direct``: past the page cache).

    Returns wall_s (s), read_mb and written_mb (uncompressed MB), bag_mb (on disk).
    """
    from parproj_ros.core.memory import tune_malloc
    from parproj_ros.ros.bag import BagReader, BagWriter

    tune_malloc(keep_bytes)  # as process_bag does
    read = written = 0
    t0 = time.perf_counter()
    with BagWriter(path, compression=compression, overwrite=True, direct=direct) as bw:
        bw.add_topic("copy", "sensor_msgs/msg/Image")
        last = b""
        for m in BagReader(src).raw_messages():
            read += len(m.data)
            if written < out_bytes:
                bw.write_raw("copy", m.data, m.log_time_ns)
                written += len(m.data)
                last = m.data
        while last and written < out_bytes:  # an output larger than the input
            bw.write_raw("copy", last, 0)
            written += len(last)
    wall = time.perf_counter() - t0
    bag_mb = sum(f.stat().st_size for f in path.iterdir()) / 2**20
    for f in path.iterdir():
        f.unlink()
    path.rmdir()
    return {
        "wall_s": wall,
        "read_mb": read / 2**20,
        "written_mb": written / 2**20,
        "bag_mb": bag_mb,
        "compression": compression,
    }


#: (label, file name, function) of the cProfile breakdown of the offline run; rows whose
#: function is not found (the code changed, or the path was not taken) are left out.
PROFILE_ROWS = (
    ("pipeline.add_strip (everything after conversion)", "pipeline.py", "add_strip"),
    ("  scene assembly (SceneAssembler.add, concatenation)", "assembly.py", "add"),
    ("  whole-image pair (_make_pair)", "pipeline.py", "_make_pair"),
    ("  streamed blocks (_stream_advance)", "pipeline.py", "_stream_advance"),
    ("    render_block", "streaming.py", "render_block"),
    ("  resample()", "resample.py", "resample"),
    ("  plan_tiles (tile affines)", "resample.py", "plan_tiles"),
    ("outputs_to_messages (conversion, anaglyph)", "conversions.py", "outputs_to_messages"),
    ("  anaglyph (preview)", "preview.py", "anaglyph"),
    ("  array_to_image (Image.data)", "conversions.py", "array_to_image"),
    ("  block_to_cdr (blocks as CDR bytes)", "conversions.py", "block_to_cdr"),
    ("bag write (serialize + zstd)", "bag.py", "write"),
    ("image_to_array (input strips)", "conversions.py", "image_to_array"),
    ("rclpy serialize_message", "serialization.py", "serialize_message"),
    ("rclpy deserialize_message", "serialization.py", "deserialize_message"),
)


def _profile_breakdown(prof: cProfile.Profile, pairs: int, top: int = 12) -> dict[str, Any]:
    """Labelled cumulative times (PROFILE_ROWS) and the functions with most own time, s."""
    stats = pstats.Stats(prof)
    cum: dict[tuple[str, str], float] = {}
    own: list[tuple[float, str]] = []
    for (fname, line, func), row in stats.stats.items():  # type: ignore[attr-defined]
        key = (Path(fname).name, func)
        cum[key] = cum.get(key, 0.0) + float(row[3])
        where = func if fname == "~" else f"{Path(fname).name}:{line} {func}"
        own.append((float(row[2]), where))
    n = max(pairs, 1)
    labelled = [
        {"what": label, "seconds": cum[(f, fn)], "seconds_per_pair": cum[(f, fn)] / n}
        for label, f, fn in PROFILE_ROWS
        if (f, fn) in cum
    ]
    own.sort(reverse=True)
    return {
        "labelled": labelled,
        "top_own_time": [
            {"what": w, "seconds": t, "seconds_per_pair": t / n} for t, w in own[:top]
        ],
    }


def bench_offline(
    cfg: BenchConfig,
    workdir: Path,
    *,
    node_params: dict[str, Any] | None = None,
    log: Log = log_stderr,
) -> dict[str, Any]:
    """Part 3: ``process_bag`` over a bag of ``offline_pairs`` pairs; then again, under cProfile.

    ``node_params`` that are pipeline settings (PipelineConfig's flat names) apply here too.

    Returns the real-time factor (sensor time / wall time of ``process_bag``), per-pair latency
    from reading a pair's last strip to its outputs handed to the writing thread (s), and the
    profile breakdown.
    """
    from parproj_ros.apps.process import process_bag
    from parproj_ros.core.config import FLAT_NAMES
    from parproj_ros.core.memory import raw_pair_bytes
    from parproj_ros.core.results import Outputs
    from parproj_ros.ros.bag import BagReader
    from parproj_ros.ros.inputs import config_from_bag

    plat = make_platform(cfg.lines, cfg.detectors)
    pairs = cfg.offline_pairs
    src, dst = workdir / "offline_input", workdir / "offline_output"
    t = time.perf_counter()
    nmsg = write_input_bag(
        plat, pairs, cfg.strip_lines, src, cfg.nav_rate_hz, compression=cfg.input_compression
    )
    t_write = time.perf_counter() - t
    log(f"offline: input bag of {pairs} pairs ({nmsg} messages) written in {t_write:.1f} s")
    gc.collect()
    marks: list[float] = []
    pair_marks: list[tuple[int, float]] = []

    def on_outputs(out: Outputs) -> None:
        now = time.perf_counter()
        for _ in out.pairs:
            pair_marks.append((len(marks), now))
        marks.append(now)

    overrides = {
        "scene_lines": cfg.lines,
        "z_avg": 0.0,
        "height_range": 500.0,
        **{k: v for k, v in (node_params or {}).items() if k in FLAT_NAMES},
    }
    # The figure: a run without the profiler. It also pays for the memory the process touches
    # first (core/memory.py); the profiled second run reuses it, so it is often faster.
    t0 = time.perf_counter()
    summary = process_bag(
        src,
        dst,
        progress=False,
        overrides=overrides,
        on_outputs=on_outputs,
        image_compression=cfg.image_compression,
        direct=cfg.direct_output,
    )
    wall = time.perf_counter() - t0
    size = sum(f.stat().st_size for f in dst.iterdir()) / 2**20 if dst.exists() else 0.0
    out_bytes = _uncompressed_bytes(dst) if dst.exists() else 0
    lat = [now - marks[i - 1] for i, now in pair_marks if i >= 1]
    # Where the time goes: the same run again, under cProfile.
    gc.collect()
    prof = cProfile.Profile()
    t1 = time.perf_counter()
    prof.enable()
    process_bag(
        src,
        dst,
        progress=False,
        overrides=overrides,
        image_compression=cfg.image_compression,
        direct=cfg.direct_output,
    )
    prof.disable()
    profiled_wall = time.perf_counter() - t1
    prof.dump_stats(str(workdir / "offline.pstats"))
    sensor_s = (pairs + plat.lag_scenes) * plat.scene_s
    # Two raw pairs of free heap kept, as process_bag keeps for the same configuration.
    keep = 2 * raw_pair_bytes(config_from_bag(BagReader(src), **overrides))
    io = io_bound(
        src,
        out_bytes,
        workdir / "io_bound",
        cfg.image_compression or "zstd",
        keep,
        direct=cfg.direct_output,
    )
    io["realtime_factor"] = sensor_s / io["wall_s"]
    log(
        f"offline: I/O bound (read the input, write {out_bytes / 2**20:.0f} MB) "
        f"{io['wall_s']:.1f} s (real-time factor {io['realtime_factor']:.3f})"
    )
    res = {
        "pairs": pairs,
        "image_compression": cfg.image_compression or "zstd",
        "input_compression": cfg.input_compression,
        "direct_output": summary.direct,
        "output_mb_uncompressed": out_bytes / 2**20,
        "io_bound": io,
        "pairs_out": summary.pairs,
        "messages_in": summary.messages_in,
        "issues": [f"{i.level} {i.where}: {i.message}" for i in summary.issues][:20],
        "input_bag_write_s": t_write,
        "output_bag_mb": size,
        "sensor_s": sensor_s,
        "wall_s": wall,
        "realtime_factor": sensor_s / wall,
        "profiled_wall_s": profiled_wall,
        "latency_s": latency_stats(lat),
        "profile": _profile_breakdown(prof, pairs),
        "profile_note": (
            "cProfile cumulative seconds of the main thread in a second run (the pipeline; the "
            "read-ahead and write-behind threads are not in it); the real-time factor is from "
            "the first run, without the profiler"
        ),
    }
    log(f"offline: {summary.pairs} pairs in {wall:.1f} s (real-time factor {sensor_s / wall:.3f})")
    for p in (src, dst):
        for f in p.iterdir():
            f.unlink()
        p.rmdir()
    return res
