"""The summary keys, the targets and the tables (text and BENCHMARKS.md) of a run."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from typing import Any


def summary_keys(res: dict[str, Any]) -> dict[str, Any]:
    """The flat figures of a run (the ``--json`` top level)."""
    mi = res.get("micro") or {}
    lv = res.get("live") or {}
    off = res.get("offline") or {}
    err = mi.get("geometric_error") or {}
    rss = lv.get("rss") or {}
    ratio = mi.get("resample_vs_warpaffine")
    return {
        # Time of resample() over that of warpAffine (lower is faster), as in the report's
        # tables; the throughput ratio the 0.8x target is about is its inverse.
        "resample_vs_warpaffine": ratio,
        "resample_throughput_vs_warpaffine": (1.0 / ratio) if ratio else None,
        "resample_mpx_s": mi.get("resample_mpx_s"),
        "warpaffine_mpx_s": mi.get("warpaffine_mpx_s"),
        "resample_vs_warpaffine_tiled": mi.get("resample_vs_warpaffine_tiled"),
        "map_coordinates_mpx_s": mi.get("map_coordinates_mpx_s"),
        "copyto_mpx_s": mi.get("copyto_mpx_s"),
        "map_coordinates_vs_warpaffine": mi.get("map_coordinates_vs_warpaffine"),
        "copyto_vs_warpaffine": mi.get("copyto_vs_warpaffine"),
        "geometric_error_max_px": err.get("max_px"),
        "geometric_error_rms_px": err.get("rms_px"),
        "realtime_factor": lv.get("realtime_factor"),
        "end_to_end_realtime_factor": lv.get("end_to_end_realtime_factor"),
        "transport_realtime_factor": (_passthrough_at(res, 1.0) or {}).get("realtime_factor"),
        "passthrough_loss": (_passthrough_at(res, 1.0) or {}).get("loss"),
        "passthrough_latency_p50_s": (_passthrough_at(res, 1.0) or {}).get("latency_p50_s"),
        "sustained_realtime_factor": lv.get("sustained_realtime_factor"),
        "paced": lv.get("paced"),
        "shm": lv.get("shm"),
        "fast_repair": lv.get("fast_repair"),
        "pairs_shed": lv.get("pairs_shed"),
        "held_back_s": lv.get("held_back_s"),
        "latency_s": (lv.get("latency_s") or {}).get("median"),
        "latency_max_s": (lv.get("latency_s") or {}).get("max"),
        "latency_published_s": (lv.get("latency_published_s") or {}).get("median"),
        "dropped_strips": lv.get("dropped_strips"),
        "peak_rss_mb": rss.get("peak_mb"),
        "peak_rss_over_pair": rss.get("peak_over_pair"),
        "peak_rss_above_base_over_pair": rss.get("peak_above_base_over_pair"),
        "rss_slope_mb_per_pair": rss.get("slope_mb_per_pair"),
        "offline_realtime_factor": off.get("realtime_factor"),
        "offline_latency_s": (off.get("latency_s") or {}).get("median"),
        **heights_keys(res),
    }


def heights_keys(res: dict[str, Any]) -> dict[str, Any]:
    """The heights figures of a run (issue 26): each a number, or None and ``<key>_reason``.

    ``sgbm_bare_mpx_s`` and ``heights_full_mpx_s`` (:mod:`tools.bench.dsm`, same pair, same
    run), the left normalized pixels the sensor delivers per second at the live rate
    (``heights_needed_mpx_s``: line rate x detectors) and how many times the heights step is
    too slow for them (``heights_full_shortfall``); the CPU seconds per sensor second of each
    process of the live run; the quick-look run's keys (:func:`tools.bench.dsm.quicklook_keys`).
    """
    from parproj_ros.sim.synthetic import LINE_RATE_HZ

    from .dsm import quicklook_keys

    hs = res.get("heights_step")
    lv = res.get("live") or {}
    cfg = res.get("config") or {}
    why = None if hs is None else hs.get("error")
    if hs is None:
        why = "the heights part was not run (--no-heights)"
    full = (hs or {}).get("heights_full_mpx_s")
    need = (
        LINE_RATE_HZ * cfg.get("live_rate", 1.0) * cfg["detectors"] / 1e6
        if cfg.get("detectors")
        else None
    )
    cpu = lv.get("cpu_per_sensor_s") or {}
    return {
        "sgbm_bare_mpx_s": (hs or {}).get("sgbm_bare_mpx_s"),
        "sgbm_bare_mpx_s_reason": why if (hs or {}).get("sgbm_bare_mpx_s") is None else None,
        "heights_full_mpx_s": full,
        "heights_full_mpx_s_reason": why if full is None else None,
        "heights_full_over_sgbm_bare": (hs or {}).get("heights_over_sgbm"),
        "heights_cv2_threads": (hs or {}).get("cv2_threads"),
        "heights_needed_mpx_s": need,
        "heights_full_shortfall": need / full if need and full else None,
        "node_cpu_per_sensor_s": cpu.get("node"),
        "render_cpu_per_sensor_s": cpu.get("render"),
        "bench_cpu_per_sensor_s": cpu.get("bench"),
        **quicklook_keys(res.get("quicklook")),
    }


def _passthrough_at(res: dict[str, Any], rate: float) -> dict[str, Any] | None:
    """The pass-through run at ``rate`` x the sensor rate, or None."""
    for r in (res.get("transport") or {}).get("rates") or []:
        if r.get("rate") == rate:
            return dict(r)
    return None


def targets(res: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's targets, each met or not, with its figure."""
    s = summary_keys(res)
    lv = res.get("live") or {}
    rss = lv.get("rss") or {}
    out: list[dict[str, Any]] = []

    def add(name: str, met: bool | None, figure: str) -> None:
        out.append({"target": name, "met": met, "figure": figure})

    if lv:
        # Met only by the figures the label names, each read from this run.
        rtf = s["realtime_factor"]
        lat_max = s["latency_max_s"]
        limit = lv.get("latency_limit_s") or 2.0
        low = (res.get("config") or {}).get("min_sustained", 0.95)
        held = s["held_back_s"] or 0.0
        ok = (
            lv.get("error") is None
            and lv.get("pairs_received") == lv.get("pairs")
            and s["dropped_strips"] == 0
            and not lv.get("pairs_shed")
            and not lv.get("publish_errors")
            and rtf is not None
            and rtf >= low
            and lat_max is not None
            and lat_max <= limit
            and held == 0.0
        )
        mode = "PACED: the publisher waited for the node" if lv.get("paced") else "open-loop"
        add(
            f"live node keeps up with the sensor ({lv.get('input_mb_s', 0):.0f} MB/s, "
            f"{mode}): all pairs, 0 strips dropped, 0 pairs shed, publisher never held back, "
            f"real-time factor >= {low:g}"
            + (" (1 within the jitter of two latencies)" if low < 1 else "")
            + f", latency max <= {limit:g} s",
            ok,
            (
                f"real-time factor {_f(rtf)} (end to end {_f(s['end_to_end_realtime_factor'])}),"
                f" {lv.get('pairs_received')}/{lv.get('pairs')} pairs, dropped "
                f"{s['dropped_strips']} strips, shed {lv.get('pairs_shed')} pairs, latency max "
                f"{_f(lat_max, 3)} s, publisher held back {_f(held, 1)} s and behind the sensor "
                f"by up to {_f(lv.get('publisher_max_lag_s'), 2)} s"
            ),
        )
        raw = rss.get("raw_pair_mb") or math.nan
        peak = rss.get("peak_mb") or math.nan
        base = rss.get("base_mb") or 0.0
        ratio = s["peak_rss_above_base_over_pair"]
        add(
            "node peak RSS <= 2 x raw input pair + fixed base",
            None if ratio is None else ratio <= 2.0,
            f"peak {peak:.0f} MB = base {base:.0f} MB + {_f(ratio, 2)} x pair ({raw:.0f} MB); "
            f"peak / pair {_f(s['peak_rss_over_pair'], 2)}",
        )
        slope = s["rss_slope_mb_per_pair"]
        tol = max(20.0, 0.05 * raw) if math.isfinite(raw) else 20.0
        add(
            "no memory growth from pair to pair",
            None if slope is None else abs(slope) <= tol,
            f"slope of per-pair peak RSS {_f(slope, 1)} MB/pair (tolerance {tol:.0f} MB/pair)",
        )
    off = res.get("offline") or {}
    if off:
        rtf = off.get("realtime_factor")
        io = off.get("io_bound") or {}
        add(
            "offline `parproj process` real-time factor >= 3 (unpaced)",
            None if rtf is None else rtf >= 3.0,
            f"real-time factor {_f(rtf)}"
            + (
                f" (the I/O alone, same run: {_f(io.get('realtime_factor'))})"
                if io.get("realtime_factor") is not None
                else ""
            ),
        )
    ql = res.get("quicklook") or {}
    qlv = ql.get("live") or {}
    if qlv:
        # Issue 26, Done when: the quick-look at the sensor rate, heights on.
        f = s["heights_quicklook_realtime_factor"]
        lat = s["heights_tile_latency_max_s"]
        budget = (res.get("config") or {}).get("memory_budget_mb")
        add(
            f"quick-look DSM at the sensor rate (heights on, heights_quicklook reduction "
            f"{ql.get('factor')}): quick-look real-time factor >= 1.0, every DSM tile within 2 s "
            "of its last strip, no pair shed",
            None
            if f is None and lat is None
            else (
                f is not None
                and f >= 1.0
                and lat is not None
                and lat <= 2.0
                and not qlv.get("pairs_shed")
            ),
            f"real-time factor {_f(f)}, tile latency max {_f(lat, 2)} s, "
            f"{(qlv.get('tiles') or {}).get('dsm_quicklook_tile', {}).get('tiles')} quick-look "
            f"tiles, {qlv.get('pairs_received')}/{qlv.get('pairs')} pairs, shed "
            f"{qlv.get('pairs_shed')}, node peak RSS "
            f"{_f((qlv.get('rss') or {}).get('peak_mb'), 0)} MB (budget: "
            f"{'the default' if budget is None else f'{budget:g} MB'}), node CPU "
            f"{_f(s['heights_quicklook_node_cpu_per_sensor_s'], 2)} s per sensor s",
        )
    q = res.get("quick_elapsed_s")
    if q is not None:
        add("`python -m tools.bench --quick` under 60 s", q < 60.0, f"{q:.1f} s")
    return out


