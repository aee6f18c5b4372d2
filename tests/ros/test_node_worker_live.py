"""Inputs nobody tried, through the live node (issue 9): parproj_node in its own process, DDS on
localhost, inputs published from rclpy nodes of the test, outputs and /diagnostics recorded.

Before issue 9, rclpy fixed the severity of the one logging line of ``ParprojNode._report`` at its
first use, so the first ERROR after a WARN (or the reverse) raised ``ValueError: Logger severity
cannot be changed between calls`` inside the worker (or a callback): the worker died, nothing more
was processed, the summary kept saying OK and SIGINT hung. Here:

1. ``sequences``: two node sessions. ``warn_first``: a strip the node cannot convert (WARN), a
   navigation gap inside a scene (WARN, then ERROR: scene skipped), a clean acquisition.
   ``error_first``: a parameter refused at start (ERROR), a bad strip (WARN), an exception in the
   worker (ERROR), bad navigation (WARN), the navigation gap (WARN, ERROR), a bad strip (WARN),
   a clean acquisition. In both the clean pair must equal ``offline.process_bag`` of the same
   messages, every issue must reach /diagnostics, and SIGINT must end the node with code 0.
2. ``watchdog``: the worker held on one input longer than ``worker_stall_s`` (summary ERROR
   naming the input, then OK again), then the worker thread gone (summary ERROR; SIGINT: no flush,
   exit 1 at once); the worker held when SIGTERM comes (exit 1 after ``stop_timeout_s``).
3. Invalid parameters that have no safe default, an unparsable parameters file: exit 2, one line.

Faults that no input produces (an exception in the pipeline, a stall, the worker thread ending)
are injected by a launcher script of the test (``LAUNCHER``) that wraps two methods and then runs
``parproj_ros.ros.node.main``: production code has no test hook. The inputs are copies of
bags/ikonos_agile (``test_faults_live.copy_of``: own scene ids, GCP ids and stamps), with the
navigation from ``NAV_MARGIN_S`` before to after each scene; reliable inputs; tie points off.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from parproj_msgs.msg import GroundControlPoints
from sensor_msgs.msg import Image
from test_faults_live import (
    BAG,
    CONFIG,
    ERROR,
    INPUTS,
    RELIABLE,
    SCENES,
    SUMMARY,
    WARN,
    Listener,
    Msg,
    Source,
    _clone,
    _shift,
    about,
    by_scene,
    copy_of,
    level,
    offline,
    pair_of,
    same_pair,
    same_scene,
    show,
    strips,
    wait,
    wait_matched,
)
from test_faults_live import base_messages as faults_base_messages

from parproj_ros.core.pipeline import GroundPoint
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import NodeProcess, node_params_yaml, ros_environment
from parproj_ros.ros.startup import StartupError, check_mounting, check_views

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # live node over DDS

NAV_MARGIN_S = 1.5  # navigation kept before and after each scene
GAP_MARGIN_S = 0.6  # the navigation gap: from this long before the scene's first line to after
OK = 0
STOP_BOUND_S = 10.0  # a clean SIGINT, queue empty: the node ends well within this

#: Runs parproj_node with faults injected by GCP ids: "inject_raise" makes Pipeline.add_gcp
#: raise, "inject_stall_<s>" makes it sleep <s> seconds, "inject_kill_worker" ends the worker
#: thread (its queue hands it the end marker), as if it had died.
LAUNCHER = """
import sys, time
from parproj_ros.core import pipeline, session
from parproj_ros.ros import node

_add_gcp = pipeline.Pipeline.add_gcp


def add_gcp(self, points):
    for p in points:
        if p.id == "inject_raise":
            raise RuntimeError("injected by the test")
        if p.id.startswith("inject_stall_"):
            time.sleep(float(p.id.rsplit("_", 1)[1]))
    return _add_gcp(self, points)


pipeline.Pipeline.add_gcp = add_gcp
_run = session.Worker._run


def run(self):
    get = self._queue.get

    def get_or_die(*args, **kwargs):
        item = get(*args, **kwargs)
        if item and item[0] == "gcp" and any(p.id == "inject_kill_worker" for p in item[1]):
            return None
        return item

    self._queue.get = get_or_die
    _run(self)


