"""The main job: the default bag through the live node over DDS, then the evaluation.

Steps: start ``parproj_node`` in its own process with the bag's cameras as parameters (reliable
input QoS for a lossless replay), replay the bag into the graph, record the node's outputs into
``<out>/output`` (an MCAP bag), stop the node, evaluate against the bag's truth, and leave the
normalized pair, the anaglyph, plots and ``evaluation.json`` in ``<out>``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from .bag import BagReader
from .conversions import OUTPUT_TOPICS
from .live import NodeProcess, Recorder, node_params_yaml, replay, ros_environment
from .recording import node_parameters, views_from_bag


def run_demo(
    bag: Path, out: Path, *, rate: float = 20.0, progress: bool = True, timeout_s: float = 300.0
) -> int:
    """Run the demo; returns 0 when at least one pair was produced and evaluated."""
    import rclpy

    from .evaluate import evaluate_bag

    out.mkdir(parents=True, exist_ok=True)
    env = ros_environment()
    reader = BagReader(bag)
    views = views_from_bag(reader)
    expected_pairs = 1  # every bag in bags/ holds one stereo pair
    params = node_parameters(views, scene_timeout=2.0)
    inputs = ["/navigation"] + [f"/{v.name}/image_strip" for v in views]
    pfile = node_params_yaml(params, out / "node_params.yaml", reliable_inputs=inputs)
    print(f"demo: ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}, node log {out / 'node.log'}")
    node_proc = NodeProcess(pfile, env, out / "node.log")
    rclpy.init()
    node = rclpy.create_node("parproj_demo")
    recorder = Recorder(node, out / "output", OUTPUT_TOPICS)
    executor = rclpy.executors.SingleThreadedExecutor()
    executor.add_node(node)
    import threading

    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    try:
        t0 = time.monotonic()
        if not recorder.wait_for_publishers(list(OUTPUT_TOPICS), timeout_s=60.0):
            print("demo: the node's output topics were not discovered in 60 s")
        res = replay(
            node,
            bag,
            rate=rate,
            max_gap_s=0.5,
            wait_for=[f"{v.name}/image_strip" for v in views],
            progress=progress,
        )
        print(f"demo: replayed {res['sent']} messages in {res['seconds']:.1f} s")
        recorder.wait_complete(
            expected_pairs,
            max(0.0, timeout_s - (time.monotonic() - t0)),
            lambda: node_proc.proc.poll() is None,
        )
        time.sleep(1.0)
    finally:
        code = node_proc.stop()
        executor.shutdown()
        spin.join(timeout=5)
        recorder.close()
        node.destroy_node()
        rclpy.try_shutdown()
    print(f"demo: node exited with {code}; recorded {recorder.counts}")
    if recorder.counts["stereo_pair"] == 0:
        print("demo: no stereo pair was published; node log follows\n" + node_proc.output())
        return 1
    result = evaluate_bag(out / "output", bag, plots=out)
    (out / "evaluation.json").write_text(json.dumps(result, indent=1, default=float))
    from .cli import _print_evaluation

    _print_evaluation(result)
    print(
        f"demo: normalized pair, anaglyph and plots in {out}/, evaluation in "
        f"{out / 'evaluation.json'}, output bag in {out / 'output'}"
    )
    return 0
