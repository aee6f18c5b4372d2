"""Inputs an adversarial user gives ``parproj process``, ``dsm``, ``fuse`` and ``evaluate``.

The cases not in RELIABILITY.md's tables that an adversarial review (2026-11-27) found handled
badly: each failed before its fix. The review's list of inputs found handled well is in its
report. ``bags/ventoux`` (19 messages, one real Pleiades pair with GCP) is processed with
heights in about 1.5 s.
"""

from __future__ import annotations

import contextlib
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from testkit.cli import run
from testkit.paths import BAGS, DATA, ROOT

from parproj_ros.apps import cli
from parproj_ros.apps.batch import BatchInput, find_inputs, run_input
from parproj_ros.core import contract
from parproj_ros.core.heights import MAX_CELLS_PER_GSD
from parproj_ros.io.files import InputError
from parproj_ros.ros.bag import BagReader, BagWriter
from parproj_ros.ros.startup import StartupError, check_frame_id

pytestmark = pytest.mark.ros  # bags written and read

BAG = BAGS / "ventoux"


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``bags/ventoux`` processed with heights (its DSM's cell: the pair's GSD)."""
    out = tmp_path_factory.mktemp("vx") / "out"
    assert cli.main(["process", str(BAG), "-o", str(out), "-q", "--heights"]) == 0
    return out


@pytest.fixture(scope="module")
def unfilled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same with ``--heights-fill none``: another DSM of the pair (its holes not filled)."""
    out = tmp_path_factory.mktemp("vx") / "unfilled"
    argv = ["process", str(BAG), "-o", str(out), "-q", "--heights", "--heights-fill", "none"]
    assert cli.main(argv) == 0
    return out


def dsm_cell(bag: Path) -> float:
    """The cell side of the (one) DSM of an output bag, metres."""
    msgs = [m.msg for m in BagReader(bag).messages(topics=[contract.DSM])]
    assert len(msgs) == 1
    return float(msgs[0].cell_size)


