"""Faults through the real node (issue 6, item 2): parproj_node in its own process, DDS on
localhost, inputs published from rclpy nodes of the test, each in a Context (a DDS participant)
of its own, outputs recorded by another.

Input: bags/ikonos_agile (one view ``pan``, two 768-line scenes 70 s apart, 20 GCP + 8 check
points), with the navigation trimmed to 0.6 s before and 0.2 s after each scene, so that a copy
takes about a second to publish at one message every ``PACE_S``. Every case publishes a copy of
it whose scene ids, GCP ids and stamps are its own (``copy_of``): one node can take several
cases in turn, since the node drops strips older than those it has (bug 2) and never reuses a
scene id. The reference for every case is ``offline.process_bag`` of the very messages the case
publishes, or of the clean copy.

The node runs with its default input QoS (sensor data: best effort) for 1 and 2, with paced input
(unpaced, best effort lost 1 to 10 of the 24 strips in trials here), scenes of 768 lines (as in
the bag), tie points off (as the offline reference) and ``scene_timeout`` 1 s (default 2 s) to
keep this file at well under a minute.

1. A publisher restarting mid-scene (``publisher_faults``): the navigation publisher, then the
   strip publisher, is destroyed with its Context in the middle of the first scene and a new
   one (new participant, new writer) created after an outage longer than ``scene_timeout``; the
   new one re-sends the last samples before the cut, as a driver restarting from a checkpoint.
2. Messages lost under best effort (same session): two strips of the first scene omitted; a
   few navigation samples around the first scene omitted.
3. The node restarted mid-pass (``node_restart``, SIGKILL and SIGINT): node A gets the first
   scene and half of the second, is killed (or stopped), node B is started and gets the rest.
"""

from __future__ import annotations

import signal
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.duration import Duration
from rclpy.serialization import deserialize_message, serialize_message
from testkit.diagnostics import level, show
from testkit.live import GraphNode as Graph
from testkit.live import wait
from testkit.paths import BAGS

from parproj_ros.apps.process import process_bag
from parproj_ros.core.pipeline import Outputs, PairResult
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader, BagWriter, get_message_class
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import (
    NodeProcess,
    Recorder,
    _qos,
    node_params_yaml,
    ros_environment,
)

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # live node over DDS

BAG = BAGS / "ikonos_agile"
#: Pipeline settings of the node and of the offline reference: scenes end on their length (as
#: in the bag, 768 lines), tie points off.
CONFIG = {"tie_points": False, "scene_lines": 768}
SCENE_TIMEOUT_S = 1.0
NODE_PARAMS = {**CONFIG, "scene_timeout": SCENE_TIMEOUT_S}
RELIABLE = ["/navigation", "/pan/image_strip"]
PACE_S = 0.004  # one input message every 4 ms (best effort; unpaced, half the strips are lost)
NAV_BEFORE_S, NAV_AFTER_S = 0.6, 0.2  # navigation kept around each scene
INPUTS = {
    "gcp": "parproj_msgs/msg/GroundControlPoints",
    "navigation": "nav_msgs/msg/Odometry",
    "pan/image_strip": "sensor_msgs/msg/Image",
}
SCENES = ("pan_scene_0000", "pan_scene_0001")
WARN = DiagnosticStatus.WARN[0]
ERROR = DiagnosticStatus.ERROR[0]
SUMMARY = "parproj_node: summary"

Msg = tuple[int, str, Any]  # (log time ns, topic, message)


# ---- inputs -------------------------------------------------------------------------------------


def _clone(msg: Any) -> Any:
    return deserialize_message(serialize_message(msg), type(msg))


def _shift(header: Any, shift_ns: int) -> None:
    conv.ns_to_stamp(conv.stamp_to_ns(header.stamp) + shift_ns, header.stamp)


def base_messages(before_s: float = NAV_BEFORE_S, after_s: float = NAV_AFTER_S) -> list[Msg]:
    """GCP, strips, and the navigation from ``before_s`` before to ``after_s`` after each
    scene, in log-time order (as recorded)."""
    reader = BagReader(BAG)
    lp = views_from_bag(reader)[0].camera.line_period
    spans: dict[str, list[int]] = {}
    for m in reader.messages(topics=["pan/image_strip"]):
        t = conv.stamp_to_ns(m.msg.header.stamp)
        end = t + round(m.msg.height * lp * 1e9)
        span = spans.setdefault(m.msg.header.frame_id, [t, end])
        span[0], span[1] = min(span[0], t), max(span[1], end)
    before, after = round(before_s * 1e9), round(after_s * 1e9)
    out: list[Msg] = []
    for m in reader.messages(topics=list(INPUTS)):
        if m.topic == "navigation":
            t = conv.stamp_to_ns(m.msg.header.stamp)
            if not any(a - before <= t <= b + after for a, b in spans.values()):
                continue
        out.append((m.log_time_ns, m.topic, m.msg))
    assert sorted(spans) == list(SCENES)
    return out


