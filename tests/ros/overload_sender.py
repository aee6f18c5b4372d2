"""The overload test's sensor: publishes the synthetic acquisition on a schedule of phases.

Run by tests/ros/test_overload_live.py in a process of its own (``python overload_sender.py
'<json>'``), so that it can load a Fast DDS profile of its own (Fast DDS reads the profile file
once per process, at its first participant; the pytest process has made participants before).
Protocol on stdout, one JSON line each: ``{"ready": true}`` once the node's subscriptions are
matched; then it waits for a line on stdin, publishes, and prints ``{"strips": n, "nav": m,
"late_max_s": x, "ack_wait_max_s": y}``: the messages sent, how late against its schedule the
latest message went out, and the longest wait for acknowledgements.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any


def wall_time(phases: list[tuple[int, float]], starts: list[float], due_s: float) -> float:
    """Wall time (s after the start) of an event due at sensor time ``due_s``.

    Each phase runs from the sensor time its first pair's fore scene begins, at its rate (x the
    sensor's); 1 s pause between phases.
    """
    t = 0.0
    for i, (_, rate) in enumerate(phases):
        end = starts[i + 1] if i + 1 < len(phases) else float("inf")
        if due_s <= end:
            return t + (due_s - starts[i]) / rate if i else t + due_s / rate
        t += (end - (starts[i] if i else 0.0)) / rate + 1.0
    return t


def main(spec: dict[str, Any]) -> int:
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.duration import Duration
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from parproj_ros.sim.synthetic import (
        VIEWS,
        StripMessages,
        acquisition,
        make_platform,
        nav_message,
    )

    phases = [(int(k), float(r)) for k, r in spec["phases"]]
    plat = make_platform(int(spec["lines"]), int(spec["detectors"]))
    events = acquisition(plat, int(spec["pairs"]), int(spec["strip_lines"]), 50.0)
    strips = StripMessages(plat, int(spec["strip_lines"]))
    starts = [plat.scene_start_s(0, k) for k, _ in phases]
    window = int(spec["ack_window"])

    rclpy.init()
    node = rclpy.create_node("overload_sender")
    strip_qos = QoSProfile(
        depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST
    )
    pubs = {v: node.create_publisher(Image, f"{v}/image_strip", strip_qos) for v in VIEWS}
    nav_pub = node.create_publisher(
        Odometry, "navigation", QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE)
    )
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        if nav_pub.get_subscription_count() and all(
            p.get_subscription_count() for p in pubs.values()
        ):
            break
        time.sleep(0.05)
    else:
        print(json.dumps({"error": "the node's subscriptions not matched within 30 s"}))
        return 1
    print(json.dumps({"ready": True}), flush=True)
    sys.stdin.readline()
    sent_strips = sent_nav = 0
    late_max = ack_max = 0.0
    unacked = dict.fromkeys(VIEWS, 0)
    t0 = time.time()
    for ev in events:
        due = t0 + wall_time(phases, starts, ev.due_s)
        now = time.time()
        if due > now:
            time.sleep(due - now)
        late_max = max(late_max, time.time() - due)
        if ev.kind == "nav":
            nav_pub.publish(nav_message(plat, ev.t_s))
            sent_nav += 1
            continue
        view = VIEWS[ev.view]
        pubs[view].publish(strips.get(ev))
        sent_strips += 1
        # Lossless (the test is about the node, not DDS): a short acknowledgement window.
        unacked[view] += 1
        if unacked[view] >= window:
            w0 = time.monotonic()
            if not pubs[view].wait_for_all_acked(Duration(seconds=30)):
                print(json.dumps({"error": f"{view}: strips not acknowledged within 30 s"}))
                return 1
            ack_max = max(ack_max, time.monotonic() - w0)
            unacked[view] = 0
    for p in [*pubs.values(), nav_pub]:
        if not p.wait_for_all_acked(Duration(seconds=30)):
            print(json.dumps({"error": "not acknowledged within 30 s at the end"}))
            return 1
    print(
        json.dumps(
            {
                "strips": sent_strips,
                "nav": sent_nav,
                "late_max_s": round(late_max, 3),
                "ack_wait_max_s": round(ack_max, 3),
            }
        ),
        flush=True,
    )
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(json.loads(sys.argv[1])))
