"""core/render_process.py: streamed blocks rendered in a child process from shared line buffers."""

from __future__ import annotations

import numpy as np

from parproj_ros.core.pipeline import Pipeline, PipelineConfig
from parproj_ros.core.render_process import RenderProcess
from parproj_ros.core.trajectory import NavSample
from parproj_ros.sim.synthetic import VIEWS, acquisition, make_platform, texture_blocks


def _stream(renderer: RenderProcess | None, sink: bool = False) -> list[np.ndarray]:
    """Two pairs of the benchmark's fore/aft platform (2048 lines, 192 detectors); the blocks.

    Fed as the node feeds the pipeline once a message is converted (NavSamples, uint16 strips),
    with no ROS message: core/ is ROS-free, and so is this test (``./dev fast`` runs it). Every
    scene has the texture of ``sim.synthetic.StripMessages``: one random 11-bit block per strip
    position. ``sink``: the blocks are taken by a block sink as they are rendered (copied there).
    """
    plat = make_platform(2048, 192)
    events = sorted(acquisition(plat, 2, 256, 50.0), key=lambda e: (e.due_s, e.kind != "nav"))
    texture = {
        r0: texture_blocks(1, min(256, plat.lines - r0), plat.camera.detectors, seed=10 + r0)[0]
        for r0 in range(0, plat.lines, 256)
    }
    pipe = Pipeline(PipelineConfig(views=plat.views, scene_lines=2048))
    if renderer is not None:
        pipe.use_render_process(renderer)
    blocks = []
    if sink:
        pipe.set_block_sink(lambda blk: blocks.append(blk.image.copy()))
    for e in events:
        if e.kind == "nav":
            nav = NavSample(e.stamp_ns, plat.position(e.t_s), plat.body, plat.velocity)
            out = pipe.add_navigation(nav)
        else:
            out = pipe.add_strip(VIEWS[e.view], e.stamp_ns, e.scene_id, texture[e.row0])
        assert not (sink and out.blocks)
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
        assert list(rp.render_blocks([None], data, 0, 10, nodata=0.0, interpolation=1)) == [
            (None, None)
        ]
        assert rp.fallbacks == 1
    finally:
        rp.close()


def test_blocks_handed_to_a_sink_as_rendered() -> None:
    """The node's way: each block to the sink from the child's output buffer, one ahead."""
    ref = _stream(None)
    rp = RenderProcess()
    try:
        got = _stream(rp, sink=True)
        assert rp.alive and rp.rendered == len(got) and rp.fallbacks == 0
    finally:
        rp.close()
    assert len(ref) == len(got) >= 16
    assert all(np.array_equal(a, b) for a, b in zip(ref, got, strict=True))


class _LeavesEarly(RenderProcess):
    """Each batch of 2 or more blocks is first asked for and left after its first block."""

    left = 0

    def render_blocks(self, blocks, data, first_line, height, **kw):  # type: ignore[no-untyped-def]
        if len(blocks) >= 2:
            gen = super().render_blocks(blocks, data, first_line, height, **kw)
            next(gen)  # block 0 handed over, block 1 in the child
            gen.close()
            self.left += 1
        return super().render_blocks(blocks, data, first_line, height, **kw)


def test_leaving_early_waits_for_the_block_in_flight() -> None:
    """A consumer that stops mid-batch: the child's pending answer is read then, not taken
    for the next batch's (which would hand over a block still being rendered)."""
    ref = _stream(None)
    rp = _LeavesEarly()
    try:
        got = _stream(rp, sink=True)
        assert rp.alive and rp.left >= 2 and rp.fallbacks == 0
    finally:
        rp.close()
    assert all(np.array_equal(a, b) for a, b in zip(ref, got, strict=True))
