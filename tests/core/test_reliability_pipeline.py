"""Bad input at the Pipeline level and through ``parproj process`` (no DDS).

Issue: bad input never crashes the node and never corrupts or drops other data; it gets a clear
error (log + diagnostics) that says what was wrong and what was done with it. Every test feeds
one kind of bad input into an acquisition of two stereo pairs and asserts

(a) no exception (a hang would show as the test's run time),
(b) a diagnostics status: its level, a name holding the scene or the input, a message saying
    what was wrong and what was done (pipeline Issues go through
    ``conversions.issues_to_diagnostics``, the node's and ``process``'s own mapping; the
    message-level cases run ``offline.process_bag`` and read ``/diagnostics`` from its output),
(c) the other pair (and whatever the bad input did not touch) exactly as in a clean run.

Scenarios: the airborne fore/aft pair and the IKONOS-like agile pair of sim/scenarios.py, each
flown twice (a second pair 100 s / 200 s later), with random textures (the geometry only needs
strips of the right shape at the right times). Tie-point refinement (image matching on finished
pairs, about 1-3 s a pair) is switched off for speed when the pipeline has it.
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Image
from testkit.diagnostics import level, show
from testkit.paths import BAGS
from testkit.scenes import Event, feed, nav_events, nav_samples
from testkit.scenes import render as render_as

from parproj_ros.apps.process import ProcessSummary, process_bag
from parproj_ros.core.pipeline import (
    GroundPoint,
    Outputs,
    PairResult,
    Pipeline,
    PipelineConfig,
    SceneResult,
)
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader, BagWriter
from parproj_ros.sim.scenarios import SCENARIOS, Scenario, ground_points

pytestmark = pytest.mark.ros  # message classes, diagnostics, bags

FAST = {"tie_points": False}

#: Words that say what was done with bad input.
DROPPED = ("dropped", "rejected", "ignored", "skipped")


# ---- scenarios ----------------------------------------------------------------------------------


def twice(name: str, later_s: float, nav_hz: float) -> Scenario:
    """A scenario whose scenes are flown again ``later_s`` seconds later (a second pair)."""
    scn = SCENARIOS[name]()
    more = tuple(dataclasses.replace(s, start_s=s.start_s + later_s) for s in scn.scenes)
    return dataclasses.replace(scn, scenes=scn.scenes + more, nav_rate_hz=nav_hz)


AIR = twice("airborne_foreaft", 100.0, 10.0)  # pairs left_scene_0000+right_scene_0001, 0002+0003
IK = twice("ikonos_agile", 200.0, 5.0)  # single camera: pan_scene_0000+0001, 0002+0003
AIR_PAIRS = ("left_scene_0000+right_scene_0001", "left_scene_0002+right_scene_0003")
IK_PAIRS = ("pan_scene_0000+pan_scene_0001", "pan_scene_0002+pan_scene_0003")


def config(scn: Scenario, **kw: Any) -> PipelineConfig:
    return scn.pipeline_config(**{**FAST, **kw})


def line_period_ns(scn: Scenario) -> float:
    return scn.views[0].camera.line_period * 1e9


def render(scn: Scenario) -> list[np.ndarray]:
    return render_as(scn, np.dtype(scn.dtype))


def strip_events(scn: Scenario, images: list[np.ndarray]) -> list[Event]:
    ev = []
    for i, sc in enumerate(scn.scenes):
        for r0 in range(0, sc.lines, scn.strip_lines):
            t = scn.time_ns(sc.start_s) + round(r0 * line_period_ns(scn))
            ev.append((t, 1, (sc.view, t, scn.scene_id(i), images[i][r0 : r0 + scn.strip_lines])))
    return ev


def strip_time(scn: Scenario, scene: int, r0: int) -> int:
    return scn.time_ns(scn.scenes[scene].start_s) + round(r0 * line_period_ns(scn))


def is_strip(e: Event, scn: Scenario, scene: int, r0: int) -> bool:
    return e[1] == 1 and e[2][2] == scn.scene_id(scene) and e[2][1] == strip_time(scn, scene, r0)


def run(
    scn: Scenario, events: Iterable[Event], gcp: Iterable[GroundPoint] = (), **kw: Any
) -> Outputs:
    pipe = Pipeline(config(scn, **kw))
    out = pipe.add_gcp(list(gcp))
    out.extend(feed(pipe, events))
    return out


# ---- checks -------------------------------------------------------------------------------------


def statuses(out: Outputs) -> list[DiagnosticStatus]:
    """The pipeline's issues as the node publishes them on /diagnostics."""
    return list(conv.issues_to_diagnostics(out.issues, stamp_ns=0, hardware_id="map").status)


