"""``parproj import``: bad inputs each get a clear error naming the file (RELIABILITY.md).

Inputs are made in tmp_path from the Ventoux pair (tests/data/ventoux), through GDAL
(rasterio) as the importer reads them; the helpers are those of tests/eval/test_conventions.py.
"""

from __future__ import annotations

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
from parproj_ros.io.scene_import import SceneImportError
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
    with pytest.raises(SceneImportError, match=r"cut\.tif: (GDAL cannot read|not a raster)"):
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
    with pytest.raises(SceneImportError, match=r"den\.tif: .*(denominator|not converge)"):
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
