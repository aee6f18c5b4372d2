"""core/render_process.py: streamed blocks rendered in a child process from shared line buffers."""

from __future__ import annotations

import numpy as np

from parproj_ros.core.pipeline import Pipeline, PipelineConfig
from parproj_ros.core.render_process import RenderProcess
from parproj_ros.ros.conversions import image_to_array, odometry_to_sample, stamp_to_ns


def _stream(renderer: RenderProcess | None) -> list[np.ndarray]:
    """Two pairs of the benchmark's fore/aft platform (2048 lines, 192 detectors); the blocks."""
    from parproj_ros.sim.synthetic import StripMessages, acquisition, make_platform, nav_message

    plat = make_platform(2048, 192)
    events = sorted(acquisition(plat, 2, 256, 50.0), key=lambda e: (e.due_s, e.kind != "nav"))
    strips = StripMessages(plat, 256)
    pipe = Pipeline(PipelineConfig(views=plat.views, scene_lines=2048))
    if renderer is not None:
        pipe.use_render_process(renderer)
    blocks = []
    for e in events:
        if e.kind == "nav":
            out = pipe.add_navigation(odometry_to_sample(nav_message(plat, e.t_s)))
        else:
            m = strips.get(e)
            out = pipe.add_strip(
                ("left", "right")[e.view],
                stamp_to_ns(m.header.stamp),
                m.header.frame_id,
                image_to_array(m),
            )
        blocks += [b.image for b in out.blocks]
    return blocks


def test_blocks_from_the_child_are_those_of_the_thread() -> None:
    ref = _stream(None)
    rp = RenderProcess()
    try:
        got = _stream(rp)
        assert rp.alive and rp.rendered == len(got) and rp.fallbacks == 0
    finally:
        rp.close()
    assert len(ref) == len(got) >= 16
    assert all(np.array_equal(a, b) for a, b in zip(ref, got, strict=True))


def test_a_dead_child_falls_back_to_the_thread() -> None:
    """The child killed mid-stream: every block still comes, rendered in the caller."""
    ref = _stream(None)
    rp = RenderProcess()
    rp._proc.kill()
    rp._proc.join(5)
    try:
        got = _stream(rp)
    finally:
        rp.close()
    assert not rp.alive and rp.rendered == 0 and rp.fallbacks == len(got)
    assert all(np.array_equal(a, b) for a, b in zip(ref, got, strict=True))


def test_private_buffers_are_rendered_in_the_thread() -> None:
    """A line buffer not in shared memory (allocated before the process was set): in-thread."""
    rp = RenderProcess()
    try:
        data = np.zeros((10, 4), np.uint16)
        assert rp.render(None, data, 0, 10, nodata=0.0, interpolation=1) is None
        assert rp.fallbacks == 1
    finally:
        rp.close()
