"""config/foxglove_layout.json (issue 25, item 2): a Foxglove layout for the demo output.

It is Foxglove's layout JSON (``configById``: panel id ``<kind>!<name>`` -> its settings;
``layout``: the split tree of the panel ids). Every topic it names is an output of the contract
with the type its panel shows, it shows the demo's products (normalized pair, anaglyph, DSM
cloud, /diagnostics), and the cloud panel colours by fields the cloud has.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from testkit.paths import ROOT

from parproj_ros.core import contract
from parproj_ros.imaging.heights import DsmGrid
from parproj_ros.ros import conversions as conv

pytestmark = pytest.mark.ros  # the cloud's fields come from the converter (sensor_msgs)

LAYOUT = ROOT / "config" / "foxglove_layout.json"

#: Foxglove panel kind -> the message type each topic it names must have.
PANEL_TYPES = {
    "3D": "sensor_msgs/msg/PointCloud2",
    "Image": "sensor_msgs/msg/Image",
    "DiagnosticSummary": "diagnostic_msgs/msg/DiagnosticArray",
}


def load() -> dict[str, Any]:
    data = json.loads(LAYOUT.read_text())
    assert isinstance(data, dict)
    return data


def leaves(node: Any) -> Iterator[str]:
    """The panel ids of a layout split tree, checking each split on the way."""
    if isinstance(node, str):
        yield node
        return
    assert set(node) <= {"direction", "first", "second", "splitPercentage"}, node
    assert node["direction"] in ("row", "column")
    assert 0 < node.get("splitPercentage", 50) < 100
    yield from leaves(node["first"])
    yield from leaves(node["second"])


def named_topics(kind: str, config: dict[str, Any]) -> list[str]:
    """The topics a panel's settings name (3D: its topic settings; the others: their field)."""
    if kind == "3D":
        return list(config.get("topics", {}))
    if kind == "Image":
        return [config["imageMode"]["imageTopic"]]
    return [config["topicToRender"]]


def strings(value: Any) -> Iterator[str]:
    """Every string in a JSON value, keys included."""
    if isinstance(value, str):
        yield value
    elif isinstance(value, dict):
        for k, v in value.items():
            yield k
            yield from strings(v)
    elif isinstance(value, list):
        for v in value:
            yield from strings(v)


def test_the_layout_is_foxglove_layout_json_with_each_panel_placed_once() -> None:
    data = load()
    assert set(data) == {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"}
    placed = list(leaves(data["layout"]))
    assert sorted(placed) == sorted(data["configById"])  # each panel once, none left over
    assert {pid.split("!")[0] for pid in placed} == set(PANEL_TYPES)


def test_every_topic_is_a_contract_output_of_the_panel_s_type() -> None:
    """Each named topic (fully qualified, the node in the root namespace) is a row of
    contract.OUTPUTS whose type the panel shows; no other topic-like string in the file."""
    data = load()
    outputs = {contract.fully_qualified(t.name): t.msgtype for t in contract.OUTPUTS}
    named: list[str] = []
    for pid, config in data["configById"].items():
        kind = pid.split("!")[0]
        for topic in named_topics(kind, config):
            assert topic in outputs, f"{pid}: {topic} is not an output of the contract"
            assert outputs[topic] == PANEL_TYPES[kind], (pid, topic, outputs[topic])
            named.append(topic)
    slashed = {s for s in strings(data) if s.startswith("/")}
    assert slashed == set(named)
    # the demo's products
    wanted = [
        contract.normalized_image_topic("left"),
        contract.normalized_image_topic("right"),
        contract.ANAGLYPH,
        contract.DSM_CLOUD,
        contract.DIAGNOSTICS,
    ]
    assert {contract.fully_qualified(t) for t in wanted} <= set(named)


def test_the_cloud_panel_colours_by_the_cloud_s_fields_in_the_outputs_frame() -> None:
    data = load()
    panel = data["configById"]["3D!dsm"]
    assert panel["followTf"] == contract.DEFAULT_FRAME  # the demo's (simulated) object frame
    heights = np.zeros((2, 2), np.float32)
    grid = DsmGrid(0.0, 0.0, 1.0, 2, 2)
    fields = {
        contract.DSM_CLOUD: conv.dsm_to_cloud(
            heights, grid, np.zeros((2, 2), np.uint8), step=1, frame_id="map", stamp_ns=0
        ).fields,
        contract.DSM_FUSED_CLOUD: conv.dsm_to_cloud(
            heights, grid, None, step=1, frame_id="map", stamp_ns=0
        ).fields,
    }
    for topic, settings in panel["topics"].items():
        names = [f.name for f in fields[topic.lstrip("/")]]
        assert settings["colorField"] in names, (topic, settings["colorField"], names)
    assert panel["topics"]["/dsm_cloud"]["visible"] is True
