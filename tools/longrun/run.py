"""The long run: the bag replayed into the live node, its report, plot and command line."""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from parproj_ros.core import contract
from parproj_ros.ros.bag import BagReader, get_message_class
from parproj_ros.ros.inputs import node_parameters, truth_from_bag, views_from_bag
from parproj_ros.ros.live import NodeProcess, _qos, node_params_yaml
from parproj_ros.ros.live import wait_until as _wait_until
from tools.harness import (
    ROOT,
    RssMonitor,
    cpu_busy_s,
    join_ros_domain,
    jsonable,
    machine_info,
    node_params_from_options,
    own_cpu_s,
)

from .checks import (
    BagPlan,
    PairChecker,
    plan_bag,
    repetition_id,
    repetition_messages,
)


def _slope(t: np.ndarray, y: np.ndarray) -> float | None:
    """Least-squares slope of y against t (None for fewer than 3 samples or no spread)."""
    if len(t) < 3 or np.ptp(t) == 0:
        return None
    return float(np.polyfit(t, y, 1)[0])


def _second_half_slope(t: np.ndarray, mb: np.ndarray, wall: float) -> float | None:
    """Slope of the per-minute median RSS over the second half of the run, MB per hour.

    Insensitive to the short spikes of a pair being processed and to a late step of the
    allocator during warm-up, which weigh on the least-squares slope of a 20-minute run.
    """
    minutes = np.floor(t / 60.0)
    sel = t >= wall / 2
    keys = np.unique(minutes[sel])
    if keys.size < 3:
        return None
    med = np.array([np.median(mb[sel & (minutes == k)]) for k in keys])
    return float(np.polyfit(keys * 60.0, med, 1)[0] * 3600)


