"""More than two acquisitions: `parproj import A B C`, the `pairs` topic, selected pairs.

Three synthetic views of a flat textured ground (nearly affine RPCs, tests/apps/test_import.py's
helpers) looking at different along-track angles: B/H 0.08 (A:B), 0.8 (A:C) and 0.72 (B:C).
"""

from __future__ import annotations

import itertools
import json
import os
from pathlib import Path
from typing import Any

import pytest
from testkit.rasters import FLAT_H
from testkit.rasters import affine_rpc as _affine_rpc
from testkit.rasters import render_crop as _render

from parproj_ros import rpc
from parproj_ros.apps.importer import import_scenes, parse_pairs, scene_ids_of
from parproj_ros.apps.process import process_bag
from parproj_ros.core.pipeline import Outputs, Pipeline
from parproj_ros.eval.evaluate import evaluate_bag
from parproj_ros.io.scene_import import SceneImportError
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.conversions import (
    ConversionError,
    gcp_from_msg,
    image_to_array,
    pairs_from_msg,
    pairs_to_msg,
    stamp_to_ns,
)
from parproj_ros.ros.inputs import config_from_bag, node_parameters, views_from_bag
from parproj_ros.ros.live import run_through_node

#: Along-track look of each view (line shift per unit normalized height) and its crop.
LOOKS = {"a": 0.1, "b": 0.08, "c": -0.1}
CROP = (1900, 1900, 200, 200)
GCP_ONLY: dict[str, Any] = {"tie_points": False}