def _transport(tr: dict[str, Any] | None) -> str:
    if not tr:
        return "n/a"
    if tr.get("error"):
        return f"failed: {tr['error']}"
    return (
        f"real-time factor {_f(tr.get('realtime_factor'), 2)}; {tr.get('strips_back')}/"
        f"{tr['strips_sent']} strips back ({_f(100 * (tr.get('loss') or 0.0), 1)} % lost); "
        f"latency p50 / p95 / max {_f(tr.get('latency_p50_s'), 3)} / "
        f"{_f(tr.get('latency_p95_s'), 3)} / {_f(tr.get('latency_max_s'), 3)} s; "
        f"pass-through CPU {_f(100 * (tr.get('passthrough_cpu') or 0.0), 0)} %"
    )


_PACING = {
    True: "PACED: the publisher waits for the node",
    False: "open-loop: the publisher never waits for the node",
}
_TRANSPORTS = {
    True: "Fast DDS shared-memory profile config/fastdds_shm.xml",
    False: "default transports",
}


def _transports(lv: dict[str, Any]) -> str:
    """The transports of a live run, as its report names them."""
    if lv.get("shm"):
        return _TRANSPORTS[True]
    if lv.get("fast_repair"):
        return (
            "default transports, reliable writers heartbeating every 100 ms "
            "(config/fastdds_fast_repair.xml)"
        )
    return _TRANSPORTS[False] + " (heartbeat 3 s)"


