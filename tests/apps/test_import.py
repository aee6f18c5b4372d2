"""``parproj import`` (parproj_ros/io/scene_import.py) and the Ventoux evaluation (ventoux.py).

Synthetic pairs: two views of a flat textured plane through nearly affine RPCs, written as
GeoTIFFs with the RPC in tag 50844 (crop RPC, no offset) or with ``.geom`` sidecars of the full
scene and the crop offset in the ModelTransformationTag. Real pair: the Mont Ventoux Pleiades
crops of tests/data/ventoux (see its README), through import -> process_bag -> evaluation.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tifffile
from testkit.rasters import DATA, FLAT_H
from testkit.rasters import affine_rpc as _affine_rpc
from testkit.rasters import render_crop as _render

from parproj_ros import rpc
from parproj_ros.apps.importer import import_pair
from parproj_ros.apps.process import process_bag
from parproj_ros.core.results import METHODS
from parproj_ros.eval.reference_grids import (
    EpipolarGrid,
    evaluate_against_grids,
    format_table,
    read_grid,
    robust_cut,
)
from parproj_ros.io.dem import grid_height
from parproj_ros.io.scene_import import (
    PRINCIPAL_DISTANCE,
    STRIP_LINES,
    SceneImportError,
    crop_offset,
    find_rpc,
    frame_from_id,
    frame_id_of,
)
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.conversions import gcp_from_msg, image_to_array, stamp_to_ns

GRIDS = DATA / "reference_grids"
#: Full-scene size and crop windows of the synthetic pair: (line0, sample0, lines, samples).
CROPS = ((1900, 1900, 200, 200), (1905, 1890, 190, 196))
GCP_ONLY: dict[str, Any] = {"tie_points": False}


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Two synthetic pairs (tag 50844 / .geom + ModelTransformationTag) and their bags."""
    root = tmp_path_factory.mktemp("synthetic")
    fulls = (_affine_rpc(0.4), _affine_rpc(-0.4))
    images = [_render(f, c) for f, c in zip(fulls, CROPS, strict=True)]
    tag_dir, geom_dir = root / "tag", root / "geom"
    tag_dir.mkdir()
    geom_dir.mkdir()
    for name, full, img, crop in zip(("a", "b"), fulls, images, CROPS, strict=True):
        rpc.write_geotiff_rpc(tag_dir / f"{name}.tif", full.shifted(-crop[0], -crop[1]), img)
        transform = (1.0, 0.0, 0.0, float(crop[1]), 0.0, 1.0, 0.0, float(crop[0]))
        transform += (0.0,) * 7 + (1.0,)
        tifffile.imwrite(geom_dir / f"{name}.tif", img, extratags=[(34264, 12, 16, transform)])
        rpc.write_geom(geom_dir / f"{name}.geom", full)
    bags = {}
    for kind, folder in (("tag", tag_dir), ("geom", geom_dir)):
        bags[kind] = root / f"bag_{kind}"
        bags[kind + "_summary"] = import_pair(
            folder / "a.tif",
            folder / "b.tif",
            bags[kind],
            heights=(FLAT_H - 100.0, FLAT_H + 100.0),
            log=lambda _: None,
        )
    return {"root": root, "fulls": fulls, "images": images, "dirs": (tag_dir, geom_dir), **bags}


def _gcp_msg(bag: Path, topic: str = "gcp") -> Any:
    return next(BagReader(bag).messages(topics=[topic])).msg