@pytest.fixture(scope="module")
def tifs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Three GeoTIFFs with their crop RPC in tag 50844."""
    root = tmp_path_factory.mktemp("three")
    out = {}
    for name, look in LOOKS.items():
        full = _affine_rpc(look)
        out[name] = root / f"{name}.tif"
        rpc.write_geotiff_rpc(out[name], full.shifted(-CROP[0], -CROP[1]), _render(full, CROP))
    return out


def _import(tifs: dict[str, Path], dst: Path, pairs: Any, **kw: Any) -> dict[str, Any]:
    return import_scenes(
        [tifs["a"], tifs["b"], tifs["c"]],
        dst,
        pairs=pairs,
        heights=(FLAT_H - 100.0, FLAT_H + 100.0),
        log=lambda _: None,
        **kw,
    )


@pytest.fixture(scope="module")
def all_bag(tifs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    dst = tmp_path_factory.mktemp("all") / "bag"
    return {"bag": dst, "summary": _import(tifs, dst, "all")}


@pytest.mark.ros
def test_base_to_height_from_the_rpcs(all_bag: dict[str, Any]) -> None:
    """B/H: 4 px per m per unit look, 1 m per line: |look_1 - look_2| x 4."""
    rows = {(r["left"], r["right"]): r for r in all_bag["summary"]["candidates"]}
    assert set(rows) == {("a", "b"), ("a", "c"), ("b", "c")}
    for (x, y), r in rows.items():
        expect = 4.0 * abs(LOOKS[x] - LOOKS[y])
        assert r["base_to_height"] == pytest.approx(expect, rel=0.05), r
        assert r["convergence_deg"] > 0 and r["common_points"] >= 100 and r["selected"]


@pytest.mark.ros
def test_bh_selection_leaves_out_the_narrow_pair(tifs: dict[str, Path], tmp_path: Path) -> None:
    s = _import(tifs, tmp_path / "bh", "bh")
    assert s["pairs"] == [("a", "c"), ("b", "c")]
    narrow = next(r for r in s["candidates"] if (r["left"], r["right"]) == ("a", "b"))
    assert not narrow["selected"] and narrow["why"] == "B/H outside window"
    msg = next(BagReader(tmp_path / "bh").messages(topics=["pairs"])).msg
    assert list(msg.left_scene_ids) == ["a", "b"] and list(msg.right_scene_ids) == ["c", "c"]
    with pytest.raises(SceneImportError, match="no pair selected"):
        _import(tifs, tmp_path / "none", "bh", bh_range=(2.0, 3.0))


def test_pairs_option_parsing() -> None:
    assert parse_pairs("all", ["a"]) == "all"
    assert parse_pairs("a:c, b:c", ["a", "b", "c"]) == [("a", "c"), ("b", "c")]
    with pytest.raises(SceneImportError, match="unknown scene id x"):
        parse_pairs("a:x", ["a", "b"])
    with pytest.raises(SceneImportError, match="not LEFT:RIGHT"):
        parse_pairs("a-b", ["a", "b"])
    assert scene_ids_of(["x/left.tif", "y/left.tif", "z.tif"]) == ["left", "left_2", "z"]


@pytest.mark.ros
def test_bag_of_three_images(all_bag: dict[str, Any]) -> None:
    reader = BagReader(all_bag["bag"])
    assert set(reader.topics()) == {
        "pan/image_strip",
        "pan/scanner_info",
        "gcp",
        "truth/points",
        "pairs",
    }
    strips = list(reader.messages(topics=["pan/image_strip"]))
    ids = [s.msg.header.frame_id for s in strips]
    assert ids == sorted(ids) and set(ids) == {"a", "b", "c"}
    stamps = [stamp_to_ns(s.msg.header.stamp) for s in strips]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert sum(image_to_array(s.msg).shape[0] for s in strips) == 3 * CROP[2]
    truth = gcp_from_msg(next(reader.messages(topics=["truth/points"])).msg)
    for pair in (("a", "b"), ("a", "c"), ("b", "c")):
        assert sum(1 for p in truth if set(pair) <= set(p.observations)) >= 300


@pytest.mark.ros
def test_process_makes_every_selected_pair(all_bag: dict[str, Any], tmp_path: Path) -> None:
    """3 scenes, 3 pairs (each scene in two), each within the single-pair tolerances."""
    summary = process_bag(all_bag["bag"], tmp_path / "out", progress=False, overrides=GCP_ONLY)
    assert summary.scenes == 3 and summary.pairs == 3, summary.issues
    assert not [i for i in summary.issues if i.level == "error"], summary.issues
    pairs = [m.msg for m in BagReader(tmp_path / "out").messages(topics=["stereo_pair"])]
    assert [p.pair_id for p in pairs] == ["a+b", "a+c", "b+c"]
    for sp in pairs:
        assert sp.y_parallax_points >= 20 and sp.y_parallax_max_px < 0.05, sp.pair_id
    res = evaluate_bag(tmp_path / "out", all_bag["bag"], matching=False)
    assert res["pair_count"] == 3
    for p in res["pairs"]:
        g = p["geometric"]
        assert g["points"] >= 250 and g["y_parallax_px"]["max_abs"] < 0.05, p["pair_id"]
        assert g["x_parallax_line_rms_px"] < 0.05, p["pair_id"]


# ---------------------------------------------------------------------------------------------
# The pipeline with bad selections


def _feed(
    bag: Path, pairs: list[tuple[str, str]] | None, **overrides: Any
) -> tuple[Pipeline, Outputs]:
    """The bag through a Pipeline, with ``pairs`` instead of its own selection (None: none)."""
    reader = BagReader(bag)
    pipe = Pipeline(config_from_bag(reader, **{**GCP_ONLY, **overrides}))
    out = Outputs()
    if pairs is not None:
        out.extend(pipe.set_pairs(pairs))
    for item in reader.messages():
        if item.topic == "gcp":
            out.extend(pipe.add_gcp(gcp_from_msg(item.msg)))
        elif item.topic == "pan/image_strip":
            arr = image_to_array(item.msg)
            sid = item.msg.header.frame_id
            out.extend(pipe.add_strip("pan", stamp_to_ns(item.msg.header.stamp), sid, arr))
    out.extend(pipe.flush())
    return pipe, out


def _issues(out: Outputs, level: str) -> list[str]:
    return [f"{i.where}: {i.message}" for i in out.issues if i.level == level]


@pytest.mark.ros
def test_bad_pair_selections_reported_others_kept(all_bag: dict[str, Any]) -> None:
    """Self pair, duplicate (either order), empty id, unknown id: reported; good pairs made."""
    sel = [("a", "a"), ("a", "c"), ("c", "a"), ("", "b"), ("a", "zzz"), ("b", "c"), ("a", "c")]
    pipe, out = _feed(all_bag["bag"], sel)
    assert [p.pair_id for p in out.pairs] == ["a+c", "b+c"]
    errors = _issues(out, "error")
    assert any("a:a" in e and "paired with itself" in e for e in errors), errors
    assert sum("listed twice" in e for e in errors) == 2, errors
    assert any("empty scene id" in e for e in errors), errors
    assert any("zzz never received" in e for e in errors), errors
    # nothing held at the end (a waited for zzz until the data ended), GCP forgotten
    assert not pipe._ready["pan"] and not pipe.gcp
    assert len(out.scenes) == 3


@pytest.mark.ros
def test_scene_in_no_pair_released_with_warning(all_bag: dict[str, Any]) -> None:
    pipe, out = _feed(all_bag["bag"], [("c", "a")])
    assert [p.pair_id for p in out.pairs] == ["c+a"]
    assert any("b" in w and "in no selected pair" in w for w in _issues(out, "warn"))
    assert not pipe._ready["pan"]


@pytest.mark.ros
def test_without_selection_2k_and_2k1_pair(all_bag: dict[str, Any]) -> None:
    """No pairs topic: acquisitions 0 and 1 pair up, the third waits for a fourth."""
    _pipe, out = _feed(all_bag["bag"], None)
    assert [p.pair_id for p in out.pairs] == ["a+b"]


@pytest.mark.ros
def test_late_selection_cannot_use_released_scenes(all_bag: dict[str, Any]) -> None:
    """A selection naming scenes already paired and released: reported, not crashing."""
    pipe, _out = _feed(all_bag["bag"], None)
    late = pipe.set_pairs([("a", "b"), ("a", "c")])
    msgs = [f"{i.level} {i.message}" for i in late.issues]
    assert any(m.startswith("ok already made") for m in msgs), msgs
    assert any("was already processed" in m for m in msgs), msgs
    assert late.pairs == []


@pytest.mark.ros
def test_pair_without_base(
    tifs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same image twice (B/H 0): refused at import; in a bag made elsewhere, normalization
    is degenerate and the pair is skipped."""
    from parproj_ros.apps import importer

    args = ([tifs["a"], tifs["a"], tifs["c"]], tmp_path / "bag")
    opts: dict[str, Any] = {
        "pairs": [("a", "a_2"), ("a", "c")],
        "heights": (FLAT_H - 100.0, FLAT_H + 100.0),
        "log": lambda _: None,
    }
    with pytest.raises(SceneImportError, match=r"pair a:a_2: B/H 0\.000.*the same image twice"):
        import_scenes(*args, **opts)
    monkeypatch.setattr(importer, "MIN_STEREO_BH", -1.0)  # such a bag, as made elsewhere
    s = import_scenes(*args, **opts)
    assert s["candidates"][0]["base_to_height"] < 1e-6
    summary = process_bag(tmp_path / "bag", tmp_path / "out", progress=False, overrides=GCP_ONLY)
    assert summary.pairs == 1, summary.issues
    errors = [i for i in summary.issues if i.level == "error"]
    assert any("a+a_2" in i.where for i in errors), summary.issues