def test_dsm_cell_far_below_the_gsd_is_named(
    processed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--heights-cell-m 0.0001`` on a 0.5 m pair: the option named, exit 1, heights kept.

    Before: ``parproj process: out of memory (Unable to allocate 36.6 TiB ...)``, exit 3 and
    no output, the option not named (the DSM grid of 5e12 cells allocated).
    """
    gsd = dsm_cell(processed)  # the default cell is the pair's GSD
    out = tmp_path / "fine"
    code, _, err = run(
        ["process", str(BAG), "-o", str(out), "-q", "--heights", "--heights-cell-m", "0.0001"],
        capsys,
    )
    assert code == 1, err
    assert "Traceback" not in err and "out of memory" not in err
    assert f"no DSM: heights_cell_m 0.0001 m is {gsd / 1e-4:.3g} times finer" in err, err
    assert f"at least {gsd / MAX_CELLS_PER_GSD:.3g} m" in err
    assert "parproj process: --heights: no DSM for left+right" in err
    reader = BagReader(out)
    counts = {t: sum(1 for _ in reader.messages(topics=[t])) for t in reader.topics()}
    assert counts[contract.DISPARITY] == 1 and counts[contract.HEIGHT] == 1  # kept
    assert counts.get(contract.DSM, 0) == 0
    # the least cell accepted gives a DSM
    edge = gsd / MAX_CELLS_PER_GSD * 1.01
    code, _, err = run(
        ["process", str(BAG), "-o", str(tmp_path / "edge"), "-q", "--heights",
         "--heights-cell-m", f"{edge:.6f}"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    assert abs(dsm_cell(tmp_path / "edge") - edge) < 1e-6


def cut_copy(bag: Path, dest: Path, share: float) -> Path:
    """A copy of ``bag`` with its MCAP file cut to ``share`` of its bytes."""
    shutil.copytree(bag, dest)
    mcap = next(dest.glob("*.mcap"))
    with mcap.open("r+b") as f:
        f.truncate(int(mcap.stat().st_size * share))
    return dest


def topic_counts(bag: Path) -> dict[str, int]:
    """Messages per topic that a reader recovers from ``bag``."""
    counts: dict[str, int] = {}
    for item in BagReader(bag).messages():
        counts[item.topic] = counts.get(item.topic, 0) + 1
    return counts


def test_cut_output_bag_is_named_by_dsm_fuse_and_evaluate(
    processed: Path, unfilled: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An output bag cut off (copied half, disk full): the cut named, never 'no pair got heights'.

    Before: ``dsm`` on the half bag said "the dsm topic has no message (no pair got heights:
    the WARN lines of parproj process say why)" and advised --z-avg; ``evaluate`` exited 0 and
    ``fuse`` advised importing three images, neither naming the cut; on a bag cut after its DSM,
    ``dsm`` and ``fuse`` exported it with no word of the messages lost.
    """
    half = cut_copy(processed, tmp_path / "half", 0.5)
    counts = topic_counts(half)
    assert contract.DSM not in counts and counts.get(contract.STEREO_PAIR) == 1
    rec = BagReader(half).recovery
    assert not rec.complete and rec.messages_expected is not None
    lost = f"{rec.messages_lost} of {rec.messages_expected} messages lost"

    code, _, err = run(["dsm", str(half), "-o", str(tmp_path / "d")], capsys)
    assert code == 1, err
    assert "no pair got heights" not in err and "Traceback" not in err
    assert f"parproj dsm: {half}: no DSM: no complete dsm message in the bag, which is cut" in err
    assert lost in err
    assert not (tmp_path / "d").exists()

    code, out, err = run(["evaluate", str(half), "--no-matching"], capsys)
    assert code == 0, err  # the pair, complete, is evaluated
    assert f"parproj evaluate: note: {half}: cut off or damaged" in err and lost in err
    assert "1 pairs" in out

    code, _, err = run(["fuse", str(half), str(processed), "-o", str(tmp_path / "f")], capsys)
    assert code == 1, err
    assert f"parproj fuse: note: {half}: cut off or damaged" in err and lost in err
    assert f"{half} cut off or damaged (note above)" in err
    assert "import three or more images" not in err

    # cut after its DSM: exported, with a note naming what was lost
    late = cut_copy(processed, tmp_path / "late", 0.8)
    assert topic_counts(late).get(contract.DSM) == 1
    rec = BagReader(late).recovery
    assert not rec.complete
    code, out, err = run(["dsm", str(late), "-o", str(tmp_path / "d2")], capsys)
    assert code == 0, err
    assert err.strip().splitlines() == [
        f"parproj dsm: note: {late}: {rec.describe()}; the DSMs complete in it are exported"
    ]
    assert (tmp_path / "d2" / "left_right_dsm.tif").is_file()
    code, out, err = run(["fuse", str(late), str(unfilled), "-o", str(tmp_path / "f2")], capsys)
    assert code == 0, err
    assert f"parproj fuse: note: {late}: {rec.describe()}; the DSMs complete in it are used" in err


def test_one_dsm_twice_is_named(
    processed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One bag given twice (spelled alike or not), or a copy of it: fused, and said so.

    Kept exit 0: tests/apps/test_fuse.py fuses a bag with itself on purpose (the fused heights
    equal the pair's). Before: no word of it, the inputs labelled ``/out:left+right`` when the
    bag was given by a relative name (the folder of ``out`` is '' then), and "levels kept as
    they are (--no-align)", not asked for (the offsets found were exactly 0).
    """
    spelled = processed.parent / ".." / processed.parent.name / processed.name
    copy = tmp_path / "copy" / processed.name
    shutil.copytree(processed, copy)
    folder = processed.parent.name
    for i, second in enumerate((processed, spelled, copy)):
        out = tmp_path / f"f{i}"
        code, stdout, err = run(["fuse", str(processed), str(second), "-o", str(out)], capsys)
        assert code == 0, err
        label = f"{second.resolve().parent.name}/out:left+right"
        assert err.strip().splitlines() == [
            f"parproj fuse: note: {label} is the same DSM as {folder}/out:left+right (same "
            "frame, grid and heights: one bag given twice, or a copy): it is fused with itself, "
            "which adds nothing"
        ]
        assert "--no-align" not in stdout
    with contextlib.chdir(processed.parent):  # a relative name: the folder named all the same
        code, stdout, err = run(["fuse", "out", "out", "-o", str(tmp_path / "rel")], capsys)
    assert code == 0, err
    assert f"  {folder}/out:left+right: " in stdout and "  /out" not in stdout


def test_levels_aligned_are_not_reported_as_no_align(
    processed: Path, unfilled: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two DSMs of one pair (holes filled or not) share their level: offsets 0, aligned.

    Before: "levels kept as they are (--no-align)" and ``"aligned": false`` in fuse.json,
    without --no-align (the offsets found were exactly 0).
    """
    code, out, err = run(
        ["fuse", str(processed), str(unfilled), "-o", str(tmp_path / "f")], capsys
    )
    assert code == 0, err
    assert "--no-align" not in out
    assert "removed (m): out:left+right +0.00, unfilled:left+right +0.00" in out
    assert json.loads((tmp_path / "f" / "fuse.json").read_text())["aligned"] is True
    argv = ["fuse", str(processed), str(unfilled), "-o", str(tmp_path / "n"), "--no-align"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    assert "levels kept as they are (--no-align)" in out
    assert json.loads((tmp_path / "n" / "fuse.json").read_text())["aligned"] is False


@pytest.mark.parametrize(
    ("name", "size", "says"),
    [
        ("N44E005.hgt", 0, "size"),  # empty, rightly named
        ("N44E005.hgt", 1000, "size"),  # cut off
        ("tile.hgt", 2 * 1201 * 1201, "name"),  # a whole tile renamed
        ("tile.hgt", 0, "both"),
    ],
)
def test_unreadable_srtm_tile_says_why(
    processed: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    name: str,
    size: int,
    says: str,
) -> None:
    """A ``.hgt`` GDAL cannot read: the advice fits the file (its name, its size).

    Before: "an SRTM tile must keep its name (e.g. N44E005.hgt)" for an empty or cut-off
    N44E005.hgt, which has that name.
    """
    dem = tmp_path / name
    dem.write_bytes(bytes(size))
    code, _, err = run(
        ["dsm", str(processed), "-o", str(tmp_path / "d"), "--dem", str(dem)], capsys
    )
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith(f"parproj dsm: {dem}: GDAL cannot read it as a raster (")
    named = "an SRTM tile must keep its name (e.g. N44E005.hgt)" in line
    sized = f"it has {size} bytes, not the size of a 1201 x 1201 tile (2884802) or a 3601" in line
    assert (named, sized) == {"size": (False, True), "name": (True, False), "both": (True, True)}[
        says
    ]


SRTM = ROOT.parent / "shared" / "data" / "ventoux" / "dem" / "N44E005.hgt"
#: Ellipsoidal ground of the Ventoux crops: the tie points of the default import measure
#: 512..567 m (percentiles 1-99).
VENTOUX_GROUND_M = 540.0


def test_heights_off_the_ground_are_named_not_the_rpc(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A DEM in feet, or ``--heights`` 1.3 km above the ground: the heights named, exit 2.

    At those heights the two footprints miss each other (B/H 0.355). Before: "do not overlap
    on the ground: footprints lon/lat [...]; not a stereo pair, or a wrong RPC / crop origin".
    """
    import rasterio

    with rasterio.open(SRTM) as src:
        profile = src.profile | {"driver": "GTiff"}
        h = src.read(1)
        # the tile's 6 voids stay voids (x 3.28 they wrap around int16 to 23566, which the DEM
        # reader refuses as no height on Earth: test_dem.py, "centimetres")
        feet = np.where(h == src.nodata, h, h * 3.28084).astype(np.int16)
    dem = tmp_path / "feet.tif"
    with rasterio.open(dem, "w", **profile) as dst:
        dst.write(feet, 1)
    imgs = [str(DATA / "left_image.tif"), str(DATA / "right_image.tif")]
    for extra, used in (
        (["--heights", "1800", "1900"], "(1800..1900 m)"),
        (["--dem", str(dem)], None),
    ):
        code, _, err = run(["import", *imgs, "-o", str(tmp_path / "i"), *extra], capsys)
        assert code == 2, err
        *notes, line = err.strip().splitlines()
        # the feet DEM also reaches beyond the RPC's height range, which is noted first
        assert all("beyond the RPC's height range" in n for n in notes), notes
        assert (not notes) if used else len(notes) in (1, 2), notes  # one per image at most
        assert "a wrong RPC / crop origin" not in line
        m = re.search(
            r"do not overlap on the ground at the heights used \((\d+)\.\.(\d+) m\), but do at "
            r"(\d+)\.\.(\d+) m \(within the RPC's height range 190\.\.1960 m\): the heights are "
            r"off the ground: a DEM \(--dem\) in feet",
            line,
        )
        assert m is not None, line
        u0, u1, h0, h1 = (float(v) for v in m.groups())
        assert used is None or used in line
        assert h0 <= VENTOUX_GROUND_M <= h1 and not u0 <= VENTOUX_GROUND_M <= u1
        if used is None:  # the feet DEM (+- the DEM margin, 100 m): over 3 x the ground's
            assert u0 + 100 > 3.0 * (VENTOUX_GROUND_M - 100)  # ~440 m above the geoid here
        assert not (tmp_path / "i").exists()


@pytest.mark.parametrize(
    ("frame", "why"),
    [
        ("enu_wgs84:lat=999,lon=5,h=0", "bad origin (999.0, 5.0, 0.0)"),
        ("enu_wgs84:lat=44,lon=5,h=inf", "not a local tangent plane frame_id"),
        ("enu_wgs84:44,5", "not a local tangent plane frame_id"),
    ],
)
def test_a_tangent_plane_that_cannot_be_is_refused(
    processed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], frame: str, why: str
) -> None:
    """``process --frame-id`` naming an impossible plane: exit 2; ``dsm`` of such a bag: exit 2.

    Before: ``process --frame-id enu_wgs84:lat=999,lon=5,h=0`` exit 0, then ``parproj dsm``
    of its output "internal error (a bug, not your input): ValueError: bad origin (999.0, 5.0,
    0.0)", exit 3.
    """
    out = tmp_path / "o"
    code, _, err = run(["process", str(BAG), "-o", str(out), "-q", "--frame-id", frame], capsys)
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith(f"parproj process: --frame-id: {frame!r}: {why}"), line
    assert not out.exists()
    # the node's frame_id parameter is not checked: a bag holding such a DSM
    (item,) = BagReader(processed).messages(topics=[contract.DSM])
    item.msg.header.frame_id = frame
    bag = tmp_path / "labelled"
    with BagWriter(bag) as bw:
        bw.add_topics([contract.topic(contract.DSM)])
        bw.write(contract.DSM, item.msg, item.log_time_ns)
    code, _, err = run(["dsm", str(bag), "-o", str(tmp_path / "d")], capsys)
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith(
        f"parproj dsm: {bag}: the DSM of left+right is in object frame {frame!r}, which cannot "
        f"be placed ({why}"
    ), line
    assert not (tmp_path / "d").exists()


def test_fuse_cell_far_below_the_inputs_is_named(
    processed: Path, unfilled: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``fuse --cell-m 0.0001`` on 0.5 m DSMs: exit 2 naming the option and the least cell.

    Before: "parproj fuse: out of memory (Unable to allocate 36.4 TiB ...)", exit 3.
    """
    cell = dsm_cell(processed)
    out = tmp_path / "f"
    argv = ["fuse", str(processed), str(unfilled), "-o", str(out), "--cell-m", "0.0001"]
    code, _, err = run(argv, capsys)
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith(
        f"parproj fuse: --cell-m: 0.0001 m is {cell / 1e-4:.3g} times finer than the finest "
        f"input DSM's cell ({cell:.3g} m)"
    ), line
    assert f"or at least {cell / MAX_CELLS_PER_GSD:.3g} m" in line
    assert not out.exists()  # (a fusion at the least cell accepted takes 90 s here)


def test_fuse_cell_coarser_than_an_input_is_named(
    processed: Path, unfilled: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``fuse --cell-m 200`` on 240 x 180 m DSMs: exit 2 naming the option and the most cell.

    Before: exit 1, "the fused DSM has no cell with a height (the inputs do not overlap or are
    empty)": the inputs blamed; a coarse cell took the one fine cell under its centre.
    """
    (m,) = [x.msg for x in BagReader(processed).messages(topics=[contract.DSM])]
    side = min(m.heights.width, m.heights.height) * m.cell_size
    out = tmp_path / "f"
    argv = ["fuse", str(processed), str(unfilled), "-o", str(out), "--cell-m", "200"]
    code, _, err = run(argv, capsys)
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith("parproj fuse: --cell-m: 200 m cells are too coarse for "), line
    assert f"give at most {np.floor(5 * side) / 10:g} m" in line
    assert not out.exists()
    argv[-1] = f"{np.floor(5 * side) / 10:g}"  # the most it allows: a DSM with heights
    code, printed, err = run(argv, capsys)
    assert code == 0, err
    assert re.search(
        r"fused: \d+ x \d+ cells of [\d.]+ m, .*; [1-9][\d.]* % of its frame", printed
    )


@pytest.mark.parametrize(
    ("nodata", "says"),
    [(7, "its only band is all no-data (GDAL mask): nothing to import; check the file and its "
          "nodata value"),
     (None, "its only band is constant (7) : nothing to match; check the file")],
)  # fmt: skip
def test_single_band_image_without_data_is_not_told_to_choose_a_band(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], nodata: int | None, says: str
) -> None:
    """A one-band image all no-data, or constant: exit 2, no advice to pick another band.

    Before: "band 1 is all no-data: choose another with --band" for a raster of one band.
    """
    import rasterio

    img = tmp_path / "blank.tif"
    profile = {"driver": "GTiff", "width": 40, "height": 40, "count": 1, "dtype": "uint16"}
    with rasterio.open(img, "w", **profile, nodata=nodata) as dst:
        dst.write(np.full((40, 40), 7, np.uint16), 1)
    shutil.copy(DATA / "left_image.geom", tmp_path / "blank.geom")  # an RPC beside it
    argv = ["import", str(img), str(DATA / "right_image.tif"), "-o", str(tmp_path / "i")]
    code, _, err = run(argv, capsys)
    assert code == 2, err
    assert err.strip().splitlines() == [f"parproj import: {img}: {says}"]


@pytest.mark.parametrize(
    ("key", "value", "says"),
    [("lat_off", "999", "lat_off must be within +-90 deg, got 999"),
     ("long_off", "400", "long_off must be within +-360 deg, got 400"),
     ("height_scale", "1e9", "height_off 1075 m +- height_scale 1e+09 m reaches beyond 100000 m "
      "from the ellipsoid: an RPC's heights are the ground's")],
)  # fmt: skip
def test_rpc_off_the_earth_names_the_rpc_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str, value: str, says: str
) -> None:
    """An RPC whose ground offset is no latitude / longitude / ground height: file, key named.

    Before (lat_off 999): "left_image.tif, right_image.tif, bad.geom: bad origin (999.0705378,
    5.1953824, 1075.0)", the three inputs named and the cause left to guess; (height_scale 1e9
    in the left RPC) "right_image.tif: RPC line denominator crosses zero over the image ...
    (right_image.geom)": the other image's RPC blamed, at the default heights (+-5e8 m).
    """
    text = (DATA / "left_image.geom").read_text()
    bad = tmp_path / "bad.geom"
    bad.write_text(re.sub(rf"(?m)^{key}:.*$", f"{key}:  {value}", text))
    imgs = [str(DATA / "left_image.tif"), str(DATA / "right_image.tif")]
    argv = ["import", *imgs, "-o", str(tmp_path / "i"), "--rpc-left", str(bad)]
    code, _, err = run(argv, capsys)
    assert code == 2, err
    assert err.strip().splitlines() == [
        f"parproj import: {bad}: not a readable RPC file (RPCFormatError: {bad}: {says})"
    ]


def test_a_scenario_is_no_truth_for_a_real_pair(
    processed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``dsm --scenario`` on a real pair's DSM (tangent plane on WGS84): exit 2, nothing written.

    Before: exit 0, "against truth NMAD 19.455 m, rms 30.314 m, 86.6 % complete": the
    simulated scenario's terrain (frame map) compared with the Ventoux DSM as if one frame.
    """
    out = tmp_path / "d"
    code, _, err = run(
        ["dsm", str(processed), "-o", str(out), "--scenario", "ikonos_agile"], capsys
    )
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith("parproj dsm: --scenario: the DSM of left+right is in 'enu_wgs84:")
    assert line.endswith("compare a real pair with --dem")
    assert not out.exists()


def test_streamed_dsm_tiles_refuse_a_cell_far_below_the_gsd(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same cell on a streamed pair (DSM tiles): no tiles, said; no DSM, exit 1.

    bags/airborne_foreaft with ``--scene-lines 768`` is streamed. Before: "parproj process:
    out of memory (Unable to allocate 1.87 TiB ...)", exit 3 (the tiles' DSM grid).
    """
    argv = ["process", str(BAGS / "airborne_foreaft"), "-o", str(tmp_path / "o"), "-q",
            "--no-tie-points", "--heights", "--scene-lines", "768",
            "--heights-cell-m", "0.0001"]  # fmt: skip
    code, _, err = run(argv, capsys)
    assert code == 1, err
    assert "out of memory" not in err and "Traceback" not in err
    pair = "left_scene_0000+right_scene_0001"
    assert "streaming: 768 x 791 px" in err  # streamed indeed
    assert f"[warn] pair {pair}: no full-resolution tiles: heights_cell_m 0.0001 m is" in err
    assert f"parproj process: --heights: no DSM for {pair}" in err


def test_a_margin_that_widens_the_range_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--heights-margin-px 300`` on a 310 px wide pair: the margin named, not only the heights.

    Before: "disparity range (-312, 343) (656 px) is as wide as the image (310 px) ...: narrow
    the height range" alone, with the terrain measured at -16..47 m (63 px of it).
    """
    argv = ["process", str(BAG), "-o", str(tmp_path / "o"), "-q", "--heights",
            "--heights-margin-px", "300"]  # fmt: skip
    code, _, err = run(argv, capsys)
    assert code == 1, err
    assert "no heights (range_too_wide): disparity range (" in err
    assert "(heights_margin_px 300 px adds 600 px of it: lower heights_margin_px)" in err


@pytest.mark.parametrize(
    ("name", "right", "says"),
    [("../evil", "right_image.tif", "name '../evil': not a plain folder name"),
     ("a/b", "right_image.tif", "name 'a/b': not a plain folder name"),
     ("_failed", "right_image.tif", "name '_failed': not a plain folder name"),
     ("same", "left_image.tif", "right left_image.tif: is the left image too")],
)  # fmt: skip
def test_batch_pair_list_names_and_pairs_are_checked(
    tmp_path: Path, name: str, right: str, says: str
) -> None:
    """A pair list whose name leaves OUTPUT, or whose pair is one image twice: InputError.

    Before: name ``../evil`` wrote (and with the task's force, would have replaced) the folder
    ``evil`` beside OUTPUT, exit 0; one image as left and right was 'done' with 0 pairs, exit 0
    (``parproj import`` refuses it).
    """
    for img in ("left_image.tif", "right_image.tif"):
        shutil.copy(DATA / img, tmp_path / img)
    pairs = tmp_path / "pairs.csv"
    pairs.write_text(f"name,left,right\n{name},left_image.tif,{right}\n")
    with pytest.raises(InputError) as info:
        find_inputs([pairs])
    assert f"{pairs}: pair 1: {says}" in str(info.value)


def test_batch_input_without_a_pair_is_failed_not_done(tmp_path: Path) -> None:
    """A batch task that makes no pair is ``failed`` with the reason (exit 1), not ``done``.

    Before: status ``done`` with 0 pairs, and ``parproj batch`` exit 0 (``parproj process``
    of the same: exit 1, "no pair was made").
    """
    row = run_input(
        BatchInput("ventoux", "bag", (BAG,)),
        tmp_path,
        {"max_output_pixels": 1, "tie_points": False},
    )
    assert row["status"] == "failed", row
    assert row["error"].startswith("EmptyResultError: no pair was made")
    assert not (tmp_path / "ventoux").exists()
    log = (tmp_path / "_failed" / "ventoux.log").read_text()
    assert "normalized images would be 310 x 613 px (> max_output_pixels 1): pair skipped" in log
    # the same bag with its pair made is done
    row = run_input(BatchInput("ok", "bag", (BAG,)), tmp_path, {"tie_points": False})
    assert row["status"] == "done" and row["pairs"] == 1, row


def test_batch_with_heights_names_the_pairs_without_a_dsm(tmp_path: Path) -> None:
    """``--heights`` asked and a pair without a DSM: ``done`` (its pair kept) with a warning.

    Before: ``done`` with no word, and ``parproj batch`` exit 0 (``parproj process
    --heights`` of the same: exit 1).
    """
    from parproj_ros.apps.batch import BatchResult, format_summary

    over = {"heights": True}
    row = run_input(BatchInput("nodsm", "bag", (BAG,)), tmp_path, {**over, "heights_cell_m": 1e-4})
    assert row["status"] == "done" and row["pairs"] == 1 and row["dsms"] == 0, row
    assert row["warning"] == "1 of 1 pairs got no DSM (the [warn] lines of nodsm/log.txt say why)"
    log = (tmp_path / "nodsm" / "log.txt").read_text()
    assert "no DSM: heights_cell_m 0.0001 m is" in log, log
    ok = run_input(BatchInput("ok", "bag", (BAG,)), tmp_path, over)
    assert ok["status"] == "done" and ok["dsms"] == 1 and "warning" not in ok, ok
    text = format_summary(BatchResult([row, ok], 1.0, 1, None))
    assert "1 of 1 pairs got no DSM" in text.splitlines()[1]


@pytest.mark.parametrize("short", [True, False])
def test_batch_exits_1_when_asked_dsms_are_missing(
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    short: bool,
) -> None:
    """``parproj batch --heights``: a row with missing DSMs makes the exit 1, as a failure."""
    from parproj_ros.apps import batch

    row = {"name": "a", "status": "done", "pairs": 1, "dsms": 0 if short else 1}
    if short:
        row["warning"] = "1 of 1 pairs got no DSM (...)"
    monkeypatch.setattr(batch, "run_batch", lambda *a, **k: batch.BatchResult([row], 1, 1, None))
    code, out, _ = run(["batch", str(BAG), "-o", str(tmp_path / "o"), "--heights"], capsys)
    assert code == (1 if short else 0) and "1 done" in out, out


def test_segments_of_one_rpc_twice_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``segments L.geom L.geom`` (or a copy): exit 2, as ``import`` refuses one image twice.

    Before: exit 0, a table of segments for a "pair" with no base ("one model L / R px 6.436
    / 6.436").
    """
    left = DATA / "left_image.geom"
    copy = tmp_path / "copy.geom"
    shutil.copy(left, copy)
    for right in (left, copy):
        code, out, err = run(["segments", str(left), str(right)], capsys)
        assert code == 2, err
        assert err.strip().splitlines() == [
            f"parproj segments: {right}: the same RPC as {left}: a stereo pair needs two scenes "
            "(no base here)"
        ]
        assert out == ""


def test_node_refuses_a_tangent_plane_that_cannot_be() -> None:
    """``parproj_node`` with ``frame_id`` enu_wgs84:lat=999,...: exit 2, one line.

    Before: the node started and labelled every output with that frame (no object-frame
    transform published, and ``parproj dsm`` of its recording failed: see the test above).
    """
    frame = "enu_wgs84:lat=999,lon=5,h=0"
    cmd = [sys.executable, "-m", "parproj_ros.ros.node", "--ros-args", "-p", f"frame_id:={frame}"]
    p = subprocess.run(cmd, capture_output=True, timeout=30, check=False)
    text = (p.stdout + p.stderr).decode(errors="replace")
    assert p.returncode == 2, text
    assert text.strip().splitlines() == [
        f"parproj_node: cannot start: parameter frame_id: {frame!r}: bad origin (999.0, 5.0, "
        "0.0); a tangent plane on WGS84 is enu_wgs84:lat=LAT,lon=LON,h=H (degrees, |LAT| <= 90; "
        "metres)"
    ]
    for good in ("", "map", "enu_wgs84:lat=44.2069738,lon=5.1950231,h=519.80"):
        assert check_frame_id(good) == good
    for bad in ("enu_wgs84:44,5", "enu_wgs84:lat=44,lon=5,h=inf", "enu_wgs84:lat=-91,lon=0,h=0"):
        with pytest.raises(StartupError, match=r"^parameter frame_id: "):
            check_frame_id(bad)


def test_evaluate_without_truth_points_names_truth(
    processed: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An imported pair's output bag holds no truth points: say where they are (--truth)."""
    code, out, err = run(["evaluate", str(processed), "--no-matching"], capsys)
    assert code == 0 and "1 pairs, 0 truth points" in out, err
    assert f"parproj evaluate: note: {processed}: it holds no truth points" in err
    assert "--truth BAG" in err
    code, out, err = run(
        ["evaluate", str(processed), "--truth", str(BAG), "--no-matching"], capsys
    )
    assert code == 0 and "1 pairs, 300 truth points" in out and "no truth points" not in err


@pytest.mark.parametrize("command", ["dsm", "import"])
def test_a_geoid_that_is_neither_file_nor_model_names_the_option(
    processed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    """``--geoid nosuch``: before, 'nosuch: no such file or folder', the option not named."""
    dem = str(ROOT.parent / "shared" / "data" / "ventoux" / "dem" / "N44E005.hgt")
    if command == "dsm":
        argv = ["dsm", str(processed), "-o", str(tmp_path / "d"), "--dem", dem]
    else:
        left, right = str(DATA / "left_image.tif"), str(DATA / "right_image.tif")
        argv = ["import", left, right, "-o", str(tmp_path / "b"), "--dem", dem]
    code, _, err = run([*argv, "--geoid", "nosuch"], capsys)
    assert code == 2, err
    assert f"parproj {command}: --geoid: nosuch: no such file or folder (a grid file, or a " in err
    assert not (tmp_path / "d").exists() and not (tmp_path / "b").exists()


def test_no_tie_point_at_all_names_the_images(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A left image 96 % no-data: 0 tie points. Before: 'only 0 tie points of 0 pairs ()'."""
    import rasterio

    with rasterio.open(DATA / "left_image.tif") as ds:
        profile, pixels = ds.profile, ds.read(1)
    keep = np.zeros(pixels.shape, dtype=bool)
    keep[: pixels.shape[0] // 5, : pixels.shape[1] // 5] = True
    pixels[~keep] = 0
    profile.update(nodata=0)
    left = tmp_path / "left_image.tif"
    with rasterio.open(left, "w", **profile) as ds:
        ds.write(pixels, 1)
    shutil.copy(DATA / "left_image.geom", tmp_path / "left_image.geom")
    argv = ["import", str(left), str(DATA / "right_image.tif"), "-o", str(tmp_path / "b")]
    code, out, err = run(argv, capsys)
    text = out + err
    assert "of 0 pairs ()" not in text, text
    assert "only 0 tie points between left and right (50 needed" in text, text
    assert code == 0, text  # the pair is written: the heights are the prior, and said so


def test_a_dem_beyond_the_rpc_height_range_is_noted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A DEM at 0 m under a scene whose RPC spans 190..1960 m: clipped, and now said so."""
    import rasterio
    from rasterio.transform import from_origin

    dem = tmp_path / "sea_level.tif"
    profile = {"driver": "GTiff", "width": 40, "height": 40, "count": 1, "dtype": "float32",
               "crs": "EPSG:4326", "transform": from_origin(5.0, 44.4, 0.01, 0.01)}  # fmt: skip
    with rasterio.open(dem, "w", **profile) as ds:
        ds.write(np.zeros((1, 40, 40), dtype=np.float32))
    left, right = str(DATA / "left_image.tif"), str(DATA / "right_image.tif")
    base = ["import", left, right, "--dem-ellipsoidal"]
    code, _, err = run([*base, "-o", str(tmp_path / "b"), "--dem", str(dem)], capsys)
    assert "beyond the RPC's height range 190..1960 m (from 0 to 0 m): used clipped" in err, err
    assert code == 0, err  # written: process measures the terrain from its tie points
    # the real SRTM tile (+ its geoid) lies within the range: no such note
    tile = str(ROOT.parent / "shared" / "data" / "ventoux" / "dem" / "N44E005.hgt")
    code, _, err = run(["import", left, right, "-o", str(tmp_path / "c"), "--dem", tile,
                          "--geoid-undulation", "50"], capsys)  # fmt: skip
    assert code == 0 and "beyond the RPC's height range" not in err, err


def test_a_full_disk_is_named_in_one_line(
    processed: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str], monkeypatch: Any
) -> None:
    """``dsm`` writing onto a full file system: "No space left on device", the output named.

    The GeoTIFFs are written to ``/dev/full`` (every write fails with ENOSPC, as on a full
    disk: the kernel's error, through GDAL and libtiff). Before: seven lines of libtiff's own
    handler (``_tiffWriteProc: No space left on device.``) and "parproj dsm: <out>: Write
    failed. See previous exception for details."; the same with a real 200 kB tmpfs.
    """
    from parproj_ros.io import geotiff

    real = geotiff._open_writer

    def onto_full_disk(tmp: Path, profile: dict[str, Any]) -> Any:
        Path(tmp).symlink_to("/dev/full")
        return real(tmp, profile)

    monkeypatch.setattr(geotiff, "_open_writer", onto_full_disk)
    out = tmp_path / "d"
    # capfd: libtiff writes to file descriptor 2 itself, past sys.stderr
    code, _, err = run(["dsm", str(processed), "-o", str(out)], capfd)
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert re.match(
        # the file whose own copy failed, or the output when the writes in the body did
        rf"parproj dsm: {re.escape(str(out))}( \(left_right_\w+\.tif\))?: No space left",
        line,
    )
    assert "GDAL: TIFF" in line and line.endswith("free some space or write elsewhere"), line
    assert "See previous exception" not in line
    assert not out.exists() and not list(tmp_path.iterdir())  # no staging folder left either


def test_a_full_disk_in_the_dsm_write_does_not_blame_the_ortho_image(
    processed: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str], monkeypatch: Any
) -> None:
    """The DSM's own write fails (ENOSPC) while the ortho-image's file is open beside it.

    Both files are open at once; the innermost (the ortho-image's) sees the DSM's failure
    first. Before (review 2026-12-02) it named itself: "OUT (left_right_ortho.tif): No space
    left". It cannot tell whose write it was, so the folder both fill is named: "OUT: No space".
    """
    import errno

    from parproj_ros.io import geotiff

    real = geotiff._open_writer

    class FullOnWrite:
        """The DSM's writer: every write fails as on a full disk."""

        def __init__(self, inner: Any) -> None:
            self._inner = inner

        def __enter__(self) -> FullOnWrite:
            self._inner.__enter__()
            return self

        def __exit__(self, *exc: Any) -> Any:
            return self._inner.__exit__(*exc)

        def write(self, *args: Any, **kwargs: Any) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name: str) -> Any:
            return getattr(self._inner, name)

    def writer(tmp: Path, profile: dict[str, Any]) -> Any:
        w = real(tmp, profile)
        return FullOnWrite(w) if "_dsm" in Path(tmp).name else w

    monkeypatch.setattr(geotiff, "_open_writer", writer)
    out = tmp_path / "d"
    code, _, err = run(["dsm", str(processed), "-o", str(out)], capfd)
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith(f"parproj dsm: {out}: No space left on device ("), line
    assert "ortho" not in line and line.endswith("free some space or write elsewhere"), line
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("ids", "said"),
    [
        (["../../ESC", "c"], r"scene id '\.\./\.\./ESC' holds '/'"),
        (["a+b", "c"], r"scene id 'a\+b' holds '\+'"),
        (["..", "c"], r"scene id '\.\.' starts with '\.'"),
        (["x" * 65, "c"], r"has 65 characters \(at most 64\)"),
    ],
)
def test_scene_ids_that_would_name_files_elsewhere_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], ids: list[str], said: str
) -> None:
    """Scene ids name the files ``dsm`` writes (a pair's id joins two with '+').

    Before (adversarial review 2026-12-02): ``--ids ../../ESC c`` imported with exit 0, and
    ``dsm`` then wrote ``ESC_c_dsm.tif`` and the rest two folders up, over a user's file of the
    same name, with exit 0.
    """
    v = DATA
    argv = ["import", str(v / "left_image.tif"), str(v / "right_image.tif")]
    code, _, err = run([*argv, "-o", str(tmp_path / "b"), "--ids", *ids], capsys)
    assert code == 2 and re.search(said, err), err
    assert not (tmp_path / "b").exists()


