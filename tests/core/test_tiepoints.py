"""Tie-point refinement removes a y-parallax that biased GCP leave, and keeps x-parallax."""

from __future__ import annotations

import numpy as np
import pytest
from testkit.paths import BAGS

from parproj_ros.core.pipeline import GroundPoint, Outputs, Pipeline
from parproj_ros.eval.published import normalized_px
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import config_from_bag, truth_from_bag

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # reads bags/ikonos_agile

BAG = BAGS / "ikonos_agile"
BIAS = 2.5  # pixels added to every sample of the right scene's GCP observations


def run(tie_points: bool) -> tuple[Outputs, object]:
    reader = BagReader(BAG)
    pipe = Pipeline(config_from_bag(reader, tie_points=tie_points))
    out = Outputs()
    for item in reader.messages():
        if item.topic == "navigation":
            out.extend(pipe.add_navigation(conv.odometry_to_sample(item.msg)))
        elif item.topic == "gcp":
            pts = []
            for p in conv.gcp_from_msg(item.msg):
                obs = dict(p.observations)
                line, sample = obs["pan_scene_0001"]
                obs["pan_scene_0001"] = (line, sample + BIAS)
                pts.append(GroundPoint(p.id, p.xyz, p.check, obs))
            out.extend(pipe.add_gcp(pts))
        elif item.topic == "pan/image_strip":
            out.extend(
                pipe.add_strip(
                    "pan",
                    conv.stamp_to_ns(item.msg.header.stamp),
                    item.msg.header.frame_id,
                    conv.image_to_array(item.msg),
                )
            )
    out.extend(pipe.flush())
    return out, truth_from_bag(reader)


def truth_parallax(out: Outputs, truth: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    (pair,) = out.pairs
    sp, _, _ = conv.pair_to_msgs(pair, frame_id="map")
    lp, rp = sp.left_params, sp.right_params
    pts = [p for p in truth if lp.scene_id in p.observations and rp.scene_id in p.observations]
    ol = np.array([p.observations[lp.scene_id] for p in pts])
    orr = np.array([p.observations[rp.scene_id] for p in pts])
    pix = sp.normalized_pixel_size
    cl, rl = normalized_px(
        lp, sp.left_to_normalized, sp.left_x_origin, sp.y_origin, pix, ol[:, 0], ol[:, 1]
    )
    cr, rr = normalized_px(
        rp, sp.right_to_normalized, sp.right_x_origin, sp.y_origin, pix, orr[:, 0], orr[:, 1]
    )
    return rl - rr, cl - cr, np.array([p.xyz[2] for p in pts])


@pytest.fixture(scope="module")
def runs() -> dict:
    return {flag: run(flag) for flag in (False, True)}


def test_biased_gcp_leave_y_parallax_that_tie_points_remove(runs: dict) -> None:
    ypar_off, _, _ = truth_parallax(*runs[False])
    ypar_on, _, _ = truth_parallax(*runs[True])
    # The 2.5 px bias goes (mostly) into y-parallax: across-track is about along the rows of
    # the normalized images here (kappa_n near 0, scan line across the epipolar lines).
    assert np.abs(ypar_off).mean() > 1.5
    # Refined with the images' own tie points: the truth points agree again.
    assert np.sqrt(np.mean(ypar_on**2)) < 0.1
    issues = [i.message for i in runs[True][0].issues if "tie points" in i.message]
    assert issues and "inliers" in issues[0]


def test_x_parallax_still_linear_in_height(runs: dict) -> None:
    _, disp, z = truth_parallax(*runs[True])
    coef = np.polyfit(z, disp, 1)
    assert np.sqrt(np.mean((np.polyval(coef, z) - disp) ** 2)) < 0.1
    (pair,) = runs[True][0].pairs
    assert pair.y_parallax_source == "tie_points"
    assert np.sqrt(np.mean(pair.y_parallax_px**2)) < 0.1