def _f(v: Any, nd: int = 3) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{nd}f}"


def format_text(res: dict[str, Any]) -> str:
    """Human-readable tables of a run (what ``python -m tools.bench`` prints without --json)."""
    return "\n".join(_report_lines(res, markdown=False))


def format_markdown(res: dict[str, Any], *, command: str = "bench/run.sh") -> str:
    """BENCHMARKS.md for a run: machine, date, tables, targets met or not."""
    return "\n".join(_report_lines(res, markdown=True, command=command)) + "\n"


def _table(head: list[str], rows: list[list[str]], markdown: bool) -> list[str]:
    if markdown:
        return [
            "| " + " | ".join(head) + " |",
            "|" + "|".join("---" for _ in head) + "|",
            *["| " + " | ".join(r) + " |" for r in rows],
        ]
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    return [fmt.format(*head), *[fmt.format(*r) for r in rows]]


def _report_lines(res: dict[str, Any], *, markdown: bool, command: str = "") -> Iterator[str]:
    cfg = res.get("config") or {}
    mach = res.get("machine") or {}
    h = "## " if markdown else "== "
    if markdown:
        yield "# Benchmarks"
        yield ""
        yield (
            f"Written by `{command}` (`python -m tools.bench`; `python -m tools.bench --quick` "
            "for the one-minute version) from the run below. Definitions: `tools/bench/`; the "
            "synthetic scene: `parproj_ros/sim/synthetic.py`."
        )
        yield ""
    yield f"{h}Run"
    yield ""
    yield (
        f"{mach.get('date')}; {cfg.get('name')} run, {res.get('elapsed_s', 0):.0f} s; "
        f"commit {mach.get('commit')}"
    )
    yield ""
    yield (
        f"Machine: {mach.get('cpu')}, {mach.get('cores')} cores, {mach.get('memory_gb')} GB; "
        f"load average (1, 5, 15 min) at start {mach.get('load_average')}, at the end "
        f"{mach.get('load_average_end')}; other processes used "
        f"{_f(mach.get('other_cpu_s'), 0)} CPU s during the run "
        f"({_f(100 * (mach.get('other_cpu_share') or 0.0), 0)} % of the machine); "
        f"Linux {mach.get('kernel')}; "
        f"Python {mach.get('python')}, numpy {mach.get('numpy')}, scipy {mach.get('scipy')}, "
        f"OpenCV {mach.get('opencv')}; OPENBLAS_CORETYPE={mach.get('openblas_coretype')}"
    )
    yield ""
    tg = targets(res)
    if tg:
        yield f"{h}Targets"
        yield ""
        for t in tg:
            met = {True: "MET", False: "NOT MET", None: "n/a"}[t["met"]]
            yield (
                f"- **{met}** {t['target']}: {t['figure']}"
                if markdown
                else (f"  [{met}] {t['target']}: {t['figure']}")
            )
        yield ""
    mi = res.get("micro") or {}
    if mi:
        sec = mi["seconds"]
        yield f"{h}Resampling one scene"
        yield ""
        yield (
            f"Input {mi['input'][0]} lines x {mi['input'][1]} detectors uint16 "
            f"({mi['input'][0] * mi['input'][1] * 2 / 2**20:.0f} MB); output grid "
            f"{mi['output'][0]} x {mi['output'][1]} px at the native pixel "
            f"({mi['output_inside_footprint'] * 100:.2f} % inside the scene); bilinear; "
            f"OpenCV threads {mi['cv2_threads']}; fastest of {cfg.get('repeats')}."
        )
        yield ""
        rows = [
            ["resample() (parproj)", mi["resample_mpx_s"], sec["resample"],
             mi["resample_vs_warpaffine"]],
            ["cv2.warpAffine, affine part only (lower bound)", mi["warpaffine_mpx_s"],
             sec["warpaffine"], 1.0],
            ["  the same in 512 x 512 output tiles", mi["warpaffine_tiled_mpx_s"],
             sec["warpaffine_tiled"], mi["warpaffine_tiled_vs_warpaffine"]],
            [f"scipy map_coordinates(order=1) + exact map ({mi['map_coordinates_rows']} rows, "
             "scaled)", mi["map_coordinates_mpx_s"], sec["map_coordinates"],
             mi["map_coordinates_vs_warpaffine"]],
            ["  of which map_coordinates alone", mi["map_coordinates_interpolation_only_mpx_s"],
             sec["map_coordinates_interpolation_only"],
             sec["map_coordinates_interpolation_only"] / sec["warpaffine"]],
            ["np.copyto of the output (memory bandwidth)", mi["copyto_mpx_s"], sec["copyto"],
             mi["copyto_vs_warpaffine"]],
        ]  # fmt: skip
        if mi.get("resample_remap_mpx_s"):
            rows.insert(
                1,
                ["resample_remap() (exact map + cv2.remap, reference)",
                 mi["resample_remap_mpx_s"], sec["resample_remap"],
                 mi["resample_remap_vs_warpaffine"]],
            )  # fmt: skip
        yield from _table(
            ["operation", "Mpx/s", "s", "time / warpAffine"],
            [[r[0], f"{r[1]:.1f}", f"{r[2]:.3f}", f"{r[3]:.2f}"] for r in rows],
            markdown,
        )
        yield ""
        e = mi["geometric_error"]
        yield (
            f"Geometric error of resample() against the exact map (float64), "
            f"{e['pixels']} output pixels at least {e['margin_px']:g} px inside the scene: "
            f"max {_f(e['max_px'], 4)} px, rms {_f(e['rms_px'], 4)} px (sample "
            f"{_f(e['max_sample_px'], 4)}, line {_f(e['max_line_px'], 4)}). The affine part "
            f"alone (what warpAffine computes) is off by up to {_f(e['affine_only_max_px'], 2)} "
            "px: the lower bound is not a valid resampler."
        )
        yield ""
    lv = res.get("live") or {}
    if lv:
        yield f"{h}End to end: strips over DDS into parproj_node"
        yield ""
        out = lv.get("output_size")
        yield (
            f"{lv['pairs']} pairs of {cfg.get('lines')} x {cfg.get('detectors')} uint16 scenes "
            f"(fore/aft cameras at -+{lv['camera_pitch_deg']:.3f} deg), {lv['strip_lines']}-line "
            f"strips ({lv['strip_mb']:.1f} MB, {lv['strips_per_s_per_view']:.1f} per s per view, "
            f"{lv['input_mb_s']:.0f} MB/s for both views), published at 6500 lines/s from the "
            f"bench process (reliable QoS, "
            f"{_PACING[bool(lv.get('paced'))]}; {_transports(lv)}"
            f"); normalized images {out} px, "
            f"{lv.get('pairs_streamed')} of {lv.get('pairs_received')} pairs streamed in column "
            "blocks, the others sent as whole images; node with "
            f"ROS_PYTHON_CHECK_FIELDS={'1' if lv['node_check_fields'] else '0'}"
            + (
                f"; the publisher waits when it would be more than {lv['pairs_ahead']} pair "
                "ahead of the node."
                if lv.get("paced")
                else "."
            )
        )
        yield ""
        lat = lv.get("latency_s") or {}
        latp = lv.get("latency_published_s") or {}
        rss = lv.get("rss") or {}
        rows2 = [
            ["real-time factor (sensor time between the first and last pair's last strip / time"
             " between their StereoPairs)", _f(lv.get("realtime_factor"))],
            ["end-to-end real-time factor (sensor time / wall time to the last pair; < 1 by"
             " the last pair's latency)", _f(lv.get("end_to_end_realtime_factor"))],
            ["pairs / scenes / strips shed by the node (memory_budget_mb)",
             f"{lv.get('pairs_shed')} / {lv.get('scenes_shed')} / {lv.get('strips_shed')}"],
            ["sustained real-time factor (scene time / time between pairs)",
             _f(lv.get("sustained_realtime_factor"))],
            *[[f"transport ceiling: pass-through node at {r.get('rate'):g} x the sensor rate,"
               " open-loop", _transport(r)]
              for r in (res.get("transport") or {}).get("rates") or []],
            ["sensor time of the data / wall time, s",
             f"{lv['sensor_s']:.2f} / {_f(lv.get('wall_s'), 2)}"],
            ["publisher held back for the node / its largest lag, s",
             f"{lv['held_back_s']:.2f} / {lv['publisher_max_lag_s']:.3f}"],
            ["latency, last strip -> StereoPair received: median / max, s",
             f"{_f(lat.get('median'), 3)} / {_f(lat.get('max'), 3)}"],
            ["latency, last strip -> pair published (node log): median / max, s",
             f"{_f(latp.get('median'), 3)} / {_f(latp.get('max'), 3)}"],
            ["strips sent / received by the node / dropped",
             f"{lv['strips_sent']} / {lv['strips_received_by_node']} / {lv['dropped_strips']}"],
            ["pairs received; of which streamed in column blocks",
             f"{lv['pairs_received']} / {lv['pairs']}; {lv.get('pairs_streamed')}"],
            ["latency per pair (StereoPair received), s",
             ", ".join(f"{x:.3f}" for x in lat.get("per_pair") or [])],
            ["node input queue, largest (1 Hz summary)", str(lv.get("node_queue_max"))],
            ["node RSS: base / peak, MB", f"{rss.get('base_mb', 0):.0f} / "
             f"{rss.get('peak_mb', 0):.0f}"],
            ["peak RSS / raw input pair; (peak - base) / pair",
             f"{_f(rss.get('peak_over_pair'), 2)}; {_f(rss.get('peak_above_base_over_pair'), 2)}"
             f" (pair = {rss.get('raw_pair_mb', 0):.0f} MB)"],
            ["per-pair peak RSS, MB", str(rss.get("per_pair_peak_mb"))],
            ["RSS slope, MB per pair", _f(rss.get("slope_mb_per_pair"), 1)],
        ]  # fmt: skip
        yield from _table(["figure", "value"], rows2, markdown)
        yield ""
        pt = _passthrough_at(res, 1.0) or {}
        yield (
            f"Gap to the transport ceiling: the pass-through node keeps up at "
            f"{_f(pt.get('realtime_factor'), 2)} x with "
            f"{_f(100 * (pt.get('passthrough_cpu') or 0), 0)} % of a core and a latency p50 "
            f"of {_f(pt.get('latency_p50_s'), 3)} s; the node "
            f"reaches {_f(lv.get('realtime_factor'), 3)} with a latency median of "
            f"{_f((lv.get('latency_s') or {}).get('median'), 3)} s. " + " ".join(GAP_NOTES)
        )
        if lv.get("error"):
            yield ""
            yield f"Run ended early: {lv['error']}"
        yield ""
    off = res.get("offline") or {}
    if off:
        yield f"{h}Offline: `parproj process` (process_bag) on the same data"
        yield ""
        lat = off.get("latency_s") or {}
        yield (
            f"{off['pairs']} pairs from a bag written by BagWriter (chunk compression "
            f"{off.get('input_compression', 'zstd')}; output image topics: "
            f"{off.get('image_compression', 'zstd')}) "
            f"({off['input_bag_write_s']:.1f} s to write); {off['pairs_out']} pairs out, "
            f"{off['output_bag_mb']:.0f} MB output bag, written "
            f"{'past' if off.get('direct_output') else 'through'} the page cache. Real-time "
            "factor "
            f"{off['realtime_factor']:.3f} ({off['sensor_s']:.2f} s of sensor data in "
            f"{off['wall_s']:.1f} s); latency from reading a pair's last strip to its outputs "
            f"handed to the writing thread: median {_f(lat.get('median'), 2)} s, max "
            f"{_f(lat.get('max'), 2)} s."
        )
        yield ""
        io = off.get("io_bound") or {}
        if io:
            yield (
                f"The I/O bound, same run: reading the input bag ({io['read_mb']:.0f} MB) and "
                f"writing a bag of the output's size ({io['written_mb']:.0f} MB uncompressed, "
                f"{io['compression']}, {io['bag_mb']:.0f} MB on disk) took {io['wall_s']:.1f} s: "
                f"real-time factor {io['realtime_factor']:.3f}. `parproj process` took "
                f"{off['wall_s'] / io['wall_s']:.2f}x that."
            )
            yield ""
        if mi.get("seconds") and off.get("sensor_s"):
            # 2 scenes a pair, each resampled as the micro-benchmark's scene (same size).
            alone = 2 * off["pairs"] * mi["seconds"]["resample"]
            yield (
                f"The resampling alone (resample() on both cores, as timed above, for the "
                f"{2 * off['pairs']} scenes): {alone:.1f} s, real-time factor "
                f"{off['sensor_s'] / alone:.2f}; the I/O and the resampling compete for the "
                "same cores."
            )
            yield ""
        if off.get("profiled_wall_s"):
            yield (
                f"Under cProfile (the breakdown below, a second run, in memory the first run "
                f"faulted in) the same took {off['profiled_wall_s']:.1f} s."
            )
            yield ""
        prof = off.get("profile") or {}
        for key, title in (
            ("labelled", "Where the time goes (cProfile of the second run's main thread, the"
             " pipeline; the threads reading ahead and writing behind are not in it; cumulative,"
             " nested rows indented):"),
            ("top_own_time", "Functions with the most own time (cProfile):"),
        ):  # fmt: skip
            if prof.get(key):
                yield title
                yield ""
                yield from _table(
                    ["function", "s per pair", "s total"],
                    [
                        [p["what"], f"{p['seconds_per_pair']:.3f}", f"{p['seconds']:.2f}"]
                        for p in prof[key]
                    ],
                    markdown,
                )
                yield ""
    yield from _heights_lines(res, h, markdown)
    sc = res.get("scaling") or []
    if sc:
        yield f"{h}Scaling of resample() with scene length and width"
        yield ""
        yield from _table(
            ["lines", "detectors", "Mpx", "resample s", "Mpx/s", "ns/px", "warpAffine s",
             "tiled warpAffine s", "resample / warpAffine", "resample / tiled"],
            [
                [str(r["lines"]), str(r["detectors"]), f"{r['mpx']:.1f}",
                 f"{r['resample_s']:.3f}", f"{r['resample_mpx_s']:.1f}",
                 f"{r['resample_ns_per_px']:.2f}", f"{r['warpaffine_s']:.3f}",
                 f"{r['warpaffine_tiled_s']:.3f}", f"{r['resample_vs_warpaffine']:.2f}",
                 f"{r['resample_vs_warpaffine_tiled']:.2f}"]
                for r in sc
            ],
            markdown,
        )  # fmt: skip
        yield ""
    spy = lv.get("py_spy") if lv else None
    if spy:
        yield f"{h}Node profile (py-spy, live run)"
        yield ""
        for name, th in list(spy.items())[:3]:
            yield (
                f"{name}: {th['samples']} samples (20 per s while the thread ran); share of them "
                "in each function and its callees (frames in every sample left out):"
            )
            yield ""
            yield from _table(
                ["function", "share"],
                [[f, f"{100 * c:.0f} %"] for f, c in th["top"] if c < 0.995][:12],
                markdown,
            )
            yield ""
    q = res.get("quick")
    if q:
        elapsed = q.get("elapsed_s", 0)
        yield f"{h}Quick run (`python -m tools.bench --quick --json`, {elapsed:.1f} s)"
        yield ""
        yield "```"
        yield json.dumps({k: v for k, v in q.items() if not isinstance(v, dict | list)}, indent=1)
        yield "```"
        yield ""
    yield f"{h}Definitions"
    yield ""
    for line in DEFINITIONS:
        yield f"- {line}" if markdown else f"  {line}"


