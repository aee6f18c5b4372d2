"""Overload through the real node over real DDS (issue 11): whole pairs shed, counts add up.

parproj_node runs in its own process with a small ``memory_budget_mb``; the synthetic fore/aft
acquisition of the benchmark (parproj_ros.sim.synthetic, 2048 x 2048 scenes, whole-image pairs,
no tie points) is published open-loop by a sensor process of its own (overload_sender.py, with
config/fastdds_fast_repair.xml): 2 pairs at the sensor rate (warm-up), 10 at 12 times the
sensor rate (the overload: several times what the node sustains here, on the shared machine),
then 6 at half the sensor rate (the load drops). 14-16 s. Checked:

- it shed whole pairs, each reported by a WARN on /diagnostics naming the scene and the reason,
  and counted in the 1 Hz summary (pairs_shed, scenes_shed, strips_shed);
- every pair it published is whole and correct: both scenes of the same index and complete,
  both normalized images whole (or every column block when streamed), y-parallax within the
  tolerance of the other tests;
- the counts add up: strips sent = strips counted by the node; every pair either published or
  shed, never both; shed strips = the strips of the shed scenes;
- it catches up: the last 3 pairs, sent after the load dropped, are all published;
- the resident memory (VmHWM, sampled every 50 ms and read at the end) stays under the budget.
"""

from __future__ import annotations

import json
import os
import queue
import re
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest

from parproj_ros.sim.synthetic import VIEWS, make_platform

pytestmark = pytest.mark.ros  # live node over DDS

LINES, DETECTORS, STRIP_LINES = 2048, 2048, 256
PAIRS = 18
#: (first pair, rate x the sensor's) of each phase: a warm-up at the sensor rate (the node
#: learns its working set), the overload, then the load drops: the node must publish all of
#: the last phase's pairs.
PHASES = ((0, 1.0), (2, 12.0), (12, 0.5))
#: Pairs after the load drops that the node may still shed.
CATCH_UP_PAIRS = 3
#: Tight enough that the burst sheds (2-5 pairs in each of 11 runs, 2026-11-24), and above the
#: least budget that holds two overlapping pairs (consecutive pairs overlap in time: at any
#: rate the node holds two): start-up (about 97 MB) + 2 raw pairs (32 MB) + the working set,
#: at least 8 raw pairs for whole images (128 MB), with 5 % headroom: about 271 MB. 200 MB,
#: the first budget here, was below it: the node shed pairs at any rate and never caught up.
BUDGET_MB = 300.0
#: y-parallax tolerance of the pair checks elsewhere (tests/apps/test_import.py), px.
Y_PARALLAX_MAX_PX = 0.05