def run_longrun(
    bag: Path,
    out: Path,
    *,
    minutes: float = 20.0,
    repetitions: int | None = None,
    rate: float = 0.0,
    margin_s: float = 1.0,
    in_flight: int = 2,
    warmup_s: float = 120.0,
    rtol: float = 0.0,
    stall_timeout_s: float = 180.0,
    node_params: dict[str, Any] | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Replay ``bag`` into a live ``parproj_node`` repeatedly; return (and write) the report.

    Args:
        bag: the bag replayed.
        out: folder for ``longrun.json``, ``longrun.png``, the node's log and parameters.
        minutes: no repetition is started after this many minutes of wall time.
        repetitions: stop after this many repetitions (None: only ``minutes`` limits).
        rate: speed factor against the bag's log times within a repetition; 0 = as fast as
            the node acknowledges.
        margin_s: simulated seconds between the end of one repetition and the next, s.
        in_flight: repetition k is sent once every pair of repetition k - ``in_flight`` is back
            (a pair is completed by the next repetition's first strip; so 2 keeps the node busy
            without queueing more than about one repetition).
        warmup_s: RSS samples of the first ``warmup_s`` seconds (at most half the run) are left
            out of the slope, s.
        rtol: relative tolerance of the comparison with the first repetition (0: bit for bit,
            see the module docstring).
        stall_timeout_s: give up waiting for a repetition's pairs after this long, s.
        node_params: extra parproj_node parameters.
        progress: tqdm bar over the repetitions.
        log: where progress messages go.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy
    from tqdm import tqdm

    out.mkdir(parents=True, exist_ok=True)
    plan = plan_bag(bag, margin_s)
    reader = BagReader(bag)
    views = views_from_bag(reader)
    truth = truth_from_bag(reader)
    env = join_ros_domain()
    params = node_parameters(views, scene_timeout=2.0, **(node_params or {}))
    inputs = [contract.fully_qualified(t) for t in contract.stream_topics(v.name for v in views)]
    pfile = _params_file(params, out / "node_params.yaml", inputs)
    machine = machine_info()
    log(
        f"longrun: {bag} ({plan.duration_ns / 1e9:.1f} s, {sum(plan.counts.values())} messages, "
        f"{len(plan.pairs)} pair(s) per repetition), ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}, "
        f"node log {out / 'node.log'}"
    )
    node_proc = NodeProcess(pfile, env, out / "node.log")
    rss = RssMonitor(node_proc.proc.pid, period_s=1.0)
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("parproj_longrun", context=ctx)
    t_start = time.monotonic()
    checker = PairChecker(plan, truth, t_start, rtol)
    checker.subscribe(node)
    pubs: dict[str, Any] = {}
    for topic, msgtype in reader.topics().items():
        cls = get_message_class(msgtype)
        if cls is not None:
            qos = _qos(reader.qos(topic))
            if f"/{topic}" in inputs:
                qos.history = HistoryPolicy.KEEP_ALL  # flow control: see _params_file
            pubs[topic] = node.create_publisher(cls, topic, qos)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    sent: dict[str, int] = {t: 0 for t in pubs}
    reps_sent = 0
    ack_s = 0.0
    stalls: list[str] = []
    aborted: str | None = None
    t_replay = t_end_send = t_done = t_start
    cpu0 = (cpu_busy_s(), time.monotonic())
    own0 = own_cpu_s(children=False)
    node_cpu = 0.0

    def alive() -> bool:
        return node_proc.proc.poll() is None

    def wait_until(ok: Callable[[], bool], timeout_s: float) -> bool:
        return _wait_until(ok, timeout_s, alive, poll_s=0.02)

    try:
        outputs = [t for t in contract.OUTPUT_TOPICS if t != contract.DIAGNOSTICS]
        discovered = wait_until(
            lambda: (
                all(node.count_publishers(t) > 0 for t in outputs)
                and all(pubs[t[1:]].get_subscription_count() > 0 for t in inputs)
            ),
            60.0,
        )
        if not discovered:
            raise RuntimeError("the node and this process did not discover each other in 60 s")
        time.sleep(1.0)  # the writers' side of discovery (see live.Recorder.wait_for_publishers)
        t_replay = time.monotonic()
        checker.t0 = t_replay
        bar = tqdm(
            total=repetitions,
            desc=f"longrun {bag.name}",
            unit="rep",
            disable=not progress,
            dynamic_ncols=True,
        )
        try:
            # The latched inputs of a repetition (GCP, scanner info, truth: transient local) go
            # out before its stream, with the previous repetition's acknowledgement wait, as a
            # ground station latches them ahead of a pass. Sent together with the stream, a GCP
            # set delayed by a DDS repair (heartbeat, about 3 s here) can reach the node after
            # its first scene: that scene then has no GCP (seen once in 281 repetitions).
            latched = {t for t in pubs if reader.qos(t) == "transient_local"}

            def more(k: int) -> bool:
                if repetitions is not None and k >= repetitions:
                    return False
                return time.monotonic() - t_replay < minutes * 60.0 and alive()

            def all_pairs_of(k: int) -> Callable[[], bool]:
                return lambda: checker.pairs_done(k) >= len(plan.pairs)

            def publish(topic: str, msg: Any) -> None:
                pubs[topic].publish(msg)
                sent[topic] += 1

            def wait_acked(k: int) -> float:
                # In slices of 50 ms: rclpy holds the GIL during the wait, which stopped the
                # RSS sampling and the subscriptions of this process for up to 3.7 s.
                t_ack = time.monotonic()
                for topic, p in pubs.items():
                    deadline = time.monotonic() + 10.0
                    while not p.wait_for_all_acked(Duration(nanoseconds=50_000_000)):
                        if time.monotonic() > deadline:
                            log(f"longrun: {topic}: not acknowledged in 10 s (repetition {k})")
                            break
                        time.sleep(0.001)
                return time.monotonic() - t_ack

            rep = 0
            planned = more(0)
            if planned:
                for topic, msg, _ in repetition_messages(plan, 0, sorted(latched)):
                    publish(topic, msg)
                ack_s += wait_acked(0)
            while planned:
                back = rep - in_flight
                if back >= 0 and not wait_until(all_pairs_of(back), stall_timeout_s):
                    if not alive():
                        break
                    stalls.append(
                        f"repetition {back}: {checker.pairs_done(back)} of {len(plan.pairs)} "
                        f"pairs after {stall_timeout_s:.0f} s"
                    )
                t_rep = time.monotonic()
                first_log: int | None = None
                stream = [t for t in pubs if t not in latched]
                for topic, msg, log_ns in repetition_messages(plan, rep, stream):
                    if rate > 0:
                        first_log = log_ns if first_log is None else first_log
                        wait = t_rep + (log_ns - first_log) / 1e9 / rate - time.monotonic()
                        if wait > 0:
                            time.sleep(wait)
                    publish(topic, msg)
                planned = more(rep + 1)
                if planned:
                    for topic, msg, _ in repetition_messages(plan, rep + 1, sorted(latched)):
                        publish(topic, msg)
                ack_s += wait_acked(rep)
                rep += 1
                reps_sent = rep
                s = checker.latest_summary()
                bar.set_postfix(
                    pairs=len(checker.records),
                    rss=f"{rss.rss_mb:.0f}MB",
                    queue=s.get("queue", "?"),
                    refresh=False,
                )
                bar.update(1)
            if not alive():
                aborted = f"node exited with {node_proc.proc.returncode}"
        except KeyboardInterrupt:
            aborted = "interrupted (Ctrl-C)"
        finally:
            bar.close()
        t_end_send = time.monotonic()
        # Drain: the last repetition's last scene closes after the node's scene_timeout.
        expected_total = reps_sent * len(plan.pairs)
        wait_until(lambda: len(checker.records) >= expected_total, stall_timeout_s)
        t_done = time.monotonic()
        # Two more summaries: the final counters and the queue once idle.
        wait_until(lambda: checker.summaries_since(t_done - t_replay) >= 2, 10.0)
        log(f"longrun: {ack_s:.1f} s waiting for acknowledgements")
        cpu = rss.cpu[-1][1] if rss.cpu else 0.0
        node_cpu = cpu
    finally:
        cpu1 = (cpu_busy_s(), time.monotonic())
        own = own_cpu_s(children=False) - own0
        code = node_proc.stop()
        rss.stop()
        executor.shutdown()
        spin.join(timeout=5)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)

    report = _report(
        plan,
        checker,
        rss,
        sent=sent,
        reps_sent=reps_sent,
        times=(t_start, t_replay, t_end_send, t_done),
        settings={
            "bag": str(bag),
            "minutes": minutes,
            "repetitions_limit": repetitions,
            "rate": rate,
            "margin_s": margin_s,
            "in_flight": in_flight,
            "warmup_s": warmup_s,
            "rtol": rtol,
            "node_params": params,
        },
        node={
            "exit_code": code,
            "cpu_s": node_cpu,
            "traceback_in_log": "Traceback" in node_proc.output(),
            "log": str(out / "node.log"),
        },
        stalls=stalls,
        aborted=aborted,
        machine=machine,
        cpu=(cpu0, cpu1, own + node_cpu),
    )
    (out / "longrun.json").write_text(json.dumps(jsonable(report), indent=1))
    plot_report(report, out / "longrun.png")
    return report