def expect_status(
    sts: list[DiagnosticStatus],
    *,
    min_level: int,
    name: str,
    says: Iterable[str] = (),
    done: Iterable[str] = DROPPED,
) -> DiagnosticStatus:
    """The first status at ``min_level`` (1 warn, 2 error) or above, ``name`` in its name (or
    its message), every string of ``says`` in its message and one of ``done``."""
    says, done = list(says), list(done)
    for s in sts:
        if (
            level(s) >= min_level
            and (name in s.name or name in s.message)
            and all(w in s.message for w in says)
            and (not done or any(w in s.message for w in done))
        ):
            return s
    raise AssertionError(
        f"no status of level >= {min_level} named *{name}* saying {says} and one of {done}; "
        f"got:\n{show(sts)}"
    )


def no_problems(sts: list[DiagnosticStatus]) -> None:
    bad = [s for s in sts if level(s) >= 1]
    assert not bad, show(bad)


def assert_same_scene(got: SceneResult, ref: SceneResult, rtol: float = 0.0) -> None:
    g, r = got.scene, ref.scene
    assert (g.view, g.scene_id, g.lines, g.first_line_ns) == (
        r.view,
        r.scene_id,
        r.lines,
        r.first_line_ns,
    )
    assert got.method == ref.method, (got.note, ref.note)
    atol = 1e-12 if rtol else 0.0
    np.testing.assert_allclose(got.affine.array, ref.affine.array, rtol=rtol, atol=atol)
    assert got.psi == pytest.approx(ref.psi, rel=rtol, abs=atol)
    assert got.gcp_count == ref.gcp_count


def assert_same_pair(got: PairResult, ref: PairResult, *, images: bool = True) -> None:
    assert got.pair_id == ref.pair_id
    assert_same_scene(got.left, ref.left)
    assert_same_scene(got.right, ref.right)
    for a, b in (
        (got.normalization.left, ref.normalization.left),
        (got.normalization.right, ref.normalization.right),
    ):
        np.testing.assert_array_equal(a, b)
    assert got.left_grid == ref.left_grid and got.right_grid == ref.right_grid
    if images:
        np.testing.assert_array_equal(got.left_image, ref.left_image)
        np.testing.assert_array_equal(got.right_image, ref.right_image)


def pairs(out: Outputs) -> dict[str, PairResult]:
    ids = [p.pair_id for p in out.pairs]
    assert len(ids) == len(set(ids)), f"a pair published twice: {ids}"
    return {p.pair_id: p for p in out.pairs}


def scenes(out: Outputs) -> dict[str, SceneResult]:
    ids = [s.scene.scene_id for s in out.scenes]
    assert len(ids) == len(set(ids)), f"scene ids not unique: {ids}"
    return {s.scene.scene_id: s for s in out.scenes}


def unchanged(out: Outputs, clean: Outputs, pair_ids: Iterable[str]) -> None:
    """These pairs (parameters, normalization, grids, images) as in the clean run."""
    got, ref = pairs(out), pairs(clean)
    for pid in pair_ids:
        assert pid in got, f"pair {pid} lost; pairs: {sorted(got)}\n{show(statuses(out))}"
        assert_same_pair(got[pid], ref[pid])


def same_parameters(out: Outputs, clean: Outputs, scene_ids: Iterable[str], rtol=0.0) -> None:
    got, ref = scenes(out), scenes(clean)
    for sid in scene_ids:
        assert sid in got, f"scene {sid} lost; scenes: {sorted(got)}\n{show(statuses(out))}"
        assert_same_scene(got[sid], ref[sid], rtol)


# ---- clean runs ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def air() -> dict[str, Any]:
    images = render(AIR)
    nav, strips = nav_events(AIR), strip_events(AIR, images)
    clean = run(AIR, nav + strips)
    assert sorted(pairs(clean)) == sorted(AIR_PAIRS)
    no_problems(statuses(clean))
    return {"images": images, "nav": nav, "strips": strips, "clean": clean}


def ik_gcp() -> tuple[list[GroundPoint], list[GroundPoint]]:
    """12 GCP on hills for each pair (Eq 8 with the roll estimated)."""
    rng = np.random.default_rng(1)

    def hills(model: Any, line: np.ndarray, sample: np.ndarray) -> np.ndarray:
        z = 250.0 * np.sin(line / 97.0) * np.cos(sample / 131.0)
        return model.locate(line, sample, z)

    g0 = ground_points(IK, (0, 1), 12, hills, rng, prefix="a")
    g1 = ground_points(IK, (2, 3), 12, hills, rng, prefix="b")
    return g0, g1