def copy_of(base: Sequence[Msg], case: str, k: int) -> list[Msg]:
    """The messages as a new acquisition: stamps ``1000 k`` s later, scene ids and GCP ids
    prefixed with ``case``."""
    shift = k * 1000 * 10**9
    out: list[Msg] = []
    for t, topic, msg in base:
        m = _clone(msg)
        _shift(m.header, shift)
        if topic == "pan/image_strip":
            m.header.frame_id = f"{case}_{m.header.frame_id}"
        elif topic == "gcp":
            for p in m.points:
                p.id = f"{case}_{p.id}"
                for o in p.observations:
                    o.scene_id = f"{case}_{o.scene_id}"
        out.append((t + shift, topic, m))
    return out


def strips(msgs: Sequence[Msg], scene: str) -> list[int]:
    """Positions in ``msgs`` of the strips of ``scene`` (a scene id without the case prefix)."""
    return [
        i
        for i, (_, topic, m) in enumerate(msgs)
        if topic == "pan/image_strip" and m.header.frame_id.endswith(scene)
    ]


def write_bag(msgs: Iterable[Msg], path: Path) -> Path:
    """The messages as a bag, with the camera (``pan/scanner_info``) of bags/ikonos_agile."""
    reader = BagReader(BAG)
    info = "pan/scanner_info"
    with BagWriter(path, overwrite=True) as bw:
        for topic, msgtype in (*INPUTS.items(), (info, reader.topics()[info])):
            bw.add_topic(topic, msgtype, reader.qos(topic))
        for m in reader.messages(topics=[info]):
            bw.write(info, m.msg, m.log_time_ns)
        for t, topic, m in msgs:
            bw.write(topic, m, t)
    return path


def offline(msgs: Iterable[Msg], tmp: Path) -> dict[str, Any]:
    """``process_bag`` of these messages: its output bag's messages and the pipeline outputs."""
    outputs = Outputs()
    process_bag(
        write_bag(msgs, tmp / "input"),
        tmp / "output",
        progress=False,
        overrides=CONFIG,
        on_outputs=outputs.extend,
    )
    got: dict[str, list[Any]] = {t: [] for t in conv.OUTPUT_TOPICS}
    for m in BagReader(tmp / "output").messages():
        got[m.topic].append(m.msg)
    return {"messages": got, "outputs": outputs}


# ---- the live graph -----------------------------------------------------------------------------


class Source(Graph):
    """A publishing node for some input topics (the QoS of ``live.replay``: reliable writers,
    transient local for GCP; the node's readers decide: best effort by default)."""

    def __init__(self, name: str, topics: Iterable[str]) -> None:
        super().__init__(name)
        reader = BagReader(BAG)
        self.pubs = {
            t: self.node.create_publisher(get_message_class(INPUTS[t]), t, _qos(reader.qos(t)))
            for t in topics
        }

    def subscriber_gids(self) -> frozenset[bytes]:
        return frozenset(
            bytes(info.endpoint_gid)
            for pub in self.pubs.values()
            for info in self.node.get_subscriptions_info_by_topic(pub.topic_name)
        )

    def matched(self, exclude: frozenset[bytes] = frozenset()) -> bool:
        """Whether every topic has a subscription not in ``exclude`` (endpoints of a node that
        is gone, still listed after SIGKILL) and every listed one is matched by the writer."""
        for pub in self.pubs.values():
            infos = self.node.get_subscriptions_info_by_topic(pub.topic_name)
            if not any(bytes(i.endpoint_gid) not in exclude for i in infos):
                return False
            if pub.get_subscription_count() < len(infos):
                return False
        return True

    def wait_acked(self) -> None:
        for pub in self.pubs.values():
            pub.wait_for_all_acked(Duration(seconds=5))


def wait_matched(
    sources: Iterable[Source], exclude: frozenset[bytes] = frozenset(), settle_s: float = 0.5
) -> None:
    """Until every source is matched (:meth:`Source.matched`), then ``settle_s`` for the
    readers' side of discovery (see Recorder.wait_for_publishers)."""
    srcs = set(sources)
    assert wait(lambda: all(s.matched(exclude) for s in srcs), 20), "inputs not matched"
    time.sleep(settle_s)


def publish(sources: dict[str, Source], msgs: Iterable[Msg], sent: Counter[str]) -> None:
    """Publish in order, one message every PACE_S; count them by topic in ``sent``."""
    for _, topic, m in msgs:
        sources[topic].pubs[topic].publish(m)
        sent[topic] += 1
        time.sleep(PACE_S)