session.Worker._run = run
sys.exit(node.main())
"""


# ---- inputs -------------------------------------------------------------------------------------


def base_messages() -> list[Msg]:
    """GCP, strips, and the navigation from NAV_MARGIN_S before to after each scene."""
    return faults_base_messages(NAV_MARGIN_S, NAV_MARGIN_S)


def navigation_gap(msgs: Sequence[Msg]) -> list[Msg]:
    """No GCP, and no navigation from GAP_MARGIN_S before the first scene's first line to
    GAP_MARGIN_S after its last strip: a gap of 1.3 s (> max_gap_s, 1 s) around the scene."""
    s0 = strips(msgs, SCENES[0])
    a = conv.stamp_to_ns(msgs[s0[0]][2].header.stamp) - GAP_MARGIN_S * 1e9
    b = conv.stamp_to_ns(msgs[s0[-1]][2].header.stamp) + GAP_MARGIN_S * 1e9
    return [
        (t, topic, m)
        for t, topic, m in msgs
        if topic != "gcp"
        and not (topic == "navigation" and a < conv.stamp_to_ns(m.header.stamp) < b)
    ]


def no_base(base: Sequence[Msg], case: str, k: int) -> list[Msg]:
    """The first scene twice, as two scenes of one pass: ``copy_of`` (no GCP) its strips and
    the navigation around them, then the same again, stamps shifted past them and scene id
    ``<case>_again_<scene>``: one position and attitude for both, so the pair (2k, 2k+1) has
    no stereo base."""
    first = copy_of(base, case, k)
    s0 = strips(first, SCENES[0])
    lo = conv.stamp_to_ns(first[s0[0]][2].header.stamp) - round(NAV_MARGIN_S * 1e9)
    hi = conv.stamp_to_ns(first[s0[-1]][2].header.stamp) + round((NAV_MARGIN_S + 0.5) * 1e9)
    part = [
        (t, topic, m)
        for i, (t, topic, m) in enumerate(first)
        if i in s0 or (topic == "navigation" and lo <= conv.stamp_to_ns(m.header.stamp) <= hi)
    ]
    shift = hi - lo
    again: list[Msg] = []
    for t, topic, m in part:
        m = _clone(m)
        _shift(m.header, shift)
        if topic == "pan/image_strip":
            m.header.frame_id = m.header.frame_id.replace(f"{case}_", f"{case}_again_", 1)
        again.append((t + shift, topic, m))
    return part + again


def bad_strip(frame_id: str) -> Image:
    arr = np.zeros((64, 768), np.uint16)
    msg = conv.array_to_image(arr, Image(), frame_id=frame_id, stamp_ns=1_000_000_000)
    msg.encoding = "rgb8"
    return msg


def bad_navigation() -> Odometry:
    m = Odometry()
    m.header.stamp.sec = 1
    m.header.frame_id, m.child_frame_id = "map", "base_link"
    m.pose.pose.orientation.w = float("nan")
    return m


def gcp_marker(point_id: str) -> GroundControlPoints:
    """A GroundControlPoints message with one point whose id triggers an injected fault."""
    pt = GroundPoint(point_id, np.zeros(3), False, {})
    return conv.gcp_to_msg([pt], GroundControlPoints(), frame_id="map", stamp_ns=0)


def publish(sources: dict[str, Source], msgs: Sequence[Msg], sent: Counter[str]) -> None:
    for _, topic, m in msgs:
        sources[topic].pubs[topic].publish(m)
        sent[topic] += 1
        time.sleep(0.001)


# ---- the node -----------------------------------------------------------------------------------


def start_node(
    tmp: Path, name: str, extra: dict[str, Any], launcher: bool = True
) -> tuple[NodeProcess, float]:
    """parproj_node (through LAUNCHER unless ``launcher`` is false) with the bag's camera,
    CONFIG, reliable inputs and ``extra`` parameters; returns it and its start time."""
    views = views_from_bag(BagReader(BAG))
    params = node_parameters(views, **CONFIG, scene_timeout=1.0, **extra)
    pfile = node_params_yaml(params, tmp / f"{name}.yaml", reliable_inputs=RELIABLE)
    program = None
    if launcher:
        script = tmp / "launch_with_faults.py"
        script.write_text(LAUNCHER)
        program = [sys.executable, str(script)]
    env = ros_environment(log_dir=tmp / "ros_log")
    return NodeProcess(pfile, env, tmp / f"{name}.log", program), time.monotonic()


def stop_timed(proc: NodeProcess, how: signal.Signals = signal.SIGINT) -> tuple[int, float]:
    """Signal the node; its exit code and the seconds it took to end (killed after 60 s)."""
    t0 = time.monotonic()
    if proc.proc.poll() is None:
        proc.proc.send_signal(how)
    try:
        proc.proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.proc.kill()
        proc.proc.wait()
    seconds = time.monotonic() - t0
    return proc.stop(), seconds


def summaries(listener: Listener) -> list[Any]:
    return [s for s in listener.statuses() if s.name == SUMMARY]


def values(status: Any) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


# ---- 1. severity sequences ----------------------------------------------------------------------

#: session -> (parameters, the steps in order). Steps: "bad_strip", "bad_nav", "raise" (an
#: exception in the worker), "navgap" (a copy with the navigation gap), "nobase" (a pair
#: without stereo base: ``no_base``), "clean" (a clean copy).
SESSIONS: dict[str, tuple[dict[str, Any], tuple[str, ...]]] = {
    "warn_first": ({"error_hold_s": 2.0}, ("bad_strip", "navgap", "nobase", "clean")),
    "error_first": (
        # refused at start (range 0..0.5): ERROR, default used; a misspelt parameter (ERROR,
        # ignored); and an unusable gcp_file
        {"segment_overlap": 0.9, "pan.principle_distance": 10.0},
        ("bad_strip", "raise", "bad_nav", "navgap", "bad_strip", "nobase", "clean"),
    ),
}


@pytest.fixture(scope="module", params=sorted(SESSIONS))
def sequence(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[dict[str, Any]]:
    session = request.param
    extra, steps = SESSIONS[session]
    tmp = tmp_path_factory.mktemp(session)
    if session == "error_first":  # and a GCP file that cannot be used: ERROR at start
        gcp_file = tmp / "gcp.csv"
        gcp_file.write_text("id,X,Y,Z,check,scene_id,line,sample\ng01,nan,0,0,0,s,1,1\n")
        extra = {**extra, "gcp_file": str(gcp_file)}
    base = base_messages()
    gap_msgs = navigation_gap(copy_of(base, f"{session}gap", 1))
    nobase_msgs = no_base(base, f"{session}nobase", 2)
    clean_msgs = copy_of(base, f"{session}clean", 3)
    ref = {
        "gap": offline(gap_msgs, tmp / "ref_gap"),
        "nobase": offline(nobase_msgs, tmp / "ref_nobase"),
        "clean": offline(clean_msgs, tmp / "ref"),
    }
    proc, t_start = start_node(tmp, "node", extra, launcher=session == "error_first")
    listener = Listener(tmp / "output")
    sources = {t: Source(f"test_worker_{session}_{t.replace('/', '_')}", [t]) for t in INPUTS}
    sent: Counter[str] = Counter()
    res: dict[str, Any] = {"ref": ref, "session": session, "steps": steps}

    def alive() -> bool:
        return proc.proc.poll() is None

    try:
        listener.wait_node()
        wait_matched(sources.values())
        for k, step in enumerate(steps):
            if step == "bad_strip":
                publish(sources, [(0, "pan/image_strip", bad_strip(f"bad{k}"))], sent)
            elif step == "bad_nav":
                publish(sources, [(0, "navigation", bad_navigation())], sent)
            elif step == "raise":
                publish(sources, [(0, "gcp", gcp_marker("inject_raise"))], sent)
            elif step == "navgap":
                publish(sources, gap_msgs, sent)
            elif step == "nobase":
                publish(sources, nobase_msgs, sent)
            else:
                publish(sources, clean_msgs, sent)
            for src in sources.values():
                src.wait_acked()
            # Let the worker take each step before the next (the ERRORs come in order).
            wait(lambda: listener.summary().get("queue") == "0", 10, alive)
        res["pair_arrived"] = wait(
            lambda: (
                pair_of({t: listener.messages(t) for t in conv.OUTPUT_TOPICS}, f"{session}clean")
                is not None
            ),
            30,
            alive,
        )

        def counted() -> bool:  # a summary after the last input
            s = listener.summary()
            return (s.get("strips", "0"), s.get("queue")) == (
                str(sent["pan/image_strip"] - steps.count("bad_strip")),
                "0",
            )

        wait(counted, 5, alive)
        if session == "warn_first":  # the summary back at OK once error_hold_s has passed
            wait(lambda: level(summaries(listener)[-1]) == OK, 10, alive)
        res["alive"] = alive()
    finally:
        res["code"], res["stop_s"] = stop_timed(proc)
        for src in sources.values():
            src.close()
        listener.close()
        listener.recorder.close()
    res["log"] = proc.output()
    res["live"] = listener.recorder.messages
    res["statuses"] = listener.statuses()
    res["seconds"] = time.monotonic() - t_start
    print(f"{session}: {res['seconds']:.1f} s, stopped in {res['stop_s']:.2f} s")
    yield res


def test_node_keeps_working_after_both_severities(sequence: dict[str, Any]) -> None:
    """WARN then ERROR (or ERROR then WARN, and alternating): the node is still up, has no
    traceback, counts no rejected input twice, and ends on SIGINT with code 0, quickly."""
    r = sequence
    assert r["alive"], r["log"]
    assert r["code"] == 0 and r["stop_s"] < STOP_BOUND_S, (r["code"], r["stop_s"], r["log"])
    assert "Traceback" not in r["log"] and "severity cannot be changed" not in r["log"], r["log"]
    last = values(summaries_of(r)[-1])
    assert last["strips_rejected"] == str(r["steps"].count("bad_strip")), last
    assert last["nav_rejected"] == str(r["steps"].count("bad_nav")), last
    assert last["internal_errors"] == str(r["steps"].count("raise")), last
    assert last["worker"] == "alive" and last["queue"] == "0", last


def summaries_of(r: dict[str, Any]) -> list[Any]:
    return [s for s in r["statuses"] if s.name == SUMMARY]


def test_good_pair_after_the_sequence(sequence: dict[str, Any]) -> None:
    """The clean acquisition after it all: parameters, normalization and images equal to the
    offline run of the same messages; y-parallax (GCP, through the normalization) as offline
    and within the tolerance of the bag's other live tests (0.1 px rms)."""
    r = sequence
    case = f"{r['session']}clean"
    assert r["pair_arrived"], r["log"]
    same_pair(r["live"], r["ref"]["clean"]["messages"], case)
    (sp,) = [p for p in r["live"]["stereo_pair"] if p.pair_id.startswith(case)]
    (ref,) = r["ref"]["clean"]["messages"]["stereo_pair"]
    assert (sp.y_parallax_rms_px, sp.y_parallax_max_px) == (
        ref.y_parallax_rms_px,
        ref.y_parallax_max_px,
    )
    assert sp.y_parallax_points > 0 and sp.y_parallax_rms_px <= 0.1, sp.y_parallax_rms_px
    assert not about(r["statuses"], case), show(about(r["statuses"], case))


