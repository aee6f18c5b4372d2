"""The long run (``python -m tools.longrun``): repetitions of a bag, the pair checks, flat memory.

``test_longrun_live`` runs the command's function for real (parproj_node in its own process,
rclpy and Fast DDS on localhost) for a few repetitions: every pair published, well formed and
equal to the first repetition's, nothing dropped. Speed and memory are measured there, not
asserted; the pipeline tests below assert what keeps memory flat (navigation and GCP forgotten
once no scene can need them) on counts, which do not depend on the machine.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from testkit.paths import BAGS

from parproj_ros.core.pipeline import Outputs, Pipeline
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import config_from_bag, truth_from_bag
from tools.longrun.checks import (
    PairChecker,
    compare_pairs,
    pair_numbers,
    plan_bag,
    repetition_id,
    repetition_messages,
    split_repetition,
)
from tools.longrun.run import run_longrun

IKONOS = BAGS / "ikonos_agile"
AIRBORNE = BAGS / "airborne_foreaft"


def feed(pipe: Pipeline, plan: Any, reps: int, per_rep: Any = None) -> Outputs:
    """Repetitions 0..reps-1 of a bag through a Pipeline (no DDS), in log order."""
    out = Outputs()
    views = {f"{name}/image_strip": name for name in plan.scenes}
    for k in range(reps):
        for topic, msg, _ in repetition_messages(plan, k):
            if topic == "navigation":
                out.extend(pipe.add_navigation(conv.odometry_to_sample(msg)))
            elif topic in views:
                stamp = conv.stamp_to_ns(msg.header.stamp)
                arr = conv.image_to_array(msg)
                out.extend(pipe.add_strip(views[topic], stamp, msg.header.frame_id, arr))
            elif topic == "gcp":
                out.extend(pipe.add_gcp(conv.gcp_from_msg(msg)))
        if per_rep is not None:
            per_rep(k)
    out.extend(pipe.flush())
    return out


# ---- repetitions ---------------------------------------------------------------------------


def test_repetition_ids_round_trip() -> None:
    assert repetition_id("pan_scene_0000", 7) == "r0007_pan_scene_0000"
    assert split_repetition("r0007_pan_scene_0000") == (7, "pan_scene_0000")
    assert split_repetition("r12345_left") == (12345, "left")
    assert split_repetition("pan_scene_0000") is None


@pytest.mark.ros
def test_repetition_shifts_stamps_and_renames_scenes() -> None:
    plan = plan_bag(IKONOS, margin_s=1.0)
    assert plan.pairs == ["pan_scene_0000+pan_scene_0001"] and plan.single_camera
    assert plan.shift_ns == plan.duration_ns + 1_000_000_000
    first = list(repetition_messages(plan, 0))
    third = list(repetition_messages(plan, 2))
    assert len(first) == len(third) == sum(plan.counts.values())
    for (t0, m0, l0), (t2, m2, l2) in zip(first, third, strict=True):
        assert t0 == t2 and l2 - l0 == 2 * plan.shift_ns
        s0, s2 = conv.stamp_to_ns(m0.header.stamp), conv.stamp_to_ns(m2.header.stamp)
        assert s2 - s0 == 2 * plan.shift_ns  # exact integer nanoseconds
        if t0.endswith("/image_strip"):
            assert m0.header.frame_id.startswith("r0000_pan_scene_")
            assert m2.header.frame_id == "r0002_" + m0.header.frame_id[6:]
            assert bytes(m0.data) == bytes(m2.data)
        if t0 in ("gcp", "truth/points"):
            ids = {o.scene_id for p in m2.points for o in p.observations}
            assert ids == {"r0002_pan_scene_0000", "r0002_pan_scene_0001"}
            assert all(p.id.startswith("r0002_") for p in m2.points)
        if t0 == "navigation":
            assert m0.header.frame_id == m2.header.frame_id == "map"


def test_compare_pairs_is_exact_and_names_the_field() -> None:
    a = {"x": 1.0, "v": (1.0, float("nan")), "s": "gcp"}
    assert compare_pairs(a, dict(a)) == {"differ": [], "max_rel_diff": 0.0}
    b = dict(a, x=1.0 + 1e-15)
    res = compare_pairs(a, b)
    assert res["differ"] == ["x"] and 0 < res["max_rel_diff"] < 1e-14
    assert compare_pairs(a, b, rtol=1e-12)["differ"] == []
    assert compare_pairs(a, dict(a, s="virtual"))["differ"] == ["s"]
    assert compare_pairs(a, dict(a, v=(1.0, 2.0)))["differ"] == ["v"]


# ---- the node's memory: what it holds stays bounded ----------------------------------------


@pytest.mark.ros
def test_pipeline_forgets_navigation_and_gcp_of_finished_pairs() -> None:
    """Repetitions of ikonos_agile (GCP scenes): navigation and GCP held stay bounded.

    Before the fix every navigation sample (1447 per repetition, about 0.6 kB each) and every
    GCP (28 per repetition) stayed in the pipeline for good: +1.0 MB of node RSS per pair.
    """
    plan = plan_bag(IKONOS)
    pipe = Pipeline(config_from_bag(BagReader(IKONOS), tie_points=False))
    held: list[tuple[int, int]] = []
    out = feed(pipe, plan, 5, lambda k: held.append((len(pipe.nav), len(pipe.gcp))))
    assert [p.pair_id for p in out.pairs] == [
        f"r000{k}_pan_scene_0000+r000{k}_pan_scene_0001" for k in range(5)
    ]
    assert [i for i in out.issues if i.level != "ok"] == []
    # Held at the end of each repetition: the last scene is still open (it closes with the next
    # repetition's first strip), so its navigation (from nav_history_s before its first line)
    # and its repetition's 28 GCP are kept; nothing older.
    rate_hz = 20
    scene_s = 768 / 6500
    bound = (pipe.config.navigation.history_s + scene_s + 1.0 + 0.1) * rate_hz
    assert all(n <= bound for n, _ in held), held
    assert all(g == 28 for _, g in held), held
    assert held[-1] == held[1]
    # flush() made the last pair: its GCP are gone too.
    assert len(pipe.gcp) == 0
    # Same numbers in every repetition (the pipeline keeps nothing from one to the next).
    ref = pair_numbers(conv.pair_to_msgs(out.pairs[0], frame_id="map")[0])
    for pair in out.pairs[1:]:
        cmp = compare_pairs(ref, pair_numbers(conv.pair_to_msgs(pair, frame_id="map")[0]))
        assert cmp == {"differ": [], "max_rel_diff": 0.0}, pair.pair_id


@pytest.mark.ros
def test_navigation_is_kept_while_a_scene_may_need_it() -> None:
    """Pruning never costs a scene its navigation: strips held back until navigation ended."""
    plan = plan_bag(IKONOS)
    pipe = Pipeline(config_from_bag(BagReader(IKONOS), tie_points=False))
    msgs = list(repetition_messages(plan, 0))
    strips = [m for m in msgs if m[0] == "pan/image_strip"]
    # All navigation first (73 s of it), then the strips: the first scene starts 72 s before
    # the newest sample, and its navigation must still be there.
    out = Outputs()
    for topic, msg, _ in msgs:
        if topic == "navigation":
            out.extend(pipe.add_navigation(conv.odometry_to_sample(msg)))
        elif topic == "gcp":
            out.extend(pipe.add_gcp(conv.gcp_from_msg(msg)))
    assert len(pipe.nav) == plan.counts["navigation"]  # no strip yet: nothing is known
    for _, msg, _ in strips:
        arr = conv.image_to_array(msg)
        out.extend(
            pipe.add_strip("pan", conv.stamp_to_ns(msg.header.stamp), msg.header.frame_id, arr)
        )
    out.extend(pipe.flush())
    assert len(out.pairs) == 1 and [s.method for s in out.scenes] == ["gcp_roll_estimated"] * 2
    assert all(s.model is not None for s in out.scenes)  # navigation-based model used too
    assert [i for i in out.issues if i.level != "ok"] == []


@pytest.mark.ros
def test_gcp_arriving_after_their_scene_are_reported_not_kept() -> None:
    """What the first 20-minute run met once: a GCP set delayed past its first scene.

    The first scene had been processed from navigation, silently, and the set stayed in the
    pipeline. Now the late observations are reported (WARN on the scene) and dropped; the
    second scene, still open, uses them.
    """
    plan = plan_bag(IKONOS)
    pipe = Pipeline(config_from_bag(BagReader(IKONOS), tie_points=False))
    msgs = list(repetition_messages(plan, 0))
    out = Outputs()
    for topic, msg, _ in msgs:
        if topic == "navigation":
            out.extend(pipe.add_navigation(conv.odometry_to_sample(msg)))
        elif topic == "pan/image_strip":
            arr = conv.image_to_array(msg)
            stamp = conv.stamp_to_ns(msg.header.stamp)
            out.extend(pipe.add_strip("pan", stamp, msg.header.frame_id, arr))
    assert [s.method for s in out.scenes] == ["navigation"]  # the second scene is open
    gcp = next(m for t, m, _ in msgs if t == "gcp")
    late = pipe.add_gcp(conv.gcp_from_msg(gcp))
    seen = sum(1 for p in gcp.points if any(o.scene_id.endswith("0000") for o in p.observations))
    assert [(i.level, i.where, i.message) for i in late.issues] == [
        (
            "warn",
            "pan/r0000_pan_scene_0000",
            f"{seen} GCP and check points observed in this scene arrived after it was "
            "processed (navigation): not used",
        )
    ]
    assert pipe.gcp and all(
        "r0000_pan_scene_0000" not in p.observations for p in pipe.gcp.values()
    )
    out.extend(pipe.flush())
    assert [s.method for s in out.scenes] == ["navigation", "gcp_roll_estimated"]
    assert len(out.pairs) == 1 and pipe.gcp == {}


# ---- the pair checks, offline (streamed pairs: column blocks) ------------------------------


def _checked(plan: Any, out: Outputs, tamper: Any = None) -> PairChecker:
    checker = PairChecker(plan, truth_from_bag(BagReader(plan.bag)), t0=0.0)
    for topic, msg, _ in conv.outputs_to_messages(out, frame_id="map", stamp_ns=0):
        if tamper is not None:
            tamper(topic, msg)
        checker.on_message(topic, msg)
    return checker


@pytest.mark.ros
def test_checker_on_streamed_pairs() -> None:
    plan = plan_bag(AIRBORNE)
    cfg = config_from_bag(BagReader(AIRBORNE), scene_lines=768, tie_points=False)
    out = feed(Pipeline(cfg), plan, 2)
    assert len(out.pairs) == 2 and all(p.left_image is None for p in out.pairs)
    checker = _checked(plan, out)
    recs = checker.records
    assert [r.rep for r in recs] == [0, 1] and all(r.streamed for r in recs)
    assert [r.problems for r in recs] == [[], []]
    assert recs[1].identical and recs[1].max_rel_diff == 0.0
    assert recs[0].truth_y_rms_px is not None and recs[0].truth_y_rms_px < 0.1
    assert checker.incomplete() == []

    def shift_block(topic: str, msg: Any) -> None:
        if (
            topic == "right/normalized_block"
            and msg.index == 1
            and msg.pair_id.startswith("r0001")
        ):
            msg.col0 += 1

    bad = _checked(plan, out, shift_block).records
    assert bad[0].problems == []
    assert any("right block 1 at column" in p for p in bad[1].problems), bad[1].problems


@pytest.mark.ros
def test_checker_flags_a_changed_parameter_and_a_wrong_image() -> None:
    plan = plan_bag(IKONOS)
    out = feed(Pipeline(config_from_bag(BagReader(IKONOS), tie_points=False)), plan, 3)

    rep_of_stamp = {p.stamp_ns: k for k, p in enumerate(out.pairs)}

    def tamper(topic: str, msg: Any) -> None:
        rep = rep_of_stamp.get(conv.stamp_to_ns(msg.header.stamp))
        if topic == "stereo_pair" and rep == 1:
            msg.left_params.affine[7] *= 1 + 1e-12
        if topic == "anaglyph" and rep == 2:
            msg.width -= 1

    recs = _checked(plan, out, tamper).records
    assert [r.rep for r in recs] == [0, 1, 2]
    assert recs[0].problems == []
    assert not recs[1].identical
    assert recs[1].problems == ["differs from the first repetition in left_params.affine"]
    assert any(p.startswith("anaglyph is ") for p in recs[2].problems), recs[2].problems


# ---- the command, live ---------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.ros
def test_longrun_live(tmp_path: Path) -> None:
    """A few repetitions through the real node: every pair, well formed, identical, no drops."""
    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    reps = 4
    rep = run_longrun(
        IKONOS,
        tmp_path,
        minutes=3.0,
        repetitions=reps,
        warmup_s=5.0,
        progress=False,
        log=lambda s: None,
    )
    p = rep["pairs"]
    detail = json.dumps({k: rep[k] for k in ("pairs", "drops", "stalls", "aborted", "node")})
    assert rep["repetitions"] == reps, detail
    assert p["expected"] == p["published"] == p["well_formed"] == reps, detail
    assert p["malformed"] == 0 and p["missing_count"] == 0 and p["incomplete"] == [], detail
    assert p["identical_to_first"] == p["compared"] == reps - 1 and p["max_rel_diff"] == 0.0
    assert rep["scenes"] == {"expected": 2 * reps, "published": 2 * reps, "problems": []}
    d = rep["drops"]
    for key in ("strips_rejected", "nav_rejected", "strips_not_received", "nav_not_received"):
        assert d[key] == 0, detail
    assert d["diagnostics_warn"] == d["diagnostics_error"] == 0, detail
    assert rep["node"]["exit_code"] == 0 and not rep["node"]["traceback_in_log"]
    assert rep["ok"] and rep["aborted"] is None and rep["stalls"] == []
    assert rep["messages_sent"]["navigation"] == reps * 1447
    assert rep["messages_sent"]["pan/image_strip"] == reps * 24
    ytruth = rep["truth_y_parallax_rms_px"]
    assert ytruth["min"] == ytruth["max"] == ytruth["first"] and ytruth["first"] < 0.1
    # The structure of the report (the figures themselves are measured, not asserted).
    assert rep["simulated_s"] == pytest.approx(reps * (72.3 + 1.0), abs=1e-6)
    assert rep["wall_s"] > 0 and rep["simulated_per_wall"] > 0
    for key in (
        "start",
        "at_warmup_end",
        "end",
        "max",
        "slope_mb_per_hour",
        "slope_mb_per_pair",
        "slope_second_half_mb_per_hour",
        "fit_from_s",
    ):
        assert key in rep["rss_mb"], rep["rss_mb"]
    assert 0 < rep["rss_mb"]["start"] <= rep["rss_mb"]["max"]
    assert rep["queue"]["last"] == 0 and rep["queue"]["max"] is not None
    assert rep["queue"]["nav_samples_held"]["last"] is not None
    assert len(rep["series"]["pairs"]) == reps and len(rep["series"]["rss"]) >= 3
    saved = json.loads((tmp_path / "longrun.json").read_text())
    assert saved["pairs"]["published"] == reps and set(saved) == set(rep)
    png = (tmp_path / "longrun.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000
    assert np.isfinite(saved["cpu"]["machine_busy_cores"])


def test_longrun_options() -> None:
    from tools.longrun.run import build_parser

    args = build_parser().parse_args(["--repetitions", "3", "-o", "x", "--node-param", "a=1"])
    assert args.repetitions == 3 and args.output == "x" and args.node_param == ["a=1"]
    assert args.bag.endswith("bags/ikonos_agile") and args.minutes == 20.0