def _heights_lines(res: dict[str, Any], h: str, markdown: bool) -> Iterator[str]:
    """The heights section (issue 26): the step against bare SGBM, CPU, the quick-look."""
    s = heights_keys(res)
    hs = res.get("heights_step") or {}
    if not hs and not res.get("quicklook"):
        return
    yield f"{h}Heights at the sensor rate (issue 26; tools/bench/dsm.py)"
    yield ""
    if hs.get("pair_size"):
        whole = hs.get("whole_pair_size") or hs["pair_size"]
        yield (
            f"The benchmark's first pair normalized in this process ({whole[0]} x {whole[1]} px"
            + (f"; its central {hs['pair_size'][1]} rows" if whole != hs["pair_size"] else "")
            + f"), disparities {hs.get('d_range')}, {_f(100 * (hs.get('matched_share') or 0), 1)}"
            f" % matched, OpenCV threads {hs.get('cv2_threads')}, best of "
            f"{(res.get('config') or {}).get('heights_repeats')}."
        )
        yield ""
    cpu = (res.get("live") or {}).get("cpu_per_sensor_s") or {}
    qlv = (res.get("quicklook") or {}).get("live") or {}
    qcpu = qlv.get("cpu_per_sensor_s") or {}
    rows = [
        ["heights step, core/heights.measure_heights (heights_full_mpx_s), Mpx/s",
         _f(s["heights_full_mpx_s"], 2)],
        ["one bare StereoSGBM pass, dense.sgbm_matcher (sgbm_bare_mpx_s), Mpx/s",
         _f(s["sgbm_bare_mpx_s"], 2)],
        ["step time / bare pass time", _f(s["heights_full_over_sgbm_bare"], 2)],
        ["left pixels the sensor delivers per second (line rate x detectors), Mpx/s",
         _f(s["heights_needed_mpx_s"], 1)],
        ["times too slow for them (heights_full_shortfall)", _f(s["heights_full_shortfall"], 1)],
        ["CPU s per sensor s, live run (node / render process / bench)",
         " / ".join(_f(cpu.get(k), 2) for k in ("node", "render", "bench"))],
        ["quick-look run: reduction (heights_quicklook_factor)",
         str(s["heights_quicklook_factor"])],
        ["quick-look real-time factor (heights_quicklook_realtime_factor)",
         _f(s["heights_quicklook_realtime_factor"])
         if s["heights_quicklook_realtime_factor"] is not None
         else f"n/a: {s['heights_quicklook_realtime_factor_reason']}"],
        ["DSM tile latency max, s (heights_tile_latency_max_s)",
         _f(s["heights_tile_latency_max_s"], 2)
         if s["heights_tile_latency_max_s"] is not None
         else f"n/a: {s['heights_tile_latency_max_s_reason']}"],
        ["quick-look run: CPU s per sensor s (node / render process / bench)",
         " / ".join(_f(qcpu.get(k), 2) for k in ("node", "render", "bench"))],
    ]  # fmt: skip
    for name, fig in (qlv.get("tiles") or {}).items():
        if "@" in name:
            continue
        lat = fig.get("latency_s") or {}
        rows.append(
            [
                f"{name}: tiles / pairs / before the last strip; latency median / max, s",
                f"{fig.get('tiles')} / {fig.get('pairs')} / {fig.get('during_pass')}; "
                f"{_f(lat.get('median'), 2)} / {_f(lat.get('max'), 2)}",
            ]
        )
    yield from _table(["figure", "value"], rows, markdown)
    yield ""


