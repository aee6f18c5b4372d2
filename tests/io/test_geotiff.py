"""GeoTIFF export (parproj_ros/io/geotiff.py): CRS choice, exact reprojection, nodata, dtypes,
Cloud Optimized GeoTIFF layout, 3-D CRS (ellipsoidal heights) and geoid heights.

Synthetic DSMs on a local tangent plane at the Ventoux origin (lat 44.17, lon 5.27, h 600 m),
8 km x 8 km, 10 m cells: a plane, a tilted plane and a Gaussian bump. Each file is read back
with rasterio (its CRS and transform, not what the writer returned); every valid cell's map
centre and written ellipsoidal height go back through pyproj (map -> lon, lat) and the tangent
plane (-> ENU x, y, z), independently of the writer's iteration, and must lie on the synthetic
surface. Tolerance: the bilinear interpolation error of the surface, (cell^2 / 8) (max |Z_xx| +
max |Z_yy|) (0 for the planes, 6.9 mm for the bump), plus float32 rounding (half an ulp of the
DSM's Z and of the written h: 3e-5 + 6e-5 m here) and 2e-5 m for the iteration. Horizontally:
an ortho-image whose values are the ENU x (or y) of its cells (bilinear is exact on it) must
give, in each output cell, the x (y) of the back-transformed point, to 1 mm (float32 half-ulp
at 4 km is 2.4e-4 m).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
import tifffile
from pyproj import CRS, Transformer
from rio_cogeo.cogeo import cog_validate

from parproj_ros.geometry.geodesy import LocalTangentPlane
from parproj_ros.imaging.heights import DsmGrid
from parproj_ros.io.geotiff import (
    WGS84_3D,
    crs_for_frame,
    export_grid,
    file_crs,
    utm_zone,
    write_dsm_geotiff,
    write_like,
    write_ortho_geotiff,
    write_plain_tiff,
)
from parproj_ros.io.scene_import import frame_id_of

FloatArray = np.ndarray[Any, np.dtype[np.float64]]
Surface = Callable[[FloatArray, FloatArray], FloatArray]

VENTOUX = LocalTangentPlane(44.17, 5.27, 600.0)
FID = frame_id_of(VENTOUX)
GRID = DsmGrid.covering(-4000.0, 4000.0, -4000.0, 4000.0, 10.0)  # 801 x 801 cells
BUMP_A, BUMP_S = 400.0, 1200.0  # bump height and width (sigma), metres
#: Bilinear error bound of the bump: (cell^2 / 8) * 2 * max |Z_xx| with max |Z_xx| = A / sigma^2.
BUMP_BOUND = GRID.cell**2 / 8.0 * 2.0 * BUMP_A / BUMP_S**2
ITERATION_TOL = 2e-5  # m: the writer's fixed point stops below 1e-5 m


def float_tol(z: Any, h: Any) -> float:
    """Float32 rounding of the DSM (Z) and of the written heights (h): half an ulp of each."""
    ulp = np.spacing(np.float32(np.nanmax(np.abs(z)))) + np.spacing(np.float32(np.nanmax(h)))
    return float(ulp) / 2.0 + ITERATION_TOL


SURFACES: dict[str, tuple[Surface, float]] = {
    "plane": (lambda x, y: np.full(np.shape(x), 150.0), 0.0),
    "tilted": (lambda x, y: 150.0 + 0.08 * x - 0.05 * y, 0.0),
    "bump": (
        lambda x, y: (
            150.0 + BUMP_A * np.exp(-((x - 300.0) ** 2 + (y + 500.0) ** 2) / (2 * BUMP_S**2))
        ),
        BUMP_BOUND,
    ),
}


def dsm_of(surface: Surface, grid: DsmGrid = GRID) -> np.ndarray[Any, np.dtype[np.float32]]:
    x, y = grid.centres()
    return surface(x, y).astype(np.float32)


def read(path: Path) -> tuple[np.ndarray[Any, Any], CRS | None, Any, dict[str, str]]:
    with rasterio.open(path) as src:
        crs = None if src.crs is None else CRS.from_wkt(src.crs.to_wkt())
        return src.read(1), crs, src.transform, dict(src.tags())


def back_to_enu(
    path: Path, frame: LocalTangentPlane = VENTOUX
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, np.ndarray[Any, Any]]:
    """Every valid cell of a DSM GeoTIFF -> (x, y, z) ENU, its height h; and the valid mask."""
    h, crs, t, _ = read(path)
    assert crs is not None
    ok = np.isfinite(h)
    rows, cols = np.nonzero(ok)
    e = t.c + (cols + 0.5) * t.a
    n = t.f + (rows + 0.5) * t.e
    to_lonlat = Transformer.from_crs(crs.to_2d(), CRS.from_epsg(4326), always_xy=True)
    lon, lat = to_lonlat.transform(e, n)
    hh = h[ok].astype(float)
    x, y, z = frame.to_local(lon, lat, hh)
    return x, y, z, hh, ok


def exact_positions(path: Path, surface: Surface, frame: LocalTangentPlane = VENTOUX) -> Any:
    """ENU (x, y) of every cell of a GeoTIFF on the true surface (the test's own iteration)."""
    _, crs, t, _ = read(path)
    with rasterio.open(path) as src:
        rows, cols = np.mgrid[0 : src.height, 0 : src.width]
    e = t.c + (cols + 0.5) * t.a
    n = t.f + (rows + 0.5) * t.e
    to_lonlat = Transformer.from_crs(crs.to_2d(), CRS.from_epsg(4326), always_xy=True)
    lon, lat = to_lonlat.transform(e, n)
    h = np.full(e.shape, frame.h0)
    for _ in range(6):
        x, y, z = frame.to_local(lon, lat, h)
        h = h + surface(x, y) - z
    x, y, _ = frame.to_local(lon, lat, h)
    return x, y


@pytest.mark.parametrize("target", ["utm", "local"])
@pytest.mark.parametrize("name", list(SURFACES))
def test_written_heights_lie_on_the_surface(tmp_path: Path, name: str, target: Any) -> None:
    surface, bound = SURFACES[name]
    path = tmp_path / "dsm.tif"
    crs, out = write_dsm_geotiff(path, dsm_of(surface), GRID, FID, target=target)
    h, in_file, t, tags = read(path)
    assert in_file is not None and in_file.is_projected
    if target == "utm":
        # 3-D: UTM 31N with an ellipsoidal height axis (GeoTIFF 1.1 VerticalGeoKey 4979)
        assert in_file.to_2d().to_epsg() == 32631
        assert [a.name for a in in_file.axis_info] == ["Easting", "Northing", "Ellipsoidal height"]
        assert in_file.equals(file_crs(FID))
    else:
        # GDAL reads a user-defined projection with VerticalGeoKey 4979 as 2-D; the name says it
        assert "ellipsoidal height" in in_file.name and in_file.ellipsoid == crs.ellipsoid
        p = {q.name: q.value for q in in_file.coordinate_operation.params}
        assert p["Latitude of natural origin"] == pytest.approx(44.17, abs=1e-9)
        assert p["Longitude of natural origin"] == pytest.approx(5.27, abs=1e-9)
    assert (t.a, -t.e) == (GRID.cell, GRID.cell) and h.dtype == np.float32
    assert h.shape == (out.height, out.width)
    assert "ellipsoidal" in tags["TIFFTAG_IMAGEDESCRIPTION"] or "WGS" in tags["PARPROJ_CRS"]

    x, y, z, hh, ok = back_to_enu(path)
    err = np.abs(z - surface(x, y))
    tol = bound + float_tol(dsm_of(surface), hh)
    assert bound < 0.01 and err.max() <= tol, (name, target, err.max(), tol)
    # the tangent plane leaves the ellipsoid by d^2 / 2R: h - h0 - Z follows it (2.5 m at the
    # corners), so the test would see heights written as h0 + Z
    d2 = x**2 + y**2
    drop = hh - VENTOUX.h0 - surface(x, y)
    assert drop.max() > 2.0
    assert np.abs(drop - d2 / (2 * 6_371_000.0)).max() < 0.02

    # complete: every output cell whose surface point lies one cell inside the DSM has a height
    xe, ye = exact_positions(path, surface)
    lo_x, hi_x = GRID.x0 + GRID.cell, GRID.x0 + (GRID.width - 2) * GRID.cell
    hi_y, lo_y = GRID.y0 - GRID.cell, GRID.y0 - (GRID.height - 2) * GRID.cell
    inner = (xe >= lo_x) & (xe <= hi_x) & (ye >= lo_y) & (ye <= hi_y)
    assert ok[inner].all()
    assert not ok[(xe < GRID.x0 - 1e-6) | (ye > GRID.y0 + 1e-6)].any()


@pytest.mark.parametrize("target", ["utm", "local"])
def test_ortho_shares_the_grid_and_is_placed_to_a_millimetre(tmp_path: Path, target: Any) -> None:
    surface = SURFACES["bump"][0]
    z = dsm_of(surface)
    gx, gy = GRID.centres()
    dsm_path = tmp_path / "dsm.tif"
    _, dsm_grid = write_dsm_geotiff(dsm_path, z, GRID, FID, target=target)
    x, y, _, _, ok = back_to_enu(dsm_path)
    for coord, truth in ((gx, x), (gy, y)):
        path = tmp_path / "ortho.tif"
        _, grid = write_ortho_geotiff(
            path, coord.astype(np.float32), GRID, FID, heights=z, target=target, nodata=np.nan
        )
        img, _, t, _ = read(path)
        assert grid == dsm_grid and img.dtype == np.float32
        with rasterio.open(dsm_path) as src:
            assert t == src.transform
        assert (np.isfinite(img) == ok).all()
        err = np.abs(img[ok] - truth)
        assert err.max() < 1e-3, err.max()


@pytest.mark.parametrize("frame", [FID, "map"])
def test_ortho_beside_the_dsm_equals_the_ortho_alone(tmp_path: Path, frame: str) -> None:
    """write_dsm_geotiff(..., ortho=Ortho(...)) writes the DSM and the ortho-image of
    write_dsm_geotiff and write_ortho_geotiff, to the bit, from one reprojection."""
    from parproj_ros.io.geotiff import Ortho

    z = dsm_of(SURFACES["bump"][0])
    z[300:320, 400:430] = np.nan  # a hole: the ortho's nodata follows it
    gx, _ = GRID.centres()
    img = (np.abs(gx) * 7 % 4000 + 1).astype(np.uint16)
    write_dsm_geotiff(tmp_path / "alone_dsm.tif", z, GRID, frame)
    write_ortho_geotiff(tmp_path / "alone_ortho.tif", img, GRID, frame, heights=z)
    write_dsm_geotiff(
        tmp_path / "both_dsm.tif", z, GRID, frame, ortho=Ortho(tmp_path / "both_ortho.tif", img)
    )
    for kind in ("dsm", "ortho"):
        with (
            rasterio.open(tmp_path / f"alone_{kind}.tif") as a,
            rasterio.open(tmp_path / f"both_{kind}.tif") as b,
        ):
            assert a.transform == b.transform and a.crs == b.crs and a.dtypes == b.dtypes
            assert a.tags() == b.tags() and a.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
            assert np.array_equal(a.read(1), b.read(1), equal_nan=True)
    assert not list(tmp_path.glob(".*partial*"))  # nothing left behind


def test_ortho_dtypes_and_nodata_follow_the_dsm_holes(tmp_path: Path) -> None:
    """A hole in the DSM: NaN exactly where a weighed neighbour is in it (less than one cell
    around it), the ortho nodata exactly there; uint8, uint16 and float32 kept."""
    surface = SURFACES["tilted"][0]
    z = dsm_of(surface)
    r0, r1, c0, c1 = 300, 340, 400, 460
    z[r0:r1, c0:c1] = np.nan
    path = tmp_path / "dsm.tif"
    write_dsm_geotiff(path, z, GRID, FID)
    h, _, _, _ = read(path)
    xe, ye = exact_positions(path, surface)
    # the hole's cell centres span [hx0, hx1] x [hy0, hy1]; NaN within one cell of that box
    hx0, hx1 = GRID.x0 + c0 * GRID.cell, GRID.x0 + (c1 - 1) * GRID.cell
    hy1, hy0 = GRID.y0 - r0 * GRID.cell, GRID.y0 - (r1 - 1) * GRID.cell
    dist = np.maximum(
        np.maximum(hx0 - xe, xe - hx1).clip(0), np.maximum(hy0 - ye, ye - hy1).clip(0)
    )
    inner = (
        (xe >= GRID.x0 + GRID.cell)
        & (xe <= GRID.x0 + (GRID.width - 2) * GRID.cell)
        & (ye <= GRID.y0 - GRID.cell)
        & (ye >= GRID.y0 - (GRID.height - 2) * GRID.cell)
    )
    nan = ~np.isfinite(h)
    assert nan[inner & (dist < GRID.cell - 1e-3)].all()
    assert not nan[inner & (dist > GRID.cell + 1e-3)].any()
    assert nan[inner].sum() < (r1 - r0 + 2) * (c1 - c0 + 2)

    rng = np.random.default_rng(5)
    for dtype, nodata in ((np.uint8, 0), (np.uint16, 0), (np.float32, -9999.0)):
        info = np.iinfo(dtype) if np.dtype(dtype).kind == "u" else None
        top = 255 if info is None else int(info.max)
        img = rng.integers(1, top, size=z.shape).astype(dtype)
        img[r0:r1, c0:c1] = nodata  # as orthoimage() leaves cells without height
        opath = tmp_path / f"ortho_{np.dtype(dtype).name}.tif"
        write_ortho_geotiff(opath, img, GRID, FID, heights=z, nodata=nodata)
        o, _, _, _ = read(opath)
        with rasterio.open(opath) as src:
            assert src.nodata == nodata
        assert o.dtype == np.dtype(dtype)
        assert ((o == nodata) == nan).all()
        assert o[~nan].min() >= 1 and o[~nan].max() <= top


def test_map_frame_is_written_as_it_is(tmp_path: Path) -> None:
    grid = DsmGrid(-35.0, 120.0, 0.5, 70, 40)
    z = dsm_of(SURFACES["tilted"][0], grid)
    z[3:7, 10:12] = np.nan
    eng = crs_for_frame("map")
    assert eng.is_engineering and [a.unit_name for a in eng.axis_info] == ["metre", "metre"]
    crs, out = write_dsm_geotiff(tmp_path / "dsm.tif", z, grid, "map")
    assert crs.equals(eng) and out == grid
    h, in_file, t, tags = read(tmp_path / "dsm.tif")
    # a local engineering CRS (GDAL: LOCAL_CS), metres, named after the frame; never none
    assert in_file is not None and in_file.is_engineering and "map" in in_file.name
    assert [a.direction for a in in_file.axis_info] == ["east", "north"]
    assert tuple(t)[:6] == (0.5, 0.0, -35.25, 0.0, -0.5, 120.25)
    np.testing.assert_array_equal(h, z)  # NaN where NaN, the rest bit for bit
    assert "engineering" in tags["TIFFTAG_IMAGEDESCRIPTION"]
    assert tags["PARPROJ_SOURCE_FRAME"] == "map"
    img = np.arange(70 * 40, dtype=np.uint16).reshape(40, 70)
    write_ortho_geotiff(tmp_path / "ortho.tif", img, grid, "map")
    o, _, t2, _ = read(tmp_path / "ortho.tif")
    assert o.dtype == np.uint16 and t2 == t
    np.testing.assert_array_equal(o, img)
    with pytest.raises(ValueError, match="local frame"):
        write_dsm_geotiff(tmp_path / "x.tif", z, grid, "map", resolution=1.0)


def test_utm_zone_and_hemisphere() -> None:
    assert utm_zone(5.27, 44.17) == (31, True)
    assert utm_zone(179.99, 10.0) == (60, True) and utm_zone(-180.0, 10.0) == (1, True)
    assert utm_zone(5.0, 60.0) == (32, True)  # 32V, south-west Norway
    assert utm_zone(15.0, 78.0) == (33, True)  # Svalbard
    south = LocalTangentPlane(-33.92, 18.42, 20.0)  # Cape Town
    crs = crs_for_frame(frame_id_of(south))
    assert crs is not None and crs.to_epsg() == 32734
    assert crs_for_frame(FID) == CRS.from_epsg(32631)
    with pytest.raises(ValueError, match="UTM"):
        crs_for_frame(frame_id_of(LocalTangentPlane(85.0, 10.0, 0.0)))
    polar = crs_for_frame(frame_id_of(LocalTangentPlane(85.0, 10.0, 0.0)), target="local")
    assert polar is not None and polar.is_projected
    with pytest.raises(ValueError):
        crs_for_frame("enu_wgs84:lat=nonsense")
    with pytest.raises(ValueError, match="target"):
        crs_for_frame(FID, target="mercator")  # type: ignore[arg-type]


def test_southern_origin_round_trip(tmp_path: Path) -> None:
    south = LocalTangentPlane(-33.92, 18.42, 20.0)
    grid = DsmGrid.covering(-2500.0, 2500.0, -2500.0, 2500.0, 25.0)
    surface = SURFACES["tilted"][0]
    crs, _ = write_dsm_geotiff(tmp_path / "s.tif", dsm_of(surface, grid), grid, frame_id_of(south))
    assert crs.to_2d().to_epsg() == 32734 and len(crs.axis_info) == 3
    x, y, z, hh, _ = back_to_enu(tmp_path / "s.tif", south)
    tol = float_tol(dsm_of(surface, grid), hh)
    assert x.size > 30_000 and np.abs(z - surface(x, y)).max() <= tol


def test_resolution_and_errors(tmp_path: Path) -> None:
    z = dsm_of(SURFACES["plane"][0])
    crs, grid = export_grid(GRID, FID, z, resolution=30.0)
    assert crs is not None and grid.cell == 30.0 and math.isclose(grid.x0 % 30.0, 0.0)
    with pytest.raises(ValueError, match="heights"):
        write_ortho_geotiff(tmp_path / "o.tif", np.zeros(z.shape, np.uint8), GRID, FID)
    with pytest.raises(ValueError, match="shape"):
        write_dsm_geotiff(tmp_path / "d.tif", z[:-1], GRID, FID)
    assert not list(tmp_path.iterdir())


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_plain_tiff_has_no_georeference(tmp_path: Path) -> None:
    d = np.linspace(-3.5, 12.25, 300 * 200, dtype=np.float32).reshape(300, 200)
    d[5, 7] = np.nan
    write_plain_tiff(tmp_path / "disp.tif", d, nodata=np.nan, description="disparity, px")
    a, crs, t, tags = read(tmp_path / "disp.tif")
    assert crs is None and t.is_identity and a.dtype == np.float32
    np.testing.assert_array_equal(a, d)
    assert tags["TIFFTAG_IMAGEDESCRIPTION"] == "disparity, px"


def geokeys(path: Path) -> dict[int, int]:
    """The GeoTIFF keys stored in the GeoKeyDirectory itself (key -> value)."""
    with tifffile.TiffFile(path) as tf:
        v = tf.pages.first.tags[34735].value
    return {v[4 + 4 * k]: v[7 + 4 * k] for k in range(v[3]) if v[5 + 4 * k] == 0}


@pytest.mark.parametrize("kind", ["dsm", "ortho", "map"])
def test_files_are_cloud_optimized(tmp_path: Path, kind: str) -> None:
    """GDAL's own COG check (IMAGE_STRUCTURE LAYOUT=COG, which its COG driver writes and its
    reader reports only for a file whose layout is a COG), rio-cogeo's cog_validate (GDAL's
    validate_cloud_optimized_geotiff.py: IFDs first, tiles in order), 256 x 256 tiles,
    deflate, overviews down to one tile (about 805 cells: levels 2 and 4), the CRS in the file
    (no .aux.xml)."""
    z = dsm_of(SURFACES["bump"][0])
    path = tmp_path / f"{kind}.tif"
    if kind == "ortho":
        img = (np.arange(z.size) % 251 + 1).astype(np.uint8).reshape(z.shape)
        write_ortho_geotiff(path, img, GRID, FID, heights=z)
    else:
        write_dsm_geotiff(path, z, GRID, "map" if kind == "map" else FID)
    with rasterio.open(path) as src:
        structure = src.tags(ns="IMAGE_STRUCTURE")
        assert structure["LAYOUT"] == "COG" and structure["COMPRESSION"] == "DEFLATE"
        assert src.block_shapes == [(256, 256)]
        levels, side = [], max(src.width, src.height)
        while side > 256:  # GDAL: halve until the smallest level fits in one tile
            side = -(-side // 2)
            levels.append(2 * (levels[-1] if levels else 1))
        assert src.overviews(1) == levels and len(levels) == 2
        over = src.read(1, out_shape=(1, src.height // 2, src.width // 2))
        assert over.dtype == src.dtypes[0] and np.isfinite(over.astype(float)).mean() > 0.9
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]
    assert cog_validate(path, quiet=True) == (True, [], [])  # GDAL's validator, ported
    keys = geokeys(path)
    if kind == "map":
        assert 1024 not in keys and keys[3076] == 9001  # no model type (LOCAL_CS), metres
    else:
        assert keys[3072] == 32631 and keys[4096] == WGS84_3D  # UTM 31N + ellipsoidal heights


def test_geoid_heights_and_compound_crs(tmp_path: Path) -> None:
    """With a geoid (here N = 49.35 m + 1e-5 m per metre east, EGM96 height): the heights
    written are the ellipsoidal ones minus N at each cell's lon, lat (to float32 rounding), and
    the file's CRS is compound UTM 31N + EPSG:5773."""
    z = dsm_of(SURFACES["tilted"][0])

    def undulation(lon: FloatArray, lat: FloatArray) -> FloatArray:
        return 49.35 + 1e-5 * (np.asarray(lon) - 5.27) * 80_000.0

    write_dsm_geotiff(tmp_path / "h.tif", z, GRID, FID)
    crs, _ = write_dsm_geotiff(tmp_path / "g.tif", z, GRID, FID, geoid=(undulation, 5773))
    h, _, t, _ = read(tmp_path / "h.tif")
    g, in_file, t2, tags = read(tmp_path / "g.tif")
    assert t == t2 and crs.is_compound and in_file is not None and in_file.is_compound
    horizontal, vertical = in_file.sub_crs_list
    assert horizontal.to_epsg() == 32631 and vertical.to_epsg() == 5773
    rows, cols = np.mgrid[0 : h.shape[0], 0 : h.shape[1]]
    to_lonlat = Transformer.from_crs(horizontal, CRS.from_epsg(4326), always_xy=True)
    lon, lat = to_lonlat.transform(t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e)
    ok = np.isfinite(h)
    assert (np.isfinite(g) == ok).all() and ok.mean() > 0.9
    err = np.abs(g[ok] - (h[ok].astype(float) - undulation(lon[ok], lat[ok])))
    assert err.max() <= float(np.spacing(np.float32(np.nanmax(h)))), err.max()
    assert "EGM96" in tags["PARPROJ_CRS"]
    with pytest.raises(ValueError, match="geodetic anchor"):
        write_dsm_geotiff(tmp_path / "m.tif", z, GRID, "map", geoid=(undulation, 5773))


def test_layer_written_like_a_dsm(tmp_path: Path) -> None:
    """write_like: a uint8 layer on a DSM's grid and 3-D CRS, as a COG, the key in the file."""
    grid = DsmGrid.covering(-600.0, 600.0, -500.0, 500.0, 2.0)
    write_dsm_geotiff(tmp_path / "dsm.tif", dsm_of(SURFACES["plane"][0], grid), grid, FID)
    with rasterio.open(tmp_path / "dsm.tif") as src:
        shape, t = (src.height, src.width), src.transform
    count = (np.arange(shape[0] * shape[1]) % 4).astype(np.uint8).reshape(shape)
    write_like(tmp_path / "count.tif", tmp_path / "dsm.tif", count, nodata=0, description="n")
    c, crs, t2, _ = read(tmp_path / "count.tif")
    np.testing.assert_array_equal(c, count)
    assert t2 == t and crs is not None and crs.equals(read(tmp_path / "dsm.tif")[1])
    assert geokeys(tmp_path / "count.tif")[4096] == WGS84_3D
    assert sorted(p.name for p in tmp_path.iterdir()) == ["count.tif", "dsm.tif"]
    with pytest.raises(ValueError, match="integer or float array like"):
        write_like(tmp_path / "x.tif", tmp_path / "dsm.tif", count[:-1])


def test_an_interrupted_write_gives_back_what_c_code_said(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """fd 2 is captured while a GeoTIFF is written; a KeyboardInterrupt does not lose it.

    Before (review 2026-12-02) only an ``Exception`` gave the captured text back: what C code
    had written to fd 2 before a Ctrl-C was dropped with the capture. Nothing is left behind.
    """
    import os

    from parproj_ros.imaging.heights import DsmGrid
    from parproj_ros.io import geotiff

    grid = DsmGrid(0.25, 9.75, 0.5, 20, 20)
    crs = geotiff.crs_for_frame("map")
    profile = geotiff._profile(grid, np.dtype(np.float32), crs, -9999.0)
    with pytest.raises(KeyboardInterrupt), geotiff._cog(tmp_path / "x.tif", profile, crs):
        os.write(2, b"ERROR 1: a C library's own line\n")
        raise KeyboardInterrupt
    assert "a C library's own line" in capfd.readouterr().err
    assert not list(tmp_path.iterdir())
