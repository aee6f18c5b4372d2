"""Bad messages and parameters through the real node: parproj_node in its own process, DDS on
localhost, crafted messages published from an rclpy node of the test (an explicit Context).

The session: start the node with bags/ikonos_agile's cameras; publish strips it cannot convert
(unsupported encoding, step < width x bytes, truncated data, no lines) and navigation it cannot
use (NaN, zero-norm quaternions, NaN velocity); try to change read-only parameters; then replay
the good bag and check that its pair comes out with the parameters and images of a clean offline
run (``offline.process_bag``). Statuses are read from /diagnostics as published.

Separately: parameters out of range (or not one of the allowed values) at start, and the replay
of a bag cut off mid-write. Tie-point refinement, where the node has it, is switched off (as in
the offline reference) to keep this file within about a minute.
"""

from __future__ import annotations

import math
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from nav_msgs.msg import Odometry
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.duration import Duration
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from testkit import live
from testkit.diagnostics import level, show
from testkit.live import wait
from testkit.paths import BAGS

from parproj_ros.apps.process import process_bag
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import (
    NodeProcess,
    Recorder,
    node_params_yaml,
    replay,
    ros_environment,
)

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # live node over DDS

BAG = BAGS / "ikonos_agile"
FAST = {"tie_points": False}
INPUTS = ["/navigation", "/pan/image_strip"]
WARN = DiagnosticStatus.WARN[0]
ERROR = DiagnosticStatus.ERROR[0]


class GraphNode(live.GraphNode):
    """An rclpy node of the test in its own Context, spun in a thread (from :meth:`start`)."""

    def __init__(self, name: str) -> None:
        super().__init__(name, start=False)
        self.diagnostics: list[DiagnosticStatus] = []
        self._lock = threading.Lock()

    def listen_diagnostics(self) -> None:
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, qos)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        with self._lock:
            self.diagnostics += list(msg.status)

    def statuses(self) -> list[DiagnosticStatus]:
        with self._lock:
            return list(self.diagnostics)


# ---- crafted messages ---------------------------------------------------------------------------


def strip(frame_id: str, change: Callable[[Image], None]) -> Image:
    arr = np.random.default_rng(3).integers(0, 2000, (64, 768)).astype(np.uint16)
    msg = conv.array_to_image(arr, Image(), frame_id=frame_id, stamp_ns=1_000_000_000)
    change(msg)
    return msg


def _set(field: str, value: Callable[[Image], Any]) -> Callable[[Image], None]:
    def change(m: Image) -> None:
        setattr(m, field, value(m))

    return change


#: frame_id of the crafted strip -> (change, what the status must say)
BAD_STRIPS: dict[str, tuple[Callable[[Image], None], str]] = {
    "bad_encoding": (_set("encoding", lambda m: "rgb8"), "unsupported encoding 'rgb8'"),
    "bad_step": (_set("step", lambda m: m.width), "step 768 < width 768 x 2 bytes"),
    "bad_data": (_set("data", lambda m: bytes(m.data)[:1000]), "data has 1000 bytes"),
    "bad_empty": (_set("height", lambda m: 0), "empty image"),
}