@pytest.mark.ros
def test_synthetic_bag_topics_strips_and_scanner(synthetic: dict[str, Any]) -> None:
    reader = BagReader(synthetic["tag"])
    assert set(reader.topics()) == {"pan/image_strip", "pan/scanner_info", "gcp", "truth/points"}
    strips = list(reader.messages(topics=["pan/image_strip"]))
    ids = [s.msg.header.frame_id for s in strips]
    n_left = -(-CROPS[0][2] // STRIP_LINES)
    assert ids == ["left"] * n_left + ["right"] * (len(ids) - n_left)
    stamps = [stamp_to_ns(s.msg.header.stamp) for s in strips]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    for sid, img in zip(("left", "right"), synthetic["images"], strict=True):
        parts = [image_to_array(s.msg) for s in strips if s.msg.header.frame_id == sid]
        assert all(p.shape[0] <= STRIP_LINES for p in parts)
        got = np.concatenate(parts)
        # One detector count for the one camera: the narrower image is padded with no-data.
        np.testing.assert_array_equal(got[:, : img.shape[1]], img)
        assert got.shape[1] == max(i.shape[1] for i in synthetic["images"])
        assert not got[:, img.shape[1] :].any()
    info = next(reader.messages(topics=["pan/scanner_info"])).msg
    assert info.principal_distance == PRINCIPAL_DISTANCE
    assert info.pixel_size == 13e-6
    assert info.principal_point == (CROPS[0][3] - 1) / 2.0
    assert info.detectors == max(c[3] for c in CROPS)


@pytest.mark.ros
@pytest.mark.parametrize("kind", ["tag", "geom"])
def test_synthetic_gcp_project_through_the_crop_rpc(synthetic: dict[str, Any], kind: str) -> None:
    """Every observation is the crop RPC's projection of the point's geodetic position."""
    msg = _gcp_msg(synthetic[kind])
    frame = frame_from_id(msg.header.frame_id)
    assert frame_id_of(frame) == msg.header.frame_id
    crops = {
        sid: full.shifted(-c[0], -c[1])
        for sid, full, c in zip(("left", "right"), synthetic["fulls"], CROPS, strict=True)
    }
    points = gcp_from_msg(msg)
    for sid in crops:
        assert sum(1 for p in points if sid in p.observations and not p.check) >= 50
        assert sum(1 for p in points if sid in p.observations and p.check) >= 5
    assert sum(1 for p in points if len(p.observations) == 2 and not p.check) >= 20
    worst = 0.0
    for p in points:
        lon, lat, h = frame.to_geodetic(*p.xyz)
        assert FLAT_H - 100.0 - 1e-6 <= h <= FLAT_H + 100.0 + 1e-6
        for sid, (line, sample) in p.observations.items():
            pl, ps = crops[sid].project(lon, lat, h)
            worst = max(worst, abs(float(pl) - line), abs(float(ps) - sample))
    assert worst < 1e-6
    truth = gcp_from_msg(_gcp_msg(synthetic[kind], "truth/points"))
    assert len(truth) == 300 and all(len(p.observations) == 2 and p.check for p in truth)


@pytest.mark.ros
def test_tag_and_geom_pairs_agree(synthetic: dict[str, Any]) -> None:
    """RPC shifted into the tag == full-scene sidecar + ModelTransformationTag offset."""
    a, b = _gcp_msg(synthetic["tag"]), _gcp_msg(synthetic["geom"])
    assert a.header.frame_id == b.header.frame_id
    pa, pb = gcp_from_msg(a), gcp_from_msg(b)
    assert [p.id for p in pa] == [p.id for p in pb]
    for p, q in zip(pa, pb, strict=True):
        assert p.observations.keys() == q.observations.keys()
        for sid in p.observations:
            np.testing.assert_allclose(p.observations[sid], q.observations[sid], atol=1e-6)
    s = synthetic["geom_summary"]["scenes"]
    assert s["left"]["offset_line_sample"] == [1900.0, 1900.0]
    assert s["right"]["offset_source"].startswith("ModelTransformationTag")
    assert s["right"]["rpc"] == "b.geom"
    assert "(GeoTIFF tag 50844" in synthetic["tag_summary"]["scenes"]["left"]["rpc"]


@pytest.mark.ros
def test_synthetic_process_single_camera(synthetic: dict[str, Any], tmp_path: Path) -> None:
    summary = process_bag(synthetic["tag"], tmp_path / "out", progress=False, overrides=GCP_ONLY)
    assert summary.scenes == 2 and summary.pairs == 1, summary.issues
    reader = BagReader(tmp_path / "out")
    methods = [it.msg.method for it in reader.messages(topics=["parallel_projection"])]
    assert methods == [METHODS.index("gcp_roll_estimated")] * 2
    sp = next(reader.messages(topics=["stereo_pair"])).msg
    assert sp.pair_id == "left+right"
    # nearly affine RPCs: the parallel model fits, the GCP y-parallax is small
    assert sp.y_parallax_points >= 20 and sp.y_parallax_max_px < 0.05


def test_rpc_search_and_offsets(tmp_path: Path) -> None:
    img = np.zeros((4, 5), np.uint16)
    tifffile.imwrite(tmp_path / "IMG_X_R1C1.tif", img)
    with pytest.raises(SceneImportError, match="no RPC"):
        find_rpc(tmp_path / "IMG_X_R1C1.tif")
    assert crop_offset(tmp_path / "IMG_X_R1C1.tif") is None
    full = _affine_rpc(0.3)
    rpc.write_dimap_rpc(tmp_path / "RPC_X.XML", full)
    found, source = find_rpc(tmp_path / "IMG_X_R1C1.tif")
    assert source == "RPC_X.XML (DIMAP, GDAL)"  # GDAL's Pleiades reader: IMG_* + RPC_*
    np.testing.assert_allclose(found.as_vector(), full.as_vector())
    rpc.write_rpc_txt(tmp_path / "IMG_X_R1C1_RPC.TXT", full.shifted(-1.0, -2.0))
    assert find_rpc(tmp_path / "IMG_X_R1C1.tif")[1].startswith("IMG_X_R1C1_RPC.TXT")
    scaled = (0.5, 0.0, 0.0, 10.0, 0.0, 0.5, 0.0, 20.0) + (0.0,) * 7 + (1.0,)
    tifffile.imwrite(tmp_path / "map.tif", img, extratags=[(34264, 12, 16, scaled)])
    with pytest.raises(SceneImportError, match="not a crop offset"):
        crop_offset(tmp_path / "map.tif")


# ---------------------------------------------------------------------------------------------
# Grids and the outlier cut


def test_grid_inverse_and_reading(tmp_path: Path) -> None:
    """A displacement grid written like OTB's reads back and inverts exactly."""
    ny, nx, step = 8, 9, 30.0
    ei, ej = np.meshgrid(step * np.arange(ny), step * np.arange(nx), indexing="ij")
    a = np.radians(105.0)
    rows = 5000 + np.sin(a) * ej + np.cos(a) * ei + 1e-4 * ei * ej
    cols = 5400 + np.cos(a) * ej - np.sin(a) * ei
    data = np.stack([cols - ej, rows - ei], axis=-1)  # band 1 column, band 2 row displacement
    transform = (step, 0.0, 0.0, -step / 2, 0.0, step, 0.0, -step / 2) + (0.0,) * 7 + (1.0,)
    tifffile.imwrite(
        tmp_path / "g.tif", data, planarconfig="contig", extratags=[(34264, 12, 16, transform)]
    )
    g = read_grid(tmp_path / "g.tif")
    assert (g.row0, g.col0, g.step_row, g.step_col) == (0.0, 0.0, step, step)
    np.testing.assert_allclose(g.rows, rows, atol=1e-9)
    rng = np.random.default_rng(1)
    er, ec = rng.uniform(0, step * (ny - 1), 50), rng.uniform(0, step * (nx - 1), 50)
    r, c = g.forward(er, ec)
    ir, ic = g.inverse(r, c)
    np.testing.assert_allclose(ir, er, atol=1e-6)
    np.testing.assert_allclose(ic, ec, atol=1e-6)
    assert isinstance(g, EpipolarGrid)


def test_robust_cut_drops_outliers_not_parallax() -> None:
    rng = np.random.default_rng(3)
    left = rng.uniform(0, 500, (300, 2))
    parallax = rng.uniform(-30, 30, 300)  # terrain: large spread along one direction
    d = np.column_stack([parallax, 0.01 * left[:, 0] + 4.8 + rng.normal(0, 0.1, 300)])
    d[:10, 1] += rng.choice([-1, 1], 10) * rng.uniform(2, 20, 10)  # bad matches
    keep, thr = robust_cut(left, left + d)
    assert not keep[:10].any()
    assert keep[10:].mean() > 0.97
    assert 0.2 < thr < 1.0


# ---------------------------------------------------------------------------------------------
# The real pair: import -> process -> evaluation


VENTOUX = [DATA / "left_image.tif", DATA / "right_image.tif"]


@pytest.fixture(scope="module")
def ventoux(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    # The crops and grids are in the repository (tests/data/ventoux/README.md).
    assert all(p.is_file() for p in [*VENTOUX, GRIDS / "otb_left_grid.tif"])
    root = tmp_path_factory.mktemp("ventoux")
    # SRTM crop of tests/data/ventoux, heights + ~50 m geoid undulation (EGM96 at Ventoux)
    dem = grid_height(
        np.loadtxt(DATA / "srtm_N44E005_crop.txt"),
        lat_max=45 - 927 / 1200,
        lon_min=5 + 206 / 1200,
        step_deg=1 / 1200,
        geoid_undulation=50.0,
    )
    summary = import_pair(*VENTOUX, root / "in", dem=dem, log=lambda _: None)
    process = process_bag(root / "in", root / "out", progress=False, overrides=GCP_ONLY)
    result = evaluate_against_grids(root / "out", *VENTOUX, GRIDS, truth_bag=root / "in")
    print(format_table(result))
    return {"root": root, "summary": summary, "process": process, "result": result}


@pytest.mark.ros
def test_ventoux_import(ventoux: dict[str, Any]) -> None:
    s = ventoux["summary"]
    assert s["scenes"]["left"]["offset_line_sample"] == [5000.0, 5000.0]
    assert s["scenes"]["right"]["offset_line_sample"] == [5162.0, 4915.0]
    assert s["scenes"]["right"]["rpc"] == "right_image.geom"
    assert min(v["gcp"] for v in s["scenes"].values()) >= 100
    assert s["gcp_in_both"] >= 30 and s["truth"] == 300  # the crops overlap by about 30 %
    assert s["size_mb"] < 1.5


@pytest.mark.ros
def test_ventoux_process_gcp_only(ventoux: dict[str, Any]) -> None:
    p = ventoux["process"]
    assert p.scenes == 2 and p.pairs == 1, p.issues
    reader = BagReader(ventoux["root"] / "out")
    for item in reader.messages(topics=["parallel_projection"]):
        assert item.msg.method == METHODS.index("gcp_roll_estimated")
        assert item.msg.sigma0_px < 0.05  # a parallel projection fits a 500 px crop's RPC


@pytest.mark.ros
def test_ventoux_evaluation(ventoux: dict[str, Any]) -> None:
    r = ventoux["result"]
    m = r["methods"]
    assert r["matches"]["after_cut"] >= 100
    for name in ("ours", "otb", "shareloc"):
        s = m[name]
        assert all(np.isfinite(s[k]) for k in ("mean_abs", "rms", "p95_abs"))
        assert s["n"] == r["matches"]["after_cut"]
        # the RPCs' relative error: a nearly constant y-offset of about 4.8 px (shared README)
        assert 4.3 < s["mean_abs"] < 5.3 and s["std"] < 0.4
    # the two reference grids agree on the matches (shared README: about 1e-2 px)
    assert r["differences"]["otb-shareloc"]["max_abs"] < 0.05
    # the GCP-only pipeline reproduces the RPC-based rectification to a few hundredths
    for ref in ("otb", "shareloc"):
        d = r["differences"][f"ours-{ref}"]
        assert abs(d["mean"]) < 0.05 and d["max_abs"] < 0.1
    # RPC-exact points: every method has (almost) no y-parallax: the offset is in the images
    for s in r["rpc_points"].values():
        assert s["mean_abs"] < 0.02
    # grid reading: unit scale along the epipolar rows and columns
    for scales in r["grid_scale"].values():
        assert all(0.95 < v < 1.05 for v in scales)


@pytest.mark.ros
def test_ventoux_tie_points_reach_the_target(ventoux: dict[str, Any]) -> None:
    """With tie points (the pipeline's default), the 4.8 px RPC offset goes: mean |y| <= 0.3."""
    out = ventoux["root"] / "out_tie"
    summary = process_bag(ventoux["root"] / "in", out, progress=False)
    assert summary.pairs == 1
    r = evaluate_against_grids(out, *VENTOUX, GRIDS)
    assert r["methods"]["ours"]["mean_abs"] <= 0.3


@pytest.mark.ros
def test_cli_import_and_ventoux_eval(
    synthetic: dict[str, Any],
    ventoux: dict[str, Any],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from parproj_ros.apps import cli

    tag_dir = synthetic["dirs"][0]
    args = ["import", str(tag_dir / "a.tif"), str(tag_dir / "b.tif"), "-o", str(tmp_path / "b")]
    assert cli.main([*args, "--heights", "400", "600", "--ids", "fwd", "aft"]) == 0
    assert cli.main([*args, "--heights", "400", "600"]) == 2  # exists: no --force
    msg = _gcp_msg(tmp_path / "b")
    assert {o.scene_id for p in msg.points for o in p.observations} == {"fwd", "aft"}
    capsys.readouterr()
    out = ventoux["root"] / "out"
    argv = ["ventoux-eval", str(out), "--left", str(VENTOUX[0]), "--right", str(VENTOUX[1])]
    assert cli.main([*argv, "--grids", str(GRIDS), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert set(res["methods"]) == {"ours", "otb", "shareloc"}
    swapped = ["ventoux-eval", str(out), "--left", str(VENTOUX[1]), "--right", str(VENTOUX[0])]
    with pytest.raises(ValueError, match="wrong image or order"):
        cli.main(["--debug", *swapped, "--grids", str(GRIDS)])


@pytest.mark.ros
def test_a_dem_above_the_geoid_imported_without_one_is_said(tmp_path: Path) -> None:
    """The tie points measure the terrain the DEM should hold: a missing geoid is a warning.

    The SRTM crop holds heights above EGM96 (about 50 m below the ellipsoid at Ventoux).
    Imported as ellipsoidal (no --geoid), the tie points' triangulated heights lie some 50 m
    above it at the same places; with the undulation given, within the DEM's and the RPCs'
    errors (SRTM: some 10 m).
    """
    from testkit.rasters import srtm_crop_geotiff

    dem = srtm_crop_geotiff(tmp_path / "srtm.tif")
    said: list[str] = []
    s = import_pair(*VENTOUX, tmp_path / "none", dem=dem, log=said.append)
    off = s["tie_points"]["dem_offset_m"]
    assert off["points"] >= 100
    assert 40.0 < off["median"] < 70.0, off  # the geoid undulation at Ventoux: some 50 m
    warning = [line for line in said if "lie" in line and "the DEM" in line]
    assert len(warning) == 1, said
    assert warning[0].startswith("warning: the tie points lie ")
    assert "above the DEM srtm.tif" in warning[0] and "--geoid" in warning[0]
    assert s["tie_points"]["dem_warning"] == warning[0]
    said.clear()
    s = import_pair(*VENTOUX, tmp_path / "n50", dem=dem, geoid_undulation=50.0, log=said.append)
    off = s["tie_points"]["dem_offset_m"]
    assert abs(off["median"]) < 20.0, off
    assert "dem_warning" not in s["tie_points"]
    assert not [line for line in said if line.startswith("warning: the tie points lie")], said


def test_the_dem_warning_of_a_height_function_names_no_file_nor_option() -> None:
    """An API caller's height function has no file and took no CLI option: none is named."""
    from parproj_ros.io.rpc_ties import dem_offset_warning

    text = dem_offset_warning(lambda lon, lat: np.zeros_like(lon), (56.0, 9.3, 486))
    assert text is not None and text.startswith("warning: the tie points lie 56 m above")
    assert "the DEM the DEM" not in text and "--" not in text, text
    assert dem_offset_warning(lambda lon, lat: lon, (-12.0, 3.0, 100)) is None
    below = dem_offset_warning(lambda lon, lat: lon, (-45.0, 3.0, 100))
    assert below is not None and "45 m below" in below