def test_navigation_gap_inside_a_scene(sequence: dict[str, Any]) -> None:
    """No navigation for 1.3 s around the first scene (and no GCP): that scene is skipped with a
    WARN (the gap) and an ERROR (skipped), exactly the statuses of the offline run; the other
    scene's parameters are the offline run's."""
    r = sequence
    case = f"{r['session']}gap"
    want = [
        (f"parproj_node: {i.where}", {"warn": WARN, "error": ERROR}[i.level], i.message)
        for i in r["ref"]["gap"]["outputs"].issues
        if i.level in ("warn", "error")
    ]
    got = [(s.name, level(s), s.message) for s in about(r["statuses"], case)]
    assert got == want, show(about(r["statuses"], case))
    first = f"pan/{case}_{SCENES[0]}"
    assert [x[1] for x in got if x[0] == f"parproj_node: {first}"] == [WARN, ERROR], got
    assert any("navigation gap of 1.3" in x[2] for x in got), got
    assert any("skipped" in x[2] and x[1] == ERROR for x in got), got
    live = by_scene(r["live"]["parallel_projection"], case)
    ref = by_scene(r["ref"]["gap"]["messages"]["parallel_projection"], case)
    assert sorted(live) == sorted(ref) == [f"{case}_{SCENES[1]}"], (sorted(live), sorted(ref))
    same_scene(live[f"{case}_{SCENES[1]}"][0], ref[f"{case}_{SCENES[1]}"][0])


