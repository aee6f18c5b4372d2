"""Long scenes cut into segments under a model error bound (issue 5, item 5).

The data: the real RPC models of the Ventoux Pleiades pair (tests/data/ventoux/*.geom) describe
the FULL scenes, 42220 and 40836 lines long (about 21 km along track). Pleiades steers its pitch
during an acquisition, so one parallel model per scene cannot represent them: over a 400-sample
wide strip of the full length, virtual GCP miss the model by several pixels. The pipeline test
images are random (only the geometry is judged: GCP and check points through the published
transforms); the geometry tests need no image.

The tolerance on the y-parallax: each segment model misses its points by at most the bound b in
its own scene, and the normalization maps scene pixels to output pixels with a scale close to 1
(s_n is within a few per cent of 1 here), so conjugate points keep |y| <= 2 b (times 1.05) where
the segments' models hold, which the check points, not used in any fit, test.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from testkit.paths import DATA

from parproj_ros import rpc
from parproj_ros.core.pipeline import GroundPoint, Pipeline, PipelineConfig, ViewConfig
from parproj_ros.eval.long_scene import check_errors, rpc_strip, segment_strip
from parproj_ros.geometry import GeometryError, LineCamera
from parproj_ros.geometry.segmentation import (
    PairSegmentation,
    SideCamera,
    fit_segment,
    segment_pair,
)

C, PIX = 12.905, 13e-6  # Pleiades principal distance and detector pitch, m
WIDTH = 400  # samples of the strip cut from the full scenes
HEIGHTS = (900.0, 1100.0)  # a DEM +- 100 m stand-in, metres above the ellipsoid


@pytest.fixture(scope="module")
def ventoux() -> dict:
    """The full-length strips: RPCs shifted to the strip, virtual GCP and check points."""
    strip = rpc_strip(
        rpc.read_geom(DATA / "left_image.geom"), rpc.read_geom(DATA / "right_image.geom"), WIDTH
    )
    gcp = strip.grid(HEIGHTS, along=241)
    check = strip.grid(HEIGHTS, along=97, shift=37.0, frame=gcp.frame)  # in no fit
    return {"lines": strip.lines, "gcp": gcp, "check": check, "strip": strip}


def _segment(v: dict, bound: float) -> PairSegmentation:
    return segment_strip(v["strip"], v["gcp"], bound)


def test_one_model_cannot_represent_the_full_scene(ventoux: dict) -> None:
    seg = _segment(ventoux, 0.5)
    assert min(seg.whole_error_px) > 3.0, seg.whole_error_px  # several px: a long scene


@pytest.mark.parametrize("bound", [1.0, 0.5, 0.3])
def test_segments_meet_the_bound(ventoux: dict, bound: float) -> None:
    seg = _segment(ventoux, bound)
    assert seg.reached, (seg.note, seg.tried)
    assert seg.count >= 2 and seg.max_error_px <= bound
    nl, nr = ventoux["lines"]
    for side, n in ((seg.left, nl), (seg.right, nr)):
        assert side[0].start == 0 and side[-1].stop == n  # every line in some segment
        for a, b in itertools.pairwise(side):
            assert b.start < a.stop, "neighbouring segments overlap"
    assert seg.count == len(seg.left) == len(seg.right)


def test_tighter_bound_needs_more_segments(ventoux: dict) -> None:
    counts = [_segment(ventoux, b).count for b in (1.0, 0.5, 0.3)]
    assert counts == sorted(counts) and counts[0] < counts[-1], counts


def test_check_points_confirm_the_error_reached(ventoux: dict) -> None:
    """Points between the GCP (another grid) stay within the bound + 20 % in every segment."""
    for bound in (1.0, 0.5, 0.3):
        assert check_errors(_segment(ventoux, bound), ventoux["check"]) <= 1.2 * bound


def test_cutting_stops_when_the_error_is_not_along_track(ventoux: dict) -> None:
    """A height range of 1.7 km over the strip: shorter segments stop helping; said so."""
    v = dict(ventoux)
    v["gcp"] = v["strip"].grid((200.0, 1900.0), along=241)
    seg = _segment(v, 0.3)
    assert not seg.reached
    assert "stopped shrinking" in seg.note or "fewer than" in seg.note, seg.note
    assert seg.max_error_px < min(seg.whole_error_px)  # still the best cut found is kept


def test_exact_parallel_scene_is_not_cut() -> None:
    """Points that fit one model exactly: one segment."""
    rng = np.random.default_rng(1)
    xyz = rng.uniform([-5e3, -500, 0], [5e3, 500, 800], (200, 3))
    ls = np.stack([xyz[:, 0] / 0.5 + 10000, xyz[:, 1] / 0.5 + 1000 + 0.1 * xyz[:, 2]], axis=1)
    idx = np.arange(200)
    cam = SideCamera(C, PIX, 1000.0, psi=0.0)
    seg = segment_pair(
        xyz, ls, xyz, ls, (idx, idx), lines=(20000, 20000), cameras=(cam, cam), bound_px=0.1
    )
    assert seg.count == 1 and seg.reached and seg.max_error_px < 1e-6


def test_bad_arguments() -> None:
    xyz = np.zeros((3, 3))
    idx = np.arange(3)
    cam = SideCamera(C, PIX, 0.0)
    with pytest.raises(GeometryError, match="bound_px"):
        segment_pair(xyz, xyz[:, :2], xyz, xyz[:, :2], (idx, idx), lines=(9, 9),
                     cameras=(cam, cam), bound_px=0.0)  # fmt: skip
    with pytest.raises(GeometryError, match="fewer than"):
        segment_pair(xyz, xyz[:, :2], xyz, xyz[:, :2], (idx, idx), lines=(9, 9),
                     cameras=(cam, cam), bound_px=1.0)  # fmt: skip
    assert fit_segment(xyz, xyz[:, :2], 0, 9, cam, min_points=5) is None


# ---- through the pipeline -----------------------------------------------------------------------


def _run_pipeline(v: dict, bound: float, output_pixel: float = 0.0) -> tuple[list, list, list]:
    cam = LineCamera(C, PIX, WIDTH, 7.4e-5)
    cfg = PipelineConfig(
        views=(ViewConfig("left", cam), ViewConfig("right", cam)),
        tie_points=False,
        streaming=False,
        segment_max_error_px=bound,
        output_pixel=output_pixel,
    )
    pipe = Pipeline(cfg)
    pts = []
    for kind, g in (("g", v["gcp"]), ("c", v["check"])):
        for i in range(len(g.points)):
            obs = {"L": tuple(g.left[i]), "R": tuple(g.right[i])}
            pts.append(GroundPoint(f"{kind}{i}", g.points[i], kind == "c", obs))
    pipe.add_gcp(pts)
    rng = np.random.default_rng(5)
    scenes, pairs, issues = [], [], []
    for view, sid, n, t0 in (
        ("left", "L", v["lines"][0], 0),
        ("right", "R", v["lines"][1], 10**10),
    ):
        for a in range(0, n, 2048):
            rows = min(2048, n - a)
            strip = rng.integers(0, 255, (rows, WIDTH), dtype=np.uint8)
            out = pipe.add_strip(view, t0 + round(a * 7.4e-5 * 1e9), sid, strip)
            scenes += out.scenes
            pairs += out.pairs
            issues += out.issues
    out = pipe.flush()
    return scenes + out.scenes, pairs + out.pairs, issues + out.issues


@pytest.fixture(scope="module")
def piped(ventoux: dict) -> dict:
    scenes, pairs, issues = _run_pipeline(ventoux, 0.5)
    return {"scenes": scenes, "pairs": pairs, "issues": issues}


def test_pipeline_publishes_segment_pairs(piped: dict) -> None:
    segs = [s for s in piped["scenes"] if s.segment_of]
    pairs = piped["pairs"]
    assert len(pairs) >= 2 and len(segs) == 2 * len(pairs)
    cut = [i for i in piped["issues"] if "cut into" in i.message]
    assert len(cut) == 1 and cut[0].level == "ok", piped["issues"]
    assert f"cut into {len(pairs)} segment pairs" in cut[0].message
    assert "bound 0.5 px" in cut[0].message and "bound met" in cut[0].message
    for s in segs:
        assert s.model_error_bound_px == 0.5 and s.residual_max_px <= 0.5
        assert s.scene.scene_id == f"{s.segment_of}.seg{s.scene.scene_id.rsplit('seg', 1)[1]}"
        assert s.scene.lines == s.scene.image.shape[0] > 1000


def test_pipeline_segment_pairs_have_no_y_parallax(piped: dict) -> None:
    """y-parallax of GCP and check points (the latter in no fit) through each segment pair."""
    for p in piped["pairs"]:
        assert p.y_parallax_source == "gcp"
        assert p.y_parallax_px.size > 100
        assert np.abs(p.y_parallax_px).max() <= 2 * 0.5 * 1.05, p.pair_id


def test_pipeline_without_cutting_leaves_pixels_of_y_parallax(ventoux: dict) -> None:
    """The same pair with segmentation off: one pair, y-parallax of several pixels.

    Normalized at 8 x the native pixel: a 21 km strip skewed to the epipolar lines would be
    40975 x 10793 px at the native one (refused by max_output_pixels); the y-parallax is
    geometric (GCP through the transforms, in detector pixels) and does not depend on it.
    """
    scenes, pairs, _issues = _run_pipeline(ventoux, 0.0, output_pixel=8 * PIX)
    assert len(pairs) == 1 and not any(s.segment_of for s in scenes)
    assert np.abs(pairs[0].y_parallax_px).max() > 3.0


@pytest.mark.ros
def test_segment_parameters_message(piped: dict) -> None:
    """ParallelProjection of a segment: where it was cut from, its first line, the bound."""
    from parproj_msgs.msg import ParallelProjection

    from parproj_ros.ros.conversions import scene_to_msg

    (seg,) = [s for s in piped["scenes"] if s.scene.scene_id == "L.seg1"]
    msg = scene_to_msg(seg, ParallelProjection(), frame_id="ltp")
    assert (msg.segment_of, msg.segment_first_line) == (seg.segment_of, seg.segment_first_line)
    assert msg.segment_first_line > 0 and msg.model_error_bound_px == 0.5
    assert msg.residual_max_px <= 0.5 and msg.lines == seg.scene.lines
    assert msg.scene_id == f"{seg.segment_of}.seg1"


def test_segments_command(capsys: pytest.CaptureFixture[str]) -> None:
    """``parproj segments`` on the Ventoux RPCs: the table the README quotes."""
    import json

    from parproj_ros.apps.cli import main

    code = main(
        ["segments", str(DATA / "left_image.geom"), str(DATA / "right_image.geom"), "--json"]
    )
    res = json.loads(capsys.readouterr().out)
    assert code == 0 and res["lines"] == [42220, 40836]
    for r in res["runs"]:
        assert r["reached"] and r["max_error_px"] <= r["bound_px"]
        assert r["check_max_error_px"] <= 1.2 * r["bound_px"] and r["segments"] >= 2


def test_evaluate_maps_truth_points_into_segments() -> None:
    """`parproj evaluate` finds a truth point of the whole scene in the segment that holds it."""
    from types import SimpleNamespace

    from parproj_ros.eval.evaluate import _observation

    p = GroundPoint("t", np.zeros(3), True, {"L": (5100.0, 12.0)})
    whole = SimpleNamespace(scene_id="L", segment_of="", segment_first_line=0, lines=9000)
    seg1 = SimpleNamespace(scene_id="L.seg1", segment_of="L", segment_first_line=4000, lines=2000)
    seg2 = SimpleNamespace(scene_id="L.seg2", segment_of="L", segment_first_line=5600, lines=2000)
    assert _observation(p, whole) == (5100.0, 12.0)
    assert _observation(p, seg1) == (1100.0, 12.0)
    assert _observation(p, seg2) is None  # before the segment's first line


@pytest.mark.slow
@pytest.mark.ros
def test_long_geotiff_pair_import_process_evaluate(ventoux: dict, tmp_path: Path) -> None:
    """The user's path on a long pair: GeoTIFFs with the RPC tag -> import -> process -> evaluate.

    The strips' RPCs in tag 50844, smooth synthetic pixels (only geometry is judged), virtual GCP
    from `parproj import` (grid rows grow with the image length), segments cut by `process`
    under 0.5 px, truth points (random, in no fit) through the published transforms.
    """
    from parproj_ros.apps.importer import import_pair
    from parproj_ros.apps.process import process_bag
    from parproj_ros.eval.evaluate import evaluate_bag

    strip = ventoux["strip"]
    for name, model, n in (("L", strip.left, strip.lines[0]), ("R", strip.right, strip.lines[1])):
        yy, xx = np.mgrid[0:n, 0:WIDTH]
        img = ((np.sin(yy / 37.0) + np.cos(xx / 23.0)) * 60 + 128).astype(np.uint8)
        rpc.write_geotiff_rpc(tmp_path / f"{name}.tif", model, img)
    import_pair(
        tmp_path / "L.tif", tmp_path / "R.tif", tmp_path / "bag", heights=HEIGHTS,
        offsets=((0.0, 0.0), (0.0, 0.0)), log=lambda s: None,
    )  # fmt: skip
    summary = process_bag(
        tmp_path / "bag",
        tmp_path / "out",
        progress=False,
        overrides={"tie_points": False, "segment_max_error_px": 0.5},
    )
    (cut,) = [i for i in summary.issues if "cut into" in i.message]
    assert "bound met" in cut.message, cut.message
    assert summary.pairs >= 2 and summary.scenes == 2 + 2 * summary.pairs
    res = evaluate_bag(tmp_path / "out", tmp_path / "bag", matching=False)
    assert res["pair_count"] == summary.pairs
    seen = 0
    for p in res["pairs"]:
        geo = p["geometric"]
        assert geo["points"] >= 10, p["pair_id"]
        assert geo["y_parallax_px"]["max_abs"] <= 2 * 0.5 * 1.05, p["pair_id"]
        seen += geo["points"]
    assert seen >= 300  # every truth point is in some segment pair (overlaps count twice)


def test_segmented_pair_leaves_no_gcp_behind(ventoux: dict) -> None:
    """After the segment pairs, no observation of the whole scenes or their segments is held."""
    cam = LineCamera(C, PIX, WIDTH, 7.4e-5)
    cfg = PipelineConfig(
        views=(ViewConfig("left", cam), ViewConfig("right", cam)),
        tie_points=False,
        streaming=False,
        segment_max_error_px=1.0,
    )
    pipe = Pipeline(cfg)
    g = ventoux["gcp"]
    pipe.add_gcp(
        [
            GroundPoint(
                f"g{i}", g.points[i], False, {"L": tuple(g.left[i]), "R": tuple(g.right[i])}
            )
            for i in range(len(g.points))
        ]
    )
    pairs = []
    for view, sid, n, t0 in (
        ("left", "L", ventoux["lines"][0], 0),
        ("right", "R", ventoux["lines"][1], 10**10),
    ):
        pairs += pipe.add_strip(view, t0, sid, np.zeros((n, WIDTH), np.uint8)).pairs
    pairs += pipe.flush().pairs
    assert len(pairs) >= 2
    assert pipe.gcp == {}