#: Output topics whose publishers tell one node from another (Listener.wait_node).
NODE_TOPICS = (
    "/parallel_projection",
    "/diagnostics",
    "/stereo_pair",
    "/left/image_normalized",
    "/right/image_normalized",
)


class Listener(Graph):
    """Records every output topic of the node (``/diagnostics`` included)."""

    def __init__(self, bag: Path) -> None:
        super().__init__("test_faults_listener")
        self.recorder = Recorder(self.node, bag, conv.OUTPUT_TOPICS)

    def messages(self, topic: str) -> list[Any]:
        with self.recorder._lock:
            return list(self.recorder.messages[topic])

    def statuses(self) -> list[DiagnosticStatus]:
        return [s for a in self.messages("/diagnostics") for s in a.status]

    def summary(self) -> dict[str, str]:
        """The node's latest 1 Hz summary (counts)."""
        sts = [s for s in self.statuses() if s.name == "parproj_node: summary"]
        return {kv.key: kv.value for kv in sts[-1].values} if sts else {}

    def publisher_gids(self) -> frozenset[bytes]:
        return frozenset(
            bytes(i.endpoint_gid)
            for t in NODE_TOPICS
            for i in self.node.get_publishers_info_by_topic(t)
        )

    def wait_node(self, exclude: frozenset[bytes] = frozenset()) -> None:
        """Until the outputs of a node (not those in ``exclude``) are discovered: every topic in
        NODE_TOPICS has a publisher not in ``exclude``. The image topics too: a pair flushed at
        SIGINT goes out on them at once, and a publisher with no matched reader yet counts as
        acknowledged (the pair lost, not late)."""
        subs = dict(zip(self.recorder.counts, self.recorder._subs, strict=True))

        def matched() -> bool:
            return all(
                any(
                    bytes(i.endpoint_gid) not in exclude
                    for i in self.node.get_publishers_info_by_topic(t)
                )
                for t in NODE_TOPICS
            ) and all(
                subs[t].get_publisher_count() > 0 for t in ("parallel_projection", "stereo_pair")
            )

        assert wait(matched, 20), "parproj_node outputs not discovered"


def about(sts: Iterable[DiagnosticStatus], case: str) -> list[DiagnosticStatus]:
    """Statuses of level WARN or above that name this case's scenes, GCP or pairs (the 1 Hz
    summary, which repeats the latest ERROR for ``error_hold_s``, excluded)."""
    return [
        s
        for s in sts
        if level(s) >= WARN and f"{case}_" in s.name + s.message and s.name != SUMMARY
    ]


# ---- comparisons --------------------------------------------------------------------------------


def by_scene(msgs: Iterable[Any], case: str) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {}
    for m in msgs:
        if m.scene_id.startswith(f"{case}_"):
            out.setdefault(m.scene_id, []).append(m)
    return out


def same_scene(got: Any, ref: Any, rtol: float = 0.0) -> None:
    assert (got.scene_id, got.method, got.lines, got.gcp_count) == (
        ref.scene_id,
        ref.method,
        ref.lines,
        ref.gcp_count,
    )
    np.testing.assert_allclose(np.array(got.affine), np.array(ref.affine), rtol=rtol, atol=0)
    assert got.roll_psi == pytest.approx(ref.roll_psi, rel=rtol, abs=1e-15)


def pair_of(messages: dict[str, list[Any]], case: str) -> tuple[Any, Any, Any] | None:
    """(StereoPair, left image, right image) of this case's pair (images by the pair's stamp),
    or None when they have not all arrived."""
    pairs = [p for p in messages["stereo_pair"] if p.pair_id.startswith(f"{case}_")]
    if not pairs:
        return None
    assert len(pairs) == 1, [p.pair_id for p in pairs]
    (sp,) = pairs
    stamp = conv.stamp_to_ns(sp.header.stamp)

    images = []
    for topic in ("left/image_normalized", "right/image_normalized"):
        found = [m for m in messages[topic] if conv.stamp_to_ns(m.header.stamp) == stamp]
        if not found:
            return None  # not yet received
        assert len(found) == 1
        images.append(conv.image_to_array(found[0]))
    return sp, images[0], images[1]