def test_pair_without_stereo_base(sequence: dict[str, Any]) -> None:
    """The same scene twice as a pair (one position and attitude): one ERROR naming the pair
    and the reason, exactly the offline run's statuses; both scenes' parameters as offline; no
    pair published; the node carries on (the clean pair after it: test_good_pair_after_...)."""
    r = sequence
    case = f"{r['session']}nobase"
    first, again = f"{case}_{SCENES[0]}", f"{case}_again_{SCENES[0]}"
    want = [
        (f"parproj_node: {i.where}", {"warn": WARN, "error": ERROR}[i.level], i.message)
        for i in r["ref"]["nobase"]["outputs"].issues
        if i.level in ("warn", "error")
    ]
    got = [(s.name, level(s), s.message) for s in about(r["statuses"], case)]
    assert got == want, show(about(r["statuses"], case))
    ((name, lvl, message),) = got
    assert (name, lvl) == (f"parproj_node: pair {first}+{again}", ERROR), got
    assert "no usable stereo base" in message and "pair skipped" in message, message
    assert pair_of(r["live"], case) is None
    assert not [p for p in r["live"]["stereo_pair"] if p.pair_id.startswith(case)]
    live = by_scene(r["live"]["parallel_projection"], case)
    ref = by_scene(r["ref"]["nobase"]["messages"]["parallel_projection"], case)
    assert sorted(live) == sorted(ref) == sorted([first, again]), (sorted(live), sorted(ref))
    for sid in ref:
        same_scene(live[sid][0], ref[sid][0])


