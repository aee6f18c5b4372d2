"""Part 2: strips over DDS into parproj_node, and the DDS ceiling (a counting sink)."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from parproj_ros.core import contract
from parproj_ros.sim.synthetic import (
    LINE_RATE_HZ,
    VIEWS,
    Event,
    Platform,
    StripMessages,
    acquisition,
    make_platform,
    nav_message,
)
from tools.harness import (
    ROOT,
    RssMonitor,
    fast_dds,
    join_ros_domain,
    mem_available_mb,
    proc_cpu_s,
    proc_status,
)

from .config import BenchConfig, Log, log_stderr


class BenchAbortError(RuntimeError):
    """The live run cannot go on (node died, memory guard, stall); says why."""


class SerializedStrips:
    """The bench's strips as CDR bytes, what ``Publisher.publish`` sends as is.

    The body (size, encoding, pixels) of each strip position is serialized once per frame_id
    length; each strip joins a new header (stamp, frame_id) to it: one copy of the pixels, as a
    sensor driver filling a buffer would, instead of rclpy's conversion and serialization (two
    copies and the message's Python fields) on every strip. The simulated sensor thus takes as
    little as it can of the cores it shares with the node.
    """

    def __init__(self, strips: StripMessages) -> None:
        self.strips = strips
        self._bodies: dict[tuple[int, int], bytes] = {}  # (strip position, frame_id length)

    def get(self, ev: Event) -> bytes:
        """The CDR bytes of the strip of ``ev`` (header stamp and frame_id from the event)."""
        fid = ev.scene_id.encode() + b"\0"
        head = 8 + 4 + len(fid)  # stamp, string length, characters (payload offsets)
        split = 4 + head + (-head) % 4  # CDR: the next field (height, uint32) is 4-aligned
        key = (ev.row0 // self.strips.strip_lines, len(fid))
        body = self._bodies.get(key)
        if body is None:
            from rclpy.serialization import serialize_message

            body = serialize_message(self.strips.get(ev))[split:]
            self._bodies = {k: v for k, v in self._bodies.items() if k[1] == len(fid)}
            self._bodies[key] = body
        sec, nsec = divmod(int(ev.stamp_ns), 1_000_000_000)
        prefix = b"\0\1\0\0" + struct.pack("<iII", sec, nsec, len(fid)) + fid
        return b"".join((prefix, b"\0" * (split - len(prefix)), body))


@dataclass
class _Observer:
    """What the bench process receives from the node."""

    pairs: dict[str, float] = field(default_factory=dict)
    pair_sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    summary: dict[str, str] = field(default_factory=dict)
    summary_t: float = 0.0
    queue_max: int = 0
    streamed_pairs: set[str] = field(default_factory=set)
    issues: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_pair(self, msg: Any) -> None:
        now = time.time()
        with self.lock:
            self.pairs[msg.pair_id] = now
            w = int(getattr(msg, "width", 0) or msg.left.width)
            h = int(getattr(msg, "height", 0) or msg.left.height)
            self.pair_sizes[msg.pair_id] = (w, h)
            if getattr(msg, "streamed", False):
                self.streamed_pairs.add(msg.pair_id)

    def on_diag(self, msg: Any) -> None:
        now = time.time()
        with self.lock:
            for st in msg.status:
                if st.name == "parproj_node: summary":
                    self.summary = {kv.key: kv.value for kv in st.values}
                    self.summary_t = now
                    self.queue_max = max(self.queue_max, int(self.summary.get("queue", 0)))
                else:
                    self.issues.append(f"{st.name}: {st.message}")


_LOG_PAIR = re.compile(r"\[(\d+\.\d+)\] \[parproj_node\]: pair (\S+):")


def _slope(y: list[float]) -> float | None:
    """Least-squares slope of y against its index (None for fewer than 2 values)."""
    if len(y) < 2:
        return None
    return float(np.polyfit(np.arange(len(y), dtype=float), np.asarray(y, dtype=float), 1)[0])


def latency_stats(v: list[float]) -> dict[str, Any]:
    """Median, max, min and the values (rounded) of latencies, seconds.

    Not :func:`parproj_ros.eval.evaluate.error_stats`: that one describes signed errors (mean |e|,
    RMS, percentiles); latencies are positive and few, and the report lists each pair's.
    """
    if not v:
        return {"median": None, "max": None, "min": None, "per_pair": []}
    return {
        "median": float(np.median(v)),
        "max": float(np.max(v)),
        "min": float(np.min(v)),
        "per_pair": [round(x, 4) for x in v],
    }


def bench_live(
    cfg: BenchConfig,
    workdir: Path,
    *,
    domain_id: int | None = None,
    py_spy: str | None = None,
    node_params: dict[str, Any] | None = None,
    tile_topics: Sequence[str] = (),
    log: Log = log_stderr,
) -> dict[str, Any]:
    """Part 2: strips at 6500 lines/s per view into parproj_node over DDS (see module doc).

    ``tile_topics``: output topics of DSM tiles (a grid message with ``x0``, ``y0``,
    ``cell_size`` and ``heights``) to receive too: per topic, each tile's latency from the
    strip that completes its ground (:func:`tile_last_strip`) to its reception (``tiles``).
    The CPU seconds of the node, its render process and this process (the simulated sensor
    and the observer) per sensor second are ``cpu_per_sensor_s``.

    ``node_params`` are extra node parameters (e.g. ``{"streaming": False}``). Returns
    real-time factors, latencies (s), strips dropped, the node's memory (MB) and the
    publisher's pacing figures; ``error`` says why a run ended early.
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from parproj_msgs.msg import StereoPair
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from parproj_ros.ros.bag import get_message_class
    from parproj_ros.ros.inputs import node_parameters
    from parproj_ros.ros.live import NodeProcess, node_params_yaml

    workdir.mkdir(parents=True, exist_ok=True)
    plat = make_platform(cfg.lines, cfg.detectors)
    env = join_ros_domain(
        domain_id,
        workdir / "ros_log",
        check_fields=cfg.check_fields,
        shm=cfg.shm,
        fast_repair=cfg.fast_repair,
    )
    inputs = [contract.fully_qualified(t) for t in contract.stream_topics(VIEWS)]
    extra = dict(node_params or {})
    if cfg.memory_budget_mb is not None:
        extra.setdefault("memory_budget_mb", float(cfg.memory_budget_mb))
    pfile = node_params_yaml(
        node_parameters(
            plat.views,
            scene_lines=cfg.lines,
            scene_timeout=0.0,
            z_avg=0.0,
            height_range=500.0,
            **extra,
        ),
        workdir / "params.yaml",
        reliable_inputs=inputs,
    )
    rate = cfg.live_rate  # the sensor's data sent at this multiple of its rate
    events = [
        dataclasses.replace(ev, due_s=ev.due_s / rate)
        for ev in acquisition(plat, cfg.pairs, cfg.strip_lines, cfg.nav_rate_hz)
    ]
    strips = StripMessages(plat, cfg.strip_lines)
    raw = SerializedStrips(strips)
    raw_pair_mb = 2 * cfg.lines * cfg.detectors * 2 / 2**20
    sensor_s = (cfg.pairs + plat.lag_scenes) * plat.scene_s / rate  # wall time of the data
    res: dict[str, Any] = {
        "pairs": cfg.pairs,
        "strip_lines": cfg.strip_lines,
        "strip_mb": cfg.strip_lines * cfg.detectors * 2 / 2**20,
        "strips_per_s_per_view": rate * LINE_RATE_HZ / cfg.strip_lines,
        "input_mb_s": rate * 2 * LINE_RATE_HZ * cfg.detectors * 2 / 2**20,
        "live_rate": rate,
        "scene_s": plat.scene_s / rate,
        "sensor_s": sensor_s,
        "camera_pitch_deg": math.degrees(plat.theta),
        "node_check_fields": cfg.check_fields,
        "pairs_ahead": cfg.pairs_ahead,
        "paced": cfg.paced,
        "shm": cfg.shm,
        "fast_repair": cfg.fast_repair and not cfg.shm and fast_dds(),
        "latency_limit_s": cfg.latency_limit_s,
        "node_params": extra,
        "error": None,
    }
    log(
        f"live: {cfg.pairs} pairs of {cfg.lines} x {cfg.detectors} uint16, {cfg.strip_lines}-line "
        f"strips, {sensor_s:.2f} s of sensor data at {res['input_mb_s']:.0f} MB/s, "
        f"{'paced by the node' if cfg.paced else 'open-loop'}"
        f"{', shared-memory profile' if cfg.shm else ''}"
        f"{', writers heartbeat 100 ms' if cfg.fast_repair and not cfg.shm else ''}"
    )
    node = NodeProcess(pfile, env, workdir / "node.log")
    mon = RssMonitor(node.proc.pid, kill_above_mb=cfg.kill_above_mb)
    spy = None
    ctx = Context()
    rclpy.init(context=ctx)
    rnode = rclpy.create_node("parproj_bench", context=ctx)
    obs = _Observer()
    strip_qos = QoSProfile(
        depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST
    )
    pubs = {v: rnode.create_publisher(Image, contract.strip_topic(v), strip_qos) for v in VIEWS}
    nav_pub = rnode.create_publisher(
        Odometry,
        contract.NAVIGATION,
        QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE),
    )
    pair_sub = rnode.create_subscription(
        StereoPair,
        contract.STEREO_PAIR,
        obs.on_pair,
        QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE),
    )
    rnode.create_subscription(DiagnosticArray, contract.DIAGNOSTICS, obs.on_diag, 100)
    tiles = _TileObserver()
    for name in tile_topics:
        cls = get_message_class(contract.topic(name).msgtype)
        if cls is None:  # its figures then say 0 tiles; the log says why
            log(f"live: no message class for {contract.topic(name).msgtype}: {name} not read")
            continue
        rnode.create_subscription(
            cls,
            name,
            # (message, info): the info's source timestamp is when the node published it
            functools.partial(tiles.on_tile, name),
            QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE),
        )
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(rnode)
    spinning = threading.Event()
    spinning.set()

    def spin_loop() -> None:
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.05)

    spin = threading.Thread(target=spin_loop, name="bench_spin", daemon=True)
    spin.start()
    sent_strips = 0
    strip_sent: dict[tuple[int, int, int], float] = {}  # (view, scene, row0) -> sent, s
    render_pid: int | None = None
    cpu0: dict[str, float | None] = {}
    cpu1: dict[str, float | None] = {}
    publish_errors = 0
    sent_nav = 0
    ack_wait = 0.0
    t_sent = math.nan
    last_sent: dict[int, float] = {}
    throttled = 0.0
    lag_max = 0.0
    start = math.nan

    counted_seen: list[float] = [-1.0, time.time()]  # strips the node counted, and since when

    def node_idle() -> bool:
        """Whether the node is idle: every strip counted, queue empty, no CPU.

        Every strip sent, or none more for 3 s (the others were lost on the way).
        """
        with obs.lock:
            got = int(obs.summary.get("strips", -1)) + int(obs.summary.get("strips_rejected", 0))
            if got != counted_seen[0]:
                counted_seen[:] = [got, time.time()]
            counted = (
                (got >= sent_strips or time.time() - counted_seen[1] > 3.0)
                and obs.summary.get("queue") == "0"
                and time.time() - obs.summary_t < 1.5
            )
        rate = mon.cpu_rate(5.0)
        return counted and rate is not None and rate < 0.1

    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            if node.proc.poll() is not None:
                raise BenchAbortError("node exited at start:\n" + node.output()[-2000:])
            ready = all(p.get_subscription_count() > 0 for p in pubs.values())
            ready &= nav_pub.get_subscription_count() > 0 and bool(obs.summary)
            ready &= pair_sub.get_publisher_count() > 0
            if ready:
                break
            time.sleep(0.05)
        else:
            raise BenchAbortError("node not discovered within 60 s")
        time.sleep(1.0)
        res["node_base_rss_mb"] = mon.rss_mb
        render_pid = child_render_pid(node.proc.pid)
        cpu0 = {
            "node": proc_cpu_s(node.proc.pid),
            "render": proc_cpu_s(render_pid) if render_pid else None,
            "bench": time.process_time(),
        }
        if py_spy:
            spy = subprocess.Popen(
                [
                    py_spy,
                    "record",
                    "--pid",
                    str(node.proc.pid),
                    "--format",
                    "raw",
                    "--rate",
                    "20",
                    "--threads",
                    "-o",
                    str(workdir / "node_py_spy.txt"),
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            time.sleep(1.0)

        def wait_until(ok: Callable[[], bool], why: str, idle_s: float | None = None) -> float:
            """Sleep until ok(); abort on a dead node or a stall; the time waited, s.

            With ``idle_s``, also abort when no pair came for that long while the node was idle.
            """
            if ok():
                return 0.0
            t = time.time()
            last = (len(obs.pairs), t)
            while not ok():
                if node.proc.poll() is not None:
                    raise BenchAbortError(mon.killed or f"node exited while {why}")
                if mem_available_mb() < 0.5 * cfg.min_available_mb:
                    raise BenchAbortError(f"machine memory nearly exhausted while {why}")
                quiet = time.time() - last[1]
                if len(obs.pairs) != last[0]:
                    last = (len(obs.pairs), time.time())
                elif quiet > cfg.stall_s:
                    raise BenchAbortError(f"no pair for {cfg.stall_s:.0f} s while {why}")
                elif idle_s is not None and quiet > idle_s and node_idle():
                    raise BenchAbortError(
                        f"node idle with {len(obs.pairs)} of {cfg.pairs} pairs while {why}"
                    )
                time.sleep(0.01)
            return time.time() - t

        def pairs_at_least(n: int) -> Callable[[], bool]:
            return lambda: len(obs.pairs) >= n

        def memory_ok() -> bool:
            return mon.rss_mb <= cfg.rss_cap_mb and mem_available_mb() >= cfg.min_available_mb

        start = time.time()
        offset = 0.0
        slot_seen = -1
        unacked = [0, 0]
        for ev in events:
            due = start + ev.due_s + offset
            w = 0.0
            if cfg.paced and ev.kind == "strip" and ev.slot > slot_seen:
                slot_seen = ev.slot
                need = ev.slot - 1 - cfg.pairs_ahead
                w += wait_until(pairs_at_least(need), "waiting for pairs")
            if cfg.paced and ev.kind == "strip" and not memory_ok():
                w += wait_until(memory_ok, "waiting for memory")
            if not cfg.paced and (node.proc.poll() is not None or mon.killed):
                raise BenchAbortError(mon.killed or "node exited while sending")
            if w > 0:
                late = max(0.0, time.time() - due)
                throttled += w
                offset += min(w, late)
                due = start + ev.due_s + offset
            now = time.time()
            if due > now:
                time.sleep(due - now)
            else:
                lag_max = max(lag_max, now - due)
            if ev.kind == "nav":
                nav_pub.publish(nav_message(plat, ev.t_s))
                sent_nav += 1
            else:
                pub = pubs[VIEWS[ev.view]]
                try:
                    pub.publish(raw.get(ev))
                except Exception:  # rclpy RCLError: an overloaded writer (ROS2_WHEELS.md)
                    publish_errors += 1
                sent_strips += 1
                # Paced only: a bounded in-flight window (a sensor does not wait for acks).
                unacked[ev.view] += 1
                if cfg.paced and unacked[ev.view] >= cfg.inflight_strips:
                    t_ack = time.time()
                    if not pub.wait_for_all_acked(Duration(seconds=cfg.stall_s)):
                        raise BenchAbortError(f"strips not acknowledged in {cfg.stall_s:.0f} s")
                    ack_wait += time.time() - t_ack
                    unacked[ev.view] = 0
                strip_sent[(ev.view, ev.scene, ev.row0)] = time.time()
                if ev.last_of_pair:
                    last_sent[ev.scene] = time.time()
        t_sent = time.time()
        log(f"live: all sent after {t_sent - start:.1f} s (held back {throttled:.1f} s)")
        if cfg.paced:
            wait_until(
                lambda: len(obs.pairs) >= cfg.pairs, "waiting for the last pairs", idle_s=20.0
            )
        else:
            # Open loop: pairs the node shed (memory_budget_mb) never come; stop when every
            # pair is accounted for, or when the node has taken everything and gone idle.
            def accounted() -> bool:
                # Pairs shed among the bench's own (the node may shed the pair of the extra
                # fore scene too: it is no pair of the bench's).
                with obs.lock:
                    shed = {
                        int(m.group(1))
                        for text in obs.issues
                        if (m := re.search(r"overload: pair (\d+) ", text))
                    }
                return len(obs.pairs) + len({k for k in shed if k < cfg.pairs}) >= cfg.pairs

            idle_since: list[float] = []

            def finished() -> bool:
                if accounted():
                    return True
                if node_idle():
                    idle_since.append(time.time())
                    return time.time() - idle_since[0] > 3.0
                idle_since.clear()
                return False

            wait_until(finished, "waiting for the last pairs")
    except BenchAbortError as err:
        res["error"] = str(err)
        log(f"live: aborted: {err}")
    finally:
        # A summary counted after the last strip (the node publishes one per second).
        t_done = time.time()
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and node.proc.poll() is None:
            with obs.lock:
                fresh = obs.summary_t > t_done + 0.05
            if fresh and node_idle():
                break
            time.sleep(0.05)
        res["node_peak_rss_mb"] = max(mon.hwm_mb, proc_status(node.proc.pid).get("VmHWM", 0.0))
        cpu1 = {
            "node": proc_cpu_s(node.proc.pid),
            "render": proc_cpu_s(render_pid) if render_pid else None,
            "bench": time.process_time(),
        }
        if spy is not None:
            spy.send_signal(signal.SIGINT)
            try:
                spy.wait(30)
            except subprocess.TimeoutExpired:
                spy.kill()
        mon.stop()
        code = node.stop(timeout=120.0)
        spinning.clear()
        spin.join(timeout=5)
        executor.shutdown()
        rnode.destroy_node()
        rclpy.shutdown(context=ctx)
    res["node_exit_code"] = code
    if mon.killed and not res["error"]:
        res["error"] = mon.killed
    # Figures.
    ids = {f"{VIEWS[0]}_{k:04d}+{VIEWS[1]}_{k:04d}": k for k in range(cfg.pairs)}
    rx = {ids[p]: t for p, t in obs.pairs.items() if p in ids}
    published: dict[int, float] = {}
    for m in _LOG_PAIR.finditer(node.output()):
        if m.group(2) in ids:
            published[ids[m.group(2)]] = float(m.group(1))
    lat = [rx[k] - last_sent[k] for k in sorted(rx) if k in last_sent]
    lat_pub = [published[k] - last_sent[k] for k in sorted(published) if k in last_sent]
    got = int(obs.summary.get("strips", 0)) + int(obs.summary.get("strips_rejected", 0))
    res.update(
        {
            "pairs_received": len(rx),
            "output_size": next(iter(obs.pair_sizes.values()), None),
            "streamed": bool(obs.streamed_pairs),
            "pairs_streamed": len(obs.streamed_pairs),
            "strips_sent": sent_strips,
            "publish_errors": publish_errors,
            "pairs_shed": int(obs.summary.get("pairs_shed", 0)),
            "scenes_shed": int(obs.summary.get("scenes_shed", 0)),
            "strips_shed": int(obs.summary.get("strips_shed", 0)),
            "nav_sent": sent_nav,
            "strips_received_by_node": got,
            "dropped_strips": sent_strips - got if obs.summary else None,
            "node_queue_max": obs.queue_max,
            # The render process's counts (blocks, drafts reduced there, rendered in the worker).
            "node_render": {
                k: int(obs.summary[k])
                for k in ("render_blocks", "render_drafts", "render_fallbacks")
                if k in obs.summary
            },
            "node_issues": obs.issues[:20],
            "held_back_s": throttled,
            "publisher_max_lag_s": lag_max,
            "publisher_ack_wait_s": ack_wait,
            "publisher_send_s": t_sent - start if math.isfinite(t_sent) else None,
        }
    )
    if rx and len(rx) == cfg.pairs and math.isfinite(start):
        wall = max(rx.values()) - start
        res["wall_s"] = wall
        res["end_to_end_realtime_factor"] = sensor_s / wall
    else:
        res["wall_s"] = None
        res["end_to_end_realtime_factor"] = None
    ordered = [rx[k] for k in sorted(rx)]
    res["sustained_realtime_factor"] = (
        (len(ordered) - 1) * plat.scene_s / rate / (ordered[-1] - ordered[0])
        if len(ordered) >= 2 and ordered[-1] > ordered[0]
        else None
    )
    # The real-time factor: sensor time between the first and the last pair's last strip (as
    # sent) over the time between their StereoPairs; every pair must have come. A node that
    # keeps up scores 1 (within timing jitter), whatever its constant latency.
    ks = sorted(k for k in rx if k in last_sent)
    res["realtime_factor"] = (
        (last_sent[ks[-1]] - last_sent[ks[0]]) / (rx[ks[-1]] - rx[ks[0]])
        if len(rx) == cfg.pairs and len(ks) >= 2 and rx[ks[-1]] > rx[ks[0]]
        else None
    )
    res["latency_s"] = latency_stats(lat)
    res["latency_published_s"] = latency_stats(lat_pub)
    # CPU per sensor second, each process, from before the first strip to the node idle.
    res["render_process_found"] = render_pid is not None
    res["cpu_s"] = {
        k: (cpu1[k] or 0.0) - (cpu0[k] or 0.0)
        if cpu0.get(k) is not None and cpu1.get(k) is not None
        else None
        for k in ("node", "render", "bench")
    }
    res["cpu_per_sensor_s"] = {
        k: v / sensor_s if v is not None else None for k, v in res["cpu_s"].items()
    }
    # Per topic, and per quick-look level of a topic whose tiles say theirs ("...@4").
    res["tiles"] = {}
    res["tiles_received"] = {}  # the same from the bench's reception (its own load in it)
    for name in tile_topics:
        res["tiles_received"][name] = tile_figures(
            tiles.of(name, "received"), plat, cfg.strip_lines, strip_sent, t_sent
        )
        came = tiles.of(name)
        res["tiles"][name] = tile_figures(came, plat, cfg.strip_lines, strip_sent, t_sent)
        for level in sorted({p[p.index("@") :] for _, p, _ in came if "@" in p}):
            mine = [g for g in came if g[1].endswith(level)]
            res["tiles"][name + level] = tile_figures(
                mine, plat, cfg.strip_lines, strip_sent, t_sent
            )
    # Memory per pair: the peak between consecutive pairs' receptions.
    peaks: list[float] = []
    prev = start
    for k in sorted(rx):
        p = mon.peak_between(prev, rx[k])
        if p is not None:
            peaks.append(p)
        prev = rx[k]
    base = res.get("node_base_rss_mb") or 0.0
    peak = res.get("node_peak_rss_mb") or 0.0
    steady = peaks[1:] if len(peaks) >= 3 else peaks
    res["rss"] = {
        "base_mb": base,
        "peak_mb": peak,
        "raw_pair_mb": raw_pair_mb,
        "per_pair_peak_mb": [round(p, 1) for p in peaks],
        "slope_mb_per_pair": _slope(steady),
        "peak_over_pair": peak / raw_pair_mb if peak else None,
        "peak_above_base_over_pair": (peak - base) / raw_pair_mb if peak else None,
        "samples": len(mon.samples),
    }
    if py_spy and (workdir / "node_py_spy.txt").exists():
        res["py_spy"] = summarize_collapsed(workdir / "node_py_spy.txt")
    return res


def child_render_pid(pid: int) -> int | None:
    """The node's render process, or None (``streaming`` off, or not started yet).

    Its child started by multiprocessing's spawn (not the resource tracker).
    """
    kids: list[int] = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            kids += [int(c) for c in (task / "children").read_text().split()]
    except OSError:
        return None
    for kid in kids:
        try:
            cmd = Path(f"/proc/{kid}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmd:
            return kid
    return None


#: A DSM tile's ground: (x_min, x_max, y_min, y_max), metres in the object frame.
Extent = tuple[float, float, float, float]


def tile_extent(msg: Any) -> Extent | None:
    """The ground of a DSM tile message's cells with a height (all its cells if none has).

    Cell (row, col) is centred at (x0 + col cell_size, y0 - row cell_size) (ElevationGrid);
    None for a message without ``x0``, ``y0``, ``cell_size`` and a 32FC1 ``heights`` image.
    """
    try:
        x0, y0, cell = float(msg.x0), float(msg.y0), float(msg.cell_size)
        img = msg.heights
        h, w, step = int(img.height), int(img.width), int(img.step)
    except AttributeError:
        return None
    if h == 0 or w == 0 or img.encoding != "32FC1" or step % 4:
        return None
    z = np.frombuffer(bytes(img.data), dtype=np.float32).reshape(h, step // 4)[:, :w]
    has = np.isfinite(z)
    rows, cols = np.nonzero(has.any(axis=1))[0], np.nonzero(has.any(axis=0))[0]
    r0, r1 = (int(rows[0]), int(rows[-1])) if rows.size else (0, h - 1)
    c0, c1 = (int(cols[0]), int(cols[-1])) if cols.size else (0, w - 1)
    return (x0 + c0 * cell, x0 + c1 * cell, y0 - r1 * cell, y0 - r0 * cell)


def tile_last_strip(plat: Platform, strip_lines: int, extent: Extent) -> tuple[int, int, int]:
    """The strip (view, scene, first row) that completes a tile's ground, of the acquisition.

    The ground (flat, Z = 0: the benchmark's) of the extent's corners is imaged last by one
    view at some line; the strip holding that line is the last one the tile can need (its
    disparity margin aside: a few lines more at most, one strip in the worst case).
    """
    x_lo, x_hi, y_lo, y_hi = extent
    pts = np.array([[x, y, 0.0] for x in (x_lo, x_hi) for y in (y_lo, y_hi)])
    best: tuple[float, int, int, int] | None = None
    lp = plat.camera.line_period
    for view in (0, 1):
        line = max(0, math.ceil(float(plat.model(view, 0).project(pts)[:, 0].max())))
        scene, row = divmod(line, plat.lines)
        row0 = row // strip_lines * strip_lines
        due = plat.scene_start_s(view, scene) + min(row0 + strip_lines, plat.lines) * lp
        if best is None or due > best[0]:
            best = (due, view, scene, row0)
    assert best is not None
    return best[1], best[2], best[3]


@dataclass
class _TileObserver:
    """DSM tiles the bench process receives: (topic, time received, pair id, ground)."""

    got: list[tuple[str, float, float, str, Extent | None]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_tile(self, topic: str, msg: Any, info: Any) -> None:
        """A tile: its publication (the writer's source timestamp) and reception times, s."""
        now = time.time()
        src = int((info or {}).get("source_timestamp", 0) or 0)
        published = src / 1e9 if src > 0 else now
        extent = tile_extent(msg)
        with self.lock:
            self.got.append((topic, published, now, str(getattr(msg, "pair_id", "")), extent))

    def of(self, topic: str, when: str = "published") -> list[tuple[float, str, Extent | None]]:
        """(time, pair id, ground) of ``topic``'s tiles: ``when`` "published" or "received"."""
        with self.lock:
            return [
                (pub if when == "published" else rx, pid, ext)
                for name, pub, rx, pid, ext in self.got
                if name == topic
            ]


def tile_figures(
    got: list[tuple[float, str, Extent | None]],
    plat: Platform,
    strip_lines: int,
    strip_sent: dict[tuple[int, int, int], float],
    all_sent: float,
) -> dict[str, Any]:
    """Latency and real-time factor of the DSM tiles of one topic.

    ``got``: (time, pair id, ground) per tile; the time is the tile's publication by the node
    (the DDS source timestamp, as issue 26 asks: "published within 2 s of its last strip"),
    or its reception by the bench (``tiles_received``: the bench's own load in it). Each
    tile's latency: from the publication of the strip that completes its ground
    (:func:`tile_last_strip`) to that time. The real-time factor: the sensor time between
    the first and the last of those strips over the time between the first and the last tile
    (as the node's real-time factor: a node that keeps up scores 1 whatever its constant
    latency). ``during_pass``: tiles before the last strip was sent. ``unplaced``: tiles
    without a ground or whose strip was never sent.
    """
    lat: list[float] = []
    spans: list[tuple[float, float]] = []
    unplaced = 0
    for rx, _, extent in got:
        sent = None
        if extent is not None:
            sent = strip_sent.get(tile_last_strip(plat, strip_lines, extent))
        if sent is None:
            unplaced += 1
            continue
        lat.append(rx - sent)
        spans.append((sent, rx))
    s = [a for a, _ in spans]
    r = [b for _, b in spans]
    factor = (
        (max(s) - min(s)) / (max(r) - min(r))
        if len(spans) >= 2 and max(r) > min(r) and max(s) > min(s)
        else None
    )
    # pair_id "<pair>#<index>/<count>[@<factor>]" (core/results.HeightTile.name).
    counts: dict[str, int] = {}
    for _, name, _ in got:
        m = re.fullmatch(r"(.*)#\d+/(\d+)(@\d+)?", name)
        if m:
            counts[m.group(1)] = int(m.group(2))
    return {
        "tiles": len(got),
        "pairs": len({name.split("#")[0] for _, name, _ in got}),
        "tiles_announced": sum(counts.values()) if counts else None,
        "unplaced": unplaced,
        "during_pass": sum(1 for rx, _, _ in got if math.isfinite(all_sent) and rx < all_sent),
        "latency_s": latency_stats(lat),
        "realtime_factor": factor,
    }


#: Where the pass-through node republishes each view's strips.
PASSTHROUGH_SUFFIX = "image_strip_passthrough"


def passthrough_main() -> None:
    """The pass-through node: receives the strips and republishes them, nothing else.

    The transport's own ceiling for the node: the same input QoS as parproj_node's (made
    reliable, as the bench makes the node's), the same Image messages out (reliable, depth 10,
    as the node's outputs) on ``<view>/image_strip_passthrough``. Prints ``{"strips": n}`` at
    SIGINT.
    """
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("parproj_bench_passthrough")
    count = [0]
    in_qos = QoSProfile(
        depth=200, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST
    )
    out_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    for v in VIEWS:
        pub = node.create_publisher(Image, f"{v}/{PASSTHROUGH_SUFFIX}", out_qos)

        def on_strip(msg: Any, pub: Any = pub) -> None:
            count[0] += 1
            try:
                pub.publish(msg)
            except Exception:  # an overloaded writer: the strip is lost (counted by the bench)
                pass

        node.create_subscription(Image, contract.strip_topic(v), on_strip, in_qos)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    while not stop.is_set():
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps({"strips": count[0]}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def bench_transport(
    cfg: BenchConfig,
    workdir: Path,
    *,
    scenes: int = 2,
    domain_id: int | None = None,
    log: Log = log_stderr,
) -> dict[str, Any]:
    """The transport ceiling: a pass-through node fed open-loop at each of ``passthrough_rates``.

    ``scenes`` scenes per view of the live run's strips, published at their sensor times (divided
    by the rate multiple) without waiting for anything, into a node process that republishes
    them (:func:`passthrough_main`); this process receives them back. Per rate: strips sent,
    received back and lost, latency (publish -> received back) p50 / p95 / max, the pass-through
    node's CPU share, and the real-time factor (sensor span / wall span of the strips received
    back, times the multiple).
    """
    workdir.mkdir(parents=True, exist_ok=True)
    return {
        "rates": [
            _passthrough_at(cfg, workdir, rate, scenes=scenes, domain_id=domain_id, log=log)
            for rate in cfg.passthrough_rates
        ],
        "shm": cfg.shm,
        "fast_repair": cfg.fast_repair and not cfg.shm and fast_dds(),
    }


def _passthrough_at(
    cfg: BenchConfig,
    workdir: Path,
    rate: float,
    *,
    scenes: int,
    domain_id: int | None,
    log: Log,
) -> dict[str, Any]:
    """One open-loop run of the pass-through node at ``rate`` x the sensor rate."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from tools.harness import proc_cpu_s

    plat = make_platform(cfg.lines, cfg.detectors)
    env = join_ros_domain(
        domain_id,
        workdir / "ros_log",
        check_fields=cfg.check_fields,
        shm=cfg.shm,
        fast_repair=cfg.fast_repair,
    )
    strips = StripMessages(plat, cfg.strip_lines)
    raw = SerializedStrips(strips)
    events = [e for e in acquisition(plat, scenes, cfg.strip_lines, 1.0) if e.kind == "strip"]
    # The node runs this module: the repository goes on its path (tools/ is not installed).
    path = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.bench.dds", "passthrough"],
        env={**env, "PYTHONPATH": path},
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    ctx = Context()
    rclpy.init(context=ctx)
    rnode = rclpy.create_node("parproj_bench_source", context=ctx)
    qos = QoSProfile(
        depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST
    )
    pubs = [rnode.create_publisher(Image, contract.strip_topic(v), qos) for v in VIEWS]
    sent: dict[tuple[int, int], float] = {}
    back: dict[tuple[int, int], float] = {}
    lock = threading.Lock()

    def on_back(msg: Any, view: int) -> None:
        now = time.time()
        key = (view, msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        with lock:
            back[key] = now

    subs = [
        rnode.create_subscription(
            Image,
            f"{v}/{PASSTHROUGH_SUFFIX}",
            lambda m, i=i: on_back(m, i),
            QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE),
        )
        for i, v in enumerate(VIEWS)
    ]
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(rnode)
    spinning = threading.Event()
    spinning.set()

    def spin_loop() -> None:
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.05)

    spin = threading.Thread(target=spin_loop, name="bench_passthrough_spin", daemon=True)
    res: dict[str, Any] = {"rate": rate, "strips_sent": 0, "publish_errors": 0, "error": None}
    cpu0 = cpu1 = None
    t0 = t1 = math.nan
    try:
        spin.start()
        deadline = time.monotonic() + 60.0
        while any(p.get_subscription_count() == 0 for p in pubs) or any(
            s.get_publisher_count() == 0 for s in subs
        ):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise BenchAbortError("pass-through node not discovered within 60 s")
            time.sleep(0.05)
        time.sleep(0.5)
        cpu0 = proc_cpu_s(proc.pid)
        t0 = time.time()
        for ev in events:
            due = t0 + ev.due_s / rate
            now = time.time()
            if due > now:
                time.sleep(due - now)
            try:
                pubs[ev.view].publish(raw.get(ev))
            except Exception:
                res["publish_errors"] += 1
            sent[(ev.view, ev.stamp_ns)] = time.time()
            res["strips_sent"] += 1
        t1 = time.time()
        # Until everything came back, or nothing came for a second.
        last = (0, time.monotonic())
        while len(back) < len(sent) and time.monotonic() - last[1] < 1.0:
            if len(back) != last[0]:
                last = (len(back), time.monotonic())
            time.sleep(0.02)
        cpu1 = proc_cpu_s(proc.pid)
    except BenchAbortError as err:
        res["error"] = str(err)
    finally:
        spinning.clear()
        spin.join(timeout=5)
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        executor.shutdown()
        rnode.destroy_node()
        rclpy.shutdown(context=ctx)
    try:
        got = int(json.loads(out.strip().splitlines()[-1])["strips"])
    except (ValueError, IndexError, KeyError):
        got = None
    lat = [back[k] - sent[k] for k in sent if k in back]
    times = sorted(back.values())
    span_sensor = (events[-1].due_s - events[0].due_s) / rate if events else 0.0
    n = res["strips_sent"]
    res.update(
        {
            "strips_received_by_passthrough": got,
            "strips_back": len(back),
            "lost": n - len(back),
            "loss": (n - len(back)) / n if n else None,
            "latency_p50_s": float(np.percentile(lat, 50)) if lat else None,
            "latency_p95_s": float(np.percentile(lat, 95)) if lat else None,
            "latency_max_s": float(np.max(lat)) if lat else None,
            "send_s": t1 - t0,
            "mb_per_s": len(back) * cfg.strip_lines * cfg.detectors * 2 / 2**20 / span_sensor
            if span_sensor > 0 and len(back) == n
            else None,
            "passthrough_cpu": (cpu1 - cpu0) / (t1 - t0)
            if cpu0 is not None and cpu1 is not None and t1 > t0
            else None,
            # Sustained factor of what came back (x the multiple): 1.0 x rate when it keeps up.
            "realtime_factor": rate * span_sensor / (times[-1] - times[0])
            if len(times) == n and n >= 2 and times[-1] > times[0]
            else None,
        }
    )
    log(
        f"pass-through at {rate:g} x the sensor rate: {len(back)}/{n} strips back, latency p50 "
        f"{_ms(res['latency_p50_s'])} p95 {_ms(res['latency_p95_s'])} ms, node CPU "
        f"{_pct(res['passthrough_cpu'])}"
    )
    return res


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{1000 * v:.0f}"


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.0f} %"


def summarize_collapsed(path: Path, top: int = 25) -> dict[str, Any]:
    """Summary of py-spy's raw (collapsed) stacks: per thread, the functions by inclusive share.

    Returns ``{thread: {"samples": n, "top": [[function, share], ...]}}`` with shares of that
    thread's samples in [0, 1].
    """
    threads: dict[str, dict[str, Any]] = {}
    for line in path.read_text(errors="replace").splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        n = int(count)
        frames = stack.split(";")
        name = frames[0]
        th = threads.setdefault(name, {"samples": 0, "funcs": {}})
        th["samples"] += n
        for f in dict.fromkeys(re.sub(r" \(.*?:\d+\)$", "", f) for f in frames[1:]):
            th["funcs"][f] = th["funcs"].get(f, 0) + n
    out = {}
    for name, th in sorted(threads.items(), key=lambda kv: -kv[1]["samples"]):
        funcs = sorted(th["funcs"].items(), key=lambda kv: -kv[1])[:top]
        out[name] = {
            "samples": th["samples"],
            "top": [[f, round(c / th["samples"], 3)] for f, c in funcs],
        }
    return out


if __name__ == "__main__":
    passthrough_main()