def same_pair(live: dict[str, list[Any]], ref: dict[str, list[Any]], case: str) -> None:
    """This case's scene parameters, normalization and images as in the offline reference."""
    got, want = (
        by_scene(live["parallel_projection"], case),
        by_scene(ref["parallel_projection"], case),
    )
    assert sorted(got) == sorted(want), (sorted(got), sorted(want))
    for sid, (r,) in want.items():
        assert len(got[sid]) == 1, f"{sid} published {len(got[sid])} times"
        same_scene(got[sid][0], r)
    a, b = pair_of(live, case), pair_of(ref, case)
    assert a is not None, f"no pair for {case}"
    assert b is not None
    assert a[0].pair_id == b[0].pair_id == f"{case}_{SCENES[0]}+{case}_{SCENES[1]}"
    for f in ("left_to_normalized", "right_to_normalized"):
        np.testing.assert_array_equal(getattr(a[0], f), getattr(b[0], f))
    assert (a[0].width, a[0].height) == (b[0].width, b[0].height)
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[2], b[2])


# ---- 1 and 2: publisher faults, one node ------------------------------------------------------


def node_session(tmp: Path, name: str, reliable: list[str]) -> tuple[Path, dict[str, str]]:
    """Parameters file and environment of a node (``reliable``: inputs made reliable)."""
    env = ros_environment(log_dir=tmp / "ros_log")
    views = views_from_bag(BagReader(BAG))
    pfile = node_params_yaml(
        node_parameters(views, **NODE_PARAMS), tmp / f"{name}.yaml", reliable_inputs=reliable
    )
    return pfile, env


def restart(sources: dict[str, Source], topic: str, last_publish: float) -> float:
    """Destroy the publisher of ``topic`` with its Context, and create a new one after an outage
    longer than scene_timeout; returns the outage in seconds."""
    old = sources[topic]
    old.wait_acked()
    old.close()
    time.sleep(max(0.0, last_publish + SCENE_TIMEOUT_S + 0.5 - time.monotonic()))
    new = Source(f"test_faults_{topic.replace('/', '_')}_restarted", [topic])
    wait_matched([new])
    for t in old.pubs:
        sources[t] = new
    return time.monotonic() - last_publish


#: Strips of the first scene lost in the best-effort case (positions in the scene, 0..11): two
#: single strips, so that each hole (64 lines) is within max_gap_lines and is filled.
LOST_STRIPS = (3, 8)
#: Two strips in a row lost (128 lines, more than max_gap_lines): the scene is split.
LOST_IN_A_ROW = (4, 5)
#: Navigation lost around the first scene: every sample from 0.1 s before its first strip to
#: 0.1 s after its last strip's first line (6 samples at 20 Hz: a hole of 0.35 s).
LOST_NAV_MARGIN_S = 0.1


def lose_strips(msgs: Sequence[Msg], which: Iterable[int] = LOST_STRIPS) -> list[Msg]:
    """The first scene without the strips ``which`` (positions in the scene)."""
    lost = {strips(msgs, SCENES[0])[k] for k in which}
    return [m for i, m in enumerate(msgs) if i not in lost]


def lose_navigation(msgs: Sequence[Msg]) -> list[Msg]:
    """Without the navigation from LOST_NAV_MARGIN_S before to after the first scene."""
    s0 = strips(msgs, SCENES[0])
    first = conv.stamp_to_ns(msgs[s0[0]][2].header.stamp) - LOST_NAV_MARGIN_S * 1e9
    last = conv.stamp_to_ns(msgs[s0[-1]][2].header.stamp) + LOST_NAV_MARGIN_S * 1e9
    return [
        (t, topic, m)
        for t, topic, m in msgs
        if topic != "navigation" or not first <= conv.stamp_to_ns(m.header.stamp) <= last
    ]


PUBLISHER_CASES = ("navrestart", "striprestart", "striploss", "stripsplit", "navloss")


