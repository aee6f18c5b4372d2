"""The Pipeline without DDS, on scenario geometry with cheap images made here.

Strips and navigation are fed in time order as parproj_ros/sim/recording.py records them; the
images are random textures (or a smooth pattern for the resampling test): the geometry only needs
strips of the right shape at the right times.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from testkit.scenes import feed, nav_events, render, strip_events

from parproj_ros.core.pipeline import Outputs, PairResult, Pipeline, SceneResult
from parproj_ros.geometry import ptp_inverse
from parproj_ros.sim.scenarios import SCENARIOS, Scenario, ground_points

# These tests are about whole-scene processing: keep the streaming mode (scene_lines > 0 with two
# views, when the pipeline has it) out of the way.
WHOLE = {"streaming": False}


def run(scn: Scenario, images: list[np.ndarray], **config: Any) -> tuple[Pipeline, Outputs]:
    pipe = Pipeline(scn.pipeline_config(**{"tie_points": False, **config}))
    return pipe, feed(pipe, nav_events(scn) + strip_events(scn, images))


def hills(model: Any, line: np.ndarray, sample: np.ndarray) -> np.ndarray:
    """Points on a smooth +-250 m relief (GCP must not be coplanar for Eq 8)."""
    return model.locate(line, sample, 250.0 * np.sin(line / 97.0) * np.cos(sample / 131.0))


def flat(model: Any, line: np.ndarray, sample: np.ndarray) -> np.ndarray:
    return model.locate(line, sample, np.zeros_like(line))


def messages(out: Outputs, level: str) -> list[str]:
    return [f"{i.where}: {i.message}" for i in out.issues if i.level == level]


# ---- scenarios as recorded ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def airborne() -> tuple[Scenario, Outputs]:
    scn = SCENARIOS["airborne_foreaft"]()
    return scn, run(scn, render(scn, np.uint8))[1]


def test_airborne_navigation_pair(airborne: tuple[Scenario, Outputs]) -> None:
    scn, out = airborne
    assert out.issues == []
    assert [s.method for s in out.scenes] == ["navigation", "navigation"]
    assert [(s.scene.view, s.scene.scene_id) for s in out.scenes] == [
        ("left", "left_scene_0000"),
        ("right", "right_scene_0001"),
    ]
    assert [s.scene.first_line_ns for s in out.scenes] == [
        scn.time_ns(sc.start_s) for sc in scn.scenes
    ]
    (pair,) = out.pairs
    assert pair.pair_id == "left_scene_0000+right_scene_0001"
    assert pair.stamp_ns == out.scenes[1].scene.last_line_ns
    assert pair.left_image.shape == pair.right_image.shape
    assert pair.left_image.dtype == np.uint8
    assert pair.left_grid.height == pair.right_grid.height
    assert pair.left_grid.y_origin == pair.right_grid.y_origin
    # Exact navigation: the virtual points of the rigorous models have no y-parallax.
    assert pair.y_parallax_source == "virtual"
    assert pair.y_parallax_px.size > 100
    mean, rms, mx = pair.y_parallax_stats
    assert mx < 0.01 and rms < 0.01 and mean < 0.01
    # x-parallax -> height: the fore/aft base over 5000 m.
    assert np.isfinite(pair.height_per_disparity_px) and pair.height_per_disparity_px != 0


def _ikonos_gcp(
    locate: Callable[..., np.ndarray], n_gcp: int, n_check: int
) -> tuple[Scenario, list[Any]]:
    scn = SCENARIOS["ikonos_agile"]()
    rng = np.random.default_rng(1)
    pts = ground_points(scn, (0, 1), n_gcp, locate, rng, prefix="g")
    pts += ground_points(scn, (0, 1), n_check, locate, rng, prefix="c", check=True)
    return scn, pts


def test_ikonos_gcp_roll_estimated() -> None:
    scn, pts = _ikonos_gcp(hills, 12, 4)
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    assert pipe.add_gcp(pts).issues == []
    out = feed(pipe, nav_events(scn) + strip_events(scn, render(scn, np.uint16)))
    assert out.issues == []
    assert [s.method for s in out.scenes] == ["gcp_roll_estimated"] * 2
    for s in out.scenes:
        assert (s.gcp_count, s.check_count) == (12, 4)
        assert s.sigma0_px < 0.1 and s.check_rms_px < 0.1  # exact observations
        assert s.covariance.shape == (9, 9) and s.covariance[8, 8] > 0
        assert s.model is not None  # navigation covered: reference for the mirror solution
    (pair,) = out.pairs
    assert pair.pair_id == "pan_scene_0000+pan_scene_0001"
    assert pair.left_image.dtype == np.uint16
    assert pair.y_parallax_source == "gcp" and pair.y_parallax_px.size == 16
    assert pair.y_parallax_stats[2] < 0.01


def test_ikonos_flat_gcp_are_coplanar_and_navigation_is_used() -> None:
    scn, pts = _ikonos_gcp(flat, 12, 0)
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    pipe.add_gcp(pts)
    out = feed(pipe, nav_events(scn) + strip_events(scn, render(scn, np.uint16)))
    assert [s.method for s in out.scenes] == ["navigation"] * 2
    warns = messages(out, "warn")
    assert len(warns) == 2 and all("coplanar" in w and "using navigation" in w for w in warns)
    (pair,) = out.pairs
    assert pair.y_parallax_stats[2] < 0.01


def test_fewer_than_min_gcp_falls_back_to_navigation() -> None:
    scn, pts = _ikonos_gcp(hills, 3, 0)
    pipe = Pipeline(scn.pipeline_config(min_gcp=5, tie_points=False))
    pipe.add_gcp(pts)
    out = feed(pipe, nav_events(scn) + strip_events(scn, render(scn, np.uint16)))
    assert [s.method for s in out.scenes] == ["navigation"] * 2
    assert [s.gcp_count for s in out.scenes] == [0, 0]
    assert messages(out, "warn") == [
        f"pan/pan_scene_000{k}: only 3 GCP observed (need 5): GCP not used" for k in (0, 1)
    ]
    assert messages(out, "error") == []
    assert len(out.pairs) == 1


def test_non_finite_gcp_ignored_with_warning() -> None:
    scn, pts = _ikonos_gcp(hills, 5, 0)
    bad = type(pts[0])("bad", np.array([0.0, np.nan, 0.0]), False, dict(pts[0].observations))
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    out = pipe.add_gcp([*pts, bad])
    assert [(i.level, i.where) for i in out.issues] == [("warn", "gcp bad")]
    assert sorted(pipe.gcp) == sorted(p.id for p in pts)


# ---- order of arrival ---------------------------------------------------------------------------


def test_strips_before_navigation_are_held() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    out = feed(pipe, strip_events(scn, render(scn, np.uint8)), flush=False)
    out.extend(pipe.close_scenes())
    assert out.scenes == [] and out.pairs == [] and out.issues == []
    assert not pipe.has_open_scene
    last_lines = [
        scn.time_ns(sc.start_s) + round((sc.lines - 1) * scn.views[0].camera.line_period * 1e9)
        for sc in scn.scenes
    ]
    done_at: dict[str, int] = {}
    pairs: list[PairResult] = []
    for t_ns, _, sample in nav_events(scn):
        o = pipe.add_navigation(sample)
        assert o.issues == []
        for s in o.scenes:
            done_at[s.scene.scene_id] = t_ns
        pairs += o.pairs
    # Each scene is processed by the first sample at or after its last line (50 Hz).
    assert sorted(done_at) == ["left_scene_0000", "right_scene_0001"]
    for t_done, t_last in zip(done_at.values(), last_lines, strict=True):
        assert t_last <= t_done < t_last + 20_000_000
    assert len(pairs) == 1 and pairs[0].y_parallax_stats[2] < 0.01
    final = pipe.flush()
    assert final.scenes == [] and final.pairs == [] and final.issues == []


def test_navigation_never_arrives_reported_by_flush() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    out = feed(pipe, strip_events(scn, render(scn, np.uint8)))
    assert out.scenes == [] and out.pairs == []
    errors = messages(out, "error")
    assert len(errors) == 2
    assert errors[0].startswith("left/left_scene_0000: navigation never covered")
    assert errors[1].startswith("right/right_scene_0001: navigation never covered")
    assert pipe.flush().issues == []  # reported once


def test_navigation_of_the_second_scene_never_arrives() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    t_cut = scn.time_ns(scn.scenes[0].start_s + 3.0)
    nav = [e for e in nav_events(scn) if e[0] < t_cut]
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    out = feed(pipe, nav + strip_events(scn, render(scn, np.uint8)))
    assert [s.scene.scene_id for s in out.scenes] == ["left_scene_0000"]
    assert out.pairs == []
    assert messages(out, "error") == [
        "right/right_scene_0001: navigation never covered this scene and it has no GCP: "
        "scene skipped"
    ]


def test_navigation_starting_after_the_first_line() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    t_from = scn.time_ns(scn.scenes[0].start_s + 0.5)
    nav = [e for e in nav_events(scn) if e[0] >= t_from]
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    out = feed(pipe, nav + strip_events(scn, render(scn, np.uint8)))
    assert [s.scene.scene_id for s in out.scenes] == ["right_scene_0001"]
    errors = messages(out, "error")
    assert len(errors) == 1
    assert errors[0].startswith("left/left_scene_0000: navigation starts after the scene's first")


def test_idle_scene_closed_only_once_navigation_moves_past() -> None:
    """close_idle_scenes (the node's scene_timeout) closes a scene whose strips stopped only
    when the navigation went on past its last line."""
    scn = SCENARIOS["airborne_foreaft"]()
    images = render(scn, np.uint8)
    events = nav_events(scn) + strip_events(scn, images)
    cut = strip_events(scn, images)[5][0]  # the 6th strip of the left scene (384 lines in)
    # Every input stopped at once (a publisher restarting, a replay paused): the scene stays
    # open, and the strips that resume continue it, as if nothing had happened.
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    out = feed(pipe, [e for e in events if e[0] <= cut], flush=False)
    assert pipe.close_idle_scenes().scenes == [] and pipe.has_open_scene
    out.extend(feed(pipe, [e for e in events if e[0] > cut]))
    clean = run(scn, images)[1]
    assert out.issues == []
    assert [(s.scene.scene_id, s.scene.lines) for s in out.scenes] == [
        (s.scene.scene_id, s.scene.lines) for s in clean.scenes
    ]
    assert len(out.pairs) == 1
    np.testing.assert_array_equal(out.pairs[0].left_image, clean.pairs[0].left_image)
    # Only the strips stopped while the navigation went on (1 s): the scene is over.
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    on = [e for e in events if e[0] <= cut or (e[1] == 0 and e[0] <= cut + 10**9)]
    feed(pipe, on, flush=False)
    closed = pipe.close_idle_scenes()
    assert not pipe.has_open_scene
    assert [(s.scene.scene_id, s.scene.lines) for s in closed.scenes] == [("left_scene_0000", 384)]
    # Without navigation at all, nothing tells: the scene is closed (and waits for navigation).
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    feed(pipe, [e for e in events if e[1] == 1 and e[0] <= cut], flush=False)
    pipe.close_idle_scenes()
    assert not pipe.has_open_scene


def test_first_scene_begun_before_the_pipeline_is_skipped() -> None:
    """A pipeline (a node) started in the middle of a scene: strips carry no line number, so
    the 384 lines it gets of pan_scene_0000 would be taken as a whole scene, and its GCP, whose
    lines count from the scene's real first line, put 384 lines off. The navigation, which
    starts with them instead of before, gives it away: that scene is skipped; the next one (its
    start seen) is processed, and the pair is lost with the first half."""
    scn, pts = _ikonos_gcp(hills, 12, 0)
    images = render(scn, np.uint16)
    events = nav_events(scn) + strip_events(scn, images)
    start = strip_events(scn, images)[6][0]  # the 7th strip: line 384 of pan_scene_0000
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    pipe.add_gcp(pts)
    out = feed(pipe, [e for e in events if e[0] >= start])
    (error,) = messages(out, "error")
    assert error.startswith("pan/pan_scene_0000: first scene received on view pan (384 lines)")
    assert error.endswith("scene skipped")
    assert [(s.scene.scene_id, s.method) for s in out.scenes] == [
        ("pan_scene_0001", "gcp_roll_estimated")
    ]
    assert out.pairs == []
    # Started 0.5 s before the scene (start_margin_s): all as usual.
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    pipe.add_gcp(pts)
    t0 = strip_events(scn, images)[0][0]
    out = feed(pipe, [e for e in events if e[0] >= t0 - 500_000_000])
    assert out.issues == [] and len(out.scenes) == 2 and len(out.pairs) == 1


def test_scenes_begun_before_the_pipeline_are_not_streamed() -> None:
    """Fore/aft cameras imaging at the same time, a pipeline started 0.2 s before their scenes
    (navigation from then on): both first scenes may be the rest of scenes under way, so no
    stream is started for them (none would be completed) and both are skipped."""
    scn = SCENARIOS["airborne_foreaft"]()
    left, right = scn.scenes
    scn = dataclasses.replace(
        scn, scenes=(left, dataclasses.replace(right, start_s=left.start_s + 0.1))
    )
    t0 = scn.time_ns(left.start_s) - 200_000_000
    events = nav_events(scn) + strip_events(scn, render(scn, np.uint8))
    pipe = Pipeline(scn.pipeline_config(tie_points=False, scene_lines=768))
    out = feed(pipe, [e for e in events if e[0] >= t0])
    assert out.blocks == [] and out.scenes == [] and out.pairs == []
    errors = [(i.where, i.message) for i in out.issues if i.level != "ok"]
    assert [w for w, _ in errors] == ["left/left_scene_0000", "right/right_scene_0001"], errors
    assert all("first scene received" in m and m.endswith("scene skipped") for _, m in errors)


# ---- scenes and pairs ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("scene_lines", "lines"), [(256, [256, 256, 256]), (300, [300, 300, 168])]
)
def test_scene_lines_splitting(scene_lines: int, lines: list[int]) -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    _, out = run(scn, render(scn, np.uint8), scene_lines=scene_lines, **WHOLE)
    assert messages(out, "error") == []
    left = [s for s in out.scenes if s.scene.view == "left"]
    right = [s for s in out.scenes if s.scene.view == "right"]
    assert [s.scene.lines for s in left] == lines and [s.scene.lines for s in right] == lines
    assert [s.scene.index for s in left] == [0, 1, 2]
    lp = scn.views[0].camera.line_period
    for part, s in enumerate(left):
        expected = scn.time_ns(scn.scenes[0].start_s + part * scene_lines * lp)
        assert abs(s.scene.first_line_ns - expected) <= 1
    assert len(out.pairs) == 3
    for k, pair in enumerate(out.pairs):
        assert pair.left is left[k] and pair.right is right[k]
        assert pair.y_parallax_stats[2] < 0.01


def test_split_scenes_get_distinct_scene_ids() -> None:
    # ParallelProjection.msg: "Scene identifier, unique in a run"; ImageObservation.scene_id
    # refers to it. Three parts of one acquisition must not share one id (nor pairs one id).
    scn = SCENARIOS["airborne_foreaft"]()
    _, out = run(scn, render(scn, np.uint8), scene_lines=256, **WHOLE)
    ids = [s.scene.scene_id for s in out.scenes]
    assert len(ids) == 6
    assert len(set(ids)) == 6, ids
    assert len({p.pair_id for p in out.pairs}) == 3


def test_split_acquisition_in_single_camera_mode() -> None:
    """Two strips in a row lost (128 lines > max_gap_lines) in the forward look: the scene is
    split, and says so; its first part is paired with the backward look (pairs are
    acquisitions 2k, 2k+1, not parts, so one split does not shift the pairing); the second
    part gets parameters and a WARN that it is not paired; the backward look is unchanged."""
    scn, pts = _ikonos_gcp(hills, 12, 0)
    images = render(scn, np.uint16)
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    pipe.add_gcp(pts)
    out = feed(pipe, nav_events(scn) + strip_events(scn, images, skip=[(0, 256), (0, 320)]))
    assert messages(out, "error") == []
    warns = messages(out, "warn")
    # GCP observed beyond the first part's 256 lines (plus a margin) are left out of it.
    gcp = [w for w in warns if w.startswith("gcp ")]
    assert gcp and all("is not in the scene (256 x 768): ignored" in w for w in gcp)
    assert [w for w in warns if not w.startswith("gcp ")] == [
        "pan/pan_scene_0000: 128 lines missing after line 255 (more than max_gap_lines, 64): "
        "scene split; it ends there, with 256 lines, and the strips after the hole make a new "
        "scene (pan_scene_0000#1)",
        "pan/pan_scene_0000#1: part 1 of an acquisition that was split: its parameters are "
        "published, but single-camera pairs are made of the first parts of two acquisitions: "
        "not paired",
    ]
    got = {s.scene.scene_id: s for s in out.scenes}
    assert [(sid, s.scene.lines) for sid, s in got.items()] == [
        ("pan_scene_0000", 256),
        ("pan_scene_0000#1", 384),
        ("pan_scene_0001", 768),
    ]
    (pair,) = out.pairs
    assert pair.pair_id == "pan_scene_0000+pan_scene_0001"
    assert pair.y_parallax_stats[2] < 0.01
    clean = Pipeline(scn.pipeline_config(tie_points=False))
    clean.add_gcp(pts)
    ref = feed(clean, nav_events(scn) + strip_events(scn, images)).scenes[1]
    assert ref.scene.scene_id == "pan_scene_0001"
    np.testing.assert_array_equal(got["pan_scene_0001"].affine.array, ref.affine.array)


def _predicted_line(res: SceneResult, xyz: np.ndarray) -> np.ndarray:
    """Line of object points in a scene, by the scene's parameters (affine, PTP, frame)."""
    xy = res.affine.project(xyz)
    y = ptp_inverse(xy[:, 1], res.camera.principal_distance, res.psi)
    return res.frame.to_image(xy[:, 0], y)[:, 0]


def test_split_scene_parameters_fit_their_own_lines() -> None:
    # GCP observations are lines of the whole acquisition (scene id = the strips' frame_id).
    # A part that starts 384 lines into the acquisition must not be given parameters that put
    # its GCP 384 lines off.
    scn, pts = _ikonos_gcp(hills, 12, 0)
    pipe = Pipeline(scn.pipeline_config(scene_lines=384, **WHOLE))
    pipe.add_gcp(pts)
    out = feed(pipe, nav_events(scn) + strip_events(scn, render(scn, np.uint16)))
    lp = scn.views[0].camera.line_period
    assert len(out.scenes) == 4
    checked = 0
    for res in out.scenes:
        # The acquisition (scenario scene) this part belongs to, and the part's first line in it.
        i = max(
            k for k in range(2) if scn.time_ns(scn.scenes[k].start_s) <= res.scene.first_line_ns
        )
        offset = round((res.scene.first_line_ns - scn.time_ns(scn.scenes[i].start_s)) / lp / 1e9)
        inside = [
            p
            for p in pts
            if offset <= p.observations[scn.scene_id(i)][0] < offset + res.scene.lines
        ]
        xyz = np.array([p.xyz for p in inside])
        lines = np.array([p.observations[scn.scene_id(i)][0] for p in inside]) - offset
        err = _predicted_line(res, xyz) - lines
        assert np.abs(err).max() < 0.5, (res.scene.index, offset, err.round(1))
        checked += len(inside)
    assert checked == 24


def test_scenes_without_overlap() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    t_mid = (scn.scenes[0].start_s + scn.scenes[1].start_s) / 2

    def far(t: float) -> np.ndarray:  # the right scene flown 1 km to the side (swath 83 m)
        return np.array([0.0, 1000.0 if t > t_mid else 0.0, 0.0])

    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    out = feed(pipe, nav_events(scn, offset=far) + strip_events(scn, render(scn, np.uint8)))
    assert [s.method for s in out.scenes] == ["navigation", "navigation"]
    assert out.pairs == []
    errors = messages(out, "error")
    assert len(errors) == 1
    assert errors[0].startswith("pair left_scene_0000+right_scene_0001: ")
    assert "do not overlap" in errors[0]
    assert pipe.pairs_done == 0


def test_unknown_view() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    out = pipe.add_strip("middle", scn.t0_ns, "m0", np.zeros((4, 768), np.uint8))
    assert [(i.level, i.where) for i in out.issues] == [("error", "view middle")]
    assert "unknown view" in out.issues[0].message
    assert out.scenes == [] and not pipe.has_open_scene


def test_rejected_strip_reported_as_warning() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    pipe = Pipeline(scn.pipeline_config(tie_points=False))
    pipe.add_strip("left", scn.t0_ns, "a", np.zeros((4, 768), np.uint8))
    out = pipe.add_strip("left", scn.t0_ns, "a", np.zeros((4, 768), np.uint8))
    assert [(i.level, i.where) for i in out.issues] == [("warn", "left/a")]
    assert "duplicate or out of order" in out.issues[0].message


def test_missing_strip_filled_and_reported(airborne: tuple[Scenario, Outputs]) -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    images = render(scn, np.uint8, low=20)
    pipe = Pipeline(scn.pipeline_config(nodata=3.0, tie_points=False))
    out = feed(pipe, nav_events(scn) + strip_events(scn, images, skip=[(0, 128)]))
    assert messages(out, "warn") == [
        "left/left_scene_0000: 64 missing lines filled with no-data (3.0)"
    ]
    left = out.scenes[0].scene
    assert (left.lines, left.gaps) == (768, 64)
    assert np.all(left.image[128:192] == 3) and np.all(left.image[192:] == images[0][192:])
    assert len(out.pairs) == 1
    # Same parameters as without the gap.
    np.testing.assert_allclose(
        out.scenes[0].affine.array, airborne[1].scenes[0].affine.array, rtol=1e-12
    )


# ---- normalized images --------------------------------------------------------------------------


@pytest.mark.slow
def test_float32_strips_give_float32_images() -> None:
    scn = SCENARIOS["airborne_foreaft"]()
    t_mid = (scn.scenes[0].start_s + scn.scenes[1].start_s) / 2
    images = [im.astype(np.float32) / 7.0 for im in render(scn, np.uint8)]
    # The scenario's cameras deliver uint8; these views accept whatever the strips carry.
    views = tuple(dataclasses.replace(v, dtype=None) for v in scn.views)
    # union: the footprints whole, so that the outputs have area outside each scene
    pipe = Pipeline(scn.pipeline_config(views=views, nodata=float("nan"), output_extent="union"))
    nav = nav_events(scn, offset=lambda t: np.array([20.0 if t > t_mid else 0.0, 0.0, 0.0]))
    out = feed(pipe, nav + strip_events(scn, images))
    (pair,) = out.pairs
    assert pair.left_image.dtype == np.float32 and pair.right_image.dtype == np.float32
    for side, img in (("left", pair.left_image), ("right", pair.right_image)):
        line, sample = _source_coordinates(pair, side)
        outside = (line < -1) | (line > 768) | (sample < -1) | (sample > 768)
        inside = (line > 1) & (line < 766) & (sample > 1) & (sample < 766)
        assert outside.mean() > 0.1 and inside.mean() > 0.5
        assert np.isnan(img[outside]).all()  # nodata NaN outside the footprint
        assert np.isfinite(img[inside]).all()
        assert img[inside].min() >= 1 / 7 - 1e-6 and img[inside].max() <= 249 / 7 + 1e-5
        assert np.unique(img[inside]).size > 1000  # interpolated, not quantized to 8 bits


def _source_coordinates(pair: PairResult, side: str) -> tuple[np.ndarray, np.ndarray]:
    res = pair.left if side == "left" else pair.right
    grid = pair.left_grid if side == "left" else pair.right_grid
    to_n = pair.normalization.left if side == "left" else pair.normalization.right
    rows, cols = np.mgrid[0 : grid.height, 0 : grid.width]
    xn = grid.x_origin + grid.pixel * cols
    yn = grid.y_origin + grid.pixel * rows
    return res.geometry(to_n).normalized_to_image(xn.astype(float), yn.astype(float))


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "dtype", "shift_m"),
    [
        ("airborne_foreaft", np.uint8, 20.0),  # right scene 20 m (185 lines) further along track
        ("ikonos_agile", np.uint16, 0.0),  # fore / aft looks of different scales
    ],
)
def test_nodata_outside_the_footprint(name: str, dtype: type, shift_m: float) -> None:
    scn = SCENARIOS[name]()
    t_mid = (scn.scenes[0].start_s + scn.scenes[1].start_s) / 2
    pipe = Pipeline(scn.pipeline_config(nodata=5.0, output_extent="union"))
    nav = nav_events(scn, offset=lambda t: np.array([shift_m if t > t_mid else 0.0, 0.0, 0.0]))
    out = feed(pipe, nav + strip_events(scn, render(scn, dtype, low=20)))
    (pair,) = out.pairs
    for side, img in (("left", pair.left_image), ("right", pair.right_image)):
        res = pair.left if side == "left" else pair.right
        line, sample = _source_coordinates(pair, side)
        n_l, n_s = res.scene.lines, res.scene.detectors
        outside = (line < -1) | (line > n_l) | (sample < -1) | (sample > n_s)
        inside = (line > 1) & (line < n_l - 2) & (sample > 1) & (sample < n_s - 2)
        assert outside.mean() > 0.02 and inside.mean() > 0.5
        assert np.all(img[outside] == 5), side
        assert img[inside].min() >= 20, side