@pytest.fixture(scope="module")
def ik() -> dict[str, Any]:
    images = render(IK)
    events = nav_events(IK) + strip_events(IK, images)
    g0, g1 = ik_gcp()
    clean = run(IK, events, g0 + g1)
    assert sorted(pairs(clean)) == sorted(IK_PAIRS)
    assert [s.method for s in clean.scenes] == ["gcp_roll_estimated"] * 4
    no_problems(statuses(clean))
    return {"images": images, "events": events, "g0": g0, "g1": g1, "clean": clean}


# ---- strips: message level, through ``parproj process`` -----------------------------------------


def messages(scn: Scenario, images: list[np.ndarray]) -> list[tuple[int, str, Any]]:
    """The acquisition as recorded: (log time, topic, message), in time order."""
    out: list[tuple[int, str, Any]] = []
    for s in nav_samples(scn):
        odo = conv.sample_to_odometry(s, Odometry(), frame_id="map", child_frame_id="base_link")
        out.append((s.t_ns, "navigation", odo))
    for _, _, (view, t, sid, arr) in strip_events(scn, images):
        msg = conv.array_to_image(arr, Image(), frame_id=sid, stamp_ns=t)
        out.append((t, f"{view}/image_strip", msg))
    out.sort(key=lambda m: (m[0], m[1] != "navigation"))
    return out


def process(
    tmp: Path, msgs: list[tuple[int, str, Any]], cfg: PipelineConfig
) -> tuple[Outputs, list[DiagnosticStatus], ProcessSummary]:
    """Write the messages to a bag, run ``process_bag`` on it, read its /diagnostics back."""
    src, dst = tmp / "input", tmp / "output"
    with BagWriter(src, overwrite=True) as bw:
        bw.add_topic("navigation", "nav_msgs/msg/Odometry", "sensor_data")
        for v in cfg.views:
            bw.add_topic(f"{v.name}/image_strip", "sensor_msgs/msg/Image", "sensor_data")
        for t, topic, msg in msgs:
            bw.write(topic, msg, t)
    return process_existing(src, dst, config=cfg)


def process_existing(
    src: Path, dst: Path, **kw: Any
) -> tuple[Outputs, list[DiagnosticStatus], ProcessSummary]:
    out = Outputs()
    summary = process_bag(src, dst, progress=False, on_outputs=out.extend, **kw)
    diag = [s for m in BagReader(dst).messages(topics=["/diagnostics"]) for s in m.msg.status]
    return out, diag, summary