#: Where the node's time goes beyond the transport (issue 11's profile; README "Keeping up").
GAP_NOTES = (
    "What the node adds (issue 11; bench/BENCHMARKS.md, 'Issue 11 at the full rate'): each "
    "strip taken as CDR bytes by the executor (one copy) and copied into its scene's line "
    "buffer (SceneAssembler.add), the resampling (the render process, about half a core at the "
    "IKONOS rate, the next block rendered while the worker publishes one), each block copied "
    "from the render process's output buffer into its CDR bytes, and DDS on both sides; the "
    "simulated sensor shares the same 2 cores. A node that falls behind "
    "grows a backlog past the prefault_mb reserve into memory touched afresh (2.2 ms per MB "
    "here), which slows it further.",
)

DEFINITIONS = (
    "Mpx/s: output pixels per second. 'time / warpAffine': the operation's time over that of "
    "cv2.warpAffine with the affine part of the map (same output size, same 2 OpenCV threads),"
    " the lower bound of the operation.",
    "Real-time factor: sensor time between the first and the last pair's last strip (as "
    "published, open-loop: on the sensor's schedule) over the time between their StereoPairs' "
    "receptions; every pair must have come. A node that keeps up scores 1 whatever its "
    "constant latency, within the jitter of the first and last pair's latencies divided by the "
    "time between them (0.9988-1.0003 in 8 of 9 runs of 2e2b686-206430b, every pair at most "
    "0.25 s late): the full run's target is 0.995 (0.1 s over 21 s), the quick run's 0.95. One "
    "that falls behind scores its throughput over the sensor's. "
    "End to end: sensor time of the data ((pairs + 1) scenes) over the wall time to the last "
    "StereoPair (< 1 by the last latency). Sustained: scene time over the time between "
    "consecutive pairs.",
    "Open-loop (the default): every strip and navigation sample goes out at its sensor time, "
    "the publisher never waits for the node, as a real sensor. The strips go out as CDR bytes "
    "(a new header joined to a body serialized once: one copy of the pixels, as a driver "
    "filling a buffer) so that the simulated sensor takes as little as it can of the 2 cores "
    "it shares with the node. --paced is the former flow "
    "control (the publisher waits until pair j - 2 is out before scene slot j, for every 4 "
    "strips' acknowledgement and for the node's memory); its keep-up target is met only when "
    "it never had to wait. A node that falls behind sheds whole pairs (memory_budget_mb) and "
    "says so on /diagnostics (pairs shed).",
    "Latency: from the publication of a pair's last strip to the StereoPair's reception by the "
    "bench process, and to the node's log line written right after it published the pair. A "
    "node that streams column blocks has sent the pixels before (the StereoPair then carries "
    "none); otherwise the StereoPair carries both normalized images.",
    "Dropped strips: strips sent minus strips counted by the node's /diagnostics summary "
    "(open-loop, a reliable KEEP_LAST writer of depth 50 overwrites what a slow reader has not "
    "acknowledged: those strips are lost, as from a real sensor). Only --paced waits for the "
    "acknowledgement of every 4 strips per view; the time this costs shows as publisher lag.",
    "Transport ceiling: two scenes per view of the same strips, published open-loop at 1x (and "
    "2x) the sensor rate into a pass-through node (its own process: receives each strip and "
    "republishes it, nothing else, with the node's QoS) and received back by the bench: loss, "
    "latency publish -> received back, the pass-through node's CPU share; real-time factor as "
    "above, times the multiple. What the node cannot beat through this transport.",
    "RSS: the node process's VmRSS sampled every 0.2 s and VmHWM; base = before the first "
    "strip; raw input pair = two scenes of lines x detectors x 2 bytes; slope = least-squares "
    "slope of the per-pair peaks (between pair receptions; the first pair left out from 3 "
    "pairs on).",
    "Offline: process_bag (what `parproj process` runs) on a bag of the same strips and "
    "navigation; its real-time factor is sensor time over the wall time of process_bag "
    "(unpaced, so it can exceed 1).",
    "The machine is shared: with other processes running (their CPU share is under Run), the "
    "live and DDS figures vary by 2x or more between runs; compare runs with a low share.",
)