@pytest.fixture(scope="module")
def publisher_faults(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """One node; the four cases in turn, each a copy of the trimmed bag of its own."""
    tmp = tmp_path_factory.mktemp("publisher_faults")
    t_start = time.monotonic()
    base = base_messages()
    cases = {case: copy_of(base, case, k) for k, case in enumerate(PUBLISHER_CASES, start=1)}
    sent_msgs = dict(cases)
    sent_msgs["striploss"] = lose_strips(cases["striploss"])
    sent_msgs["stripsplit"] = lose_strips(cases["stripsplit"], LOST_IN_A_ROW)
    sent_msgs["navloss"] = lose_navigation(cases["navloss"])
    clean = {c: offline(m, tmp / f"clean_{c}") for c, m in cases.items()}
    ref = {c: offline(sent_msgs[c], tmp / f"sent_{c}") for c in PUBLISHER_CASES[2:]}

    pfile, env = node_session(tmp, "params", reliable=[])  # the node's default: best effort
    proc = NodeProcess(pfile, env, tmp / "node.log")
    listener = Listener(tmp / "output")
    sources: dict[str, Source] = {}
    sent: Counter[str] = Counter()
    outages: dict[str, float] = {}
    result: dict[str, Any] = {"clean": clean, "ref": ref, "sent_msgs": sent_msgs}

    def alive() -> bool:
        return proc.proc.poll() is None

    try:
        for t in INPUTS:
            sources[t] = Source(f"test_faults_{t.replace('/', '_')}", [t])
        listener.wait_node()
        wait_matched(sources.values())
        for pairs, (case, msgs) in enumerate(sent_msgs.items(), start=1):
            if case in ("navrestart", "striprestart"):
                topic = "navigation" if case == "navrestart" else "pan/image_strip"
                cut = strips(msgs, SCENES[0])[5]  # after the 6th of 12 strips: mid-scene
                publish(sources, msgs[: cut + 1], sent)
                outages[case] = restart(sources, topic, time.monotonic())
                # The new publisher starts again a little before the cut (a checkpoint): the
                # last 3 navigation samples, or the last strip, are published once more.
                mine = [m for m in msgs[: cut + 1] if m[1] == topic]
                publish(sources, mine[-3 if topic == "navigation" else -1 :], sent)
                publish(sources, msgs[cut + 1 :], sent)
            else:
                publish(sources, msgs, sent)
            listener.recorder.wait_complete(pairs, 15, alive)

        def counted() -> bool:  # a 1 Hz summary after the last message
            s = listener.summary()
            return (s.get("strips"), s.get("nav"), s.get("queue")) == (
                str(sent["pan/image_strip"]),
                str(sent["navigation"]),
                "0",
            )

        wait(counted, 3, alive)
        result["alive"] = alive()
    finally:
        result["code"] = proc.stop()
        for src in set(sources.values()):
            src.close()
        listener.close()
        listener.recorder.close()
    result["log"] = proc.output()
    result["live"] = listener.recorder.messages
    result["statuses"] = listener.statuses()
    result["summary"] = listener.summary()
    result["sent"] = sent
    result["outages"] = outages
    print(f"publisher_faults: {time.monotonic() - t_start:.1f} s, outages {outages}")
    yield result


def test_node_survives_publisher_faults(publisher_faults: dict[str, Any]) -> None:
    """Running throughout, clean exit, and every message published was received (the pacing
    keeps best effort lossless here: what is lost is what the cases leave out)."""
    r = publisher_faults
    assert r["alive"] and r["code"] == 0, r["log"]
    assert "Traceback" not in r["log"], r["log"]
    summary = r["summary"]
    assert summary["strips"] == str(r["sent"]["pan/image_strip"]), (summary, r["sent"])
    assert summary["nav"] == str(r["sent"]["navigation"]), (summary, r["sent"])
    assert summary["pairs"] == str(len(PUBLISHER_CASES)), (summary, show(r["statuses"]))


@pytest.mark.parametrize("case", ["navrestart", "striprestart"])
def test_publisher_restart_mid_scene(case: str, publisher_faults: dict[str, Any]) -> None:
    """A publisher restarted mid-scene (new Context, new writer) after an outage longer than
    scene_timeout: the pair is that of the offline run, parameters and images. The restarted
    publisher's repeated navigation samples replace identical ones silently; its repeated strip
    is dropped as a duplicate, with a WARN."""
    r = publisher_faults
    assert r["outages"][case] > SCENE_TIMEOUT_S
    same_pair(r["live"], r["clean"][case]["messages"], case)
    sts = about(r["statuses"], case)
    if case == "navrestart":
        assert not sts, show(sts)
    else:
        (s,) = sts
        assert s.name == f"parproj_node: pan/{case}_{SCENES[0]}" and level(s) == WARN, show(sts)
        assert "duplicate" in s.message and "dropped" in s.message, s.message


def lost_line_masks(pair: PairResult, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(pixels of the left normalized image made only of lost lines, pixels made only of
    received lines): each output pixel's source line, through the pair's exact geometry."""
    grid = pair.left_grid
    assert shape == (grid.height, grid.width)
    rows, cols = np.mgrid[0 : grid.height, 0 : grid.width].astype(float)
    geom = pair.left.geometry(pair.normalization.left)
    line, sample = geom.normalized_to_image(
        grid.x_origin + cols * grid.pixel, grid.y_origin + rows * grid.pixel
    )
    inside = (sample >= 0) & (sample <= pair.left.scene.detectors - 1)
    lost = np.zeros(shape, bool)
    near = np.zeros(shape, bool)
    eps = 0.01  # the resampler's tiles follow the exact map to 0.004 px
    for k in LOST_STRIPS:
        a, b = 64 * k, 64 * k + 63  # first and last lost line
        lost |= inside & (line >= a + eps) & (line <= b - eps)
        near |= (line > a - 1 - eps) & (line < b + 1 + eps)  # bilinear: touches a lost line
    return lost, inside & ~near & (line >= 0) & (line <= pair.left.scene.lines - 1)


def test_strips_lost_under_best_effort(publisher_faults: dict[str, Any]) -> None:
    """Strips 3 and 8 of the first scene lost: a WARN names the scene and the 128 lines; the
    parameters of both scenes are unchanged (GCP and navigation do not depend on the pixels);
    the left normalized image is no-data exactly where the lost lines map and equal to the clean
    run's wherever only received lines contribute; the right image (the other scene) is
    unchanged; everything equals the offline run of the same messages."""
    r, case = publisher_faults, "striploss"
    lines = 64 * len(LOST_STRIPS)
    sts = about(r["statuses"], case)
    (s,) = sts
    assert s.name == f"parproj_node: pan/{case}_{SCENES[0]}" and level(s) == WARN, show(sts)
    assert s.message == f"{lines} missing lines filled with no-data (0.0)"
    same_pair(r["live"], r["ref"][case]["messages"], case)
    live_p = by_scene(r["live"]["parallel_projection"], case)
    clean_p = by_scene(r["clean"][case]["messages"]["parallel_projection"], case)
    for sid in clean_p:
        same_scene(live_p[sid][0], clean_p[sid][0])
    got, clean = pair_of(r["live"], case), pair_of(r["clean"][case]["messages"], case)
    assert got is not None and clean is not None
    np.testing.assert_array_equal(got[2], clean[2])  # the other scene
    (pair,) = r["ref"][case]["outputs"].pairs
    lost, kept = lost_line_masks(pair, got[1].shape)
    assert lost.sum() > 0.9 * lines * 768, lost.sum()  # about 1 px per line and detector
    assert np.all(got[1][lost] == 0), "lost lines not no-data"
    assert np.count_nonzero(clean[1][lost]) > 0.99 * lost.sum()  # they held data before
    np.testing.assert_array_equal(got[1][kept], clean[1][kept])


def test_strips_lost_in_a_row_split_the_scene(publisher_faults: dict[str, Any]) -> None:
    """Strips 4 and 5 of the first scene lost: 128 lines, more than max_gap_lines (64), so the
    scene is split, with a WARN naming it and the 128 lines. Its first part (256 lines) is
    paired with the other scene, whose parameters are unchanged; the second part is published
    and flagged as not paired (before: the two parts were paired with each other, and the
    other scene was left without a pair, silently). All as the offline run of the messages."""
    r, case = publisher_faults, "stripsplit"
    first, second = f"{case}_{SCENES[0]}", f"{case}_{SCENES[1]}"
    sts = [s for s in about(r["statuses"], case) if not s.name.startswith("parproj_node: gcp ")]
    assert [(s.name, level(s)) for s in sts] == [
        (f"parproj_node: pan/{first}", WARN),
        (f"parproj_node: pan/{first}#1", WARN),
    ], show(sts)
    assert (
        sts[0].message.startswith("128 lines missing after line 255") and "split" in sts[0].message
    )
    assert "not paired" in sts[1].message
    same_pair(r["live"], r["ref"][case]["messages"], case)
    live_p = by_scene(r["live"]["parallel_projection"], case)
    assert {sid: m[0].lines for sid, m in live_p.items()} == {
        first: 256,
        f"{first}#1": 384,
        second: 768,
    }
    clean_p = by_scene(r["clean"][case]["messages"]["parallel_projection"], case)
    same_scene(live_p[second][0], clean_p[second][0])


def test_navigation_lost_under_best_effort(publisher_faults: dict[str, Any]) -> None:
    """The 6 navigation samples around the first scene lost (a hole of 0.35 s at 20 Hz): no
    status (the hole is under max_gap_s, 1 s), and the parameters are those of the clean run to
    rounding. The trajectory is a straight line at constant attitude, so the fit through the
    samples left (0.10 s before the scene and 0.13 s after it) is the same line, up to the
    rounding of positions of about 7e5 m (1e-10 m) over a span of 0.35 s: 3e-10 m/s of
    7000 m/s, 4e-14 relative in the velocity and so in A1..A8 (1.4e-13 measured). Tolerance
    1e-11, relative. The images are the offline run's of the same messages."""
    r, case = publisher_faults, "navloss"
    kept = sum(1 for m in r["sent_msgs"][case] if m[1] == "navigation")
    full = sum(1 for m in copy_of(base_messages(), case, 0) if m[1] == "navigation")
    assert full - kept == 6
    assert not about(r["statuses"], case), show(about(r["statuses"], case))
    same_pair(r["live"], r["ref"][case]["messages"], case)
    live_p = by_scene(r["live"]["parallel_projection"], case)
    clean_p = by_scene(r["clean"][case]["messages"]["parallel_projection"], case)
    for sid in clean_p:
        same_scene(live_p[sid][0], clean_p[sid][0], rtol=1e-11)


# ---- 3: the node restarted mid-pass ------------------------------------------------------------


def restart_node(
    tmp: Path, case: str, k: int, how: signal.Signals, listener: Listener, sources: Source
) -> dict[str, Any]:
    """Node A gets the first scene and 6 of the 12 strips of the second; it is killed (or
    stopped); node B is started and gets the rest."""
    msgs = copy_of(base_messages(), case, k)
    cut = strips(msgs, SCENES[1])[5]
    before, rest = msgs[: cut + 1], msgs[cut + 1 :]
    res: dict[str, Any] = {
        "clean": offline(msgs, tmp / f"clean_{case}"),
        "before": offline(before, tmp / f"before_{case}"),
    }
    # Reliable inputs: a node started right after a SIGKILL discovers the running publishers
    # 0.5-1.5 s later than they discover it (seen here with Fast DDS); reliable delivery
    # repairs what best effort would lose in that window, so the "rest" is exactly the rest.
    pfile, env = node_session(tmp, case, reliable=RELIABLE)
    # The node's writers heartbeat every 100 ms (README, "Overload"): a datagram of the flushed
    # outputs lost on UDP is repaired at once, not at the default 3 s heartbeat. Without it the
    # stopped node's left/image_normalized was once not acknowledged within its 5 s wait at exit
    # and the listener never got the pair (CI of ce1162e; 4 times in 3 days before, unexplained).
    from tools.harness import FAST_REPAIR_PROFILE

    env = dict(env, FASTDDS_DEFAULT_PROFILES_FILE=str(FAST_REPAIR_PROFILE))
    old_pubs, old_subs = listener.publisher_gids(), sources.subscriber_gids()
    a = NodeProcess(pfile, env, tmp / f"{case}_a.log")
    sent: Counter[str] = Counter()
    try:
        listener.wait_node(exclude=old_pubs)
        wait_matched([sources], exclude=old_subs)
        publish({t: sources for t in INPUTS}, before, sent)

        def received() -> bool:  # A has every message and its queue is empty
            s = listener.summary()
            return (s.get("strips"), s.get("nav"), s.get("queue")) == (
                str(sent["pan/image_strip"]),
                str(sent["navigation"]),
                "0",
            )

        assert wait(received, 10), (listener.summary(), sent)
        first = f"{case}_{SCENES[0]}"
        assert wait(lambda: first in by_scene(listener.messages("parallel_projection"), case), 5)
        a_pubs, a_subs = listener.publisher_gids(), sources.subscriber_gids()
        if how == signal.SIGKILL:
            a.proc.kill()
            a.proc.wait()
            res["a_code"] = a.stop()
        else:
            res["a_code"] = a.stop()  # SIGINT: the node flushes and exits
            # 15 s: under the whole suite's load the flushed whole pair (images, reliable) once
            # took more than 5 s to reach the listener (CI, 2026-11-24).
            wait(lambda: pair_of(listener_messages(listener), case) is not None, 15)
    finally:
        a.stop()
    n_before = len(listener.statuses()), len(listener.messages("parallel_projection"))
    b = NodeProcess(pfile, env, tmp / f"{case}_b.log")
    try:
        listener.wait_node(exclude=old_pubs | a_pubs)
        wait_matched([sources], exclude=old_subs | a_subs)

        def b_has_gcp() -> bool:  # the transient-local GCP set reached B (a summary says so)
            return any(
                s.name == SUMMARY
                and int({kv.key: kv.value for kv in s.values}.get("gcp_points", "0")) > 0
                for s in listener.statuses()[n_before[0] :]
            )

        # Under load B once got the GCP only after the rest of the scene, and skipped it for
        # want of GCP ("navigation starts after ... no GCP") before the check meant here.
        assert wait(b_has_gcp, 10), "node B did not get the GCP set"
        publish({t: sources for t in INPUTS}, rest, sent)
        second = f"{case}_{SCENES[1]}"

        def answered() -> bool:  # B said something about the second scene
            new = listener.statuses()[n_before[0] :]
            pp = listener.messages("parallel_projection")[n_before[1] :]
            return any(second in s.name for s in new) or any(m.scene_id == second for m in pp)

        wait(answered, 3 * SCENE_TIMEOUT_S + 5, lambda: b.proc.poll() is None)
        res["b_alive"] = b.proc.poll() is None
    finally:
        res["b_code"] = b.stop()
    res["a_log"], res["b_log"] = a.output(), b.output()
    res["sent"] = sent
    res["b_statuses"] = listener.statuses()[n_before[0] :]
    return res


def listener_messages(listener: Listener) -> dict[str, list[Any]]:
    return {t: listener.messages(t) for t in conv.OUTPUT_TOPICS}


@pytest.fixture(scope="module")
def node_restart(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """SIGKILL, then SIGINT, in the middle of the second scene (one listener, one source)."""
    tmp = tmp_path_factory.mktemp("node_restart")
    t_start = time.monotonic()
    listener = Listener(tmp / "output")
    sources = Source("test_faults_inputs", INPUTS)
    result: dict[str, Any] = {}
    try:
        result["kill"] = restart_node(tmp, "kill", 11, signal.SIGKILL, listener, sources)
        result["int"] = restart_node(tmp, "int", 12, signal.SIGINT, listener, sources)
    finally:
        sources.close()
        listener.close()
        listener.recorder.close()
    result["live"] = listener.recorder.messages
    result["statuses"] = listener.statuses()
    result["bag"] = tmp / "output"
    print(f"node_restart: {time.monotonic() - t_start:.1f} s")
    yield result


def _restart_checks(r: dict[str, Any], case: str) -> None:
    res = r[case]
    assert res["b_alive"] and res["b_code"] == 0, res["b_log"]
    assert "Traceback" not in res["a_log"] + res["b_log"]
    assert "XMLPARSER" not in res["a_log"] + res["b_log"]  # the heartbeat profile was read
    # Node B: the rest of the second scene is not a scene: skipped, with an ERROR saying why.
    second = f"pan/{case}_{SCENES[1]}"
    errors = [s for s in res["b_statuses"] if s.name == f"parproj_node: {second}"]
    assert len(errors) == 1 and level(errors[0]) == ERROR, show(res["b_statuses"])
    msg = errors[0].message
    assert "384 lines" in msg and "skipped" in msg, msg
    others = [
        s
        for s in res["b_statuses"]
        if level(s) >= WARN and s is not errors[0] and s.name != SUMMARY
    ]
    assert not others, show(res["b_statuses"])


def test_node_killed_mid_pass(node_restart: dict[str, Any]) -> None:
    """SIGKILL in the middle of the second scene. Lost: the second scene and the pair (node A
    held half of the scene in memory; node B cannot tell where the scene began, so the half it
    gets is not published as a scene). Kept: the first scene's parameters, published by A before
    the kill, as in the offline run of the whole bag."""
    r, case = node_restart, "kill"
    assert r[case]["a_code"] == -signal.SIGKILL
    _restart_checks(r, case)
    recorded = BagReader(r["bag"]).messages(topics=["parallel_projection"])
    got = by_scene((m.msg for m in recorded), case)  # the recording, read back
    clean = by_scene(r[case]["clean"]["messages"]["parallel_projection"], case)
    assert sorted(got) == [f"{case}_{SCENES[0]}"], sorted(got)
    (first,) = got[f"{case}_{SCENES[0]}"]
    same_scene(first, clean[f"{case}_{SCENES[0]}"][0])
    assert pair_of(r["live"], case) is None


def test_node_stopped_mid_pass(node_restart: dict[str, Any]) -> None:
    """SIGINT in the middle of the second scene: node A flushes, so it publishes the half it
    has as a short scene (384 lines) with its pair, flagged by a WARN saying that the node
    stopped with the scene open; all of it equal to the offline run of what A received. Node B
    skips the other half, as after SIGKILL. The first scene is as in the whole-bag run."""
    r, case = node_restart, "int"
    assert r[case]["a_code"] == 0, r[case]["a_log"]
    _restart_checks(r, case)
    second = f"pan/{case}_{SCENES[1]}"
    stops = [
        s for s in r["statuses"] if s.name == f"parproj_node: {second}" and "stopping" in s.message
    ]
    assert len(stops) == 1 and level(stops[0]) == WARN, show(about(r["statuses"], case))
    assert "384 lines" in stops[0].message
    try:
        same_pair(r["live"], r[case]["before"]["messages"], case)
    except AssertionError as err:
        # Rare (4 times in 3 days, before node A had the heartbeat profile): the flushed
        # outputs missing at the listener. Node A's log says whether they were acknowledged.
        raise AssertionError(f"{err}\nnode A's log (end):\n{r[case]['a_log'][-4000:]}") from err
    got = by_scene(r["live"]["parallel_projection"], case)
    assert got[f"{case}_{SCENES[1]}"][0].lines == 384
    clean = by_scene(r[case]["clean"]["messages"]["parallel_projection"], case)
    same_scene(got[f"{case}_{SCENES[0]}"][0], clean[f"{case}_{SCENES[0]}"][0])