def test_every_issue_reached_diagnostics(sequence: dict[str, Any]) -> None:
    """The bad strips and navigation (WARN), the refused parameter and the injected exception
    (ERROR, named and counted) are on /diagnostics; the summary is ERROR after an ERROR."""
    r = sequence
    sts = r["statuses"]
    for k, step in enumerate(r["steps"]):
        if step == "bad_strip":
            hits = [s for s in sts if s.name == f"parproj_node: pan/bad{k}"]
            assert len(hits) == 1 and level(hits[0]) == WARN, show(sts)
        elif step == "bad_nav":
            hits = [s for s in sts if s.name == "parproj_node: navigation"]
            assert len(hits) == 1 and level(hits[0]) == WARN, show(sts)
        elif step == "raise":
            (s,) = [s for s in sts if s.name == "parproj_node: internal error"]
            assert level(s) == ERROR
            assert s.message.startswith("RuntimeError: injected by the test at "), s.message
            assert "while processing a GCP set (1 points)" in s.message, s.message
            assert "the node carries on (1 internal errors so far)" in s.message, s.message
    levels = [level(s) for s in summaries_of(r)]
    if r["session"] == "error_first":  # a parameter refused at start: ERROR throughout
        assert set(levels) == {ERROR}, levels
        first = summaries_of(r)[0].message
        assert "at start: parameter segment_overlap: " in first, first
        assert (
            "parameter pan.principle_distance: 10.0 given, but parproj_node has no such" in first
        )
        gcp = first[first.index("gcp_file: ") :]
        assert "gcp.csv" in gcp and "continuing without it" in gcp, first
    else:  # OK, ERROR for error_hold_s after the scene was skipped, OK again
        assert levels[0] == OK and levels[-1] == OK, levels
        errs = [s for s in summaries_of(r) if level(s) == ERROR]
        assert errs and "errors so far, the latest" in errs[0].message, levels
        assert "scene skipped" in errs[0].message, errs[0].message


# ---- 2. the watchdog and the stop ---------------------------------------------------------------


def marker_source(name: str) -> Source:
    """A GCP publisher of its own (transient local, as the node's reader needs: a node started
    later would get the last marker of an old one)."""
    src = Source(name, ["gcp"])
    assert wait(lambda: src.pubs["gcp"].get_subscription_count() >= 1, 20)
    time.sleep(0.5)
    return src