def test_dsm_names_its_files_inside_its_folder_whatever_the_pair_id(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: Any
) -> None:
    """A bag from elsewhere whose pair id holds '../..': every product stays in ``-o``.

    The bag is made as such a bag would be (the import's id check switched off); before, the
    products landed two folders above the output and overwrote a file there.
    """
    from parproj_ros.apps import importer

    monkeypatch.setattr(importer, "scene_id_problem", lambda sid: None)
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    v = DATA
    argv = ["import", str(v / "left_image.tif"), str(v / "right_image.tif")]
    assert run([*argv, "-o", str(work / "in"), "--ids", "../../ESC", "c"], capsys)[0] == 0
    assert (
        run(["process", str(work / "in"), "-o", str(work / "out"), "-q", "--heights"], capsys)[0]
        == 0
    )
    precious = tmp_path / "ESC_c_ortho.png"
    precious.write_text("PRECIOUS")
    code, _, err = run(["dsm", str(work / "out"), "-o", str(work / "d")], capsys)
    assert code == 0, err
    assert precious.read_text() == "PRECIOUS"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ESC_c_ortho.png", "a"]
    made = sorted(p.name for p in (work / "d").iterdir())
    assert "_._.._ESC_c_dsm.tif" in made and "_._.._ESC_c_ortho.png" in made, made
    assert sorted(p.name for p in work.iterdir()) == ["d", "in", "out"]