def _cut_strip() -> bytes:
    """A strip's CDR bytes cut in the middle of its pixels (as a broken driver could send)."""
    from rclpy.serialization import serialize_message

    raw = serialize_message(strip("cdr_cut", lambda m: None))
    return raw[: len(raw) // 2]


#: CDR bytes published as they are (``Publisher.publish(bytes)``) -> what the WARN must say.
#: The node takes strips raw (ros/cdr.py): they never become rclpy messages.
BAD_CDR: dict[str, tuple[Callable[[], bytes], str]] = {
    "cut": (_cut_strip, "unreadable CDR (truncated: data needs 98304 bytes"),
    "garbage": (
        lambda: b"\x00\x01\x00\x00" + bytes([0xFF] * 12),  # frame_id of 4 GB
        "unreadable CDR (truncated: header.frame_id needs 4294967295 bytes",
    ),
}


def odometry(q: tuple[float, float, float, float], v: tuple[float, float, float]) -> Odometry:
    m = Odometry()
    m.header.stamp.sec = 1
    m.header.frame_id, m.child_frame_id = "map", "base_link"
    o, lin = m.pose.pose.orientation, m.twist.twist.linear
    o.x, o.y, o.z, o.w = q
    lin.x, lin.y, lin.z = v
    return m


BAD_NAV: dict[str, tuple[Odometry, str]] = {
    "NaN quaternion": (
        odometry((math.nan, 0.0, 0.0, 1.0), (7000.0, 0.0, 0.0)),
        "quaternion must be 4 finite",
    ),
    "zero-norm quaternion": (odometry((0.0, 0.0, 0.0, 0.0), (7000.0, 0.0, 0.0)), "zero norm"),
    "NaN velocity": (odometry((0.0, 0.0, 0.0, 1.0), (7000.0, math.nan, 0.0)), "velocity"),
}


# ---- the session --------------------------------------------------------------------------------


def call(node: Any, srv: Any, name: str, request: Any, timeout: float = 10.0) -> Any:
    client = node.create_client(srv, name)
    assert client.wait_for_service(timeout_sec=timeout), f"{name} not available"
    future = client.call_async(request)
    assert wait(future.done, timeout), f"{name}: no response"
    return future.result()


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("reliability_node")
    t_start = time.monotonic()
    # The clean offline run: the reference for the good pair.
    offline = tmp / "offline"
    summary = process_bag(BAG, offline, progress=False, overrides=FAST)
    assert summary.pairs == 1
    env = ros_environment(log_dir=tmp / "ros_log")
    views = views_from_bag(BagReader(BAG))
    pfile = node_params_yaml(
        node_parameters(views, **FAST), tmp / "params.yaml", reliable_inputs=INPUTS
    )
    proc = NodeProcess(pfile, env, tmp / "node.log")
    test = GraphNode("test_reliability")
    recorder = Recorder(test.node, tmp / "output", conv.OUTPUT_TOPICS)
    result: dict[str, Any] = {"offline": offline, "proc": proc}
    try:
        test.listen_diagnostics()
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        pub_strip = test.node.create_publisher(Image, "pan/image_strip", qos)
        pub_nav = test.node.create_publisher(Odometry, "navigation", qos)
        test.start()
        assert recorder.wait_for_publishers(list(conv.OUTPUT_TOPICS)), proc.output()
        assert wait(lambda: pub_strip.get_subscription_count() > 0, 20), proc.output()
        assert wait(lambda: pub_nav.get_subscription_count() > 0, 20), proc.output()
        # Bad messages.
        for frame_id, (change, _) in BAD_STRIPS.items():
            pub_strip.publish(strip(frame_id, change))
        for make, _ in BAD_CDR.values():
            pub_strip.publish(make())
        for msg, _ in BAD_NAV.values():
            pub_nav.publish(msg)
        assert pub_strip.wait_for_all_acked(Duration(seconds=5))
        assert pub_nav.wait_for_all_acked(Duration(seconds=5))
        # Run-time parameter changes (the node's parameters are read-only).
        req = SetParameters.Request()
        req.parameters = [
            Parameter("z_avg", value=100.0).to_parameter_msg(),
            Parameter("pan.principal_distance", value=5.0).to_parameter_msg(),
            Parameter("pan.principal_distance", value=1000.0).to_parameter_msg(),
        ]
        result["set"] = call(test.node, SetParameters, "/parproj_node/set_parameters", req)
        get = GetParameters.Request()
        get.names = ["z_avg", "pan.principal_distance"]
        result["get"] = call(test.node, GetParameters, "/parproj_node/get_parameters", get)

        def reported() -> bool:
            names = " ".join(s.name for s in test.statuses())
            msgs = " ".join(s.message for s in test.statuses())
            return (
                all(f in names for f in BAD_STRIPS)
                and msgs.count("sample dropped") >= 3
                and msgs.count("unreadable CDR") >= len(BAD_CDR)
            )

        wait(reported, 10, lambda: proc.proc.poll() is None)
        # The good bag after all that.
        result["replay"] = replay(
            test.node, BAG, rate=0.0, max_gap_s=0.2, wait_for=["pan/image_strip"], log=print
        )

        recorder.wait_complete(1, 60, lambda: proc.proc.poll() is None)
        time.sleep(1.2)  # one more 1 Hz summary after the pair
        result["alive"] = proc.proc.poll() is None
    finally:
        result["code"] = proc.stop()
        test.close()
        recorder.close()
    result["log"] = proc.output()
    result["statuses"] = test.statuses()
    result["output"] = tmp / "output"
    result["seconds"] = time.monotonic() - t_start
    yield result


def test_node_survives_bad_input(session: dict[str, Any]) -> None:
    assert session["alive"], session["log"]
    assert session["code"] == 0, session["log"]
    assert "Traceback" not in session["log"], session["log"]


@pytest.mark.parametrize("frame_id", sorted(BAD_STRIPS))
def test_bad_strip_reported(frame_id: str, session: dict[str, Any]) -> None:
    """Strip rejected: a WARN status named after the view and the strip's scene id."""
    says = BAD_STRIPS[frame_id][1]
    hits = [s for s in session["statuses"] if s.name == f"parproj_node: pan/{frame_id}"]
    assert hits, show(session["statuses"])
    (s,) = hits
    assert level(s) == WARN
    assert says in s.message and "dropped" in s.message, s.message
    assert f"pan/{frame_id}: strip rejected" in session["log"]  # and logged


@pytest.mark.parametrize("case", sorted(BAD_CDR))
def test_unreadable_cdr_reported(case: str, session: dict[str, Any]) -> None:
    """Bytes that are not a well-formed Image: a WARN naming the view and what was wrong."""
    says = BAD_CDR[case][1]
    hits = [s for s in session["statuses"] if s.name == "parproj_node: pan" and says in s.message]
    assert len(hits) == 1, show(session["statuses"])
    assert level(hits[0]) == WARN and "strip rejected" in hits[0].message
    assert hits[0].message.endswith(": dropped"), hits[0].message


@pytest.mark.parametrize("case", sorted(BAD_NAV))
def test_bad_navigation_reported(case: str, session: dict[str, Any]) -> None:
    says = BAD_NAV[case][1]
    hits = [
        s
        for s in session["statuses"]
        if s.name == "parproj_node: navigation" and says in s.message
    ]
    assert len(hits) == 1, show(session["statuses"])
    assert level(hits[0]) == WARN and "sample dropped" in hits[0].message


def test_summary_counts_rejections(session: dict[str, Any]) -> None:
    summaries = [s for s in session["statuses"] if s.name == "parproj_node: summary"]
    assert summaries
    values = {kv.key: kv.value for kv in summaries[-1].values}
    assert values["strips_rejected"] == str(len(BAD_STRIPS) + len(BAD_CDR)), values
    assert values["nav_rejected"] == str(len(BAD_NAV)), values
    assert values["pairs"] == "1" and values["scenes"] == "2", values


def test_parameters_are_read_only(session: dict[str, Any]) -> None:
    results = session["set"].results
    assert len(results) == 3
    for r in results:
        assert not r.successful
        assert "read-only" in r.reason, r.reason
    values = [v.double_value for v in session["get"].values]
    assert values[0] == 0.0 and values[1] == pytest.approx(10.0)  # unchanged


def _by_scene(bag: Path) -> dict[str, Any]:
    return {m.msg.scene_id: m.msg for m in BagReader(bag).messages(topics=["parallel_projection"])}


def _one(bag: Path, topic: str) -> Any:
    (m,) = [m.msg for m in BagReader(bag).messages(topics=[topic])]
    return m


def test_good_pair_after_bad_input(session: dict[str, Any]) -> None:
    """The good bag's pair: the parameters and images of the clean offline run."""
    assert session["replay"]["recovery"].complete
    live, off = _by_scene(session["output"]), _by_scene(session["offline"])
    assert sorted(live) == sorted(off) == ["pan_scene_0000", "pan_scene_0001"], session["log"]
    for sid, o in off.items():
        m = live[sid]
        assert (m.method, m.lines, m.gcp_count) == (o.method, o.lines, o.gcp_count)
        np.testing.assert_allclose(np.array(m.affine), np.array(o.affine), rtol=1e-12, atol=0)
        assert m.roll_psi == pytest.approx(o.roll_psi, abs=1e-15)
    sp_live, sp_off = (
        _one(session["output"], "stereo_pair"),
        _one(session["offline"], "stereo_pair"),
    )
    assert sp_live.pair_id == sp_off.pair_id == "pan_scene_0000+pan_scene_0001"
    for f in ("left_to_normalized", "right_to_normalized"):
        np.testing.assert_allclose(getattr(sp_live, f), getattr(sp_off, f), rtol=1e-12, atol=0)
    assert (sp_live.width, sp_live.height) == (sp_off.width, sp_off.height)
    for topic in ("left/image_normalized", "right/image_normalized"):
        a = conv.image_to_array(_one(session["output"], topic))
        b = conv.image_to_array(_one(session["offline"], topic))
        np.testing.assert_array_equal(a, b)
    # Nothing about the good data went wrong.
    bad = [
        s
        for s in session["statuses"]
        if level(s) >= WARN
        and not any(k in s.name for k in (*BAD_STRIPS, "navigation"))
        and "unreadable CDR" not in s.message  # BAD_CDR: no frame id to name them by
    ]
    assert not bad, show(bad)


# ---- parameters at start ------------------------------------------------------------------------

#: parameter -> value out of its declared range (or not one of the allowed values)
AT_START = {
    "pan.principal_distance": 1000.0,  # declared range 1e-4 .. 100 m
    "pan.detectors": 0,  # declared range 1 .. 1e6
    "gcp_roll": "bogus",  # 'estimate', 'navigation' or 'none'
}


@pytest.mark.parametrize("name", sorted(AT_START))
def test_bad_parameter_at_start(name: str, tmp_path: Path) -> None:
    """The node does not die: it keeps running and says, in its log and on /diagnostics
    (repeatedly, e.g. in the summary, since a subscriber may join late), which parameter was
    refused and what it did instead."""
    value = AT_START[name]
    views = views_from_bag(BagReader(BAG))
    params = node_parameters(views, **FAST)
    params[name] = value
    pfile = node_params_yaml(params, tmp_path / "params.yaml", reliable_inputs=INPUTS)
    test = GraphNode("test_parameters")
    test.listen_diagnostics()
    test.start()
    proc = NodeProcess(pfile, ros_environment(log_dir=tmp_path / "ros_log"), tmp_path / "n.log")
    try:

        def said() -> bool:
            return any(
                level(s) == ERROR and name in s.name + s.message and str(value) in s.message
                for s in test.statuses()
            )

        wait(said, 5, lambda: proc.proc.poll() is None)
        alive = proc.proc.poll() is None
    finally:
        code = proc.stop()
        test.close()
    log = proc.output()
    assert alive, f"parproj_node exited (code {code}) with {name} = {value!r}:\n{log}"
    assert said(), show(test.statuses())
    assert name in log, log


# ---- replay of a cut-off bag --------------------------------------------------------------------


@pytest.fixture(scope="module")
def cut_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """bags/ikonos_agile cut off at 80 % of its MCAP file (a recorder killed mid-write)."""
    cut = tmp_path_factory.mktemp("cut") / "ikonos_agile"
    cut.mkdir()
    mcap = BAG / "ikonos_agile_0.mcap"
    data = mcap.read_bytes()
    (cut / mcap.name).write_bytes(data[: int(0.8 * len(data))])
    shutil.copy(BAG / "metadata.yaml", cut / "metadata.yaml")
    return cut


def test_replay_of_cut_off_bag_returns_the_recovery(cut_bag: Path) -> None:
    test = GraphNode("test_replay_cut")
    test.start()
    lines: list[str] = []
    try:
        res = replay(test.node, cut_bag, rate=0.0, log=lines.append)
    finally:
        test.close()
    rec = res["recovery"]
    assert not rec.complete and "cut off" in (rec.error or "")
    assert rec.messages_expected == 1474
    assert 0 < rec.messages_read < 1474 and rec.messages_lost == 1474 - rec.messages_read
    assert res["sent"] == rec.messages_read  # every recovered message was published
    assert res["skipped_types"] == {}


def test_replay_waits_for_acknowledgements(cut_bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """replay() ends by waiting until reliable deliveries are acknowledged (``parproj replay``
    exits right after it: messages still in flight would be lost). Every such wait must be a
    valid call of rclpy's ``Publisher.wait_for_all_acked``."""
    from rclpy.publisher import Publisher

    original = Publisher.wait_for_all_acked
    calls: list[str] = []

    def recording(self: Publisher, *args: Any, **kwargs: Any) -> bool:
        try:
            ok = original(self, *args, **kwargs)
        except Exception as err:
            calls.append(f"{self.topic_name}: {type(err).__name__}: {err}")
            raise
        calls.append(f"{self.topic_name}: ok" if ok else f"{self.topic_name}: not acknowledged")
        return ok

    monkeypatch.setattr(Publisher, "wait_for_all_acked", recording)
    test = GraphNode("test_replay_acks")
    test.start()
    try:
        replay(test.node, cut_bag, rate=0.0, log=lambda s: None)
    finally:
        test.close()
    assert calls, "replay did not wait for acknowledgements"
    assert all(c.endswith(": ok") for c in calls), "\n".join(calls)