def _params_file(params: dict[str, Any], path: Path, inputs: list[str]) -> Path:
    """The node's --params-file: reliable, keep-all input subscriptions.

    Keep-all rather than the demo's keep-last 1000: while the node's worker runs a pair (tie
    points), its executor thread gets the GIL only now and then and takes a few tens of messages
    a second; a repetition sent at once (1447 navigation messages) then overran a keep-last
    history and 564 navigation samples were lost in a 6-repetition trial. With keep-all on both
    sides the reliable protocol holds the writer back instead: nothing is lost, and the
    replay runs at the rate the node takes messages.
    """
    import yaml

    node_params_yaml(params, path, reliable_inputs=inputs)
    doc = yaml.safe_load(path.read_text())
    for topic in inputs:
        sub = doc["parproj_node"]["ros__parameters"]["qos_overrides"][topic]["subscription"]
        sub["history"] = "keep_all"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _report(
    plan: BagPlan,
    checker: PairChecker,
    rss: Any,
    *,
    sent: dict[str, int],
    reps_sent: int,
    times: tuple[float, float, float, float],
    settings: dict[str, Any],
    node: dict[str, Any],
    stalls: list[str],
    aborted: str | None,
    machine: dict[str, Any],
    cpu: tuple[tuple[float, float], tuple[float, float], float],
) -> dict[str, Any]:
    """The figures of a run (see the module docstring); series for the plot included."""
    t_start, t_replay, t_end_send, t_done = times
    wall = t_done - t_replay
    wall0 = time.time() - (time.monotonic() - t_replay)  # epoch time of t_replay
    records = checker.records
    expected = reps_sent * len(plan.pairs)
    malformed = [r for r in records if r.problems]
    published_ids = {(r.rep, r.original) for r in records}
    missing = [
        repetition_id(p.split("+")[0], k)
        for k in range(reps_sent)
        for p in plan.pairs
        if (k, p) not in published_ids
    ]
    final = checker.summaries[-1][1] if checker.summaries else {}

    def count(key: str) -> int | None:
        return int(final[key]) if key in final else None

    strips_sent = sum(n for t, n in sent.items() if contract.view_of(t) is not None)
    nav_sent = sent.get(contract.NAVIGATION, 0)
    drops = {
        "strips_rejected": count("strips_rejected"),
        "nav_rejected": count("nav_rejected"),
        "strips_not_received": None if (got := count("strips")) is None else strips_sent - got,
        "nav_not_received": None if (got := count("nav")) is None else nav_sent - got,
        "diagnostics_warn": checker.issue_levels.get("warn", 0),
        "diagnostics_error": checker.issue_levels.get("error", 0),
        "diagnostics_messages": dict(sorted(checker.issues.items(), key=lambda kv: -kv[1])[:20]),
    }
    # RSS: samples relative to the start of the replay.
    samples = np.array(rss.samples, dtype=float).reshape(-1, 2)
    ts = samples[:, 0] - wall0
    mb = samples[:, 1]
    in_run = (ts >= 0) & (ts <= wall)
    warm = min(settings["warmup_s"], 0.5 * wall)
    fit = in_run & (ts >= warm)
    pair_times = np.array(sorted(r.wall_s for r in records))
    pairs_at = np.searchsorted(pair_times, ts, side="right").astype(float)
    slope_s = _slope(ts[fit], mb[fit])
    slope_p = _slope(pairs_at[fit], mb[fit])
    half = _second_half_slope(ts[in_run], mb[in_run], wall)
    run_mb = mb[in_run] if in_run.any() else mb
    queue = [
        (t, int(s.get("queue", 0)), int(s.get("queue_max", s.get("queue", 0))))
        for t, s in checker.summaries
    ]
    q_run = [q for q in queue if q[0] <= wall + 5]
    nav_held = [(t, int(s["nav_samples"])) for t, s in checker.summaries if "nav_samples" in s]
    gcp_held = [(t, int(s["gcp_points"])) for t, s in checker.summaries if "gcp_points" in s]
    ytruth = [r.truth_y_rms_px for r in records if r.truth_y_rms_px is not None]
    (busy0, w0), (busy1, w1), ours = cpu
    machine_cpu = (busy1 - busy0) / max(w1 - w0, 1e-9)
    ok = (
        aborted is None
        and not stalls
        and len(records) == expected
        and not malformed
        and not missing
        and all(
            v == 0
            for k, v in drops.items()
            if k in ("strips_rejected", "nav_rejected", "strips_not_received", "nav_not_received")
        )
        and drops["diagnostics_warn"] == 0
        and drops["diagnostics_error"] == 0
        and node["exit_code"] == 0
        and not node["traceback_in_log"]
    )
    return {
        "ok": ok,
        "date": datetime.fromtimestamp(wall0, UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "settings": settings,
        "machine": machine,
        "bag": {
            "duration_s": plan.duration_ns / 1e9,
            "shift_s": plan.shift_ns / 1e9,
            "messages": plan.counts,
            "pairs": plan.pairs,
        },
        "wall_s": wall,
        "send_s": t_end_send - t_replay,
        "startup_s": t_replay - t_start,
        "simulated_s": reps_sent * plan.shift_ns / 1e9,
        "simulated_per_wall": reps_sent * plan.shift_ns / 1e9 / wall if wall > 0 else None,
        "repetitions": reps_sent,
        "messages_sent": sent,
        "pairs": {
            "expected": expected,
            "published": len(records),
            "well_formed": len(records) - len(malformed),
            "malformed": len(malformed),
            "missing": missing[:20],
            "missing_count": len(missing),
            "identical_to_first": sum(1 for r in records if r.identical and r.rep > 0),
            "compared": sum(1 for r in records if r.rep > 0),
            "max_rel_diff": max((r.max_rel_diff for r in records), default=0.0),
            "streamed": sum(1 for r in records if r.streamed),
            "incomplete": checker.incomplete()[:20],
            "malformed_examples": [
                {"pair_id": r.pair_id, "problems": r.problems} for r in malformed[:10]
            ],
            "per_hour": len(records) / wall * 3600 if wall > 0 else None,
        },
        "scenes": {
            "expected": reps_sent * plan.scene_count,
            "published": sum(checker.scenes.values()),
            "problems": checker.scene_problems[:10],
        },
        "truth_y_parallax_rms_px": {
            "first": ytruth[0] if ytruth else None,
            "min": min(ytruth) if ytruth else None,
            "max": max(ytruth) if ytruth else None,
        },
        "drops": drops,
        "rss_mb": {
            "start": float(run_mb[0]) if run_mb.size else None,
            "end": float(run_mb[-1]) if run_mb.size else None,
            "max": float(run_mb.max()) if run_mb.size else None,
            "hwm": rss.hwm_mb,
            "slope_mb_per_hour": None if slope_s is None else slope_s * 3600,
            "slope_mb_per_pair": slope_p,
            "at_warmup_end": float(mb[fit][0]) if fit.any() else None,
            "slope_second_half_mb_per_hour": half,
            "fit_from_s": warm,
            "fit_samples": int(fit.sum()),
        },
        "queue": {
            "max": max((q[2] for q in q_run), default=None),
            "max_sampled": max((q[1] for q in q_run), default=None),
            "last": q_run[-1][1] if q_run else None,
            "nav_samples_held": {
                "max": max((v for _, v in nav_held), default=None),
                "last": nav_held[-1][1] if nav_held else None,
            },
            "gcp_points_held": {
                "max": max((v for _, v in gcp_held), default=None),
                "last": gcp_held[-1][1] if gcp_held else None,
            },
        },
        "node": {**node, "final_summary": final},
        "cpu": {
            "machine_busy_cores": machine_cpu,
            "ours_cores": ours / max(w1 - w0, 1e-9),
            "others_cores": machine_cpu - ours / max(w1 - w0, 1e-9),
            "load_average_end": [round(x, 2) for x in os.getloadavg()],
        },
        "stalls": stalls,
        "aborted": aborted,
        "series": {
            "rss": [[round(float(t), 2), round(float(m), 2)] for t, m in zip(ts, mb, strict=True)],
            "queue": [[round(t, 2), q, qm] for t, q, qm in queue],
            "nav_samples": [[round(t, 2), v] for t, v in nav_held],
            "gcp_points": [[round(t, 2), v] for t, v in gcp_held],
            "pairs": [round(float(t), 2) for t in pair_times],
        },
    }


def plot_report(report: dict[str, Any], path: Path) -> None:
    """RSS (with the fitted slope), queue length and pairs against wall time, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ser = report["series"]
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    rss = np.array(ser["rss"], dtype=float).reshape(-1, 2)
    if rss.size:
        ax[0].plot(rss[:, 0] / 60, rss[:, 1], lw=1, label="node VmRSS")
        r = report["rss_mb"]
        if r["slope_mb_per_hour"] is not None:
            t = rss[:, 0]
            sel = (t >= r["fit_from_s"]) & (t <= report["wall_s"])
            if sel.sum() >= 2:
                c = np.polyfit(t[sel], rss[sel, 1], 1)
                ax[0].plot(
                    t[sel] / 60,
                    np.polyval(c, t[sel]),
                    "--",
                    lw=1,
                    label=f"fit {r['slope_mb_per_hour']:+.2f} MB/h",
                )
        ax[0].legend(loc="lower right")
    ax[0].set(ylabel="RSS (MB)", title=f"longrun: {Path(report['settings']['bag']).name}")
    q = np.array(ser["queue"], dtype=float).reshape(-1, 3)
    if q.size:
        ax[1].plot(q[:, 0] / 60, q[:, 2], lw=0.8, label="peak in the last second")
        ax[1].plot(q[:, 0] / 60, q[:, 1], lw=0.8, label="at the 1 Hz summary")
        ax[1].legend(loc="upper right")
    ax[1].set(ylabel="input queue (items)")
    pt = np.array(ser["pairs"], dtype=float)
    ax[2].step(pt / 60, np.arange(1, pt.size + 1), where="post", lw=1, label="pairs")
    nav = np.array(ser["nav_samples"], dtype=float).reshape(-1, 2)
    if nav.size:
        ax2 = ax[2].twinx()
        ax2.plot(nav[:, 0] / 60, nav[:, 1], color="tab:orange", lw=0.8)
        ax2.set_ylabel("navigation samples held", color="tab:orange")
    ax[2].set(xlabel="wall time since the first message (min)", ylabel="pairs published")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def format_report(r: dict[str, Any]) -> str:
    """A short table of the figures."""

    def f(v: Any, fmt: str = ".1f") -> str:
        return "-" if v is None else format(v, fmt)

    p, m, q, d = r["pairs"], r["rss_mb"], r["queue"], r["drops"]
    rows = [
        ("result", "ok" if r["ok"] else "NOT OK" + (f" ({r['aborted']})" if r["aborted"] else "")),
        ("wall duration", f"{f(r['wall_s'] / 60)} min"),
        (
            "simulated duration",
            f"{f(r['simulated_s'] / 3600, '.2f')} h ({f(r['simulated_per_wall'])} x wall)",
        ),
        ("repetitions", str(r["repetitions"])),
        (
            "pairs expected / published / malformed",
            f"{p['expected']} / {p['published']} / {p['malformed']}",
        ),
        (
            "identical to the first repetition",
            f"{p['identical_to_first']} of {p['compared']} (max rel diff {p['max_rel_diff']:.1e})",
        ),
        (
            "drops: strips/nav rejected, not received",
            f"{d['strips_rejected']} / {d['nav_rejected']}, "
            f"{d['strips_not_received']} / {d['nav_not_received']}",
        ),
        (
            "diagnostics warn / error",
            f"{d['diagnostics_warn']} / {d['diagnostics_error']}",
        ),
        (
            "RSS start / after warm-up / end / max",
            f"{f(m['start'])} / {f(m['at_warmup_end'])} / {f(m['end'])} / {f(m['max'])} MB",
        ),
        (
            "RSS slope",
            f"{f(m['slope_mb_per_hour'], '+.2f')} MB/h, "
            f"{f(m['slope_mb_per_pair'], '+.4f')} MB/pair (after {m['fit_from_s']:.0f} s); "
            f"second half, per-minute medians: {f(m['slope_second_half_mb_per_hour'], '+.2f')} "
            "MB/h",
        ),
        ("queue max / last", f"{q['max']} / {q['last']}"),
        (
            "navigation samples / GCP held (last)",
            f"{q['nav_samples_held']['last']} / {q['gcp_points_held']['last']}",
        ),
        (
            "CPU: machine busy / ours / others",
            f"{r['cpu']['machine_busy_cores']:.2f} / {r['cpu']['ours_cores']:.2f} / "
            f"{r['cpu']['others_cores']:.2f} cores",
        ),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    for s in r["stalls"]:
        lines.append(f"stall: {s}")
    for e in p["malformed_examples"][:3]:
        lines.append(f"malformed: {e['pair_id']}: {'; '.join(e['problems'][:3])}")
    for k, n in list(d["diagnostics_messages"].items())[:5]:
        lines.append(f"diagnostics x{n}: {k}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The options of ``python -m tools.longrun`` (those of the former ``parproj longrun``)."""
    p = argparse.ArgumentParser(
        prog="python -m tools.longrun",
        description="replay a bag for hours into the live node: memory, queue, every pair",
    )
    p.add_argument("--bag", default=str(ROOT / "bags" / "ikonos_agile"))
    p.add_argument("-o", "--output", default="out/longrun", help="folder for the report")
    p.add_argument("--minutes", type=float, default=20.0, help="wall time to replay (min)")
    p.add_argument("--repetitions", type=int, default=None, help="stop after N repetitions")
    p.add_argument("--rate", type=float, default=0.0, help="speed factor (0 = as acknowledged)")
    p.add_argument("--margin", type=float, default=1.0, help="s between repetitions (simulated)")
    p.add_argument("--in-flight", type=int, default=2, help="repetitions ahead of the pairs")
    p.add_argument("--warmup", type=float, default=120.0, help="s left out of the RSS slope")
    p.add_argument(
        "--node-param", action="append", default=[], metavar="KEY=VALUE", help="node parameter"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the long run and print its table; 0 when everything held, 1 if not, 2 bad options."""
    args = build_parser().parse_args(argv)
    params = node_params_from_options(args.node_param)
    if params is None:
        return 2
    report = run_longrun(
        Path(args.bag),
        Path(args.output),
        minutes=args.minutes,
        repetitions=args.repetitions,
        rate=args.rate,
        margin_s=args.margin,
        in_flight=args.in_flight,
        warmup_s=args.warmup,
        node_params=params,
        progress=not args.quiet,
    )
    print(format_report(report))
    print(f"report {Path(args.output) / 'longrun.json'}, plot {Path(args.output) / 'longrun.png'}")
    return 0 if report["ok"] else 1
