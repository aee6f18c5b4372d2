"""The streaming policy (core/streaming.py :func:`decide_streams`, :func:`side_end`) as data.

The policy is pure: it reads the ledger, the scenes open in each view and the navigation, and
returns a decision per pair that can be decided; the :class:`Streamer` carries the decisions
out. Each case builds the ledger and the open scenes by hand (the fore/aft bag's configuration:
two views, 768-line scenes, one line clock) and checks the decision, its times, its message,
and that the ledger is left as it was.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from testkit.paths import BAGS

from parproj_ros.core.config import PipelineConfig
from parproj_ros.core.ledger import PairLedger, StreamPair
from parproj_ros.core.results import Level
from parproj_ros.core.streaming import (
    STALE_MIN_S,
    Decision,
    NavState,
    SideEnd,
    decide_streams,
    held,
    side_end,
)
from parproj_ros.imaging.assembly import OpenScene, Scene
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import config_from_bag

pytestmark = pytest.mark.ros  # the configuration is the bag's

LINES = 768
T0 = 10_000_000_000  # first line of pair 0's scenes, ns


@pytest.fixture(scope="module")
def config() -> PipelineConfig:
    return config_from_bag(BagReader(BAGS / "airborne_foreaft"), scene_lines=LINES)


def _period_ns(config: PipelineConfig) -> float:
    return config.views[0].camera.line_period * 1e9


def _scene(config: PipelineConfig, view: str, k: int, lines: int, t0: int = T0) -> Scene:
    cam = next(v.camera for v in config.views if v.name == view)
    return Scene(view, f"{view}_{k}", k, t0, cam.line_period, np.zeros((lines, 4), np.uint16))


def _decide(
    config: PipelineConfig,
    ledger: PairLedger,
    opened: dict[str, OpenScene | None],
    nav: NavState,
) -> list:  # type: ignore[type-arg]
    before = _snapshot(ledger)
    decisions = decide_streams(ledger, opened, nav, config)
    assert _snapshot(ledger) == before, "the policy changed the ledger"
    return decisions


def _snapshot(ledger: PairLedger) -> dict[str, object]:
    """The ledger's records by value (scenes by identity: their pixels are not compared)."""
    return {
        name: (
            [id(x) for x in value]
            if name == "waiting"
            else copy.deepcopy({v: {k: id(r) for k, r in d.items()} for v, d in value.items()})
            if name == "ready"
            else id(value)
            if name == "admission"  # the admission's book: not the streaming policy's
            else copy.copy(value)
        )
        for name, value in vars(ledger).items()
    }


def test_both_views_begun_streams(config: PipelineConfig) -> None:
    fore, aft = (v.name for v in config.views)
    ledger = PairLedger([fore, aft])
    opened = {fore: OpenScene("f0", 0, T0, 100), aft: OpenScene("a0", 0, T0 + 5_000, 40)}
    nav = NavState(last_ns=T0 + 1_000_000, first_ns=T0 - 2_000_000_000, max_gap_s=1.0)
    (d,) = _decide(config, ledger, opened, nav)
    assert d.kind is Decision.STREAM and d.pair == 0
    assert [n for n, _ in d.parts] == [fore, aft]
    assert d.until_ns == T0 + 5_000  # the decision time: the later scene's first line
    assert d.issue is None and not d.held


def test_decided_pairs_get_no_decision(config: PipelineConfig) -> None:
    fore, aft = (v.name for v in config.views)
    ledger = PairLedger([fore, aft])
    ledger.not_stream(0)
    opened = {fore: OpenScene("f0", 0, T0, 100), aft: OpenScene("a0", 0, T0, 40)}
    nav = NavState(T0, T0 - 2_000_000_000, 1.0)
    assert _decide(config, ledger, opened, nav) == []


def test_lagging_navigation_holds_the_decision(config: PipelineConfig) -> None:
    """The fore scene is complete and waits for navigation; the aft scene has begun; navigation
    lags more than ``max_gap_s`` behind the aft scene's start: HOLD until that start."""
    fore, aft = (v.name for v in config.views)
    ledger = PairLedger([fore, aft])
    ledger.waiting.append(_scene(config, fore, 0, LINES))
    t_aft = T0 + 3_000_000_000
    opened = {fore: None, aft: OpenScene("a0", 0, t_aft, 10)}
    lag = NavState(last_ns=t_aft - 1_500_000_000, first_ns=T0 - 2_000_000_000, max_gap_s=1.0)
    (d,) = _decide(config, ledger, opened, lag)
    assert d.kind is Decision.HOLD and d.until_ns == t_aft
    # Navigation within max_gap_s of the start: no hold (the pipeline processes fore whole).
    near = NavState(last_ns=t_aft - 500_000_000, first_ns=lag.first_ns, max_gap_s=1.0)
    assert _decide(config, ledger, opened, near) == []