def test_two_view_mode_ignores_selection() -> None:
    from parproj_ros.sim.scenarios import SCENARIOS

    pipe = Pipeline(SCENARIOS["airborne_foreaft"]().pipeline_config())
    out = pipe.set_pairs([("x", "y")])
    assert [i.level for i in out.issues] == ["warn"] and "ignored" in out.issues[0].message


@pytest.mark.ros
def test_pair_selection_message_round_trip() -> None:
    from parproj_msgs.msg import PairSelection

    msg = pairs_to_msg([("a", "b"), ("a", "c")], PairSelection(), stamp_ns=5)
    assert pairs_from_msg(msg) == [("a", "b"), ("a", "c")]
    msg.right_scene_ids = ["b"]
    with pytest.raises(ConversionError, match="2 left_scene_ids but 1"):
        pairs_from_msg(msg)


def _with_selection(src_bag: Path, dst: Path, left: list[str], right: list[str]) -> Path:
    """A copy of ``src_bag`` whose PairSelection lists are ``left`` and ``right``."""
    from parproj_msgs.msg import PairSelection

    from parproj_ros.ros.bag import BagWriter

    src = BagReader(src_bag)
    with BagWriter(dst, compression="zstd") as bw:
        for topic, msgtype in src.topics().items():
            kind = "sensor_data" if topic.endswith("image_strip") else "transient_local"
            bw.add_topic(topic, msgtype, kind)
        for item in src.messages():
            msg = item.msg
            if item.topic == "pairs":
                msg = PairSelection()
                msg.left_scene_ids, msg.right_scene_ids = left, right
            bw.write(item.topic, msg, item.log_time_ns)
    return dst


