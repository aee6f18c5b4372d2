"""The committed bags are what `parproj simulate` makes, and what bags/README.md says they hold."""

from __future__ import annotations

import numpy as np
import pytest
from testkit.paths import BAGS

from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.conversions import image_to_array, stamp_to_ns
from parproj_ros.ros.inputs import truth_from_bag, views_from_bag
from parproj_ros.sim.scenarios import SCENARIOS
from parproj_ros.sim.simulate import render_scene
from parproj_ros.sim.terrain import procedural_terrain

pytestmark = pytest.mark.ros  # reads the bags (rclpy deserializes)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_bag_reproduces(name: str) -> None:
    scn = SCENARIOS[name]()
    reader = BagReader(BAGS / name)
    assert reader.recovery.complete if reader.recovery else True
    size = sum(f.stat().st_size for f in (BAGS / name).iterdir())
    assert size < 10e6  # "each at most about 10 MB"
    views = views_from_bag(reader)
    assert [v.name for v in views] == [v.name for v in scn.views]
    first = next(reader.messages(topics=[f"{scn.scenes[0].view}/image_strip"])).msg
    assert first.header.frame_id == scn.scene_id(0)
    assert stamp_to_ns(first.header.stamp) == scn.time_ns(scn.scenes[0].start_s)
    strip = image_to_array(first)
    terrain = procedural_terrain(
        scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
    )
    again = render_scene(scn.model(0), terrain, 0, strip.shape[0], dtype=np.dtype(scn.dtype))
    assert np.array_equal(strip, again), "bag differs from `parproj simulate`: re-record it"
    truth = truth_from_bag(reader)
    assert len(truth) == scn.truth
    counts = reader.message_counts()
    lines = sum(sc.lines for sc in scn.scenes)
    strips = sum(c for t, c in counts.items() if t.endswith("/image_strip"))
    assert strips == sum(-(-sc.lines // scn.strip_lines) for sc in scn.scenes)
    assert lines > 0 and counts["navigation"] > 10
