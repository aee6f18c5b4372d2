"""The main job: the default bag through the live node over DDS, then the evaluation.

Steps: start ``parproj_node`` in its own process with the bag's cameras as parameters (reliable
input QoS for a lossless replay), replay the bag into the graph, record the node's outputs into
``<out>/output`` (an MCAP bag), stop the node, evaluate against the bag's truth, and leave the
normalized pair, the anaglyph, plots, the DSM (its hillshade, ortho-image and height error map)
and ``evaluation.json`` in ``<out>``.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..core import contract
from ..ros.bag import BagReader
from ..ros.inputs import node_parameters, views_from_bag
from ..ros.live import ros_environment, run_through_node


def run_demo(
    bag: Path,
    out: Path,
    *,
    rate: float = 20.0,
    progress: bool = True,
    timeout_s: float = 300.0,
    shown_as: Path | None = None,
) -> int:
    """Run the demo; returns 0 when at least one pair was produced and evaluated.

    ``shown_as``: the folder named in the messages (``out`` is then a temporary name that the
    caller renames to it when the demo is complete).
    """
    from ..eval.evaluate import evaluate_bag, print_evaluation

    out.mkdir(parents=True, exist_ok=True)
    env = ros_environment()
    views = views_from_bag(BagReader(bag))
    print(f"demo: ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}, node log {(shown_as or out) / 'node.log'}")
    run = run_through_node(
        bag,
        out,
        params=node_parameters(views, scene_timeout=2.0, heights=True),
        rate=rate,
        max_gap_s=0.5,
        pairs=1,  # every bag in bags/ holds one stereo pair
        timeout_s=timeout_s,
        env=env,
        progress=progress,
        also=(contract.DISPARITY, contract.HEIGHT),
    )
    print(f"demo: replayed {run.replay.get('sent', 0)} messages in "
          f"{run.replay.get('seconds', 0.0):.1f} s")  # fmt: skip
    print(f"demo: node exited with {run.code}; recorded {run.counts}")
    if run.counts[contract.STEREO_PAIR] == 0:
        print("demo: no stereo pair was published; node log follows\n" + run.log)
        return 1
    result = evaluate_bag(run.output, bag, plots=out)
    (out / "evaluation.json").write_text(json.dumps(result, indent=1, default=float))
    print_evaluation(result)
    shown = shown_as or out
    print(
        f"demo: normalized pair, anaglyph, DSM and plots in {shown}/, evaluation in "
        f"{shown / 'evaluation.json'}, output bag in {shown / run.output.relative_to(out)}"
    )
    return 0
