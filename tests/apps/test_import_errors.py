"""``parproj import``: bad inputs each get a clear error naming the file (RELIABILITY.md).

Inputs are made in tmp_path from the Ventoux pair (tests/data/ventoux), through GDAL
(rasterio) as the importer reads them; the helpers are those of tests/eval/test_conventions.py.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
import tifffile
from rasterio.transform import from_origin
from testkit.rasters import DATA, crop_rpcs, pixels, to_rasterio, write

from parproj_ros import rpc
from parproj_ros.apps import cli
from parproj_ros.apps.importer import import_pair
from parproj_ros.io.scene_import import SceneImportError, check_image, load_image
from parproj_ros.rpc import RPCFormatError, RPCModel

QUIET: dict[str, Any] = {"log": lambda _: None}


@pytest.fixture
def pair(tmp_path: Path) -> tuple[Path, Path]:
    """The Ventoux crops with their crop RPCs in tag 50844."""
    paths = []
    for name, model in zip(("left", "right"), crop_rpcs(), strict=True):
        p = tmp_path / f"{name}.tif"
        write(p, pixels(name), model)
        paths.append(p)
    return paths[0], paths[1]


@pytest.mark.ros
def test_unsupported_raster(pair: tuple[Path, Path], tmp_path: Path) -> None:
    bad = tmp_path / "notes.tif"
    bad.write_text("this is not an image\n")
    with pytest.raises(SceneImportError, match=r"notes\.tif: not a raster GDAL reads"):
        import_pair(bad, pair[1], tmp_path / "o", heights=(500, 1500), **QUIET)
    with pytest.raises(SceneImportError, match=r"missing\.tif: no such file"):
        import_pair(tmp_path / "missing.tif", pair[1], tmp_path / "o", **QUIET)
    cut = tmp_path / "cut.tif"
    data = pair[0].read_bytes()
    cut.write_bytes(data[: len(data) // 2])  # header and RPC intact, pixels cut off
    with pytest.raises(SceneImportError, match=r"cut\.tif: truncated: .* GDAL cannot read"):
        import_pair(cut, pair[1], tmp_path / "o", heights=(500, 1500), **QUIET)


@pytest.mark.ros
def test_corrupt_rpc(pair: tuple[Path, Path], tmp_path: Path) -> None:
    """A truncated .RPB sidecar, an explicit RPC file that is no RPC."""
    img = tmp_path / "c.tif"
    write(img, pixels("left"), None)
    rpc.write_rpb(tmp_path / "c.RPB", crop_rpcs()[0])
    text = (tmp_path / "c.RPB").read_text()
    (tmp_path / "c.RPB").write_text(text[: len(text) // 2])
    with pytest.raises(RPCFormatError, match=r"c\.RPB: missing RPC values"):
        import_pair(img, pair[1], tmp_path / "o", heights=(500, 1500), **QUIET)
    (tmp_path / "junk.txt").write_text("hello: world\n")
    with pytest.raises(RPCFormatError, match=r"junk\.txt: not a known RPC format"):
        import_pair(pair[0], pair[1], tmp_path / "o", rpc_left=tmp_path / "junk.txt", **QUIET)


@pytest.mark.ros
def test_decimal_comma_is_an_error(pair: tuple[Path, Path], tmp_path: Path) -> None:
    """Through GDAL: a .RPB with ``lineScale = 250,5;`` is refused, never read as 250."""
    img = tmp_path / "d.tif"
    write(img, pixels("left"), None)
    rpc.write_rpb(tmp_path / "d.RPB", crop_rpcs()[0])
    text = (tmp_path / "d.RPB").read_text().splitlines()
    text = ["\tlineScale = 21137,5;" if "lineScale" in t else t for t in text]
    (tmp_path / "d.RPB").write_text("\n".join(text) + "\n")
    with pytest.raises(RPCFormatError) as err:
        import_pair(img, pair[1], tmp_path / "o", heights=(500, 1500), **QUIET)
    msg = str(err.value)
    # GDAL hands "21137,5" on as "21137 5": still refused, file, key and value named
    assert "d.RPB" in msg and "LINE_SCALE" in msg and "21137 5" in msg, msg


@pytest.mark.ros
def test_nan_coefficients(pair: tuple[Path, Path], tmp_path: Path) -> None:
    vec = crop_rpcs()[0].as_vector()
    vec[12 + 20 + 3] = np.nan  # line denominator, 4th coefficient
    img = tmp_path / "n.tif"
    extratags = [(rpc.RPC_TIFF_TAG, 12, 92, tuple(float(v) for v in vec), True)]
    tifffile.imwrite(img, pixels("left"), extratags=extratags)
    with pytest.raises(RPCFormatError) as err:
        import_pair(img, pair[1], tmp_path / "o", heights=(500, 1500), **QUIET)
    msg = str(err.value)
    assert "n.tif" in msg and "LINE_DEN_COEFF" in msg.upper(), msg


def _moved(model: RPCModel, d_lon: float) -> RPCModel:
    v = model.as_vector()
    v[5] += d_lon  # LONG_OFF
    return RPCModel.from_vector(v)


@pytest.mark.ros
def test_no_overlap(pair: tuple[Path, Path], tmp_path: Path) -> None:
    far = tmp_path / "far.tif"
    write(far, pixels("right"), _moved(crop_rpcs()[1], 0.2))  # 16 km east
    with pytest.raises(SceneImportError, match=r"far\.tif do not overlap on the ground"):
        import_pair(pair[0], far, tmp_path / "o", heights=(500, 1500), **QUIET)


@pytest.mark.ros
def test_image_and_rpc_of_different_scenes(pair: tuple[Path, Path], tmp_path: Path) -> None:
    """A map-georeferenced image whose RPC describes another place (wrong sidecar)."""
    model = crop_rpcs()[0]
    lon, lat = model.localize(0.0, 0.0, 1000.0)
    img = tmp_path / "geo.tif"
    with rasterio.open(
        img,
        "w",
        driver="GTiff",
        width=500,
        height=500,
        count=1,
        dtype="uint16",
        crs="EPSG:4326",
        transform=from_origin(float(lon), float(lat), 6.3e-6, 4.5e-6),
        rpcs=None,
    ) as dst:
        dst.write(pixels("left"), 1)
    rpc.write_rpc_txt(tmp_path / "other_RPC.TXT", _moved(model, 0.5))  # 40 km away
    with pytest.raises(SceneImportError, match=r"geo\.tif: the image and its RPC describe"):
        import_pair(
            img,
            pair[1],
            tmp_path / "o",
            rpc_left=tmp_path / "other_RPC.TXT",
            heights=(500, 1500),
            **QUIET,
        )


@pytest.mark.ros
def test_denominator_crossing_zero(pair: tuple[Path, Path], tmp_path: Path) -> None:
    model = crop_rpcs()[0]
    lon, lat = model.localize([0.0, 499.0], [0.0, 499.0], 1000.0)
    L, _, _ = model.normalize_ground(lon, lat, 1000.0)
    v = model.as_vector()
    v[12 + 20 : 12 + 40] = 0.0
    v[12 + 20] = 1.0
    v[12 + 21] = -2.0 / float(L[0] + L[1])  # zero in the middle of the image
    bad = RPCModel.from_vector(v)
    assert bad.denominator_check(lon, lat, np.full(2, 1000.0)) is not None
    img = tmp_path / "den.tif"
    write(img, pixels("left"), bad)
    with pytest.raises(SceneImportError, match=r"den\.tif: RPC line denominator changes sign"):
        import_pair(img, pair[1], tmp_path / "o", heights=(500, 1500), **QUIET)


@pytest.mark.ros
def test_bad_options(pair: tuple[Path, Path], tmp_path: Path) -> None:
    with pytest.raises(SceneImportError, match="HMAX > HMIN"):
        import_pair(*pair, tmp_path / "o", heights=(800.0, 800.0), **QUIET)
    with pytest.raises(SceneImportError, match="finite"):
        import_pair(*pair, tmp_path / "o", heights=(float("nan"), 800.0), **QUIET)
    with pytest.raises(SceneImportError, match="geoid_undulation must be finite"):
        import_pair(*pair, tmp_path / "o", geoid_undulation=float("nan"), **QUIET)
    with pytest.raises(SceneImportError, match="crop origin must be finite"):
        import_pair(*pair, tmp_path / "o", offsets=((float("inf"), 0.0), None), **QUIET)
    args = ["import", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "o")]
    for extra in (
        ["--heights", "800", "800"],
        ["--heights", "nan", "800"],
        ["--crop-origin", "nothere.tif", "1", "2"],
        ["--crop-origin", "left.tif", "nan", "2"],
        ["--rpc", "nothere.tif", "x.geom"],
        ["--rpc-left", "a.geom", "--rpc", "left.tif", "b.geom"],  # twice
    ):
        assert exit_code([*args, *extra]) == 2, extra


def exit_code(argv: list[str]) -> int:
    """``parproj`` in process: its exit code, also when argparse refuses an option."""
    try:
        return cli.main(argv)
    except SystemExit as err:
        return int(err.code or 0)


@pytest.mark.ros
def test_bands(pair: tuple[Path, Path], tmp_path: Path) -> None:
    """Multi-band: band 1 by default (logged); --band chooses; a constant band is refused."""
    img = pixels("left")
    path = tmp_path / "rgb.tif"
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=500,
        height=500,
        count=3,
        dtype="uint16",
        rpcs=to_rasterio(crop_rpcs()[0]),
    ) as dst:
        dst.write(img, 1)
        dst.write(np.full_like(img, 7), 2)
        dst.write(img[:, ::-1], 3)
    logged: list[str] = []
    s = import_pair(
        path, pair[1], tmp_path / "o1", dem=None, heights=(500, 1500), log=logged.append
    )
    assert any("3 bands, band 1 imported" in t for t in logged)
    assert s["scenes"]["left"]["band"] == 1
    with pytest.raises(SceneImportError, match=r"rgb\.tif: band 2 is constant \(7\)"):
        import_pair(path, pair[1], tmp_path / "o2", band=2, heights=(500, 1500), **QUIET)
    with pytest.raises(SceneImportError, match=r"band 4 asked for, the raster has 3"):
        import_pair(path, pair[1], tmp_path / "o3", band=4, heights=(500, 1500), **QUIET)


def test_pixel_types_and_nodata(tmp_path: Path) -> None:
    """uint8, 12-bit uint16, float32 kept; int16 -> float32; GDAL nodata -> 0 (pipeline's)."""
    from parproj_ros.io.raster import read_band

    base = pixels("left")
    cases = {
        "uint8": (base // 16).astype(np.uint8),
        "uint16": base,
        "float32": base.astype(np.float32) / 7.0,
        "int16": base.astype(np.int16),
    }
    for name, data in cases.items():
        p = tmp_path / f"{name}.tif"
        with rasterio.open(
            p, "w", driver="GTiff", width=500, height=500, count=1, dtype=name, nodata=data[0, 0]
        ) as dst:
            dst.write(data, 1)
        got = read_band(p)
        want = np.where(data == data[0, 0], 0, data)
        assert got.dtype == (np.float32 if name == "int16" else data.dtype)
        np.testing.assert_array_equal(got, want.astype(got.dtype))


@pytest.mark.ros
def test_named_assumption_without_origin(pair: tuple[Path, Path], tmp_path: Path) -> None:
    """No crop origin in the file: (0, 0), said once per image with the option to override."""
    logged: list[str] = []
    s = import_pair(*pair, tmp_path / "o", heights=(500, 1500), log=logged.append)
    said = [t for t in logged if "--crop-origin" in t]
    assert len(said) == 2 and "left.tif" in said[0] and "as GDAL assumes" in said[0]
    assert s["scenes"]["left"]["offset_source"].startswith("assumed (0, 0)")
    # and the explicit option overrides it: the .geom of the full scene + --crop-origin
    rpc.write_geom(tmp_path / "full.geom", rpc.read_rpc(DATA / "left_image.geom"))
    args = ["import", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "o2"), "--heights"]
    args += ["500", "1500", "--rpc-left", str(tmp_path / "full.geom")]
    assert cli.main([*args, "--crop-origin", "left.tif", "5000", "5000"]) == 0


# ---- issue 24, item 6: messages that name the real cause ----------------------------------------
# Each bad input is made here from the Ventoux crops; the checks run through load_image and
# check_image (no bag), and test_one_line_exit_2 runs every case through `parproj import`.


def _checked(path: Path, **kw: Any) -> None:
    """The import's reading and checks of one image (no bag is written)."""
    img = load_image(path, "x", **kw)
    check_image(img, (500.0, 1500.0))


def _sign_changing(model: RPCModel) -> tuple[RPCModel, float]:
    """``model`` with a line denominator 1 - L / L_mid (zero at the image's middle longitude)."""
    lon, lat = model.localize([0.0, 499.0], [0.0, 499.0], 1000.0)
    L, _, _ = model.normalize_ground(lon, lat, 1000.0)
    mid = 0.5 * float(L[0] + L[1])
    v = model.as_vector()
    v[12 + 20 : 12 + 40] = 0.0
    v[12 + 20], v[12 + 21] = 1.0, -1.0 / mid
    return RPCModel.from_vector(v), mid


def test_denominator_changing_sign_is_named(tmp_path: Path) -> None:
    """Not "does not converge": which denominator, and where in the image it vanishes."""
    good = crop_rpcs()[0]
    bad, mid = _sign_changing(good)
    img = tmp_path / "den.tif"
    write(img, pixels("left"), bad)
    with pytest.raises(SceneImportError) as err:
        _checked(img)
    msg = str(err.value)
    m = re.search(
        r"RPC line denominator changes sign over the image "
        r"at line (\d+), sample (\d+), h (\d+) m",
        msg,
    )
    assert m is not None and "does not converge" not in msg, msg
    line, sample, h = (float(g) for g in m.groups())
    # the true zero on that line and height: the column whose longitude is L_mid (good model)
    cols = np.arange(0.0, 500.0, 0.25)
    lon, lat = good.localize(np.full(cols.shape, line), cols, np.full(cols.shape, h))
    L, _, _ = good.normalize_ground(lon, lat, h)
    zero = float(cols[np.argmin(np.abs(L - mid))])
    step = 499.0 / 10  # the check's test points: an 11 x 11 grid over the image
    assert abs(sample - zero) <= step, (sample, zero)


def test_denominator_all_zero_is_named(tmp_path: Path) -> None:
    v = crop_rpcs()[0].as_vector()
    v[12 + 60 : 12 + 80] = 0.0  # SAMP_DEN_COEFF
    img = tmp_path / "den0.tif"
    write(img, pixels("left"), RPCModel.from_vector(v))
    with pytest.raises(
        SceneImportError,
        match=r"den0\.tif: RPC sample denominator zero everywhere "
        r"\(its 20 SAMP_DEN_COEFF are all 0\)",
    ):
        _checked(img)


def test_truncated_raster_names_the_cut(tmp_path: Path) -> None:
    """Not rasterio's "Read failed. See previous exception": the size, and GDAL's own words."""
    from parproj_ros.io.raster import read_band

    src = tmp_path / "whole.tif"
    write(src, pixels("left"), crop_rpcs()[0])
    data = src.read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(SceneImportError) as err:
        read_band(cut)
    msg = str(err.value)
    assert msg.startswith(f"{cut}: truncated: the file has {len(data) // 2} bytes, ") and (
        f"image data up to byte {len(data)} (50 % present" in msg
    ), msg
    assert "TIFFReadEncodedStrip" in msg and "See previous exception" not in msg, msg
    # a real Pleiades view whose TIFF directory is at the end (after the pixels), cut at 90 %
    # of its bytes: GDAL cannot even open it; the header's offset of the lost directory is named
    real = Path(__file__).resolve().parents[3] / "shared/data/marseille_triplet/img_01.tif"
    with tifffile.TiffFile(real) as tif:
        ifd = int(tif.pages[0].offset)
    data = real.read_bytes()
    n = len(data) * 9 // 10
    assert ifd > n  # the case: the directory comes after the pixels
    m1 = tmp_path / "m1.tif"
    m1.write_bytes(data[:n])
    with pytest.raises(SceneImportError) as err:
        read_band(m1)
    assert str(err.value).startswith(
        f"{m1}: truncated: the file has {n} bytes, its TIFF header puts its first directory at "
        f"byte {ifd}"
    ), err.value
    # a JPEG cut short: libjpeg's words, and "truncated"
    jpg = tmp_path / "j.jpg"
    with rasterio.open(
        jpg, "w", driver="JPEG", width=500, height=500, count=1, dtype="uint8"
    ) as d:
        d.write((pixels("left") // 16).astype(np.uint8), 1)
    jcut = tmp_path / "jcut.jpg"
    jcut.write_bytes(jpg.read_bytes()[: jpg.stat().st_size // 2])
    with pytest.raises(SceneImportError, match=r"jcut\.jpg: truncated .*Premature end of JPEG"):
        read_band(jcut)


def test_image_too_small(tmp_path: Path) -> None:
    """One row, one column: the image's size and the minimum, not an RPC problem."""
    import inspect

    from parproj_ros.imaging.matching import match_normalized
    from parproj_ros.io.scene_import import MIN_IMAGE_SIDE

    sig = inspect.signature(match_normalized).parameters
    assert MIN_IMAGE_SIDE == 2 * (sig["half"].default + sig["search"].default) + 1
    full = pixels("left")
    for name, block in (("row", full[:1]), ("col", full[:, :1]), ("small", full[:26, :40])):
        p = tmp_path / f"{name}.tif"
        write(p, block, crop_rpcs()[0])
        size = f"{block.shape[0]} x {block.shape[1]} px"
        with pytest.raises(
            SceneImportError, match=rf"{name}\.tif: image too small: {size} .*at least 27 x 27"
        ):
            load_image(p, "x")
    ok = tmp_path / "ok.tif"
    write(ok, full[:MIN_IMAGE_SIDE, :MIN_IMAGE_SIDE], crop_rpcs()[0])
    assert load_image(ok, "x").lines == MIN_IMAGE_SIDE


#: Image formats and whether GDAL (3.10) reads (.RPB, _RPC.TXT) sidecars beside them.
SIDECAR_CASES = {
    "GTiff": "tif", "PNG": "png", "JPEG": "jpg", "JP2OpenJPEG": "jp2", "NITF": "ntf",
    "BMP": "bmp", "GIF": "gif", "ENVI": "bin", "HFA": "img",
}  # fmt: skip


def test_sidecar_drivers_match_gdal(tmp_path: Path) -> None:
    """raster.SIDECAR_DRIVERS says for each driver what GDAL itself does with the sidecars."""
    from parproj_ros.io.raster import raster_info, sidecar_read

    img = (pixels("left")[:64, :64] // 16).astype(np.uint8)
    for driver, ext in SIDECAR_CASES.items():
        for suffix in (".RPB", "_RPC.TXT"):
            f = tmp_path / f"{driver}{suffix[1:4]}.{ext}"
            with rasterio.open(
                f, "w", driver=driver, width=64, height=64, count=1, dtype="uint8"
            ) as dst:
                dst.write(img, 1)
            side = f.with_suffix(".RPB") if suffix == ".RPB" else f.with_name(f.stem + suffix)
            (rpc.write_rpb if suffix == ".RPB" else rpc.write_rpc_txt)(side, crop_rpcs()[0])
            got = bool(raster_info(f).rpc_metadata)
            assert got == sidecar_read(driver, suffix), (driver, suffix, got)


def test_sidecar_beside_a_format_gdal_ignores(tmp_path: Path) -> None:
    """A PNG / JPEG with a good _RPC.TXT / .RPB: not "bad syntax", but where GDAL reads them."""
    model = crop_rpcs()[0]
    png = tmp_path / "p.png"
    write(png, pixels("left"), None)
    rpc.write_rpc_txt(tmp_path / "p_RPC.TXT", model)
    with pytest.raises(RPCFormatError) as err:
        load_image(png, "x")
    msg = str(err.value)
    assert msg == (
        f"{tmp_path / 'p_RPC.TXT'}: GDAL reads no _RPC.TXT sidecar beside a PNG image (only "
        "beside GeoTIFF, JPEG 2000 and NITF images); pass it explicitly: "
        f"--rpc p.png {tmp_path / 'p_RPC.TXT'}"
    ), msg
    jpg = tmp_path / "j.jpg"
    with rasterio.open(
        jpg, "w", driver="JPEG", width=500, height=500, count=1, dtype="uint8"
    ) as d:
        d.write((pixels("left") // 16).astype(np.uint8), 1)
    rpc.write_rpb(tmp_path / "j.RPB", model)
    with pytest.raises(
        RPCFormatError,
        match=r"no \.RPB sidecar beside a JPEG image \(only beside GeoTIFF and JPEG 2000 "
        r"images\); pass it explicitly: --rpc j\.jpg ",
    ):
        load_image(jpg, "x")
    # the advice works: the same file given with --rpc is read, the footprint that of the TIFF
    img = load_image(png, "x", rpc_path=tmp_path / "p_RPC.TXT")
    ref = tmp_path / "ref.tif"
    write(ref, pixels("left"), model)
    a = check_image(img, (500.0, 1500.0))["footprint_lon_lat"]
    b = check_image(load_image(ref, "x"), (500.0, 1500.0))["footprint_lon_lat"]
    np.testing.assert_allclose(a, b, atol=1e-9)


def _decimated(model: RPCModel, k: int) -> RPCModel:
    """The RPC of the image reduced k times (k x k pixels -> 1), as GDAL rescales overviews.

    Pixel centre j of the reduced image is at k (j + 0.5) - 0.5 of the full image's grid.
    """
    v = model.as_vector()
    for off, scale in ((2, 7), (3, 8)):  # LINE_OFF, LINE_SCALE; SAMP_OFF, SAMP_SCALE
        v[off] = (v[off] + 0.5) / k - 0.5
        v[scale] = v[scale] / k
    return RPCModel.from_vector(v)


def test_scaled_geotransform_is_refused_with_safe_advice(tmp_path: Path) -> None:
    """A 2 px/px geotransform (a reduced-resolution product): refused; the advice it gives, for
    an RPC fitted to the reduced grid, lands on the full-resolution footprint (and the advice it
    replaced, a bare --crop-origin with the full scene's RPC, would halve it)."""
    from rasterio.transform import Affine

    full = crop_rpcs()[0]
    px = pixels("left")[:500, :500].astype(np.float64)
    small = px.reshape(250, 2, 250, 2).mean(axis=(1, 3)).astype(np.uint16)
    p = tmp_path / "s2.tif"
    write(p, small, _decimated(full, 2), transform=Affine(2.0, 0.0, 0.0, 0.0, 2.0, 0.0))
    with pytest.raises(SceneImportError) as err:
        load_image(p, "x")
    msg = str(err.value)
    assert "pixels of 2 x 2 units (a reduced-resolution product" in msg, msg
    assert "give --crop-origin s2.tif 0 0" in msg and "not a crop offset" in msg, msg
    # following it: the footprint is the full-resolution image's, to a full-resolution pixel
    img = load_image(p, "x", offset=(0.0, 0.0))
    got = np.array(check_image(img, (500.0, 1500.0))["footprint_lon_lat"])
    ref = tmp_path / "full.tif"
    write(ref, pixels("left"), full)
    want = np.array(check_image(load_image(ref, "x"), (500.0, 1500.0))["footprint_lon_lat"])
    deg_per_px = 0.7 / 111_320.0  # Pleiades 0.7 m pixels
    np.testing.assert_allclose(got, want, atol=deg_per_px)
    # the full scene's RPC on the reduced pixels: half the footprint, what the old advice gave
    write(tmp_path / "s2b.tif", small, full)
    wrong = np.array(
        check_image(load_image(tmp_path / "s2b.tif", "x"), (500.0, 1500.0))["footprint_lon_lat"]
    )
    ratio = (wrong[2] - wrong[0]) / (want[2] - want[0])
    assert 0.4 < ratio < 0.6, ratio


def test_one_line_warnings(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Python warnings inside a command: one line each, no ``file.py:123:`` source lines; the
    NotGeoreferencedWarning of images without a geotransform not at all."""
    import logging
    import warnings

    with cli.one_line_warnings("parproj import"):
        warnings.warn("GDAL said\nsomething", RuntimeWarning, stacklevel=1)
        png = tmp_path / "p.png"
        write(png, pixels("left"), None)  # rasterio warns: no geotransform
        with rasterio.open(png) as src:
            src.read(1)
        # GDAL's own warnings reach Python through rasterio's error handler, which logs them
        logging.getLogger("rasterio._env").warning(
            "%s in %s", "CPLE_AppDefined", "TIFFReadDirectory: Unknown field with tag 65000"
        )
    err = capsys.readouterr().err
    assert err == (
        "parproj import: note: GDAL said something\n"
        "parproj import: note: GDAL: TIFFReadDirectory: Unknown field with tag 65000\n"
    ), err
    # the handler goes with the command (rasterio's own NullHandler stays)
    assert [type(h) for h in logging.getLogger("rasterio").handlers] == [logging.NullHandler]


@pytest.mark.ros
@pytest.mark.parametrize(
    "case",
    ["den", "den0", "cut", "row", "col", "png_sidecar", "jpeg_sidecar", "scale2", "complex"],
)
def test_one_line_exit_2(
    case: str, pair: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every case of item 6 through ``parproj import``: exit 2, one line naming file and cause."""
    from rasterio.transform import Affine

    model, right = crop_rpcs()[0], str(pair[1])
    extra: list[str] = []
    if case == "den":
        path = tmp_path / "den.tif"
        write(path, pixels("left"), _sign_changing(model)[0])
        want = r"RPC line denominator changes sign over the image at line \d+, sample \d+"
    elif case == "den0":
        v = model.as_vector()
        v[12 + 20 : 12 + 40] = 0.0
        path = tmp_path / "den0.tif"
        write(path, pixels("left"), RPCModel.from_vector(v))
        want = r"RPC line denominator zero everywhere"
    elif case == "cut":
        path = tmp_path / "cut.tif"
        data = pair[0].read_bytes()
        path.write_bytes(data[: len(data) // 2])
        want = r"truncated: the file has \d+ bytes.*GDAL cannot read band 1: .*Read error"
    elif case in ("row", "col"):
        path = tmp_path / f"{case}.tif"
        write(path, pixels("left")[:1] if case == "row" else pixels("left")[:, :1], model)
        want = r"image too small: (1 x 500|500 x 1) px \(rows x columns\), at least 27 x 27"
    elif case == "png_sidecar":
        path = tmp_path / "p.png"
        write(path, pixels("left"), None)
        rpc.write_rpc_txt(tmp_path / "p_RPC.TXT", model)
        want = (
            r"no usable RPC: .*p_RPC\.TXT: GDAL reads no _RPC\.TXT sidecar "
            r"beside a PNG image .*--rpc p\.png "
        )
    elif case == "jpeg_sidecar":
        path = tmp_path / "j.jpg"
        with rasterio.open(
            path, "w", driver="JPEG", width=500, height=500, count=1, dtype="uint8"
        ) as d:
            d.write((pixels("left") // 16).astype(np.uint8), 1)
        rpc.write_rpb(tmp_path / "j.RPB", model)
        want = r"j\.RPB: GDAL reads no \.RPB sidecar beside a JPEG image"
    elif case == "complex":  # before: imported as the real part, with numpy's ComplexWarning
        path = tmp_path / "c.tif"
        write(path, pixels("left").astype(np.complex64), model)
        want = r"complex pixels \(complex64: a SAR or Fourier product\).*give its amplitude"
    else:
        path = tmp_path / "s2.tif"
        write(path, pixels("left"), model, transform=Affine(2.0, 0.0, 0.0, 0.0, 2.0, 0.0))
        want = r"pixels of 2 x 2 units .*give --crop-origin s2\.tif 0 0"
    argv = ["import", str(path), right, "-o", str(tmp_path / "o"), "--heights", "500", "1500"]
    assert exit_code([*argv, *extra]) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"parproj import: {path}: "), err
    assert re.search(want, lines[0]), err
    assert not (tmp_path / "o").exists()


@pytest.mark.ros
@pytest.mark.parametrize("dtype", ["float64", "int8", "float32"])
def test_pixel_types_that_differ_are_named_as_the_files_hold_them(
    dtype: str, pair: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A uint16 left image and a float64 / int8 / float32 right one: each file's own type.

    Before: "pixel types differ: left.tif uint16, f.tif float32" for a float64 or int8 file
    (the type it would be imported as), and no advice.
    """
    model = crop_rpcs()[1]
    path = tmp_path / f"{dtype}.tif"
    write(path, (pixels("right") // 16).astype(dtype), model)
    argv = [
        "import",
        str(pair[0]),
        str(path),
        "-o",
        str(tmp_path / "o"),
        "--heights",
        "500",
        "1500",
    ]
    assert exit_code(argv) == 2
    (line,) = capsys.readouterr().err.splitlines()
    shown = dtype if dtype == "float32" else f"{dtype} (as float32)"
    assert line == (
        f"parproj import: pixel types differ: {pair[0]} uint16, {path} {shown}: one pair is "
        "matched on one radiometric scale; convert one image to the other's type first (e.g. "
        "gdal_translate -ot UInt16 -scale ...)"
    ), line


# ---- advice names only options that exist ------------------------------------------------------

#: Options of other programs that messages may name: ROS 2's (``ros2 run ... --ros-args
#: --params-file FILE``), which parproj_node takes from the ROS 2 command line.
FOREIGN_OPTIONS = {"--ros-args": "ROS 2", "--params-file": "ROS 2"}
#: rosbags-convert's, in the foreign-bag advice of parproj_ros/ros/bag.py.
FOREIGN_OPTIONS |= dict.fromkeys(("--src", "--dst", "--dst-storage"), "rosbags-convert")
_OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9]*(?:-[a-z0-9]+)*")


def _parser_options(parser: Any) -> set[str]:
    """Every option string of an argparse parser and of its sub-command parsers."""
    import argparse

    out: set[str] = set()
    for action in parser._actions:
        out.update(action.option_strings)
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                out |= _parser_options(sub)
    return out


def _strings(tree: Any) -> list[tuple[int, str]]:
    """(line, text) of every string in a module; f-strings with their fields as NUL."""
    import ast

    inside: set[int] = set()
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            parts = []
            for v in node.values:
                inside.add(id(v))
                is_text = isinstance(v, ast.Constant) and isinstance(v.value, str)
                parts.append(v.value if is_text else "\0")  # type: ignore[union-attr]
            out.append((node.lineno, "".join(parts)))
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            if id(node) not in inside:
                out.append((node.lineno, node.value))
    return out


def test_advice_names_only_existing_options() -> None:
    """Every ``--option`` a string in parproj_ros/ names (messages, advice, help, docstrings) is
    an option of a parser the package builds: ``parproj`` and its sub-commands (as
    cli.build_parser makes them, ``--no-<name>`` included) and the ``python -m`` tools
    (any ``add_argument("--...")`` in the package), or ROS 2's own (:data:`FOREIGN_OPTIONS`).
    An f-string's ``--no-{name}`` is a family, not an option, and is skipped."""
    import ast

    from parproj_ros.apps import cli as cli_module

    root = Path(cli_module.__file__).resolve().parents[1]
    known = _parser_options(cli_module.build_parser()) | set(FOREIGN_OPTIONS)
    trees = {f: ast.parse(f.read_text(), str(f)) for f in sorted(root.rglob("*.py"))}
    for tree in trees.values():  # the other parsers (python -m parproj_ros.core.config, ...)
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument":
                known |= {
                    a.value
                    for a in node.args
                    if isinstance(a, ast.Constant) and str(a.value).startswith("--")
                }
    unknown: list[str] = []
    mentions = 0
    for f, tree in trees.items():
        for line, text in _strings(tree):
            for m in _OPTION.finditer(text):
                if text[m.end() : m.end() + 1] in ("\0", "-"):  # --no-{name}, --rpc-*
                    continue
                mentions += 1
                if m.group() not in known:
                    unknown.append(f"{f.relative_to(root.parent)}:{line}: {m.group()}")
    assert mentions > 100  # the scan sees the messages (227 mentions of 66 options when written)
    assert not unknown, unknown


@pytest.mark.ros
def test_real_import_prints_no_warning_lines(pair: tuple[Path, Path], tmp_path: Path) -> None:
    """``parproj import`` as a process, on a PNG (no geotransform: rasterio warns on every open)
    with its RPC given as the sidecar message advises: exit 0 and nothing on stderr (it used to
    print rasterio's NotGeoreferencedWarning with its source line at each opening)."""
    import subprocess
    import sys

    png = tmp_path / "p.png"
    write(png, pixels("left"), None)
    rpc.write_rpc_txt(tmp_path / "p_RPC.TXT", crop_rpcs()[0])
    argv = [sys.executable, "-m", "parproj_ros.apps.cli", "import", str(png), str(pair[1])]
    argv += ["-o", str(tmp_path / "o"), "--heights", "500", "1500"]
    argv += ["--rpc", "p.png", str(tmp_path / "p_RPC.TXT")]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stderr == "", done.stderr
    assert (tmp_path / "o" / "metadata.yaml").is_file()


def test_segments_names_a_vanishing_denominator(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``parproj segments`` on a full-scene RPC whose line denominator vanishes in the scene:
    exit 2 naming the file and the denominator (it used to cut the strip anyway, 6690 px model
    error, exit 1); an all-zero one used to be '1 of 1 points did not converge'."""
    full = rpc.read_rpc(DATA / "left_image.geom")
    right = str(DATA / "right_image.geom")
    v = full.as_vector()
    v[12 + 20 : 12 + 40] = 0.0
    v[12 + 20], v[12 + 21] = 1.0, -1.0 / 0.05  # zero at L = 0.05, inside the scene
    rpc.write_geom(tmp_path / "den.geom", RPCModel.from_vector(v))
    v[12 + 20 : 12 + 40] = 0.0
    rpc.write_geom(tmp_path / "den0.geom", RPCModel.from_vector(v))
    for name, want in (
        ("den", r"RPC line denominator changes sign over the scene at line \d+, sample \d+"),
        ("den0", r"RPC line denominator zero everywhere"),
    ):
        capsys.readouterr()
        assert exit_code(["segments", str(tmp_path / f"{name}.geom"), right]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"parproj segments: {tmp_path / name}.geom: "), err
        assert len(err.splitlines()) == 1 and re.search(want, err), err
