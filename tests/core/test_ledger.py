"""The ledger of pairs (core/ledger.py): one owner answers where each pair is, all along.

The fore/aft bag streamed through the Pipeline, input by input: pair 0's state read from the
ledger after each input must walk waiting -> streaming -> made (and through ``held`` when
navigation arrives after the strips), and the ledger's counts must end empty but for the pair
made. The policies (navigation feed, pairing, streamer) keep no pair state of their own.
"""

from __future__ import annotations

import pytest
from testkit.paths import BAGS

from parproj_ros.core.ledger import PairLedger, PairState
from parproj_ros.core.pipeline import Pipeline
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import config_from_bag

pytestmark = pytest.mark.ros  # reads a bag

BAG = BAGS / "airborne_foreaft"
LINES = 768  # scene lines: the bag's two scenes of 768 lines make pair 0


def _walk(nav_delay_s: float) -> tuple[list[PairState], Pipeline, list[bool]]:
    """Pair 0's states, each new one as it appears, with navigation ``nav_delay_s`` late; the
    pipeline; whether each pair made was streamed (no whole images)."""
    reader = BagReader(BAG)
    pipe = Pipeline(config_from_bag(reader, scene_lines=LINES, tie_points=False))
    items = []
    for i, it in enumerate(reader.messages()):
        late = it.topic == "navigation"
        items.append((it.log_time_ns + (round(nav_delay_s * 1e9) if late else 0), i, it))
    states = [pipe.ledger.state(0)]
    streamed: list[bool] = []
    for _, _, item in sorted(items, key=lambda x: x[:2]):
        out = None
        if item.topic == "navigation":
            out = pipe.add_navigation(conv.odometry_to_sample(item.msg))
        elif item.topic.endswith("/image_strip"):
            m = item.msg
            out = pipe.add_strip(
                item.topic.split("/")[0],
                conv.stamp_to_ns(m.header.stamp),
                m.header.frame_id,
                conv.image_to_array(m),
            )
        streamed += [p.left_image is None for p in (out.pairs if out else [])]
        if pipe.ledger.state(0) != states[-1]:
            states.append(pipe.ledger.state(0))
    streamed += [p.left_image is None for p in pipe.flush().pairs]
    if pipe.ledger.state(0) != states[-1]:
        states.append(pipe.ledger.state(0))
    return states, pipe, streamed


def test_a_streamed_pair_walks_waiting_streaming_made() -> None:
    states, pipe, streamed = _walk(0.0)
    assert streamed == [True]
    assert states == [PairState.WAITING, PairState.STREAMING, PairState.MADE]
    assert pipe.ledger.counts() == {
        "pairs_streaming": 0,
        "pairs_held": 0,
        "scenes_waiting_navigation": 0,
        "scenes_waiting_partner": 0,
        "pairs_made": 1,
        "pairs_released": 0,
    }
    assert pipe.pairs_done == 1


def test_late_navigation_holds_the_decision_first() -> None:
    """Navigation 2 s behind the strips (until after the right scene is complete): the
    streaming decision is held; when navigation reaches the scenes' start the pair is streamed
    and, both scenes being complete by then, made within that same input."""
    states, pipe, streamed = _walk(2.0)
    assert states == [PairState.WAITING, PairState.HELD, PairState.MADE]
    assert streamed == [True] and pipe.ledger.counts()["pairs_made"] == 1


def test_the_policies_keep_no_pair_state() -> None:
    """Navigation feed, pairing and streamer read and write the pipeline's one ledger."""
    reader = BagReader(BAG)
    pipe = Pipeline(config_from_bag(reader, scene_lines=LINES))
    assert pipe.pairing.ledger is pipe.ledger
    assert pipe.streamer.ledger is pipe.ledger
    assert pipe.feed.ledger is pipe.ledger
    owned = {"waiting", "ready", "streams", "not_streamed", "held_until", "done", "selection"}
    for policy in (pipe.pairing, pipe.streamer, pipe.feed):
        assert not owned & set(vars(policy)), (type(policy).__name__, set(vars(policy)))
    assert isinstance(pipe.ledger, PairLedger)


def test_a_broken_stream_is_released() -> None:
    """The right view's last strips never come (the pass stops): the streamed pair is given
    up after its blocks were published; the ledger says released, and it is not made."""
    reader = BagReader(BAG)
    pipe = Pipeline(config_from_bag(reader, scene_lines=LINES, tie_points=False))
    items = [i for i in reader.messages() if i.topic == "navigation" or "image_strip" in i.topic]
    rights = [k for k, i in enumerate(items) if i.topic == "right/image_strip"]
    drop = set(rights[-2:])
    states = [pipe.ledger.state(0)]
    for k, item in enumerate(items):
        if k in drop:
            continue
        if item.topic == "navigation":
            pipe.add_navigation(conv.odometry_to_sample(item.msg))
        else:
            m = item.msg
            pipe.add_strip(
                item.topic.split("/")[0],
                conv.stamp_to_ns(m.header.stamp),
                m.header.frame_id,
                conv.image_to_array(m),
            )
        if pipe.ledger.state(0) != states[-1]:
            states.append(pipe.ledger.state(0))
    out = pipe.flush()
    assert not out.pairs and any(i.level == "error" for i in out.issues), out.issues
    assert pipe.ledger.state(0) == PairState.RELEASED
    assert states[:2] == [PairState.WAITING, PairState.STREAMING]
    assert pipe.ledger.counts()["pairs_released"] == 1 and pipe.pairs_done == 0
