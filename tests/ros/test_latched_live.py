"""Latched outputs over real DDS: a subscriber started after the pass still gets its results.

parproj_node runs in its own process on the fore/aft bag with heights on; a recorder follows
the pass. Once the pair, its DSM and its scenes' parameters have come, a second participant
(another rclpy context: a map server or viewer started late) subscribes transient-local to
``dsm``, ``dsm_cloud`` and ``parallel_projection``: it must receive the same messages the live
recorder got, field for field, while nothing is published any more (issue 25, item 3).
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from testkit.paths import BAGS

from parproj_ros.core import contract
from parproj_ros.ros.bag import BagReader, get_message_class
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import (
    NodeProcess,
    Recorder,
    node_params_yaml,
    replay,
    ros_environment,
    wait_until,
)

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # live node over DDS

BAG = BAGS / "airborne_foreaft"
LATE = (contract.DSM, contract.DSM_CLOUD, contract.PARALLEL_PROJECTION)


def _same(a: Any, b: Any) -> bool:
    """Field for field (NaN equal to NaN: a parameter not estimated is NaN)."""
    import numpy as np

    if hasattr(a, "get_fields_and_field_types"):
        return type(a) is type(b) and all(
            _same(getattr(a, f), getattr(b, f)) for f in a.get_fields_and_field_types()
        )
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or hasattr(a, "dtype") or hasattr(b, "dtype"):
        return bool(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True))
    return bool(a == b)


def test_a_late_subscriber_gets_the_latched_results(tmp_path: Path) -> None:
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    views = views_from_bag(BagReader(BAG))
    inputs = [contract.fully_qualified(t) for t in contract.stream_topics(v.name for v in views)]
    params = node_parameters(views, heights=True)
    pfile = node_params_yaml(params, tmp_path / "params.yaml", reliable_inputs=inputs)
    proc = NodeProcess(pfile, ros_environment(log_dir=tmp_path / "ros_log"), tmp_path / "n.log")
    contexts: list[Any] = []
    try:
        # 1. The pass, followed live.
        ctx = Context()
        rclpy.init(context=ctx)
        contexts.append(ctx)
        node = rclpy.create_node("parproj_live_recorder", context=ctx)
        recorder = Recorder(node, tmp_path / "live", contract.OUTPUT_TOPICS)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        threading.Thread(target=ex.spin, daemon=True).start()
        assert recorder.wait_for_publishers(list(LATE), timeout_s=60.0), proc.output()
        replay(node, BAG, rate=0.0, max_gap_s=0.2, wait_for=inputs, log=lambda s: None)
        assert recorder.wait_complete(
            1, 180.0, lambda: proc.proc.poll() is None, also=(contract.DSM,)
        ), proc.output()[-3000:]
        wait_until(lambda: recorder.counts[contract.DSM_CLOUD] >= 1, 10.0)
        # The node done publishing them (no count moved for 1.5 s): the live lists complete.
        seen = [{t: recorder.counts[t] for t in LATE}, time.monotonic()]

        def settled() -> bool:
            now = {t: recorder.counts[t] for t in LATE}
            if now != seen[0]:
                seen[:] = [now, time.monotonic()]
            return time.monotonic() - float(seen[1]) >= 1.5

        assert wait_until(settled, 30.0)
        live = {t: list(recorder.messages[t]) for t in LATE}
        assert all(live[t] for t in LATE), {t: len(v) for t, v in live.items()}

        # 2. After the pass: a new participant subscribes, transient local.
        late_ctx = Context()
        rclpy.init(context=late_ctx)
        contexts.append(late_ctx)
        late_node = rclpy.create_node("parproj_late_viewer", context=late_ctx)
        got: dict[str, list[Any]] = {t: [] for t in LATE}
        lock = threading.Lock()
        qos = QoSProfile(
            depth=10,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )

        def keep(topic: str, msg: Any) -> None:
            with lock:
                got[topic].append(msg)

        for t in LATE:
            cls = get_message_class(contract.topic(t).msgtype)
            late_node.create_subscription(cls, t, lambda m, t=t: keep(t, m), qos)
        late_ex = SingleThreadedExecutor(context=late_ctx)
        late_ex.add_node(late_node)
        threading.Thread(target=late_ex.spin, daemon=True).start()
        assert wait_until(lambda: all(len(got[t]) >= len(live[t]) for t in LATE), 30.0), {
            t: (len(got[t]), len(live[t])) for t in LATE
        }
        with lock:
            for t in LATE:  # the same messages, field for field, in the order published
                # The live recorder subscribes volatile: at a full-speed replay it may miss a
                # message published while its match was still settling (seen in 2 of 7 CI
                # runs), which the late, transient-local subscriber then holds in addition.
                # So: every message the recorder got is among the late one's, in order.
                n, k = len(live[t]), 0
                for m in got[t]:
                    if k < n and _same(m, live[t][k]):
                        k += 1
                assert len(got[t]) >= n >= 1 and k == n, (t, len(got[t]), n, k)
        assert proc.proc.poll() is None  # the node still runs: nothing was published again
        late_ex.shutdown()
        ex.shutdown()
        recorder.close()
    finally:
        code = proc.stop()
        for c in contexts:
            rclpy.shutdown(context=c)
    assert code == 0, proc.output()[-3000:]