def test_a_held_scene_that_ended_short_goes_whole(config: PipelineConfig) -> None:
    fore, aft = (v.name for v in config.views)
    ledger = PairLedger([fore, aft])
    short = _scene(config, fore, 0, LINES - 100)
    ledger.waiting.append(short)
    ledger.hold(0, T0)  # the decision waits for navigation to reach T0
    opened = {fore: None, aft: OpenScene("a0", 0, T0, 300)}
    nav = NavState(last_ns=None, first_ns=None, max_gap_s=1.0)
    assert held(ledger, short, nav.last_ns)
    (d,) = _decide(config, ledger, opened, nav)
    assert d.kind is Decision.WHOLE and d.issue is not None
    assert d.issue.level is Level.WARN
    assert f"{fore}/{short.scene_id} ended short ({LINES - 100} of {LINES} lines)" in (
        d.issue.message
    )


def test_a_view_whose_strips_stopped_goes_whole(config: PipelineConfig) -> None:
    """The fore scene's strips stopped while the aft view went on for more than a scene and
    at least STALE_MIN_S: its pair is processed whole, with an OK line naming the scene."""
    fore, aft = (v.name for v in config.views)
    ledger = PairLedger([fore, aft])
    period = _period_ns(config)
    stale = max(STALE_MIN_S, LINES * period / 1e9) * 1e9
    t_aft = T0 + int(stale) + int(200 * period)  # aft's next line comes > stale after fore's
    opened = {fore: OpenScene("f0", 0, T0, 100), aft: OpenScene("a0", 0, t_aft, 100)}
    nav = NavState(t_aft, T0 - 2_000_000_000, 1.0)
    (d,) = _decide(config, ledger, opened, nav)
    assert d.kind is Decision.WHOLE and d.issue is not None and d.issue.level is Level.OK
    assert "the strips of f0 stopped arriving" in d.issue.message
    # Delivered within the stale bound: streamed.
    opened[aft] = OpenScene("a0", 0, T0 + int(stale) - int(200 * period), 100)
    (d,) = _decide(config, ledger, opened, nav)
    assert d.kind is Decision.STREAM


def test_pair_0_begun_before_navigation_goes_whole_silently(config: PipelineConfig) -> None:
    fore, aft = (v.name for v in config.views)
    ledger = PairLedger([fore, aft])
    opened = {fore: OpenScene("f0", 0, T0, 100), aft: OpenScene("a0", 0, T0, 100)}
    margin = config.navigation.start_margin_s
    late = NavState(T0, first_ns=T0 - int(margin * 1e9) + 1, max_gap_s=1.0)
    (d,) = _decide(config, ledger, opened, late)
    assert d.kind is Decision.WHOLE and d.issue is None
    seen = NavState(T0, first_ns=T0 - int(margin * 1e9), max_gap_s=1.0)
    assert _decide(config, ledger, opened, seen)[0].kind is Decision.STREAM


def test_side_end(config: PipelineConfig) -> None:
    """As planned at the planned length; short before anything was published: whole; short
    after a block was published: abandoned."""
    from types import SimpleNamespace

    fore, aft = (v.name for v in config.views)
    sides = {
        "left": SimpleNamespace(view=fore, lines=LINES, next_block=0),
        "right": SimpleNamespace(view=aft, lines=LINES, next_block=0),
    }
    stream = StreamPair(0, None, sides, T0)  # type: ignore[arg-type]
    assert side_end(stream, _scene(config, fore, 0, LINES)) is SideEnd.AS_PLANNED
    assert side_end(stream, _scene(config, fore, 0, LINES - 1)) is SideEnd.WHOLE
    sides["right"].next_block = 1
    assert side_end(stream, _scene(config, fore, 0, LINES - 1)) is SideEnd.ABANDON
