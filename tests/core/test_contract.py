"""The interface contract (parproj_ros/core/contract.py): its tables hold together, and name
what the bags and the node have always used (the literals here are the expected values)."""

from __future__ import annotations

import pytest

from parproj_ros.core import contract


def test_output_table_is_the_published_topics_in_order() -> None:
    """The output rows, in the order the node creates its publishers and bags declare them."""
    assert list(contract.OUTPUT_TOPICS.items()) == [
        ("parallel_projection", "parproj_msgs/msg/ParallelProjection"),
        ("stereo_pair", "parproj_msgs/msg/StereoPair"),
        ("left/image_normalized", "sensor_msgs/msg/Image"),
        ("right/image_normalized", "sensor_msgs/msg/Image"),
        ("anaglyph", "sensor_msgs/msg/Image"),
        ("left/normalized_block", "parproj_msgs/msg/NormalizedBlock"),
        ("right/normalized_block", "parproj_msgs/msg/NormalizedBlock"),
        ("disparity", "stereo_msgs/msg/DisparityImage"),
        ("height", "sensor_msgs/msg/Image"),
        ("dsm", "parproj_msgs/msg/ElevationGrid"),
        ("dsm_cloud", "sensor_msgs/msg/PointCloud2"),
        ("dsm_tile", "parproj_msgs/msg/ElevationGrid"),
        ("dsm_quicklook_tile", "parproj_msgs/msg/ElevationGrid"),
        ("dsm_fused", "parproj_msgs/msg/ElevationGrid"),
        ("dsm_fused_cloud", "sensor_msgs/msg/PointCloud2"),
        ("object_frame", "geometry_msgs/msg/TransformStamped"),
        ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
    ]
    # Per-scene and per-pair results a late subscriber needs are latched (and recorded so, for
    # a replay to offer them latched); the rest reliable and volatile.
    latched = {"parallel_projection", "stereo_pair", "dsm", "dsm_cloud", "dsm_fused"}
    latched |= {"dsm_fused_cloud", "object_frame"}
    for t in contract.OUTPUTS:
        want = t.name in latched
        assert (t.qos == contract.LATCHED_OUTPUT_QOS) == want, t.name
        assert (t.qos == contract.OUTPUT_QOS) != want, t.name
        assert t.recorded == ("transient_local" if want else "reliable"), t.name
    assert all(t.carries and t.description for t in contract.OUTPUTS)
    assert contract.PAIR_IMAGE_TOPICS == (
        "left/image_normalized",
        "right/image_normalized",
        "anaglyph",
    )
    assert contract.image_topics() == (
        "stereo_pair",
        *contract.PAIR_IMAGE_TOPICS,
        "left/normalized_block",
        "right/normalized_block",
    )


def test_input_rows_name_types_and_recorded_qos() -> None:
    """An input bag's topics as ``parproj simulate`` declares them (types, offered QoS)."""
    rows = [(t.name, t.msgtype, t.recorded) for t in contract.input_topics(["left", "right"])]
    assert rows == [
        ("navigation", "nav_msgs/msg/Odometry", "sensor_data"),
        ("left/image_strip", "sensor_msgs/msg/Image", "sensor_data"),
        ("left/scanner_info", "parproj_msgs/msg/ScannerInfo", "transient_local"),
        ("right/image_strip", "sensor_msgs/msg/Image", "sensor_data"),
        ("right/scanner_info", "parproj_msgs/msg/ScannerInfo", "transient_local"),
        ("gcp", "parproj_msgs/msg/GroundControlPoints", "transient_local"),
        ("truth/points", "parproj_msgs/msg/GroundControlPoints", "transient_local"),
    ]
    imported = [t.name for t in contract.input_topics(["pan"], navigation=False)]
    assert imported == ["pan/image_strip", "pan/scanner_info", "gcp", "truth/points"]
    assert contract.topic("pairs").msgtype == "parproj_msgs/msg/PairSelection"
    assert [t.name for t in contract.INPUTS if t.subscribed] == [
        "navigation",
        "<view>/image_strip",
        "gcp",
        "pairs",
    ]
    assert contract.stream_topics(["fore", "aft"]) == [
        "navigation",
        "fore/image_strip",
        "aft/image_strip",
    ]
    assert contract.FRAME_TOPICS == ("gcp", "truth/points", "navigation")


def test_the_node_qos_as_plain_data() -> None:
    """The node's profiles (subscriptions, publishers) and the bags' presets, as data."""
    q = {t.name: t.qos for t in contract.INPUTS}
    assert (q["navigation"].reliability, q["navigation"].durability, q["navigation"].depth) == (
        "best_effort",
        "volatile",
        500,
    )
    s = q["<view>/image_strip"]
    assert (s.reliability, s.durability, s.depth) == (
        "best_effort",
        "volatile",
        200,
    )
    for name in ("gcp", "pairs"):
        assert (q[name].reliability, q[name].durability, q[name].depth) == (
            "reliable",
            "transient_local",
            10,
        )
    out = contract.OUTPUT_QOS
    assert (out.reliability, out.durability, out.depth) == ("reliable", "volatile", 10)
    assert all(t.qos.why for t in (*contract.INPUTS, *contract.OUTPUTS))
    assert {k: v.as_dict() for k, v in contract.BAG_QOS.items()} == {
        "reliable": {
            "history": "keep_last",
            "depth": 10,
            "reliability": "reliable",
            "durability": "volatile",
        },
        "sensor_data": {
            "history": "keep_last",
            "depth": 5,
            "reliability": "best_effort",
            "durability": "volatile",
        },
        "transient_local": {
            "history": "keep_last",
            "depth": 1,
            "reliability": "reliable",
            "durability": "transient_local",
        },
    }


def test_names_and_frames() -> None:
    assert contract.strip_topic("left") == "left/image_strip"
    assert contract.scanner_info_topic("pan") == "pan/scanner_info"
    assert contract.normalized_block_topic("right") == "right/normalized_block"
    assert contract.normalized_frame("map", "left") == "map/normalized_left"
    assert contract.fully_qualified("navigation") == "/navigation"
    assert contract.fully_qualified("/diagnostics") == "/diagnostics"
    assert contract.view_of("left/image_strip") == "left"
    assert contract.view_of("/aft/image_strip") == "aft"
    assert contract.view_of("left/scanner_info", contract.SCANNER_INFO) == "left"
    assert contract.view_of("navigation") is None
    assert contract.view_of("a/b/image_strip") is None
    assert (contract.DEFAULT_FRAME, contract.BODY_FRAME) == ("map", "base_link")
    assert contract.topic("/stereo_pair").name == "stereo_pair"
    assert contract.topic("fore/image_strip").name == "fore/image_strip"
    with pytest.raises(KeyError, match="not a topic of the contract"):
        contract.topic("left/image_strips")