@pytest.fixture(scope="module")
def watchdog(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """Node A (worker_stall_s 1): the worker held 3 s on a GCP set, then its thread ended;
    SIGINT. Then node B (stop_timeout_s 2): the worker held 60 s when SIGTERM comes."""
    tmp = tmp_path_factory.mktemp("watchdog")
    params = {"worker_stall_s": 1.0, "stop_timeout_s": 2.0}
    listener = Listener(tmp / "output")
    res: dict[str, Any] = {}
    a, _ = start_node(tmp, "a", params)
    src = None
    try:
        listener.wait_node()
        src = marker_source("test_worker_watchdog_a")
        src.pubs["gcp"].publish(gcp_marker("inject_stall_3"))

        def stalled() -> bool:
            return any(
                level(s) == ERROR and "has been processing a GCP set (1 points)" in s.message
                for s in summaries(listener)
            )

        res["stalled"] = wait(stalled, 10)
        n = len(summaries(listener))
        res["recovered"] = wait(
            lambda: sum(level(s) == OK for s in summaries(listener)[n:]) >= 2, 10
        )
        src.pubs["gcp"].publish(gcp_marker("inject_kill_worker"))
        res["dead"] = wait(
            lambda: any(values(s).get("worker") == "dead" for s in summaries(listener)), 10
        )
        res["dead_summary"] = next(
            (s for s in summaries(listener) if values(s).get("worker") == "dead"), None
        )
        res["a_code"], res["a_stop_s"] = stop_timed(a)
    finally:
        a.stop()
        if src is not None:
            src.close()
    res["a_log"] = a.output()
    res["a_statuses"] = listener.statuses()
    old = listener.publisher_gids()
    b, _ = start_node(tmp, "b", params)
    src = None
    try:
        listener.wait_node(exclude=old)
        src = marker_source("test_worker_watchdog_b")
        n = len(summaries(listener))
        src.pubs["gcp"].publish(gcp_marker("inject_stall_60"))
        res["b_stalled"] = wait(
            lambda: any(
                level(s) == ERROR and "has been processing" in s.message
                for s in summaries(listener)[n:]
            ),
            10,
        )
        res["b_code"], res["b_stop_s"] = stop_timed(b, signal.SIGTERM)
    finally:
        b.stop()
        if src is not None:
            src.close()
        listener.close()
        listener.recorder.close()
    res["b_log"] = b.output()
    print(f"watchdog: A stopped in {res['a_stop_s']:.2f} s, B in {res['b_stop_s']:.2f} s")
    yield res


def test_watchdog_stalled_worker(watchdog: dict[str, Any]) -> None:
    """The worker 3 s on one input (worker_stall_s 1 s): the summary turns ERROR and says on
    what and for how long; once the input is done, it is OK again (no ERROR was reported)."""
    r = watchdog
    assert r["stalled"] and r["recovered"], show(r["a_statuses"])
    s = next(
        s for s in r["a_statuses"] if s.name == SUMMARY and "has been processing" in s.message
    )
    v = values(s)
    # Reported once over worker_stall_s (1 s); busy_s is shown to 0.1 s, so 1.04 s reads 1.0.
    assert v["busy_with"] == "a GCP set (1 points)" and float(v["busy_s"]) >= 1.0, v
    assert "(more than worker_stall_s, 1 s)" in s.message, s.message


def test_watchdog_dead_worker_and_sigint(watchdog: dict[str, Any]) -> None:
    """The worker thread gone: the summary is ERROR ("not running"); SIGINT does not wait for
    a flush no one would do: an ERROR says so and the node exits with code 1 at once."""
    r = watchdog
    assert r["dead"], show(r["a_statuses"])
    s = r["dead_summary"]
    assert level(s) == ERROR and "the worker thread is not running" in s.message, s.message
    assert r["a_code"] == 1 and r["a_stop_s"] < STOP_BOUND_S, (r["a_code"], r["a_stop_s"])
    assert "the worker thread is not running: open scenes lost" in r["a_log"], r["a_log"]
    assert "Traceback" not in r["a_log"], r["a_log"]


def test_sigterm_with_the_worker_held(watchdog: dict[str, Any]) -> None:
    """SIGTERM while the worker is held (60 s) on one input: the flush waits stop_timeout_s
    (2 s), an ERROR says why, and the node exits with code 1 soon after."""
    r = watchdog
    assert r["b_stalled"], r["b_log"]
    assert r["b_code"] == 1, (r["b_code"], r["b_log"])
    assert 2.0 <= r["b_stop_s"] < 2.0 + STOP_BOUND_S, r["b_stop_s"]
    assert "not flushed: stop_timeout_s (2 s) passed with the worker on a GCP set" in r["b_log"]
    assert "Traceback" not in r["b_log"], r["b_log"]


# ---- 3. parameters that cannot be replaced, parameters file -------------------------------------

#: case -> (what the parameters file holds, in place of the good one, or None: the good
#: parameters with ``override``), override, what the one line must say)
BAD_START: dict[str, tuple[str | None, dict[str, Any], str]] = {
    "views empty": (None, {"views": []}, "parameter views: no view names given"),
    "views three": (None, {"views": ["a", "b", "c"]}, "has 3 names"),
    "views twice": (None, {"views": ["pan", "pan"]}, "names the same view twice"),
    "views not a name": (None, {"views": ["pan/x"]}, "'pan/x' is not a valid view name"),
    "views a string": (None, {"views": "pan"}, "'pan' is not a list of view names"),
    "mounting NaN": (
        None,
        {"pan.mounting_rpy_deg": [0.0, float("nan"), 0.0]},
        "parameter pan.mounting_rpy_deg: [0.0, nan, 0.0]: each angle must be finite",
    ),
    "mounting two": (
        None,
        {"pan.mounting_rpy_deg": [0.0, 1.0]},
        "parameter pan.mounting_rpy_deg: [0.0, 1.0] is not 3 numbers",
    ),
    "file unparsable": (
        "parproj_node:\n  ros__parameters:\n    z_avg: [1, 'a'\n",
        {},
        "cannot parse the parameters file",
    ),
    "file missing": ("", {}, "No such file or directory"),
    "file a FIFO": ("@fifo", {}, "not a regular file"),
    "file too large": ("@large", {}, "more than the 16777216 bytes"),
}


@pytest.fixture(scope="module")
def bad_start(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[int, str, Path]]:
    """Every BAD_START case, the node processes started together: exit code, output, file."""
    tmp = tmp_path_factory.mktemp("bad_start")
    views = views_from_bag(BagReader(BAG))
    env = ros_environment(log_dir=tmp / "ros_log")
    procs = {}
    for k, (case, (text, override, _)) in enumerate(sorted(BAD_START.items())):
        path = tmp / f"params_{k}.yaml"
        if text is None:
            params = {**node_parameters(views, **CONFIG), **override}
            node_params_yaml(params, path, reliable_inputs=[])
        elif text == "@fifo":
            os.mkfifo(path)  # rcl would wait for a writer forever
        elif text == "@large":
            path.write_text("# padding\n" * (17 * 1024 * 1024 // 10))
        elif text:
            path.write_text(text)
        cmd = [
            sys.executable,
            "-m",
            "parproj_ros.ros.node",
            "--ros-args",
            "--params-file",
            str(path),
        ]
        procs[case] = (
            subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT),
            path,
        )
    out = {}
    for case, (p, path) in procs.items():
        try:
            text, _ = p.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            p.kill()
            text, _ = p.communicate()
        out[case] = (int(p.returncode), text.decode(errors="replace"), path)
    return out


@pytest.mark.parametrize("case", sorted(BAD_START))
def test_invalid_start_exits_2_with_one_line(
    case: str, bad_start: dict[str, tuple[int, str, Path]]
) -> None:
    code, text, path = bad_start[case]
    says = BAD_START[case][2]
    lines = text.strip().splitlines()
    assert code == 2, text
    assert len(lines) == 1 and lines[0].startswith("parproj_node: cannot start: "), text
    assert says in lines[0], lines[0]
    if case.startswith("file"):
        assert path.name in lines[0], lines[0]


def test_checks_of_views_and_mounting() -> None:
    """The checks themselves (no ROS): integers are numbers; bools and strings are not."""
    assert check_views(["pan"]) == ["pan"]
    assert check_views(["left", "right_2"]) == ["left", "right_2"]
    assert check_mounting("m", [1, 2, 3]) == (1.0, 2.0, 3.0)
    assert check_mounting("m", (0.0, -360.0, 360.0)) == (0.0, -360.0, 360.0)
    for bad in (["_hidden"], ["2pan"], ["a b"], [""], [1], None, "pan", [], ["a", "b", "c"]):
        with pytest.raises(StartupError, match="parameter views"):
            check_views(bad)
    for m in ([0, 0], [0, 0, 0, 0], [True, 0, 0], "abc", [0, 0, float("inf")], [361.0, 0, 0]):
        with pytest.raises(StartupError, match="parameter m: "):
            check_mounting("m", m)


# ---- 4. in process: reporting that fails, exceptions in callbacks -------------------------------


@pytest.fixture
def node_in_process(monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """A ParprojNode in this process (its own Context; default parameters), stopped after."""
    import os

    import rclpy
    from rclpy.context import Context

    from parproj_ros.ros.node import ParprojNode

    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    ctx = Context()
    rclpy.init(context=ctx)
    node = ParprojNode(context=ctx)
    try:
        yield node
    finally:
        node.stop(5.0)
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_reporting_cannot_fail(node_in_process: Any, capsys: pytest.CaptureFixture[str]) -> None:
    """Every severity in turn on one node (the old _report raised at the second); then
    publishing /diagnostics raising: the issues go to stderr and nothing is raised."""
    from parproj_ros.core.pipeline import Issue

    node = node_in_process
    for lv in ("warn", "error", "warn", "ok", "error", "ok", "warn"):
        node._report([Issue(lv, "here", f"a {lv}")])
    assert (node.counts["warnings"], node.counts["errors"]) == (3, 2)

    def broken(msg: Any) -> None:
        raise RuntimeError("publisher gone")

    node.pub_diag.publish = broken
    node._report([Issue("error", "there", "after the publisher broke")])
    node.internal_error("a test input", ValueError("boom"))
    err = capsys.readouterr().err
    assert "reporting failed (RuntimeError: publisher gone)" in err, err
    assert "[error] there: after the publisher broke" in err, err
    assert "ValueError: boom" in err and node.counts["internal_errors"] == 1, err


def test_a_block_that_cannot_be_published(node_in_process: Any) -> None:
    """The node's block sink (blocks published as rendered, inside the streamer's loop): a
    block whose publishing raises, or whose pixels no Image carries, is counted and reported,
    and nothing is raised into the streamer; the next block is published."""
    from dataclasses import replace

    from parproj_ros.core.results import BlockResult
    from parproj_ros.imaging.resample import OutputGrid

    node = node_in_process
    sent: list[Any] = []

    def publish(raw: Any) -> None:
        sent.append(raw)
        if len(sent) == 1:
            raise RuntimeError("writer gone")

    pub = node.pubs["left/normalized_block"]
    pub.publish = publish
    grid = OutputGrid(1.0, 0.0, 0.0, 8, 4)
    blk0 = BlockResult(
        "p0", "left", 0, 0, np.arange(8, dtype=np.uint16).reshape(4, 2), grid, 5, False
    )
    # Nobody subscribed: nothing is built nor sent (volatile), the block is counted.
    before = node.blocks_unsubscribed
    node._publish_block(blk0)
    assert not sent and node.blocks_unsubscribed == before + 1
    pub.get_subscription_count = lambda: 1  # a subscriber from now on
    blk = BlockResult(
        "p0", "left", 0, 0, np.arange(8, dtype=np.uint16).reshape(4, 2), grid, 5, False
    )
    node._publish_block(blk)  # raises in publish
    node._publish_block(replace(blk, index=1, image=np.zeros((4, 2), np.complex64)))
    node._publish_block(replace(blk, index=2, col0=2))
    assert node.counts["internal_errors"] == 2, node.counts
    assert len(sent) == 2 and isinstance(sent[1], bytes | bytearray | memoryview), sent
    assert node.worker.alive


def test_worker_and_callbacks_survive_exceptions(node_in_process: Any) -> None:
    """An exception in the pipeline (the worker), a message a callback cannot read, a flush
    that raises: each counted and reported; the worker is alive and serves the next input."""
    node = node_in_process
    calls: list[str] = []

    def add_gcp(points: Any) -> Any:
        calls.append("gcp")
        raise KeyError("in the pipeline")

    node.pipeline.add_gcp = add_gcp
    node._enqueue(("gcp", []))
    node._on_gcp(object())  # no .points: AttributeError in the callback
    node._on_strip("left", object())
    assert wait(lambda: node.worker._queue.unfinished_tasks == 0, 10)
    assert calls == ["gcp"] and node.counts["internal_errors"] == 3, node.counts
    assert node.worker.alive and node.worker_problem() is None
    level_, message = node.summary_status()
    assert level_ == ERROR and "3 errors so far" in message, message
    assert node.flush(timeout_s=10.0)  # the worker still works
    node.pipeline.flush = lambda: 1 / 0
    assert not node.flush(timeout_s=10.0)  # raised inside: not flushed, reported
    assert node.counts["internal_errors"] == 4 and node.worker.alive