@pytest.mark.ros
def test_mismatched_selection_message_in_a_bag(all_bag: dict[str, Any], tmp_path: Path) -> None:
    """process: a PairSelection whose lists differ is dropped (ERROR); 2k/2k+1 pairing then."""
    bad = _with_selection(all_bag["bag"], tmp_path / "bad", ["a", "b"], ["c"])
    summary = process_bag(bad, tmp_path / "out", progress=False, overrides=GCP_ONLY)
    assert summary.pairs == 1
    assert any(i.where == "pairs" and "dropped" in i.message for i in summary.issues)


# ---------------------------------------------------------------------------------------------
# Through the live node over DDS


@pytest.mark.slow
@pytest.mark.ros
def test_selected_pairs_through_the_live_node(all_bag: dict[str, Any], tmp_path: Path) -> None:
    """3 images, 3 good pairs among bad entries: every good pair published, the bad reported.

    The selection (a:b, a:a, a:c, b:c, c:a, a:zzz) reaches the node on the latched ``pairs``
    topic; a:a (no base), c:a (a:c again) and a:zzz (never arrives; reported at stop) are
    errors on /diagnostics, and nothing else is lost.
    """
    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    left = ["a", "a", "a", "b", "c", "a"]
    right = ["b", "a", "c", "c", "a", "zzz"]
    bag = _with_selection(all_bag["bag"], tmp_path / "bag", left, right)
    views = views_from_bag(BagReader(bag))
    run = run_through_node(
        bag,
        tmp_path / "live",
        params=node_parameters(views, tie_points=False),
        pairs=3,
        log=lambda _: None,
    )
    assert run.discovered and run.code == 0, run.log
    assert run.counts["stereo_pair"] == 3 and run.counts["parallel_projection"] == 3, run.log
    assert run.counts["left/image_normalized"] == 3
    reader = BagReader(run.output)
    pairs = [m.msg for m in reader.messages(topics=["stereo_pair"])]
    assert [p.pair_id for p in pairs] == ["a+b", "a+c", "b+c"]
    for sp in pairs:
        assert sp.y_parallax_points >= 20 and sp.y_parallax_max_px < 0.05, sp.pair_id
    res = evaluate_bag(run.output, bag, matching=False)
    assert res["pair_count"] == 3
    for p in res["pairs"]:
        assert p["geometric"]["y_parallax_px"]["max_abs"] < 0.05, p["pair_id"]
    diag = [
        f"{s.name}: {s.message}"
        for m in reader.messages(topics=["/diagnostics"])
        for s in m.msg.status
        if (s.level[0] if isinstance(s.level, bytes | bytearray) else int(s.level)) == 2
    ]
    for text in ("paired with itself", "listed twice", "zzz never received"):
        assert any(text in d for d in diag), (text, diag)