class _Seen:
    """What the test receives from the node."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.pairs: dict[str, Any] = {}
        self.blocks: dict[tuple[str, str], list[Any]] = defaultdict(list)
        self.scenes: dict[str, Any] = {}
        self.images: dict[tuple[str, int], tuple[int, int, int, int]] = {}
        self.summary: dict[str, str] = {}
        self.summary_t = 0.0
        self.statuses: list[tuple[str, str]] = []

    def on_pair(self, msg: Any) -> None:
        with self.lock:
            self.pairs[msg.pair_id] = msg

    def on_block(self, msg: Any) -> None:
        with self.lock:
            self.blocks[(msg.pair_id, msg.side)].append(
                (int(msg.col0), int(msg.image.width), int(msg.image.height), bool(msg.last))
            )

    def on_image(self, msg: Any, side: str) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self.lock:
            self.images[(side, stamp)] = (msg.width, msg.height, msg.step, len(msg.data))

    def on_scene(self, msg: Any) -> None:
        with self.lock:
            self.scenes[msg.scene_id] = int(msg.lines)

    def on_diag(self, msg: Any) -> None:
        with self.lock:
            for st in msg.status:
                if st.name == "parproj_node: summary":
                    self.summary = {kv.key: kv.value for kv in st.values}
                    self.summary_t = time.time()
                else:
                    self.statuses.append((st.name, st.message))


@pytest.fixture(scope="module")
def overload(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The run (once for the module): what the node published and reported, its VmHWM."""
    tmp_path = tmp_path_factory.mktemp("overload")
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from parproj_msgs.msg import NormalizedBlock, ParallelProjection, StereoPair
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from parproj_ros.ros.inputs import node_parameters
    from parproj_ros.ros.live import NodeProcess, node_params_yaml, ros_environment
    from tools.harness import FAST_REPAIR_PROFILE, ROOT, RssMonitor, proc_status

    plat = make_platform(LINES, DETECTORS)
    env = ros_environment(None, tmp_path / "ros_log")
    for key in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "ROS_LOG_DIR"):
        os.environ[key] = env[key]
    inputs = ["/navigation"] + [f"/{v}/image_strip" for v in VIEWS]
    pfile = node_params_yaml(
        node_parameters(
            plat.views,
            scene_lines=LINES,
            scene_timeout=0.0,
            z_avg=0.0,
            height_range=500.0,
            tie_points=False,  # image matching (seconds per pair) is not what is tested here
            # Whole images: under overload navigation waits behind the strips and the pipeline
            # falls back to them anyway; so the warm-up learns the working set of the burst.
            streaming=False,
            # What a memory-bounded deployment sets: each whole image sent once, no preview
            # (Fast DDS keeps the last 10 messages of each output topic).
            stereo_pair_images=False,
            anaglyph=False,
            memory_budget_mb=BUDGET_MB,
            # No reserve touched at start (the default, two raw pairs and two line buffers per
            # view, adds about 65 MB here): the budget is sized on a 90 MB start-up.
            prefault_mb=0.0,
        ),
        tmp_path / "params.yaml",
        reliable_inputs=inputs,
    )
    # The node's writers heartbeat every 100 ms too: its outputs keep their last 10 samples, and
    # in the burst a datagram lost on UDP and repaired only at the default 3 s heartbeat can be
    # overwritten by newer ones before the repair (most likely what CI of c642a5b saw: a
    # StereoPair received, its scene's ParallelProjection never).
    node_env = dict(env, FASTDDS_DEFAULT_PROFILES_FILE=str(FAST_REPAIR_PROFILE))
    node = NodeProcess(pfile, node_env, tmp_path / "node.log")
    mon = RssMonitor(node.proc.pid, period_s=0.05)
    ctx = Context()
    rclpy.init(context=ctx)
    rnode = rclpy.create_node("overload_test", context=ctx)
    seen = _Seen()
    rel = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    pair_sub = rnode.create_subscription(StereoPair, "stereo_pair", seen.on_pair, rel)
    for side in ("left", "right"):
        rnode.create_subscription(
            NormalizedBlock, f"{side}/normalized_block", seen.on_block, QoSProfile(
                depth=200, reliability=ReliabilityPolicy.RELIABLE
            )
        )  # fmt: skip
    rnode.create_subscription(ParallelProjection, "parallel_projection", seen.on_scene, rel)
    for side in ("left", "right"):
        rnode.create_subscription(
            Image,
            f"{side}/image_normalized",
            lambda m, side=side: seen.on_image(m, side),
            QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE),
        )
    rnode.create_subscription(DiagnosticArray, "/diagnostics", seen.on_diag, 200)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(rnode)
    spinning = threading.Event()
    spinning.set()

    def spin() -> None:
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.05)

    th = threading.Thread(target=spin, daemon=True)
    th.start()
    spec = {
        "phases": PHASES,
        "pairs": PAIRS,
        "lines": LINES,
        "detectors": DETECTORS,
        "strip_lines": STRIP_LINES,
        "ack_window": 8,
    }
    sender_env = dict(env, RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
    # The sensor's writers heartbeat every 100 ms, not every 3 s: a datagram lost in the burst
    # otherwise stalls a reader for up to 3 s, and the sensor's own acknowledgement waits with
    # it (README, Overload). Without it (4 runs, 2026-11-24): waits of 1.1-1.4 s in 2 runs, 7-9
    # pairs shed (2-5 with it), the catch-up failed once.
    sender_env["FASTDDS_DEFAULT_PROFILES_FILE"] = str(FAST_REPAIR_PROFILE)
    sender_env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    with (tmp_path / "sender.err").open("w") as err_file:
        sender = subprocess.Popen(
            [
                sys.executable,
                str(Path(__file__).with_name("overload_sender.py")),
                json.dumps(spec),
            ],
            env=sender_env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=err_file,
            text=True,
        )
    assert sender.stdin is not None and sender.stdout is not None
    # The sender's lines, read in a thread: a sender that hangs fails the test, not hangs it.
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(
        target=lambda: [lines.put(x) for x in iter(sender.stdout.readline, "")] + [lines.put("")],
        daemon=True,
    ).start()

    def sender_line(timeout_s: float) -> str:
        try:
            return lines.get(timeout=timeout_s)
        except queue.Empty:
            pytest.fail(f"the sender said nothing within {timeout_s:.0f} s")

    sent: dict[str, Any] = {}
    try:
        line = sender_line(60.0)
        assert json.loads(line or "{}").get("ready"), line
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            assert node.proc.poll() is None, node.output()[-3000:]
            if pair_sub.get_publisher_count() > 0 and seen.summary:
                break
            time.sleep(0.05)
        else:
            pytest.fail("node not discovered within 30 s")
        sender.stdin.write("go\n")
        sender.stdin.flush()
        line = sender_line(120.0)  # when it has sent everything and all was acknowledged
        sent = json.loads(line or "{}")
        assert "strips" in sent, (line, sender.wait(timeout=10))
        sent_strips, sent_nav = int(sent["strips"]), int(sent["nav"])

        def settled() -> bool:
            with seen.lock:
                s = seen.summary
                fresh = seen.summary_t > time.time() - 1.2
                return (
                    fresh
                    and int(s.get("strips", 0)) >= sent_strips
                    and int(s.get("nav", 0)) >= sent_nav
                    and int(s.get("pairs", 0)) + int(s.get("pairs_shed", 0)) >= PAIRS
                    and s.get("queue") == "0"
                    and int(s.get("pairs_in_flight", 9)) <= 1
                    and s.get("busy_with", "x") == ""
                )

        deadline = time.monotonic() + 30.0
        while not settled() and time.monotonic() < deadline:
            assert node.proc.poll() is None, node.output()[-3000:]
            time.sleep(0.1)
        time.sleep(1.5)  # the last blocks and a summary after them
        hwm = max(mon.hwm_mb, proc_status(node.proc.pid).get("VmHWM", 0.0))
    finally:
        if sender.poll() is None:
            sender.kill()
        sender.wait(timeout=10)
        mon.stop()
        code = node.stop(timeout=60.0)
        spinning.clear()
        th.join(timeout=5)
        executor.shutdown()
        rnode.destroy_node()
        rclpy.shutdown(context=ctx)
    log = node.output()
    assert code == 0, log[-3000:]
    # Fast DDS reports a profile it cannot parse on stderr ("[XMLPARSER Error] ...") and runs
    # without it: the sensor's heartbeat would be the default 3 s.
    sender_err = (tmp_path / "sender.err").read_text()
    assert "XMLPARSER" not in sender_err, sender_err[-2000:]
    assert "XMLPARSER" not in log, log[-2000:]

    rss = [round(r) for _, r in mon.samples[:: max(1, len(mon.samples) // 60)]]
    print(
        f"\noverload: VmHWM {hwm:.0f} MB (budget {BUDGET_MB:.0f}); sender {sent}; RSS {rss}; "
        f"{seen.summary}"
    )
    return {"seen": seen, "hwm": hwm, "rss": rss, "sent_strips": sent_strips}


def shed_pairs(seen: Any) -> set[int]:
    """The pair numbers the node reported shed (``overload: pair N ...`` WARNs)."""
    found = (re.search(r"overload: pair (\d+) ", m) for _n, m in seen.statuses)
    return {int(f.group(1)) for f in found if f}


def published_pairs(seen: Any) -> set[int]:
    """The pair numbers of the StereoPairs received (``left_NNNN+right_NNNN``)."""
    found = (re.fullmatch(r"left_(\d{4})\+right_\d{4}", pid) for pid in seen.pairs)
    return {int(f.group(1)) for f in found if f}


def test_overload_sheds_whole_pairs_and_counts_add_up(
    overload: dict[str, Any],
) -> None:
    seen, sent_strips = overload["seen"], overload["sent_strips"]
    # Shedding happened, whole pairs, each reported with its reason.
    shed_warns = [(n, m) for n, m in seen.statuses if "overload: pair" in m]
    for _name, message in shed_warns:
        assert "memory_budget_mb" in message, message
    shed_groups = shed_pairs(seen)
    s = seen.summary
    assert int(s["pairs_shed"]) == len(shed_groups) >= 1, (s, shed_warns)

    # Every published pair: whole and correct.
    published: set[int] = set()
    for pid, sp in seen.pairs.items():
        m = re.fullmatch(r"left_(\d{4})\+right_(\d{4})", pid)
        assert m and m.group(1) == m.group(2), pid  # both scenes of the same index
        k = int(m.group(1))
        published.add(k)
        assert (
            seen.scenes.get(f"left_{k:04d}") == LINES
            and seen.scenes.get(f"right_{k:04d}") == LINES
        ), pid
        assert sp.y_parallax_points >= 20, pid
        assert abs(sp.y_parallax_max_px) < Y_PARALLAX_MAX_PX, (pid, sp.y_parallax_max_px)
        # The normalized images: whole (in the StereoPair, or as column blocks when streamed).
        stamp = sp.header.stamp.sec * 1_000_000_000 + sp.header.stamp.nanosec
        for side in ("left", "right"):
            if not sp.streamed:  # on <side>/image_normalized, stamped as the StereoPair
                w, h, step, size = seen.images[(side, stamp)]
                assert (w, h) == (sp.width, sp.height), (pid, side)
                assert size == step * h > 0, (pid, side)
                continue
            blocks = sorted(seen.blocks[(pid, side)])
            assert blocks, (pid, side)
            cols = 0
            for col0, width, height, _ in blocks:
                assert col0 == cols and height == sp.height, (pid, side, blocks)
                cols += width
            assert cols == sp.width and blocks[-1][3], (pid, side, cols, sp.width)

    # The counts add up.
    assert int(s["strips"]) + int(s["strips_rejected"]) == sent_strips
    assert not (published & shed_groups)
    assert published | shed_groups >= set(range(PAIRS)), (published, shed_groups)
    assert int(s["pairs"]) == len(published)
    strips_per_scene = LINES // STRIP_LINES
    # The fore view's tail scene (index PAIRS, no aft partner sent) is in group PAIRS.
    scenes_shed = sum(2 if g < PAIRS else 1 for g in shed_groups)
    assert int(s["scenes_shed"]) == scenes_shed
    assert int(s["strips_shed"]) == scenes_shed * strips_per_scene
    assert int(s["internal_errors"]) == 0 and int(s["errors"]) == 0, s


def test_overload_node_memory_stays_under_budget(overload: dict[str, Any]) -> None:
    hwm = overload["hwm"]
    assert 0 < hwm < BUDGET_MB, (
        f"node VmHWM {hwm:.0f} MB, budget {BUDGET_MB:.0f} MB; RSS {overload['rss']}"
    )


def test_overload_catches_up_when_the_load_drops(overload: dict[str, Any]) -> None:
    published, shed = published_pairs(overload["seen"]), shed_pairs(overload["seen"])
    assert set(range(PHASES[-1][0] + CATCH_UP_PAIRS, PAIRS)) <= published, (published, shed)
