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
        "transport_realtime_factor": (res.get("transport") or {}).get("realtime_factor"),
        "sustained_realtime_factor": lv.get("sustained_realtime_factor"),
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
    }


def targets(res: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's targets, each met or not, with its figure."""
    s = summary_keys(res)
    lv = res.get("live") or {}
    rss = lv.get("rss") or {}
    out: list[dict[str, Any]] = []

    def add(name: str, met: bool | None, figure: str) -> None:
        out.append({"target": name, "met": met, "figure": figure})

    if lv:
        ok = (
            lv.get("error") is None
            and lv.get("pairs_received") == lv.get("pairs")
            and s["dropped_strips"] == 0
            and (s["held_back_s"] or 0.0) < 0.5
            and (lv.get("publisher_max_lag_s") or 0.0) < 0.5
        )
        rtf = s["realtime_factor"]
        add(
            "live node keeps up at 6500 lines/s per view, nothing dropped (real-time factor >= 1)",
            ok,
            (
                f"real-time factor {_f(rtf)} (sustained {_f(s['sustained_realtime_factor'])}), "
                f"{lv.get('pairs_received')}/{lv.get('pairs')} pairs, "
                f"dropped {s['dropped_strips']} strips, publisher held back "
                f"{_f(s['held_back_s'], 1)} s for the node and behind the sensor by up to "
                f"{_f(lv.get('publisher_max_lag_s'), 2)} s"
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
        add(
            "offline `parproj process` faster than real time",
            None if rtf is None else rtf >= 1.0,
            f"real-time factor {_f(rtf)}",
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
        f"{_f(tr.get('strips_per_s'), 1)} ({_f(tr.get('realtime_factor'), 2)}; "
        f"{_f(tr.get('mb_per_s'), 0)} MB/s, {tr.get('strips_received')}/{tr['strips_sent']} "
        "received)"
    )


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
            f"bench process (reliable QoS); normalized images {out} px, "
            f"{lv.get('pairs_streamed')} of {lv.get('pairs_received')} pairs streamed in column "
            "blocks, the others sent as whole images; node with "
            f"ROS_PYTHON_CHECK_FIELDS={'1' if lv['node_check_fields'] else '0'}; the publisher "
            f"waits when it would be more than {lv['pairs_ahead']} pair ahead of the node."
        )
        yield ""
        lat = lv.get("latency_s") or {}
        latp = lv.get("latency_published_s") or {}
        rss = lv.get("rss") or {}
        rows2 = [
            ["real-time factor (sensor time / wall time to the last pair)",
             _f(lv.get("realtime_factor"))],
            ["sustained real-time factor (scene time / time between pairs)",
             _f(lv.get("sustained_realtime_factor"))],
            ["DDS alone: same strips unpaced into a counting sink, strips/s (real-time factor)",
             _transport(res.get("transport"))],
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
            f"{off['pairs']} pairs from a zstd bag written by BagWriter "
            f"({off['input_bag_write_s']:.1f} s to write); {off['pairs_out']} pairs out, "
            f"{off['output_bag_mb']:.0f} MB output bag. Real-time factor "
            f"{off['realtime_factor']:.3f} ({off['sensor_s']:.2f} s of sensor data in "
            f"{off['wall_s']:.1f} s); latency from reading a pair's last strip to its outputs "
            f"written: median {_f(lat.get('median'), 2)} s, max {_f(lat.get('max'), 2)} s."
        )
        yield ""
        prof = off.get("profile") or {}
        for key, title in (
            ("labelled", "Where the time goes (cProfile of that run; cumulative, nested rows"
             " indented):"),
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


DEFINITIONS = (
    "Mpx/s: output pixels per second. 'time / warpAffine': the operation's time over that of "
    "cv2.warpAffine with the affine part of the map (same output size, same 2 OpenCV threads),"
    " the lower bound of the operation.",
    "Real-time factor: sensor time of the data ((pairs + 1) scenes, since the aft camera lags "
    "one scene) over the wall time from sensor time 0 to the last StereoPair received. With "
    "input paced at the sensor's rate it cannot exceed 1 (the last pair's latency is in the wall"
    " time); a node that keeps up scores (sensor time) / (sensor time + latency). Sustained: "
    "scene time over the time between consecutive pairs (1.0 when the node keeps up).",
    "Flow control: before the data of scene slot j the publisher waits until pair j - 2 has "
    "been received (held back time); a node that keeps up is never waited for. Without it a "
    "slow node's input queue (unbounded, in Python) grows until memory runs out.",
    "Latency: from the publication of a pair's last strip to the StereoPair's reception by the "
    "bench process, and to the node's log line written right after it published the pair. A "
    "node that streams column blocks has sent the pixels before (the StereoPair then carries "
    "none); otherwise the StereoPair carries both normalized images.",
    "Dropped strips: strips sent minus strips counted by the node's /diagnostics summary. "
    "The publisher waits for the acknowledgement of every 4 strips per view (a free-running "
    "reliable KEEP_LAST publisher loses strips when the subscriber falls behind); the time "
    "this costs shows as publisher lag.",
    "DDS alone: two scenes per view of the same strips, published as fast as the same "
    "acknowledgement window allows into a subscriber process that only counts them: the "
    "ceiling the transport puts on the node; its real-time factor is strips/s over the 2 x "
    "6500 / strip lines per second the sensor sends.",
    "RSS: the node process's VmRSS sampled every 0.2 s and VmHWM; base = before the first "
    "strip; raw input pair = two scenes of lines x detectors x 2 bytes; slope = least-squares "
    "slope of the per-pair peaks (between pair receptions; the first pair left out from 3 "
    "pairs on).",
    "Offline: process_bag (what `parproj process` runs) on a zstd bag of the same strips and "
    "navigation; its real-time factor is sensor time over the wall time of process_bag "
    "(unpaced, so it can exceed 1).",
    "The machine is shared: with other processes running (their CPU share is under Run), the "
    "live and DDS figures vary by 2x or more between runs; compare runs with a low share.",
)
