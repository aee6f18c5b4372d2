"""The quick-look is shed before any pair, through parproj_node over real DDS (issue 26).

parproj_node runs in its own process on the fore/aft bag with heights on, the quick-look 1/4
alongside the full resolution (``heights_quicklook`` 2), and the least ``memory_budget_mb``
(64 MB: below the node's start-up memory alone). The admission takes pair 0 (nothing is in
flight: a pair is always admitted then) and, since one more pair in flight could not fit,
sheds the quick-look from pair 0 on (core/admission.decide_quicklook: the work given up before
pairs). Checked on what the node publishes: a WARN on /diagnostics naming the quick-look shed
and the pair; no quick-look tile; the pair itself whole (its StereoPair, its 3 full-resolution
tiles and its DSM); no pair shed; the 1 Hz summary says ``quicklook`` shed, once.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest
from testkit.paths import BAGS

from parproj_ros.core import contract
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import NodeProcess, Recorder, node_params_yaml, replay, ros_environment

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # live node over DDS

BAG = BAGS / "airborne_foreaft"
SETTINGS = {
    "scene_lines": 768,
    "heights": True,
    "heights_quicklook": 2,  # 1/4, alongside the full resolution
    "memory_budget_mb": 64.0,  # the least the parameter takes
}


def test_the_quicklook_is_shed_and_the_pair_kept(tmp_path: Path) -> None:
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    views = views_from_bag(BagReader(BAG))
    inputs = [contract.fully_qualified(t) for t in contract.stream_topics(v.name for v in views)]
    params = node_parameters(views, **SETTINGS)
    pfile = node_params_yaml(params, tmp_path / "params.yaml", reliable_inputs=inputs)
    proc = NodeProcess(pfile, ros_environment(log_dir=tmp_path / "ros_log"), tmp_path / "n.log")
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("parproj_shed_recorder", context=ctx)
        recorder = Recorder(node, tmp_path / "live", dict(contract.OUTPUT_TOPICS))
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        spin = threading.Thread(target=ex.spin, daemon=True)
        spin.start()
        assert recorder.wait_for_publishers([contract.DSM_TILE], timeout_s=60.0), proc.output()
        replay(node, BAG, rate=1.0, max_gap_s=0.05, wait_for=inputs, log=lambda s: None)
        assert recorder.wait_complete(
            1, 120.0, lambda: proc.proc.poll() is None, also=(contract.DSM,)
        ), proc.output()[-3000:]
        # One more summary after the pair (the summary is published at 1 Hz).
        n = recorder.counts[contract.DIAGNOSTICS]
        threading.Event().wait(1.5)
        assert recorder.counts[contract.DIAGNOSTICS] > n
        ex.shutdown()
        spin.join(timeout=5)
        recorder.close()
    finally:
        code = proc.stop()
        rclpy.shutdown(context=ctx)
    assert code == 0, proc.output()[-3000:]

    msgs = recorder.messages
    statuses = [(st.level, st.message) for d in msgs[contract.DIAGNOSTICS] for st in d.status]
    shed = [m for lvl, m in statuses if "quick-look tiles shed from pair 0 on" in m]
    assert len(shed) == 1, statuses
    assert "one more pair in flight would need" in shed[0]
    assert not any("overload: pair" in m for _, m in statuses)  # no pair shed
    assert not msgs[contract.DSM_QUICKLOOK_TILE]
    full = msgs[contract.DSM_TILE]
    assert [m.pair_id.split("#")[1] for m in full] == ["0/3", "1/3", "2/3"]
    assert len(msgs[contract.STEREO_PAIR]) == 1 and len(msgs[contract.DSM]) == 1
    summaries = [
        {kv.key: kv.value for kv in st.values}
        for d in msgs[contract.DIAGNOSTICS]
        for st in d.status
        if st.name == "parproj_node: summary"
    ]
    last = summaries[-1]
    assert last["quicklook"] == "shed" and last["quicklook_sheds"] == "1", last
    assert last["pairs_shed"] == "0", last