def test_a_dsm_of_one_cell_is_no_dsm_and_plots_do_not_crash(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--heights-cell-m`` as large as the pair: a WARN and exit 1, not a 1 x 1 "DSM".

    Before (adversarial review 2026-12-02): "[ok] ... DSM 1 x 1 cells of 1e+04 m" with exit 0,
    then ``dsm`` and ``evaluate --plots`` crashed (exit 3) in the hillshade's np.gradient.
    """
    from parproj_ros.eval.heights import hillshade

    out = tmp_path / "out"
    argv = ["process", str(BAG), "-o", str(out), "--heights", "--heights-cell-m", "10000"]
    code, _, err = run(argv, capsys)
    assert code == 1, err
    assert "no DSM: heights_cell_m 10000 m gives a DSM of 1 x 1 cells" in err, err
    for shape in ((1, 1), (1, 5), (4, 1)):
        shade = hillshade(np.full(shape, 100.0), 1.0)
        assert shade.shape == shape and (shade == shade.flat[0]).all()


@pytest.mark.parametrize("how", ["copy", "same_rpc"])
def test_the_same_view_twice_is_refused_at_import(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], how: str
) -> None:
    """A byte copy of an image (or a hard link: not the same path, so not caught as a symlink
    is), or one RPC for both images: B/H 0, refused at import naming why.

    Before (adversarial review 2026-12-02): "selected (by order)", exit 0; ``process`` then
    exited 1 ("no usable stereo base"), and with a DEM the import blamed its vertical reference.
    """
    left, right = DATA / "left_image.tif", DATA / "right_image.tif"
    argv = ["import", str(left)]
    if how == "copy":
        for f in ("left_image.tif", "left_image.geom"):
            shutil.copy(DATA / f, tmp_path / f)
        argv += [str(tmp_path / "left_image.tif")]
    else:
        argv += [str(right), "--rpc-right", str(DATA / "left_image.geom")]
    code, _, err = run([*argv, "-o", str(tmp_path / "b")], capsys)
    assert code == 2, err
    assert "B/H 0.000" in err and "the same image twice, or one RPC for both?" in err, err
    assert not (tmp_path / "b").exists()


def test_rpcs_swapped_between_the_images_are_said_at_import(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each image with the other's RPC: few matches agree with the RPCs, and the import says so.

    Before (adversarial review 2026-12-02): "506 matched, 13 consistent with the RPCs" and
    exit 0 with no word; ``process`` later blamed the height range and advised --dem.
    """
    argv = ["import", str(DATA / "left_image.tif"), str(DATA / "right_image.tif")]
    argv += ["--rpc-left", str(DATA / "right_image.geom")]
    argv += ["--rpc-right", str(DATA / "left_image.geom"), "-o", str(tmp_path / "b")]
    code, out, err = run(argv, capsys)
    said = [line for line in (out + err).splitlines() if "agree with their RPCs" in line]
    assert len(said) == 1, out + err
    assert said[0].startswith("warning: only ") and "swapped --rpc-left / --rpc-right" in said[0]
    # the right RPCs: nothing said
    argv = ["import", str(DATA / "left_image.tif"), str(DATA / "right_image.tif")]
    code, out, err = run([*argv, "-o", str(tmp_path / "ok")], capsys)
    assert code == 0 and "agree with their RPCs" not in out + err, out + err


def test_force_onto_a_bag_where_a_folder_goes_says_so(
    processed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``fuse -o BAG --force`` (or ``dsm``): a bag is not replaced by a folder of files.

    Before (adversarial review 2026-12-02): "exists and was not written by parproj", false for a
    bag ``parproj import`` wrote.
    """
    bag = tmp_path / "bag"
    shutil.copytree(BAG, bag)
    for cmd in (["fuse", str(processed), str(processed)], ["dsm", str(processed)]):
        code, _, err = run([*cmd, "-o", str(bag), "--force"], capsys)
        assert code == 2, err
        assert "is a bag, and this command writes a folder of files" in err, err
        assert "not written by parproj" not in err
