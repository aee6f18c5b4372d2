"""``output_extent``: the normalized pair covers the two scenes' overlap (default) or their union.

Overlap keeps every ground point that both scenes see, at the pair's heights, inside both
normalized images; union adds each scene's area that the other one does not see.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from testkit.paths import BAGS
from testkit.scenes import feed, nav_events, render, strip_events

from parproj_ros.apps.process import process_bag
from parproj_ros.core.pipeline import PairResult, Pipeline
from parproj_ros.eval.published import normalized_px
from parproj_ros.geometry.navigation import virtual_points
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import truth_from_bag
from parproj_ros.sim.scenarios import SCENARIOS


def _pair(extent: str, shift_m: float) -> PairResult:
    """airborne_foreaft with the right scene ``shift_m`` further along track."""
    scn = SCENARIOS["airborne_foreaft"]()
    t_mid = (scn.scenes[0].start_s + scn.scenes[1].start_s) / 2
    pipe = Pipeline(scn.pipeline_config(tie_points=False, streaming=False, output_extent=extent))
    nav = nav_events(scn, offset=lambda t: np.array([shift_m if t > t_mid else 0.0, 0.0, 0.0]))
    out = feed(pipe, nav + strip_events(scn, render(scn, np.uint8)))
    (pair,) = out.pairs
    return pair


def _columns_rows(pair: PairResult, heights: list[float]) -> tuple[np.ndarray, ...]:
    """Output (col, row) in both images of points seen by both scenes at ``heights``."""
    lm, rm = pair.left.model, pair.right.model
    assert lm is not None and rm is not None
    obj = virtual_points(lm, (0.0, pair.left.scene.lines - 1.0), heights, grid=41)
    lr = rm.project(obj)
    ok = (lr[:, 0] >= 0) & (lr[:, 0] <= pair.right.scene.lines - 1)
    ok &= (lr[:, 1] >= 0) & (lr[:, 1] <= pair.right.scene.detectors - 1)
    ll = lm.project(obj[ok])
    out = []
    for res, ls, grid, to_n in (
        (pair.left, ll, pair.left_grid, pair.normalization.left),
        (pair.right, lr[ok], pair.right_grid, pair.normalization.right),
    ):
        n = res.geometry(to_n).image_to_normalized(ls[:, 0], ls[:, 1])
        out += [(n[:, 0] - grid.x_origin) / grid.pixel, (n[:, 1] - grid.y_origin) / grid.pixel]
    return tuple(out)


def test_overlap_keeps_every_common_point_and_drops_the_rest() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    union, overlap = _pair("union", 20.0), _pair("overlap", 20.0)
    assert overlap.left_grid.height == union.left_grid.height
    assert overlap.left_grid.width < union.left_grid.width
    assert overlap.left_image is not None and overlap.left_image.shape == (
        overlap.left_grid.height,
        overlap.left_grid.width,
    )
    z, h = scn.z_avg, scn.relief_m
    cl, _rl, cr, _rr = _columns_rows(overlap, [z - h, z, z + h])
    assert cl.size > 500
    w = overlap.left_grid.width
    for c in (cl, cr):
        assert c.min() >= -0.5 and c.max() <= w - 0.5
    # The overlap's first and last columns are used by some common point (it is tight).
    cols = np.concatenate([cl, cr])
    assert cols.min() < 0.05 * w and cols.max() > 0.95 * w  # (41 x 41 grid: ~19 px steps)


@pytest.mark.ros
def test_ventoux_overlap_sizes(tmp_path: Path) -> None:
    """The real pair: 949 -> 507 columns; every truth point inside both images.

    At the heights of the pair's GCP (``terrain`` prior): the truth points lie up to 100 m
    above and below the DEM's ground, outside the terrain measured from the images.
    """
    bag = BAGS / "ventoux"
    sizes = {}
    for extent in ("union", "overlap"):
        s = process_bag(
            bag,
            tmp_path / extent,
            progress=False,
            overrides={"tie_points": False, "output_extent": extent, "terrain": "prior"},
        )
        assert s.pairs == 1, s.issues
        sp = next(BagReader(tmp_path / extent).messages(topics=["stereo_pair"])).msg
        sizes[extent] = (sp.width, sp.height)
    assert sizes["union"][1] == sizes["overlap"][1]
    assert sizes["overlap"][0] < 0.6 * sizes["union"][0], sizes
    truth = truth_from_bag(BagReader(bag))
    lp, rp = sp.left_params, sp.right_params
    both = [p for p in truth if lp.scene_id in p.observations and rp.scene_id in p.observations]
    assert len(both) >= 250
    ol = np.array([p.observations[lp.scene_id] for p in both])
    orr = np.array([p.observations[rp.scene_id] for p in both])
    pix = sp.normalized_pixel_size
    cl, _ = normalized_px(
        lp, sp.left_to_normalized, sp.left_x_origin, sp.y_origin, pix, ol[:, 0], ol[:, 1]
    )
    cr, _ = normalized_px(
        rp, sp.right_to_normalized, sp.right_x_origin, sp.y_origin, pix, orr[:, 0], orr[:, 1]
    )
    for c in (cl, cr):
        assert c.min() >= 0 and c.max() <= sp.width - 1


def test_output_extent_parameter_is_declared() -> None:
    from parproj_ros.core.params import PARAMS

    (p,) = [p for p in PARAMS if p.name == "output_extent"]
    assert p.default == "overlap" and p.choices == ("overlap", "union")


@pytest.mark.parametrize("extent", ["overlap", "union"])
def test_streamed_pair_follows_the_extent(extent: str) -> None:
    """Column blocks tile the same grid as a whole-scene pair of that extent."""
    from parproj_ros.core.streaming import plan_blocks

    pair = _pair(extent, 20.0)
    geom = pair.left.geometry(pair.normalization.left)
    blocks = plan_blocks(geom, pair.left_grid, pair.left.scene.lines)
    assert blocks[0].col0 == 0
    assert sum(b.cols for b in blocks) == pair.left_grid.width
