"""Streamed DSM tiles through parproj_node over real DDS (issue 26).

parproj_node runs in its own process on the fore/aft bag (heights on, 768-line scenes: the pair
streams; quick-look 1/4 alongside). One recorder subscribes to the node's outputs and to the
replay's right strips, writing each message with its arrival time under one lock: the bag it
writes is the arrival order. The first ``dsm_tile`` must arrive before the replay's last right
strip (tile 0 needs right strip 9 of 12; the replay runs at a fifth of the recorded speed, so
the three strips after it take 0.3 / 0.2 = 1.5 s, while the tile takes some 0.5 s to match).
The bag's 38.8 s are mostly navigation between the scenes (the left scene at 1.0-2.1 s, the
right one at 36.6-37.7 s): the replayed copy keeps the 50 Hz navigation within 1 s of the
strips and one sample every 0.5 s between (within the feed's 1 s gap bound), whose idle
stretches the replay shortens to 0.05 s, so the slow replay takes some 50 s.
The tiles must equal those ``parproj process`` makes of the same bag with the same parameters
(same blocks, same matcher on the same threads: to the bit), and assemble into the pair's DSM.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest
from testkit.live import thinned_navigation
from testkit.paths import BAGS

from parproj_ros.apps.process import process_bag
from parproj_ros.core import contract
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.conversions import elevation_grid_from_msg
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import NodeProcess, Recorder, node_params_yaml, replay, ros_environment

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # live node over DDS

BAG = BAGS / "airborne_foreaft"
SETTINGS = {"scene_lines": 768, "heights": True, "heights_quicklook": 2}  # 1/4
RATE = 0.2


def _trimmed(path: Path) -> Path:
    return thinned_navigation(BAG, path)


def test_tiles_arrive_while_the_strips_are_sent_and_equal_the_offline_ones(
    tmp_path: Path,
) -> None:
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    bag = _trimmed(tmp_path / "input")
    views = views_from_bag(BagReader(bag))
    inputs = [contract.fully_qualified(t) for t in contract.stream_topics(v.name for v in views)]
    params = node_parameters(views, **SETTINGS)
    pfile = node_params_yaml(params, tmp_path / "params.yaml", reliable_inputs=inputs)
    proc = NodeProcess(pfile, ros_environment(log_dir=tmp_path / "ros_log"), tmp_path / "n.log")
    right_strips = contract.strip_topic("right")
    topics = {**contract.OUTPUT_TOPICS, right_strips: "sensor_msgs/msg/Image"}
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("parproj_tiles_recorder", context=ctx)
        recorder = Recorder(node, tmp_path / "live", topics)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        spin = threading.Thread(target=ex.spin, daemon=True)
        spin.start()
        assert recorder.wait_for_publishers([contract.DSM_TILE], timeout_s=60.0), proc.output()
        replay(node, bag, rate=RATE, max_gap_s=0.05, wait_for=inputs, log=lambda s: None)
        assert recorder.wait_complete(
            1, 180.0, lambda: proc.proc.poll() is None, also=(contract.DSM,)
        ), proc.output()[-3000:]
        ex.shutdown()
        spin.join(timeout=5)
        recorder.close()
    finally:
        code = proc.stop()
        rclpy.shutdown(context=ctx)
    assert code == 0, proc.output()[-3000:]

    # Arrival order: the first tile before the last right strip.
    order = [
        m.topic
        for m in BagReader(tmp_path / "live").messages(
            topics=[contract.DSM_TILE, contract.DSM_QUICKLOOK_TILE, right_strips]
        )
    ]
    assert order.count(right_strips) == 12
    last_strip = len(order) - 1 - order[::-1].index(right_strips)
    first_tile = order.index(contract.DSM_TILE)
    assert first_tile < last_strip, order
    strips_before = order[:first_tile].count(right_strips)
    print(f"first dsm_tile after right strip {strips_before} of 12 (arrival order)")
    assert strips_before < 12

    # The same tiles as parproj process makes of the bag with the same parameters.
    s = process_bag(bag, tmp_path / "offline", progress=False, overrides=dict(SETTINGS))
    assert s.pairs == 1, s.issues
    for topic in (contract.DSM_TILE, contract.DSM_QUICKLOOK_TILE):
        live = [m.msg for m in BagReader(tmp_path / "live").messages(topics=[topic])]
        off = [m.msg for m in BagReader(tmp_path / "offline").messages(topics=[topic])]
        assert [m.pair_id for m in live] == [m.pair_id for m in off] and live, topic
        for a, b in zip(live, off, strict=True):
            ha, ga, oa = elevation_grid_from_msg(a)
            hb, gb, ob = elevation_grid_from_msg(b)
            assert ga == gb
            np.testing.assert_array_equal(ha, hb)
            np.testing.assert_array_equal(oa, ob)
            assert (a.disparity_min, a.disparity_max) == (b.disparity_min, b.disparity_max)
            assert a.terrain_source == b.terrain_source == "tie_points"
    full = [m.msg for m in BagReader(tmp_path / "live").messages(topics=[contract.DSM_TILE])]
    assert [m.pair_id.split("#")[1] for m in full] == ["0/3", "1/3", "2/3"]