@pytest.fixture(scope="module")
def air_msgs(air: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    msgs = messages(AIR, air["images"])
    clean, diag, _ = process(tmp_path_factory.mktemp("clean"), msgs, config(AIR))
    no_problems(diag)
    assert sorted(pairs(clean)) == sorted(AIR_PAIRS)
    return {"msgs": msgs, "clean": clean}


def replace_message(
    msgs: list[tuple[int, str, Any]], topic: str, t_ns: int, change: Callable[[Any], None]
) -> list[tuple[int, str, Any]]:
    """A copy of ``msgs`` in which the message of ``topic`` at ``t_ns`` is changed."""
    from rclpy.serialization import deserialize_message, serialize_message

    out, hit = [], 0
    for t, tp, m in msgs:
        if tp == topic and t == t_ns:
            m = deserialize_message(serialize_message(m), type(m))
            change(m)
            hit += 1
        out.append((t, tp, m))
    assert hit == 1
    return out


def _set(field: str, value: Callable[[Any], Any]) -> Callable[[Any], None]:
    def change(m: Any) -> None:
        setattr(m, field, value(m))

    return change


BAD_STRIPS: dict[str, tuple[Callable[[Any], None], str]] = {
    "unsupported encoding": (_set("encoding", lambda m: "rgb8"), "unsupported encoding 'rgb8'"),
    "unknown encoding": (_set("encoding", lambda m: "mono12p"), "unsupported encoding"),
    "step < width x bytes": (_set("step", lambda m: m.width - 1), "step"),
    "truncated data": (_set("data", lambda m: bytes(m.data)[: len(m.data) // 2]), "bytes"),
    "no data": (_set("data", lambda m: b""), "0 bytes"),
    "zero height": (_set("height", lambda m: 0), "empty"),
    "zero width": (_set("width", lambda m: 0), "empty"),
}


@pytest.mark.parametrize("case", sorted(BAD_STRIPS))
def test_bad_strip_message(case: str, air_msgs: dict[str, Any], tmp_path: Path) -> None:
    """A strip that cannot be converted is dropped; its 64 lines become no-data."""
    change, says = BAD_STRIPS[case]
    msgs = replace_message(air_msgs["msgs"], "left/image_strip", strip_time(AIR, 0, 320), change)
    out, diag, _ = process(tmp_path, msgs, config(AIR))
    expect_status(diag, min_level=1, name="left/image_strip", says=[says], done=["dropped"])
    expect_status(
        diag, min_level=1, name="left/left_scene_0000", says=["64 missing lines"], done=["filled"]
    )
    unchanged(out, air_msgs["clean"], [AIR_PAIRS[1]])
    # navigation-derived: the pixels lost do not change the parameters of the pair
    same_parameters(out, air_msgs["clean"], ["left_scene_0000", "right_scene_0001"])
    assert pairs(out)[AIR_PAIRS[0]].left.scene.gaps == 64


def test_padded_step_is_accepted(air_msgs: dict[str, Any], tmp_path: Path) -> None:
    """step > width x bytes is row padding (sensor_msgs/Image): the pixels are unchanged."""

    def pad(m: Any) -> None:
        rows = np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.step)
        m.data = np.hstack([rows, np.full((m.height, 3), 7, np.uint8)]).tobytes()
        m.step = m.step + 3

    msgs = replace_message(air_msgs["msgs"], "left/image_strip", strip_time(AIR, 0, 320), pad)
    out, diag, _ = process(tmp_path, msgs, config(AIR))
    no_problems(diag)
    unchanged(out, air_msgs["clean"], AIR_PAIRS)


def _quat(x: float, y: float, z: float, w: float) -> Callable[[Any], None]:
    def change(m: Any) -> None:
        q = m.pose.pose.orientation
        q.x, q.y, q.z, q.w = x, y, z, w

    return change


def _vec(which: str, value: float) -> Callable[[Any], None]:
    def change(m: Any) -> None:
        v = m.pose.pose.position if which == "position" else m.twist.twist.linear
        v.y = value

    return change


NAN = float("nan")
BAD_NAV: dict[str, tuple[Callable[[Any], None], str]] = {
    "NaN quaternion": (_quat(NAN, 0.0, 0.0, 1.0), "quaternion"),
    "Inf quaternion": (_quat(0.0, float("inf"), 0.0, 1.0), "quaternion"),
    "zero-norm quaternion": (_quat(0.0, 0.0, 0.0, 0.0), "quaternion"),
    "NaN velocity": (_vec("velocity", NAN), "velocity"),
    "Inf position": (_vec("position", float("-inf")), "position"),
}


@pytest.mark.parametrize("case", sorted(BAD_NAV))
def test_bad_navigation_message(case: str, air_msgs: dict[str, Any], tmp_path: Path) -> None:
    """A navigation sample that cannot be used is dropped; the scene fits the others."""
    change, says = BAD_NAV[case]
    # a sample inside the left scene of the first pair
    t = next(s.t_ns for s in nav_samples(AIR) if s.t_ns >= strip_time(AIR, 0, 384))
    msgs = replace_message(air_msgs["msgs"], "navigation", t, change)
    out, diag, _ = process(tmp_path, msgs, config(AIR))
    expect_status(diag, min_level=1, name="navigation", says=[says], done=["dropped"])
    unchanged(out, air_msgs["clean"], [AIR_PAIRS[1]])
    # one sample fewer in an exact trajectory: the same fit to rounding
    same_parameters(out, air_msgs["clean"], ["left_scene_0000", "right_scene_0001"], 1e-9)


def test_huge_quaternion_is_normalised_or_rejected() -> None:
    """(1e300, 0, 0, 0) is a 180 deg turn about x (a non-unit quaternion is normalised)."""
    msg = Odometry()
    q = msg.pose.pose.orientation
    q.x, q.y, q.z, q.w = 1e300, 0.0, 0.0, 0.0
    try:
        sample = conv.odometry_to_sample(msg)
    except conv.ConversionError as err:
        assert "quaternion" in str(err)
        return
    np.testing.assert_allclose(sample.rotation, np.diag([1.0, -1.0, -1.0]), atol=1e-12)


# ---- strips: pipeline level ---------------------------------------------------------------------


def replace_strip(events: list[Event], scene: int, r0: int, new: Callable[[Any], Any]) -> list:
    out = []
    for e in events:
        if is_strip(e, AIR, scene, r0):
            view, t, sid, arr = e[2]
            out.append((e[0], 1, (view, t, sid, new(arr))))
        else:
            out.append(e)
    return out


CHANGES = {"width": lambda a: np.ascontiguousarray(a[:, :700]), "type": lambda a: a.astype("u2")}


@pytest.mark.parametrize("what", sorted(CHANGES))
def test_strip_width_or_type_changes_inside_scene(what: str, air: dict[str, Any]) -> None:
    strips = replace_strip(air["strips"], 0, 320, CHANGES[what])
    out = run(AIR, air["nav"] + strips)
    sts = statuses(out)
    says = ["700 px"] if what == "width" else ["uint16"]
    expect_status(sts, min_level=1, name="left/left_scene_0000", says=says, done=["dropped"])
    expect_status(
        sts, min_level=1, name="left/left_scene_0000", says=["64 missing lines"], done=[]
    )
    unchanged(out, air["clean"], [AIR_PAIRS[1]])
    same_parameters(out, air["clean"], ["left_scene_0000", "right_scene_0001"])


@pytest.mark.parametrize("what", sorted(CHANGES))
def test_bad_first_strip_does_not_cost_the_scene(what: str, air: dict[str, Any]) -> None:
    """The first strip of a scene is narrower (or of another type) than the rest.

    It alone is dropped: the other 11 strips (704 lines) still make the left scene of the
    first pair, and the second pair is untouched.
    """
    strips = replace_strip(air["strips"], 0, 0, CHANGES[what])
    out = run(AIR, air["nav"] + strips)
    sts = statuses(out)
    expect_status(sts, min_level=1, name="left/left_scene_0000", done=["dropped"])
    dropped = [s for s in sts if "dropped" in s.message]
    assert len(dropped) == 1, f"good strips dropped after a bad first strip:\n{show(dropped)}"
    unchanged(out, air["clean"], [AIR_PAIRS[1]])
    left = [s for s in out.scenes if s.scene.view == "left" and s.scene.index == 0]
    assert left and left[0].scene.lines >= 704, [(s.scene.scene_id, s.scene.lines) for s in left]
    assert left[0].scene.detectors == 768 and left[0].scene.image.dtype == np.uint8
    assert AIR_PAIRS[0] in pairs(out)


def test_duplicate_strip(air: dict[str, Any]) -> None:
    dup = [(e[0] + 1, 1, e[2]) for e in air["strips"] if is_strip(e, AIR, 0, 320)]
    out = run(AIR, air["nav"] + air["strips"] + dup)
    sts = statuses(out)
    expect_status(sts, min_level=1, name="left/left_scene_0000", says=["duplicate"])
    assert len([s for s in sts if level(s) >= 1]) == 1, show(sts)
    unchanged(out, air["clean"], AIR_PAIRS)


def test_out_of_order_strips(air: dict[str, Any]) -> None:
    """Strip 320 arrives after strip 384: it is dropped, its lines are no-data."""
    late = strip_time(AIR, 0, 384) + 1
    strips = [(late, 1, e[2]) if is_strip(e, AIR, 0, 320) else e for e in air["strips"]]
    out = run(AIR, air["nav"] + strips)
    sts = statuses(out)
    expect_status(sts, min_level=1, name="left/left_scene_0000", says=["out of order"])
    expect_status(
        sts, min_level=1, name="left/left_scene_0000", says=["64 missing lines"], done=[]
    )
    unchanged(out, air["clean"], [AIR_PAIRS[1]])
    same_parameters(out, air["clean"], ["left_scene_0000", "right_scene_0001"])


def _stray(air: dict[str, Any], frame_id: str) -> list[Event]:
    """A copy of strip 320 of the left scene stamped 10 s earlier, arriving after it."""
    (e,) = [e for e in air["strips"] if is_strip(e, AIR, 0, 320)]
    view, t, _, arr = e[2]
    return [(e[0] + 1, 1, (view, t - 10_000_000_000, frame_id, arr))]


BACKWARDS: dict[str, Callable[[dict[str, Any]], list[Event]]] = {
    "one strip, same scene id": lambda air: _stray(air, "left_scene_0000"),
    "one strip, another scene id": lambda air: _stray(air, "left_scene_0099"),
    "first pair re-sent at the end": lambda air: [
        (10**20 + k, 1, e[2])
        for k, e in enumerate(e for e in air["strips"] if e[2][2] in AIR_PAIRS[0].split("+"))
    ],
}


@pytest.mark.parametrize("case", sorted(BACKWARDS))
def test_strip_stamps_going_backwards(case: str, air: dict[str, Any]) -> None:
    """Strips older than lines already received from their view are dropped, whatever their
    frame_id: nothing else changes (no scene cut short, no scene or pair published twice)."""
    out = run(AIR, air["nav"] + air["strips"] + BACKWARDS[case](air))
    assert len(out.scenes) == 4, [(s.scene.scene_id, s.scene.lines) for s in out.scenes]
    assert sorted(pairs(out)) == sorted(AIR_PAIRS), show(statuses(out))
    unchanged(out, air["clean"], AIR_PAIRS)
    expect_status(statuses(out), min_level=1, name="left/", done=["dropped"])


# ---- navigation ---------------------------------------------------------------------------------


def test_navigation_gap_in_a_scene(air: dict[str, Any]) -> None:
    """No navigation for 1.2 s (> max gap 1 s) over the first left scene: that scene is
    skipped; the second pair is untouched."""
    a = strip_time(AIR, 0, 0) + 100_000_000
    b = a + 1_200_000_000
    nav = [e for e in air["nav"] if not a < e[0] < b]
    out = run(AIR, nav + air["strips"])
    sts = statuses(out)
    expect_status(sts, min_level=1, name="left/left_scene_0000", says=["gap"], done=[])
    expect_status(sts, min_level=2, name="left/left_scene_0000", done=["skipped"])
    assert AIR_PAIRS[0] not in pairs(out)
    unchanged(out, air["clean"], [AIR_PAIRS[1]])


def test_navigation_ends_early(air: dict[str, Any]) -> None:
    """Navigation stops in the middle of the last scene: it is reported and skipped at the end
    of data; the first pair is untouched."""
    cut = strip_time(AIR, 3, 384)
    nav = [e for e in air["nav"] if e[0] < cut]
    out = run(AIR, nav + air["strips"])
    expect_status(statuses(out), min_level=2, name="right/right_scene_0003", done=["skipped"])
    assert AIR_PAIRS[1] not in pairs(out)
    unchanged(out, air["clean"], [AIR_PAIRS[0]])


def test_navigation_position_outlier(air: dict[str, Any]) -> None:
    """One finite but wrong navigation position (1 km across track, a GNSS glitch) inside the
    first left scene: the straight-line fit through it is off by hundreds of pixels, so the
    node must say so (or drop the sample); the second pair is untouched."""
    t = next(e[0] for e in air["nav"] if e[0] >= strip_time(AIR, 0, 384))
    nav = [
        (e[0], 0, dataclasses.replace(e[2], position=e[2].position + np.array([0, 1000.0, 0])))
        if e[0] == t
        else e
        for e in air["nav"]
    ]
    out = run(AIR, nav + air["strips"])
    unchanged(out, air["clean"], [AIR_PAIRS[1]])
    sts = statuses(out)
    hits = [
        s for s in sts if level(s) >= 1 and ("left_scene_0000" in s.name or "navigation" in s.name)
    ]
    assert hits, f"no status for a navigation sample 1 km off the trajectory:\n{show(sts)}"


JUMPS = {"1000 s ahead": 1000 * 10**9, "back to stamp 0": None}


@pytest.mark.parametrize("case", sorted(JUMPS))
def test_navigation_stamp_jump(case: str, air: dict[str, Any]) -> None:
    """One navigation sample with a wild stamp (a clock jump, an unset header) arrives in the
    middle of the first left scene; scenes end on their length (scene_lines = 768)."""
    kw = {"scene_lines": 768, "streaming": False}
    clean = run(AIR, air["nav"] + air["strips"], **kw)
    assert sorted(pairs(clean)) == sorted(AIR_PAIRS)
    arrival = strip_time(AIR, 0, 320)
    jump = JUMPS[case]
    stray = dataclasses.replace(air["nav"][0][2], t_ns=0 if jump is None else arrival + jump)
    out = run(AIR, [*air["nav"], (arrival, 0, stray), *air["strips"]], **kw)
    unchanged(out, clean, AIR_PAIRS)
    expect_status(statuses(out), min_level=1, name="navigation")


# ---- GCP ----------------------------------------------------------------------------------------


def _collinear(g0: list[GroundPoint]) -> list[GroundPoint]:
    a, b = g0[0], g0[1]
    out = []
    for i in range(8):
        f = i / 7.0  # between a and b: every observation stays inside the scene
        obs = {}
        for k, start in a.observations.items():
            step = np.subtract(b.observations[k], start)
            obs[k] = (float(start[0] + f * step[0]), float(start[1] + f * step[1]))
        out.append(GroundPoint(f"l{i}", a.xyz + f * (b.xyz - a.xyz), False, obs))
    return out


UNUSABLE_GCP: dict[str, tuple[Callable[[list[GroundPoint]], list[GroundPoint]], list[str], str]]
UNUSABLE_GCP = {
    "fewer than min_gcp": (lambda g: g[:3], ["only 3 GCP"], "not used"),
    "duplicates": (
        lambda g: [*g[:4], dataclasses.replace(g[0], id="a_again")],
        ["4 distinct", "duplicate"],
        "using navigation",
    ),
    "collinear": (_collinear, ["collinear"], "using navigation"),
}


@pytest.mark.parametrize("case", sorted(UNUSABLE_GCP))
def test_unusable_gcp(case: str, ik: dict[str, Any]) -> None:
    """The first pair's GCP cannot be used: both its scenes fall back to navigation."""
    make, says, done = UNUSABLE_GCP[case]
    out = run(IK, ik["events"], make(ik["g0"]) + ik["g1"])
    sts = statuses(out)
    for sid in IK_PAIRS[0].split("+"):
        expect_status(sts, min_level=1, name=f"pan/{sid}", says=says, done=[done])
    got = scenes(out)
    assert [got[s].method for s in IK_PAIRS[0].split("+")] == ["navigation"] * 2
    assert IK_PAIRS[0] in pairs(out)
    unchanged(out, ik["clean"], [IK_PAIRS[1]])


BAD_OBSERVATION = {"line -1e6 (far outside the scene)": -1e6, "NaN line": float("nan")}


@pytest.mark.parametrize("case", sorted(BAD_OBSERVATION))
def test_one_bad_gcp_observation(case: str, ik: dict[str, Any]) -> None:
    """One more GCP, "bad", observed in the first scene at an impossible line: that
    observation is ignored and reported; the 12 good GCP give the same parameters."""
    g = ik["g0"][0]
    sid = IK.scene_id(0)
    bad = GroundPoint(
        "bad", g.xyz + np.array([40.0, -30.0, 25.0]), False, {sid: (BAD_OBSERVATION[case], 300.0)}
    )
    out = run(IK, ik["events"], [*ik["g0"], *ik["g1"], bad])
    unchanged(out, ik["clean"], [IK_PAIRS[1]])
    same_parameters(out, ik["clean"], [sid])
    expect_status(statuses(out), min_level=1, name="bad")


# ---- pairs --------------------------------------------------------------------------------------


def test_pair_without_stereo_base() -> None:
    """The first pair's two looks have the same attitude (single camera): no base."""
    sc = list(IK.scenes)
    sc[1] = dataclasses.replace(sc[1], attitude_rpy_deg=sc[0].attitude_rpy_deg)
    same = dataclasses.replace(IK, scenes=tuple(sc))
    images = render(IK)
    clean = run(IK, nav_events(IK) + strip_events(IK, images))
    out = run(same, nav_events(same) + strip_events(same, images))
    expect_status(
        statuses(out), min_level=2, name=f"pair {IK_PAIRS[0]}", says=["base"], done=["skipped"]
    )
    assert IK_PAIRS[0] not in pairs(out)
    unchanged(out, clean, [IK_PAIRS[1]])


def test_pair_without_overlap(air: dict[str, Any]) -> None:
    """The first pair's right scene is flown 1 km to the side (swath 83 m)."""
    t0, t1 = AIR.scenes[1].start_s - 5.0, AIR.scenes[1].start_s + 5.0

    def aside(t: float) -> np.ndarray:
        return np.array([0.0, 1000.0 if t0 < t < t1 else 0.0, 0.0])

    out = run(AIR, nav_events(AIR, offset=aside) + air["strips"])
    expect_status(
        statuses(out), min_level=2, name=f"pair {AIR_PAIRS[0]}", says=["overlap"], done=["skipped"]
    )
    assert AIR_PAIRS[0] not in pairs(out)
    unchanged(out, air["clean"], [AIR_PAIRS[1]])


# ---- bags ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ik_bag(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """bags/ikonos_agile processed as it is (the clean reference)."""
    tmp = tmp_path_factory.mktemp("ik_bag")
    out, diag, summary = process_existing(BAGS / "ikonos_agile", tmp / "out", overrides=FAST)
    assert summary.recovery.complete and summary.pairs == 1
    no_problems(diag)
    return {"out": out, "summary": summary}


def copy_bag(
    src: Path, dst: Path, raw: Iterable[tuple[str, str, bytes, int]], extra: Callable | None = None
) -> Path:
    """A bag with ``src``'s topics holding the raw messages given; ``extra(writer)`` adds more."""
    reader = BagReader(src)
    with BagWriter(dst, overwrite=True) as bw:
        for topic, msgtype in reader.topics().items():
            bw.add_topic(topic, msgtype, reader.qos(topic))
        if extra is not None:
            extra(bw)
        for topic, _, data, t in raw:
            bw.write_raw(topic, data, t)
    return dst


@pytest.fixture(scope="module")
def cut_bag(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """bags/ikonos_agile cut off at 80 % of its MCAP file (a recorder killed mid-write)."""
    tmp = tmp_path_factory.mktemp("cut")
    src = BAGS / "ikonos_agile"
    cut = tmp / "ikonos_agile"
    cut.mkdir()
    mcap = src / "ikonos_agile_0.mcap"
    data = mcap.read_bytes()
    (cut / mcap.name).write_bytes(data[: int(0.8 * len(data))])
    shutil.copy(src / "metadata.yaml", cut / "metadata.yaml")
    out, diag, summary = process_existing(cut, tmp / "out", overrides=FAST)
    return {"dir": cut, "tmp": tmp, "out": out, "diag": diag, "summary": summary}


def test_cut_off_bag_recovers_every_complete_message(
    cut_bag: dict[str, Any], ik_bag: dict[str, Any]
) -> None:
    summary = cut_bag["summary"]
    rec = summary.recovery
    full = list(BagReader(BAGS / "ikonos_agile").raw_messages())
    assert not rec.complete and "cut off" in (rec.error or "")
    assert rec.messages_expected == len(full) == 1474
    assert 0 < rec.messages_read < len(full)
    assert rec.messages_lost == len(full) - rec.messages_read
    assert summary.messages_in == rec.messages_read  # every recovered message was processed
    got = list(BagReader(cut_bag["dir"]).raw_messages())
    assert [(m[0], m[3]) for m in got] == [(m[0], m[3]) for m in full[: len(got)]]
    assert [m[2] for m in got] == [m[2] for m in full[: len(got)]]
    # The outputs are those of a clean bag holding exactly the recovered messages ...
    prefix = copy_bag(BAGS / "ikonos_agile", cut_bag["tmp"] / "prefix", full[: len(got)])
    ref, _, _ = process_existing(prefix, cut_bag["tmp"] / "prefix_out", overrides=FAST)
    assert [s.scene.scene_id for s in cut_bag["out"].scenes] == [
        s.scene.scene_id for s in ref.scenes
    ]
    for a, b in zip(cut_bag["out"].scenes, ref.scenes, strict=True):
        assert_same_scene(a, b)
    assert sorted(pairs(cut_bag["out"])) == sorted(pairs(ref))
    for pid, p in pairs(cut_bag["out"]).items():
        assert_same_pair(p, pairs(ref)[pid])
    # ... and the forward look, complete before the cut, is as in the whole bag.
    same_parameters(cut_bag["out"], ik_bag["out"], ["pan_scene_0000"])


def test_cut_off_bag_is_reported_on_diagnostics(cut_bag: dict[str, Any]) -> None:
    """The output bag's /diagnostics say that the input was cut off and how much was lost."""
    lost = cut_bag["summary"].recovery.messages_lost
    expect_status(
        cut_bag["diag"],
        min_level=1,
        name="ikonos_agile",
        says=[str(lost)],
        done=["cut off", "truncated", "lost"],
    )


UNKNOWN_DEF = "int32 a\nstring b\n"


def _foo_cdr(a: int) -> bytes:
    raw = f"foo{a}".encode() + b"\x00"
    return (
        b"\x00\x01\x00\x00" + int(a).to_bytes(4, "little") + len(raw).to_bytes(4, "little") + raw
    )


@pytest.fixture(scope="module")
def mixed_bag(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """bags/ikonos_agile with an unknown type on /mystery (5 messages) and one undecodable
    navigation message (a CDR header and nothing else) mixed in."""
    tmp = tmp_path_factory.mktemp("mixed")
    full = list(BagReader(BAGS / "ikonos_agile").raw_messages())
    raw: list[tuple[str, str, bytes, int]] = []
    for k, m in enumerate(full):
        raw.append(m)
        if k % 300 == 7:
            raw.append(("/mystery", "unknown_pkg/msg/Foo", _foo_cdr(k), m[3]))
        if k == 900:
            raw.append(("navigation", "nav_msgs/msg/Odometry", b"\x00\x01\x00\x00", m[3]))

    def mystery(bw: BagWriter) -> None:
        bw.add_topic("/mystery", "unknown_pkg/msg/Foo", definition=UNKNOWN_DEF)

    bag = copy_bag(BAGS / "ikonos_agile", tmp / "mixed", raw, mystery)
    out, diag, summary = process_existing(bag, tmp / "out", overrides=FAST)
    return {"out": out, "diag": diag, "summary": summary}


def test_unknown_topic_and_undecodable_message_skipped(
    mixed_bag: dict[str, Any], ik_bag: dict[str, Any]
) -> None:
    summary = mixed_bag["summary"]
    assert summary.skipped_topics == {"/mystery": 5}
    assert summary.recovery.complete
    assert summary.pairs == 1
    same_parameters(mixed_bag["out"], ik_bag["out"], ["pan_scene_0000", "pan_scene_0001"])
    unchanged(mixed_bag["out"], ik_bag["out"], [IK_PAIRS[0]])


def test_unknown_topic_is_reported_on_diagnostics(mixed_bag: dict[str, Any]) -> None:
    expect_status(mixed_bag["diag"], min_level=1, name="/mystery", says=["5"])


def test_undecodable_message_is_reported_on_diagnostics(mixed_bag: dict[str, Any]) -> None:
    expect_status(mixed_bag["diag"], min_level=1, name="navigation", says=["1"])