def _bilinear(img: np.ndarray, line: np.ndarray, sample: np.ndarray) -> np.ndarray:
    l0 = np.floor(line).astype(int)
    s0 = np.floor(sample).astype(int)
    fl, fs = line - l0, sample - s0
    a = img.astype(float)
    return (
        a[l0, s0] * (1 - fl) * (1 - fs)
        + a[l0, s0 + 1] * (1 - fl) * fs
        + a[l0 + 1, s0] * fl * (1 - fs)
        + a[l0 + 1, s0 + 1] * fl * fs
    )


def test_resampling_is_exact() -> None:
    scn = SCENARIOS["ikonos_agile"]()
    images = render(scn, np.uint16, smooth=True)
    _, out = run(scn, images)
    (pair,) = out.pairs
    for side, img, src in (
        ("left", pair.left_image, images[0]),
        ("right", pair.right_image, images[1]),
    ):
        res = pair.left if side == "left" else pair.right
        grid = pair.left_grid if side == "left" else pair.right_grid
        geom = res.geometry(
            pair.normalization.left if side == "left" else pair.normalization.right
        )
        line_all, sample_all = _source_coordinates(pair, side)
        ok = (line_all > 2) & (line_all < src.shape[0] - 3) & (sample_all > 2)
        ok &= sample_all < src.shape[1] - 3
        rows, cols = np.nonzero(ok)
        pick = np.random.default_rng(5).choice(rows.size, 200, replace=False)
        rows, cols = rows[pick], cols[pick]
        xn = grid.x_origin + grid.pixel * cols
        yn = grid.y_origin + grid.pixel * rows
        line, sample = geom.normalized_to_image(xn, yn)
        back = geom.image_to_normalized(line, sample)
        assert np.abs(back[:, 0] - xn).max() < 1e-9 and np.abs(back[:, 1] - yn).max() < 1e-9
        # The map is not a trivial one: sub-pixel positions, and not the identity.
        assert np.ptp(line - rows) > 1 or np.ptp(sample - cols) > 1
        expected = _bilinear(src, line, sample)
        diff = img[rows, cols].astype(float) - expected
        assert np.abs(diff).max() <= 1.0, (side, np.abs(diff).max())
        # ... and a map one pixel off would not pass.
        assert np.abs(img[rows, cols] - _bilinear(src, line + 1.0, sample)).max() > 5
