"""The outputs' object frame (parproj_ros/core/frames.py): given, else the inputs' first."""

from __future__ import annotations

import threading

from parproj_ros.core.frames import DEFAULT_FRAME, ObjectFrame
from parproj_ros.core.results import Level

ENU = "enu_wgs84:lat=43.2617438,lon=5.4429495,h=187.88"


def test_first_input_names_the_frame_and_a_different_one_warns_once() -> None:
    f = ObjectFrame()
    assert f.frame_id == DEFAULT_FRAME == "map"
    assert f.observe("gcp", "") == [] and f.frame_id == "map"  # names no frame
    assert f.observe("gcp", ENU) == [] and f.frame_id == ENU
    (w,) = f.observe("navigation", "map")
    assert w.level == Level.WARN and w.where == "navigation"
    assert "'map'" in w.message and ENU in w.message and "gcp" in w.message
    assert f.observe("navigation", "map") == []  # once per input and frame
    assert f.observe("gcp", ENU) == [] and f.frame_id == ENU


def test_given_frame_wins_and_inputs_elsewhere_warn() -> None:
    f = ObjectFrame("  odom ")
    assert f.frame_id == "odom" and f.observe("gcp", "odom") == []
    (w,) = f.observe("gcp", ENU)
    assert "given by the user" in w.message and f.frame_id == "odom"


def _race(f: ObjectFrame) -> dict[str, list[object]]:
    """gcp (ENU) and navigation (map) observed by two threads started together, 20 times each."""
    out: dict[str, list[object]] = {}
    go = threading.Barrier(2)

    def feed(topic: str, frame: str) -> None:
        go.wait()
        out[topic] = [x for _ in range(20) for x in f.observe(topic, frame)]

    ts = [threading.Thread(target=feed, args=a) for a in (("gcp", ENU), ("navigation", "map"))]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    return out


def test_concurrent_inputs_agree_on_one_frame() -> None:
    """Callbacks of two threads: one frame wins, the other input gets exactly one WARN."""
    for _ in range(50):
        f = ObjectFrame()
        out = _race(f)
        loser, winner = ("navigation", "gcp") if f.frame_id == ENU else ("gcp", "navigation")
        assert len(out[loser]) == 1 and out[winner] == []