@pytest.mark.ros
def test_cli_import_process_evaluate_three_images(
    tifs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The user's path: parproj import A B C -> process -> evaluate, every pair evaluated."""
    from parproj_ros.apps import cli

    imgs = [str(tifs[n]) for n in "abc"]
    bag, out = str(tmp_path / "bag"), str(tmp_path / "out")
    heights = ["--heights", str(FLAT_H - 100.0), str(FLAT_H + 100.0)]
    assert cli.main(["import", *imgs, "-o", bag, "--pairs", "a:zzz", *heights]) == 2
    assert "unknown scene id zzz" in capsys.readouterr().err
    assert cli.main(["import", *imgs, "-o", bag, *heights]) == 0  # default: --pairs bh
    assert "pair a:b: B/H 0.08" in capsys.readouterr().out
    assert cli.main(["process", bag, "-o", out, "-q", "--no-tie-points"]) == 0
    assert "3 scenes, 2 pairs" in capsys.readouterr().out
    assert cli.main(["evaluate", out, "--truth", bag, "--json", "--no-matching"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert [p["pair_id"] for p in res["pairs"]] == ["a+c", "b+c"]
    assert all(p["geometric"]["y_parallax_px"]["max_abs"] < 0.05 for p in res["pairs"])


@pytest.mark.ros
def test_crop_origin_band_and_rpc_of_the_third_image(
    tifs: dict[str, Path], all_bag: dict[str, Any], tmp_path: Path
) -> None:
    """`--rpc`, `--crop-origin`, `--band` reach image 3: a 2-band TIFF, no georeferencing.

    All three images have the view in band 2 (band 1: the view upside down); the third has
    neither RPC nor crop origin in the file: its full scene's .geom and the crop origin are
    given. The virtual points are then those of the GeoTIFFs with crop RPCs (``all_bag``), and
    the third scene's strips are its band 2.
    """
    import numpy as np
    import rasterio
    from testkit.rasters import to_rasterio

    from parproj_ros.apps import cli

    views = {}
    for name, look in LOOKS.items():
        full = _affine_rpc(look)
        views[name] = _render(full, CROP)
        kw: dict[str, Any] = {"rpcs": to_rasterio(full.shifted(-CROP[0], -CROP[1]))}
        if name == "c":
            rpc.write_geom(tmp_path / "c_full.geom", full)
            kw = {}  # no RPC, no geotransform
        size = {"width": CROP[3], "height": CROP[2], "count": 2, "dtype": "uint16"}
        with rasterio.open(tmp_path / f"{name}.tif", "w", driver="GTiff", **size, **kw) as dst:
            dst.write(views[name][::-1], 1)
            dst.write(views[name], 2)
    imgs = [str(tmp_path / f"{n}.tif") for n in "abc"]
    heights = ["--heights", str(FLAT_H - 100.0), str(FLAT_H + 100.0)]
    given = ["--rpc", "c.tif", str(tmp_path / "c_full.geom"), "--band", "2"]
    bag = tmp_path / "bag"
    # without its crop origin the third image lies elsewhere: a pair with it is refused
    assert cli.main(["import", *imgs, "-o", str(bag), "--pairs", "a:c", *heights, *given]) == 2
    origin = ["--crop-origin", "c.tif", str(CROP[0]), str(CROP[1])]
    assert (
        cli.main(["import", *imgs, "-o", str(bag), "--pairs", "all", *heights, *given, *origin])
        == 0
    )

    reader = BagReader(bag)
    strips = [s.msg for s in reader.messages(topics=["pan/image_strip"])]
    got = np.vstack([image_to_array(m) for m in strips if m.header.frame_id == "c"])
    np.testing.assert_array_equal(got, views["c"])
    want = {p.id: p for p in gcp_from_msg(_gcp(all_bag["bag"]))}
    points = gcp_from_msg(_gcp(bag))
    assert len(points) == len(want) and {p.id for p in points} == set(want)
    for p in points:
        assert set(p.observations) == set(want[p.id].observations), p.id
        for sid, (line, sample) in p.observations.items():
            w = want[p.id].observations[sid]
            assert abs(line - w[0]) < 1e-6 and abs(sample - w[1]) < 1e-6, (p.id, sid)
    with pytest.raises(SceneImportError, match=r"c\.tif: no RPC .* --rpc IMAGE FILE"):
        import_scenes(imgs, tmp_path / "b3", pairs="all", band=2, heights=(400.0, 600.0))


def _gcp(bag: Path) -> Any:
    return next(BagReader(bag).messages(topics=["gcp"])).msg
