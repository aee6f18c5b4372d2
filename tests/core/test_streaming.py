"""Streaming: normalized column blocks while the scenes arrive, equal to the whole-scene pair."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from testkit.paths import BAGS

from parproj_ros.apps.process import process_bag
from parproj_ros.core.pipeline import Pipeline
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.conversions import assemble_blocks, image_to_array, stamp_to_ns
from parproj_ros.ros.inputs import config_from_bag

pytestmark = pytest.mark.ros  # reads and processes bags

BAG = BAGS / "airborne_foreaft"
LINES = 768


@pytest.fixture(scope="module")
def outputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("streaming")
    out = {}
    for name, streaming in (("whole", False), ("streamed", True)):
        # Tie points refine whole-scene pairs only: compare like with like.
        overrides = {"scene_lines": LINES, "streaming": streaming, "tie_points": False}
        s = process_bag(BAG, d / name, progress=False, overrides=overrides)
        assert s.pairs == 1 and s.scenes == 2, s.issues
        out[name] = d / name
    return out


def test_streamed_pair_equals_whole_scene_pair(outputs: dict[str, Path]) -> None:
    whole, streamed = BagReader(outputs["whole"]), BagReader(outputs["streamed"])
    assert streamed.message_counts()["left/image_normalized"] == 0
    sp = next(streamed.messages(topics=["stereo_pair"])).msg
    assert sp.streamed and sp.left.height == 0 and sp.width > 0 and sp.height > 0
    for side in ("left", "right"):
        blocks = [m.msg for m in streamed.messages(topics=[f"{side}/normalized_block"])]
        assert [b.index for b in blocks] == list(range(len(blocks)))
        assert blocks[-1].last and not any(b.last for b in blocks[:-1])
        img = assemble_blocks(blocks)
        ref = image_to_array(next(whole.messages(topics=[f"{side}/image_normalized"])).msg)
        assert img.shape == ref.shape == (sp.height, sp.width)
        # Same parameters, same grid; tiles are planned per block instead of per 512 tile, so
        # a few pixels may differ by rounding (1 DN), none by more.
        diff = np.abs(img.astype(int) - ref.astype(int))
        assert diff.max() <= 1 and (diff > 0).mean() < 1e-3
    pw = [m.msg for m in whole.messages(topics=["parallel_projection"])]
    ps = [m.msg for m in streamed.messages(topics=["parallel_projection"])]
    for a, b in zip(pw, ps, strict=True):
        # The streamed right scene's motion was extrapolated from the navigation at its first
        # line: for this constant-velocity flight it equals the fit on the whole scene.
        np.testing.assert_allclose(a.affine, b.affine, rtol=1e-9, atol=1e-15)


def test_blocks_leave_before_the_scene_ends(outputs: dict[str, Path]) -> None:
    src = BagReader(BAG)
    last_strip = max(
        stamp_to_ns(m.msg.header.stamp) for m in src.messages(topics=["right/image_strip"])
    )
    first_strip = min(
        stamp_to_ns(m.msg.header.stamp) for m in src.messages(topics=["right/image_strip"])
    )
    times = [
        m.log_time_ns
        for m in BagReader(outputs["streamed"]).messages(topics=["right/normalized_block"])
    ]
    # process_bag logs outputs at the time of the input message that produced them.
    assert len(times) >= 2
    assert times[0] < last_strip and times[0] > first_strip


def test_memory_released_while_streaming() -> None:
    reader = BagReader(BAG)
    pipe = Pipeline(config_from_bag(reader, scene_lines=LINES))
    strips = {"left/image_strip": "left", "right/image_strip": "right"}
    from parproj_ros.ros import conversions as conv

    held = []
    blocks = 0
    for item in reader.messages():
        if item.topic == "navigation":
            pipe.add_navigation(conv.odometry_to_sample(item.msg))
        elif item.topic in strips:
            out = pipe.add_strip(
                strips[item.topic],
                stamp_to_ns(item.msg.header.stamp),
                item.msg.header.frame_id,
                conv.image_to_array(item.msg),
            )
            blocks += len(out.blocks)
            asm = pipe.assemblers["right"]
            if asm.is_open:
                _, data = asm.retained()
                held.append(data.shape[0])
    assert blocks >= 2
    # The right scene never holds all its lines at once: released as blocks go out.
    assert max(held) < LINES


def test_short_last_scene_is_processed_whole(tmp_path: Path) -> None:
    # 768-line scenes cut into 300-line parts: 300, 300, 168. The last parts are short (end of
    # the pass), so their length is unknown when their pair could start streaming: whole-scene.
    s = process_bag(BAG, tmp_path / "o", progress=False, overrides={"scene_lines": 300})
    assert s.scenes == 6 and s.pairs == 3, s.issues
    assert not [i for i in s.issues if i.level == "error"]
    pairs = [m.msg for m in BagReader(tmp_path / "o").messages(topics=["stereo_pair"])]
    assert [p.streamed for p in pairs] == [True, True, False]
    ids = [p.pair_id for p in pairs]
    assert len(set(ids)) == 3  # split scenes have distinct ids ("#1", "#2")


def _feed_synthetic(
    delay_s: Callable[[Any], float], *, flush: bool, lines: int = 2048, strip_lines: int = 256
) -> tuple[int, int, list[Any]]:
    """Two pairs of the benchmark's fore/aft platform (one line clock, narrow: ``lines`` lines,
    256 detectors) through the pipeline, each event delivered ``delay_s(event)`` s after it is
    due (navigation first among events due together); with ``flush``, the pipeline is flushed
    at the end. Returns pairs streamed, pairs processed whole, and the issues."""
    from parproj_ros.core.pipeline import PipelineConfig
    from parproj_ros.ros import conversions as conv
    from parproj_ros.sim.synthetic import StripMessages, acquisition, make_platform, nav_message

    # 2048 lines: the platform's fore/aft angle follows the scene length (base/height 0.0025);
    # 256 detectors keep the test fast.
    plat = make_platform(lines, 256)
    events = acquisition(plat, 2, strip_lines, 50.0)
    strips = StripMessages(plat, strip_lines)
    order = sorted(events, key=lambda e: (e.due_s + delay_s(e), e.kind != "nav"))
    pipe = Pipeline(PipelineConfig(views=plat.views, scene_lines=lines))
    streamed = whole = 0
    issues: list[Any] = []
    for e in [*order, None] if flush else order:
        if e is None:
            out = pipe.flush()
        elif e.kind == "nav":
            out = pipe.add_navigation(conv.odometry_to_sample(nav_message(plat, e.t_s)))
        else:
            m = strips.get(e)
            out = pipe.add_strip(
                ("left", "right")[e.view],
                stamp_to_ns(m.header.stamp),
                m.header.frame_id,
                conv.image_to_array(m),
            )
        streamed += sum(p.left_image is None for p in out.pairs)
        whole += sum(p.left_image is not None for p in out.pairs)
        issues += out.issues
    return streamed, whole, issues


@pytest.mark.parametrize(
    ("delay_s", "lines", "strip_lines"),
    [
        (0.0, 2048, 256),
        (0.08, 2048, 256),
        (-0.08, 2048, 256),
        (1.5, 14000, 500),
        (-1.5, 14000, 500),
    ],
)
def test_a_view_delivered_late_still_streams(delay_s: float, lines: int, strip_lines: int) -> None:
    """Fore/aft cameras on one line clock (the benchmark's platform, narrow): one view's strips
    arrive 0.08 s (two strips) after the other's, or, with IKONOS-length scenes (2.15 s),
    1.5 s after (as over DDS at the full rate: a reliable writer resending). Both pairs must
    still stream: a view that is merely late is not a short scene."""
    streamed, whole, _ = _feed_synthetic(
        lambda e: delay_s if e.kind == "strip" and e.view == 0 else 0.0,
        flush=False,
        lines=lines,
        strip_lines=strip_lines,
    )
    assert (streamed, whole) == (2, 0)


def _feed(nav_delay_s: float, drop_nav: tuple[float, float] | None = None) -> dict:
    """The fore/aft bag through the pipeline, navigation delivered ``nav_delay_s`` late (its
    stamps unchanged: strips overtake it, as across DDS topics); ``drop_nav``: a span of
    navigation (s from the bag start) never delivered."""
    from parproj_ros.ros import conversions as conv

    reader = BagReader(BAG)
    pipe = Pipeline(config_from_bag(reader, scene_lines=LINES, tie_points=False))
    t_first = reader.start_ns
    items = []
    for i, it in enumerate(reader.messages()):
        t = it.log_time_ns
        if it.topic == "navigation":
            if drop_nav and drop_nav[0] <= (t - t_first) / 1e9 < drop_nav[1]:
                continue
            t += round(nav_delay_s * 1e9)
        items.append((t, i, it))
    got: dict = {"blocks": [], "pairs": [], "scenes": [], "issues": []}
    for _, _, item in sorted(items, key=lambda x: x[:2]):
        if item.topic == "navigation":
            out = pipe.add_navigation(conv.odometry_to_sample(item.msg))
        elif item.topic in ("left/image_strip", "right/image_strip"):
            m = item.msg
            out = pipe.add_strip(
                item.topic.split("/")[0],
                stamp_to_ns(m.header.stamp),
                m.header.frame_id,
                conv.image_to_array(m),
            )
        else:
            continue
        for key in got:
            got[key] += getattr(out, key)
    out = pipe.flush()
    for key in got:
        got[key] += getattr(out, key)
    return got


@pytest.mark.parametrize("delay_s", [2.0, 5.0])
def test_navigation_behind_the_strips_still_streams(delay_s: float) -> None:
    """Navigation on its own topic may arrive after the strips of a scene (more than the
    1 s that streaming tolerates, here until after the whole right scene): the decision is held
    until navigation reaches the scene start, and the outputs are those of on-time navigation,
    bit for bit."""
    ref, late = _feed(0.0), _feed(delay_s)
    assert [p.left_image is None for p in late["pairs"]] == [True]
    assert len(late["blocks"]) == len(ref["blocks"]) >= 4
    for a, b in zip(ref["blocks"], late["blocks"], strict=True):
        assert (a.side, a.index, a.col0, a.last) == (b.side, b.index, b.col0, b.last)
        assert np.array_equal(a.image, b.image)
    for a, b in zip(ref["scenes"], late["scenes"], strict=True):
        assert a.scene.scene_id == b.scene.scene_id
        assert np.array_equal(a.affine, b.affine) and a.psi == b.psi
    held = [i for i in late["issues"] if "decision held" in i.message]
    assert [(i.level, i.where) for i in held] == [("ok", "pair left_scene_0000+right_scene_0001")]
    assert not [i for i in late["issues"] if i.level in ("warn", "error")], late["issues"]


def test_navigation_missing_at_the_scene_start_is_reported() -> None:
    """Navigation late and with a hole around the right scene's start (36.6 s): it cannot be
    streamed; the fallback to whole-scene processing says why (WARN), never silently."""
    got = _feed(2.0, drop_nav=(35.0, 36.7))
    assert [p.left_image is None for p in got["pairs"]] in ([False], [])
    assert not got["blocks"]
    warns = [i for i in got["issues"] if i.level == "warn" and "not streamed" in i.message]
    assert len(warns) == 1 and warns[0].where == "right/right_scene_0001", got["issues"]
    assert "navigation at the scene start" in warns[0].message


@pytest.mark.parametrize("nav_delay_s", [2.0, 6.0])
def test_two_open_scenes_wait_for_late_navigation(nav_delay_s: float) -> None:
    """Fore/aft cameras on one line clock, both scenes of a pair arriving together, navigation
    delivered 2 s (or 6 s: after whole scenes) late: both pairs still stream, each saying that
    its decision was held, and nothing is processed whole."""
    streamed, whole, issues = _feed_synthetic(
        lambda e: nav_delay_s if e.kind == "nav" else 0.0, flush=True
    )
    assert (streamed, whole) == (2, 0), issues
    assert len([i for i in issues if "decision held" in i.message]) == 2, issues


def test_a_side_complete_at_the_opening_is_paced_with_the_other() -> None:
    """Fore/aft cameras: the fore (left) scene of a pair is complete when the aft one begins.

    Its blocks used to go out all in the input that opened the stream (55 at the IKONOS
    width: 0.7-0.8 s before the pair's first DSM tile could be made, docs/stream_start.md).
    Now they go out as the right side's do, at most PACED_LEAD_BLOCKS ahead, each once and in
    order, and all of them before the pair.
    """
    from parproj_ros.core.pipeline import PipelineConfig
    from parproj_ros.core.streaming import PACED_LEAD_BLOCKS
    from parproj_ros.ros import conversions as conv
    from parproj_ros.sim.synthetic import StripMessages, acquisition, make_platform, nav_message

    plat = make_platform(2048, 256)
    strips = StripMessages(plat, 128)
    pipe = Pipeline(PipelineConfig(views=plat.views, scene_lines=2048))
    sent: dict[tuple[str, str], list[tuple[int, bool]]] = {}  # (pair, side) -> (index, last)
    lead: dict[str, list[int]] = {}  # pair -> left minus right blocks out, per input with any
    for e in acquisition(plat, 2, 128, 50.0):
        if e.kind == "nav":
            out = pipe.add_navigation(conv.odometry_to_sample(nav_message(plat, e.t_s)))
        else:
            m = strips.get(e)
            out = pipe.add_strip(
                ("left", "right")[e.view],
                stamp_to_ns(m.header.stamp),
                m.header.frame_id,
                conv.image_to_array(m),
            )
        for b in out.blocks:
            sent.setdefault((b.pair_id, b.side), []).append((b.index, b.last))
        for pid in {b.pair_id for b in out.blocks}:
            left, right = (sent.get((pid, s), []) for s in ("left", "right"))
            if not (right and right[-1][1]):  # the right side still streams
                lead.setdefault(pid, []).append(len(left) - len(right))
        for pair in out.pairs:  # every block of the pair is out before it
            assert all(sent[(pair.pair_id, s)][-1][1] for s in ("left", "right")), pair.pair_id
    assert len(lead) == 2, sorted(sent)
    for (pid, side), got in sent.items():
        idx = [i for i, _ in got]
        assert idx == list(range(len(idx))) and len(idx) > PACED_LEAD_BLOCKS, (pid, side)
    for pid, ahead in lead.items():
        # The left side (complete) leads the right one by at most the lead, over many inputs.
        assert max(ahead) == PACED_LEAD_BLOCKS and len(ahead) >= 4, (pid, ahead)
