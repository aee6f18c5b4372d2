"""RPC models: every format, pixel conventions, ground <-> image, frames, virtual GCP (paper 2).

Data: tests/data/ventoux (the Mont Ventoux Pleiades pair's full-scene RPCs, see its README).
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from testkit.paths import DATA
from testkit.rasters import to_rasterio as _gdal_rpc

from parproj_ros import rpc
from parproj_ros.geometry.geodesy import WGS84_A, WGS84_F
from parproj_ros.io.dem import grid_height, srtm_height
from parproj_ros.rpc import RPCModel

LEFT_GEOM = DATA / "left_image.geom"
RIGHT_GEOM = DATA / "right_image.geom"
DIMAP = DATA / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML"
DEM_CROP = DATA / "srtm_N44E005_crop.txt"
#: (lines, samples) of the full scenes (number_lines / number_samples of the .geom files).
LEFT_SIZE = (41801, 39182)
RIGHT_SIZE = (40845, 38987)
#: Centre of the 500 x 500 px crop of the left scene at (line 5000, sample 5000)
#: (shared/data/ventoux/README.md).
CROP_CENTRE = 5249.5
#: Pleiades PAN: c = 12.905 m, 13 um detectors; principal point at the line centre.
C_PHR = 12.905
PIXEL_PHR = 13e-6
PP_PHR = (LEFT_SIZE[1] - 1) / 2.0


@pytest.fixture(scope="module")
def left() -> RPCModel:
    return rpc.read_rpc(LEFT_GEOM)


@pytest.fixture(scope="module")
def right() -> RPCModel:
    return rpc.read_rpc(RIGHT_GEOM)


@pytest.fixture(scope="module")
def dem() -> rpc.HeightFunction:
    """The SRTM crop (geoid heights used as they are: sigma0 does not depend on a 50 m shift)."""
    return grid_height(
        np.loadtxt(DEM_CROP), lat_max=45 - 927 / 1200, lon_min=5 + 206 / 1200, step_deg=1 / 1200
    )


def _ground_grid(mdl: RPCModel, n: int = 9, limit: float = 1.0) -> tuple[np.ndarray, ...]:
    """Ground points on an n^3 grid of the normalized domain [-limit, limit]^3."""
    u = np.linspace(-limit, limit, n)
    L, P, H = np.meshgrid(u, u, u, indexing="ij")
    return (
        mdl.long_off + L.ravel() * mdl.long_scale,
        mdl.lat_off + P.ravel() * mdl.lat_scale,
        mdl.height_off + H.ravel() * mdl.height_scale,
    )


def _random_rpc(seed: int) -> RPCModel:
    """A well-behaved random RPC with awkward (non-round) values, for round trips."""
    rng = np.random.default_rng(seed)
    coeffs = rng.normal(0.0, 1e-3, (4, 20)) * np.logspace(0, -6, 20)
    coeffs[0, 2] = -1.0 + rng.normal(0, 0.01)
    coeffs[2, 1] = 1.0 + rng.normal(0, 0.01)
    coeffs[1, 0] = coeffs[3, 0] = 1.0
    head = [
        abs(rng.normal(5.0, 1.0)),  # err_bias
        abs(rng.normal(0.5, 0.1)),  # err_rand
        rng.uniform(1000, 20000) + 0.5,  # line_off
        rng.uniform(1000, 20000) + 0.5,
        rng.uniform(-60, 60),
        rng.uniform(-179, 179),
        rng.uniform(0, 3000),
        rng.uniform(1000, 20000),
        rng.uniform(1000, 20000),
        rng.uniform(0.01, 0.2),
        rng.uniform(0.01, 0.2),
        rng.uniform(100, 1000),
    ]
    return RPCModel.from_vector(np.concatenate([head, coeffs.ravel()]))


# ---------------------------------------------------------------------------------------------
# Readers on the real files


def test_read_geom_ventoux(left: RPCModel) -> None:
    assert rpc.detect_rpc_format(LEFT_GEOM) == "geom"
    assert left.line_off == 21109.5
    assert left.samp_off == 19207.5
    assert left.lat_off == 44.1371659937345
    assert left.long_off == 5.28464655928485
    assert left.height_off == 1075.0
    assert left.height_scale == 885.0
    assert left.line_num_coeff[2] == -1.03205102244059
    assert left.samp_num_coeff[1] == 1.01915446681969
    assert left.samp_den_coeff[19] == 5.90483872722103e-09
    assert left.line_den_coeff[0] == 1.0
    kwl = rpc.read_keyword_list(LEFT_GEOM)
    assert (int(kwl["number_lines"]), int(kwl["number_samples"])) == LEFT_SIZE
    # The reference point of the .geom is consistent with the model to a fraction of a pixel.
    line, sample = left.project(
        float(kwl["ref_point_lon"]), float(kwl["ref_point_lat"]), float(kwl["ref_point_hgt"])
    )
    assert abs(line - float(kwl["ref_point_line"])) < 0.5
    assert abs(sample - float(kwl["ref_point_samp"])) < 0.5


def test_read_dimap_ventoux(left: RPCModel) -> None:
    assert rpc.detect_rpc_format(DIMAP) == "dimap"
    assert rpc.dimap_pixel_origin(DIMAP) == 1.0  # DIMAP v2: centre of the first pixel is (1, 1)
    raw = rpc.read_dimap_rpc(DIMAP, origin=0.0)
    assert raw.samp_off == 19208.5
    assert raw.line_off == pytest.approx(21110.5, abs=1e-9)
    model = rpc.read_rpc(DIMAP)
    assert model.samp_off == raw.samp_off - 1.0
    assert model.line_off == raw.line_off - 1.0
    # Same coefficients as the OSSIM .geom of the scene (which has 15 significant digits).
    np.testing.assert_allclose(model.coefficients, left.coefficients, rtol=1e-14, atol=1e-20)
    for name in ("lat_off", "long_off", "height_off", "lat_scale", "long_scale", "height_scale"):
        assert getattr(model, name) == pytest.approx(getattr(left, name), rel=1e-14)


def test_dimap_and_geom_differ_by_exactly_one_pixel(left: RPCModel) -> None:
    """DIMAP v2 is 1-based, OSSIM .geom 0-based: raw projections differ by (1, 1) px."""
    lon, lat, h = _ground_grid(left, 7, 1.1)
    geom = np.stack(left.project(lon, lat, h), axis=-1)
    raw = np.stack(rpc.read_dimap_rpc(DIMAP, origin=0.0).project(lon, lat, h), axis=-1)
    offset = raw - geom
    assert np.array_equal(np.unique(np.round(offset), axis=0), [[1.0, 1.0]])
    assert np.abs(offset - 1.0).max() < 1e-6
    converted = np.stack(rpc.read_rpc(DIMAP).project(lon, lat, h), axis=-1)
    assert np.abs(converted - geom).max() < 1e-6


# ---------------------------------------------------------------------------------------------
# Write / read round trips


WRITERS = {
    "geom": (rpc.write_geom, rpc.read_geom, "scene.geom"),
    "rpc_txt": (rpc.write_rpc_txt, rpc.read_rpc_txt, "scene_RPC.TXT"),
    "rpb": (rpc.write_rpb, rpc.read_rpb, "scene.RPB"),
    "geotiff": (rpc.write_geotiff_rpc, rpc.read_geotiff_rpc, "scene.tif"),
    "dimap": (rpc.write_dimap_rpc, rpc.read_dimap_rpc, "RPC_scene.XML"),
}


@pytest.mark.parametrize("fmt", sorted(WRITERS))
@pytest.mark.parametrize("which", ["ventoux", "random0", "random1"])
def test_round_trip(fmt: str, which: str, left: RPCModel, tmp_path: Path) -> None:
    model = left if which == "ventoux" else _random_rpc(int(which[-1]))
    write, read, name = WRITERS[fmt]
    path = tmp_path / name
    write(path, model)
    assert rpc.detect_rpc_format(path) == fmt
    back = read(path)
    via_dispatch = rpc.read_rpc(path)
    # Content, not the extension, decides the format.
    renamed = tmp_path / "no_extension"
    shutil.copy(path, renamed)
    assert rpc.detect_rpc_format(renamed) == fmt
    expected = model.as_vector()
    if fmt == "dimap":
        # No ERR_BIAS / ERR_RAND in metres in DIMAP; offsets go through +1 and -1.
        expected[:2] = -1.0
        np.testing.assert_allclose(back.as_vector(), expected, rtol=1e-15, atol=0)
    else:
        assert np.array_equal(back.as_vector(), expected)
    assert np.array_equal(via_dispatch.as_vector(), back.as_vector())
    assert np.array_equal(rpc.read_rpc(renamed).as_vector(), back.as_vector())


def test_read_classic_rpc_txt_and_rpb(left: RPCModel, tmp_path: Path) -> None:
    """The layouts vendors deliver (fixed decimals, units, tabs, multi-line lists)."""
    txt = [
        "LINE_OFF: +021109.50 pixels",
        "SAMP_OFF: +019207.50 pixels",
        f"LAT_OFF: {left.lat_off:+.8f} degrees",
        f"LONG_OFF: {left.long_off:+.8f} degrees",
        "HEIGHT_OFF: +1075.000 meters",
        "LINE_SCALE: +021137.50 pixels",
        "SAMP_SCALE: +019999.50 pixels",
        f"LAT_SCALE: {left.lat_scale:+.8f} degrees",
        f"LONG_SCALE: {left.long_scale:+.8f} degrees",
        "HEIGHT_SCALE: +0885.000 meters",
    ]
    for name in ("line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff"):
        txt += [f"{name.upper()}_{i + 1}: {c:+.15E}" for i, c in enumerate(getattr(left, name))]
    (tmp_path / "a_RPC.TXT").write_text("\r\n".join(txt) + "\r\n")
    rpb = [
        'satId = "PHR1B";',
        'bandId = "P";',
        'SpecId = "RPC00B";',
        "BEGIN_GROUP = IMAGE",
        "\terrBias =   56.01;",
        "\terrRand =    0.12;",
        "\tlineOffset = 21109.5;",
        "\tsampOffset = 19207.5;",
        f"\tlatOffset =    {left.lat_off:.8f};",
        f"\tlongOffset =  {left.long_off:.8f};",
        "\theightOffset =  1075.000;",
        "\tlineScale = 21137.5;",
        "\tsampScale = 19999.5;",
        f"\tlatScale =     {left.lat_scale:.8f};",
        f"\tlongScale =    {left.long_scale:.8f};",
        "\theightScale =  885.000;",
    ]
    for key, name in (
        ("lineNumCoef", "line_num_coeff"),
        ("lineDenCoef", "line_den_coeff"),
        ("sampNumCoef", "samp_num_coeff"),
        ("sampDenCoef", "samp_den_coeff"),
    ):
        body = ",\n".join(f"\t\t\t{c:+.15E}" for c in getattr(left, name))
        rpb.append(f"\t{key} = (\n{body});")
    rpb += ["END_GROUP = IMAGE", "END;"]
    (tmp_path / "a.RPB").write_text("\n".join(rpb) + "\n")
    lon, lat, h = _ground_grid(left, 5)
    ref = np.stack(left.project(lon, lat, h), axis=-1)
    for name, fmt in (("a_RPC.TXT", "rpc_txt"), ("a.RPB", "rpb")):
        assert rpc.detect_rpc_format(tmp_path / name) == fmt
        model = rpc.read_rpc(tmp_path / name)
        np.testing.assert_allclose(model.coefficients, left.coefficients, rtol=1e-14)
        assert model.line_off == 21109.5
        got = np.stack(model.project(lon, lat, h), axis=-1)
        assert np.abs(got - ref).max() < 5e-3  # lat/long offsets, scales to 8 decimals
    assert rpc.read_rpb(tmp_path / "a.RPB").err_bias == 56.01


def test_geom_polynomial_format_a(left: RPCModel, tmp_path: Path) -> None:
    """RPC00A keyword lists (PLH before the squares) are reordered to RPC00B."""
    kwl = rpc.read_keyword_list(LEFT_GEOM)
    out = [f"{k}:  {v}" for k, v in kwl.items() if "_coeff_" not in k]
    out = [line.replace("polynomial_format:  B", "polynomial_format:  A") for line in out]
    a_from_b = [0, 1, 2, 3, 4, 5, 6, 10, 7, 8, 9, 11, 12, 13, 14, 15, 16, 17, 18, 19]
    for name in ("line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff"):
        b = getattr(left, name)
        out += [f"{name}_{i:02d}:  {float(b[a_from_b[i]])!r}" for i in range(20)]
    (tmp_path / "a.geom").write_text("\n".join(out) + "\n")
    model = rpc.read_rpc(tmp_path / "a.geom")
    assert np.array_equal(model.coefficients, left.coefficients)


def test_unknown_format(tmp_path: Path) -> None:
    (tmp_path / "x.txt").write_text("hello: world\n")
    with pytest.raises(rpc.RPCFormatError):
        rpc.read_rpc(tmp_path / "x.txt")
    (tmp_path / "y.geom").write_text("line_off: 1\n")
    with pytest.raises(rpc.RPCFormatError, match="missing"):
        rpc.read_geom(tmp_path / "y.geom")


# ---------------------------------------------------------------------------------------------
# Projection, localization, validity domain


def test_project_localize_round_trip_over_domain(left: RPCModel, right: RPCModel) -> None:
    for mdl in (left, right):
        u = np.linspace(-1.0, 1.0, 41)
        ln, sn, hn = np.meshgrid(u, u, np.linspace(-1.0, 1.0, 9), indexing="ij")
        line = mdl.line_off + ln.ravel() * mdl.line_scale
        sample = mdl.samp_off + sn.ravel() * mdl.samp_scale
        h = mdl.height_off + hn.ravel() * mdl.height_scale
        lon, lat = mdl.localize(line, sample, h)
        l2, s2 = mdl.project(lon, lat, h)
        assert np.hypot(l2 - line, s2 - sample).max() < 1e-6
        # ground -> image -> ground
        glon, glat, gh = _ground_grid(mdl, 11, 1.0)
        gl, gs = mdl.project(glon, glat, gh)
        lon2, lat2 = mdl.localize(gl, gs, gh)
        assert np.abs(lon2 - glon).max() < 1e-10
        assert np.abs(lat2 - glat).max() < 1e-10


def test_localize_scalar_and_shape(left: RPCModel) -> None:
    lon, lat = left.localize(5000.0, 6000.0, 800.0)
    assert lon.shape == () and lat.shape == ()
    lon, lat = left.localize(np.full((2, 3), 5000.0), 6000.0, [700.0, 800.0, 900.0])
    assert lon.shape == (2, 3)
    assert lon[0, 0] != lon[0, 2]  # another height, another ground point


def test_validity_domain(left: RPCModel) -> None:
    """The declared domain limits only when asked (domain="limit"); by default it is advice."""
    far_lon = left.long_off + 1.2 * left.long_scale
    lim = {"domain": "limit"}
    with pytest.raises(rpc.RPCDomainError):
        left.project(far_lon, left.lat_off, left.height_off, **lim)  # type: ignore[arg-type]
    line, sample = left.project(
        [far_lon, left.long_off], left.lat_off, left.height_off, outside="nan", domain="limit"
    )
    assert np.isnan(line[0]) and np.isnan(sample[0]) and np.isfinite(line[1])
    line, _ = left.project(far_lon, left.lat_off, left.height_off)  # advice: evaluated
    assert np.isfinite(line)
    assert not left.in_domain(left.long_off, left.lat_off, left.height_off + 2 * 885.0)
    with pytest.raises(rpc.RPCDomainError):
        left.localize(
            left.line_off + 1.2 * left.line_scale, left.samp_off, left.height_off, domain="limit"
        )
    with pytest.raises(rpc.RPCDomainError):
        left.localize(left.line_off, left.samp_off, -500.0, domain="limit")  # 101.5 .. 2048.5
    lon, _ = left.localize(
        [left.line_off, -30000.0], left.samp_off, 1000.0, outside="nan", domain="limit"
    )
    assert np.isfinite(lon[0]) and np.isnan(lon[1])
    # advice: outside the declared domain the formula is solved all the same, exactly
    line0, samp0 = left.line_off + 1.3 * left.line_scale, left.samp_off - 1.2 * left.samp_scale
    lon, lat = left.localize(line0, samp0, -500.0)
    back = left.project(lon, lat, -500.0)
    assert abs(float(back[0]) - line0) < 1e-6 and abs(float(back[1]) - samp0) < 1e-6


def test_shifted_is_a_crop(left: RPCModel) -> None:
    crop = left.shifted(-5000.0, -5000.0)
    lon, lat = left.localize(5100.0, 5200.0, 900.0)
    assert np.allclose(crop.project(lon, lat, 900.0), (100.0, 200.0), atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Geodetic, ECEF, ENU

LON = st.floats(-180.0, 180.0, allow_nan=False)
LAT = st.floats(-90.0, 90.0, allow_nan=False)
HEIGHT = st.floats(-1.0e4, 1.0e6, allow_nan=False)


def test_ecef_known_values() -> None:
    x, y, z = rpc.ecef_from_geodetic(0.0, 0.0, 0.0)
    assert (x, y, z) == (WGS84_A, 0.0, 0.0)
    x, y, z = rpc.ecef_from_geodetic(90.0, 90.0, 100.0)
    assert abs(x) < 1e-9 and abs(y) < 1e-9
    assert z == pytest.approx(WGS84_A * (1 - WGS84_F) + 100.0, abs=1e-9)


@settings(max_examples=300, deadline=None)
@given(LON, LAT, HEIGHT)
def test_geodetic_ecef_round_trip(lon: float, lat: float, h: float) -> None:
    xyz = np.array(rpc.ecef_from_geodetic(lon, lat, h), dtype=float)
    lon2, lat2, h2 = (float(v) for v in rpc.geodetic_from_ecef(*xyz))
    assert abs(lat2 - lat) < 1e-9
    assert abs(h2 - h) < 1e-6
    if abs(lat) < 89.99:  # longitude is undefined at the poles
        assert abs((lon2 - lon + 180.0) % 360.0 - 180.0) < 1e-9
    back = np.array(rpc.ecef_from_geodetic(lon2, lat2, h2), dtype=float)
    assert np.abs(back - xyz).max() < 1e-6


@settings(max_examples=200, deadline=None)
@given(
    st.floats(-85.0, 85.0),
    LON,
    st.floats(-500.0, 5000.0),
    st.floats(-1e5, 1e5),
    st.floats(-1e5, 1e5),
    st.floats(-2e3, 1e5),
)
def test_local_tangent_plane_round_trip(
    lat0: float, lon0: float, h0: float, x: float, y: float, z: float
) -> None:
    frame = rpc.LocalTangentPlane(lat0, lon0, h0)
    lon, lat, h = frame.to_geodetic(x, y, z)
    x2, y2, z2 = frame.to_local(lon, lat, h)
    assert max(abs(x2 - x), abs(y2 - y), abs(z2 - z)) < 1e-6
    # and the other way round
    x3, y3, z3 = frame.to_local(lon0 + 0.01, lat0 - 0.02, h0 + 300.0)
    lon3, lat3, h3 = frame.to_geodetic(x3, y3, z3)
    assert abs(lat3 - (lat0 - 0.02)) < 1e-9 and abs(h3 - (h0 + 300.0)) < 1e-6
    assert abs((lon3 - (lon0 + 0.01) + 180.0) % 360.0 - 180.0) < 1e-9


def test_local_tangent_plane_axes() -> None:
    frame = rpc.LocalTangentPlane(44.2, 5.2, 1000.0)
    assert np.allclose(frame.to_local(5.2, 44.2, 1000.0), 0.0, atol=1e-8)
    assert np.allclose(frame.to_local(5.2, 44.2, 1100.0), (0.0, 0.0, 100.0), atol=1e-8)
    x, y, _ = frame.to_local(5.201, 44.2, 1000.0)
    assert x > 70.0 and abs(y) < 0.01  # east: 0.001 deg * 111 km * cos(44.2 deg) = 80 m
    x, y, _ = frame.to_local(5.2, 44.201, 1000.0)
    assert abs(x) < 1e-6 and 110.0 < y < 112.0  # north


# ---------------------------------------------------------------------------------------------
# DEM


def test_srtm_height_reader(tmp_path: Path) -> None:
    """A synthetic 3" tile holding a plane: bilinear interpolation reproduces it exactly."""
    n = 1201
    rows, cols = np.mgrid[0:n, 0:n]
    tile = (500 + 0.5 * cols - 0.25 * rows).astype(np.int16)
    tile[0, 0] = -32768  # a void: filled from its neighbour
    tile.astype(">i2").tofile(tmp_path / "N44E005.hgt")
    height = srtm_height(tmp_path / "N44E005.hgt")
    lon = np.array([5.3, 5.5, 5.99, 6.5])
    lat = np.array([44.2, 44.5, 44.01, 44.5])
    h = height(lon, lat)
    col, row = (lon[:3] - 5.0) * 1200, (45.0 - lat[:3]) * 1200
    expected = np.floor(500 + 0.5 * np.floor(col) - 0.25 * np.floor(row))  # int16 truncation
    assert np.all(np.abs(h[:3] - (500 + 0.5 * col - 0.25 * row)) <= 1.0)
    assert np.all(np.abs(h[:3] - expected) <= 1.0)
    assert np.isnan(h[3])  # outside the tile
    shifted = srtm_height(tmp_path / "N44E005.hgt", geoid_undulation=49.5)
    assert np.allclose(shifted(lon[:3], lat[:3]), h[:3] + 49.5)
    assert height(np.array(5.0), np.array(45.0)) in (499.0, 500.0)  # void: from a neighbour


# ---------------------------------------------------------------------------------------------
# Virtual GCP on the Ventoux pair


def _window(size: float) -> tuple[float, float, float, float]:
    half = size / 2.0
    return (CROP_CENTRE - half, CROP_CENTRE - half, CROP_CENTRE + half, CROP_CENTRE + half)


def test_virtual_gcp_ventoux(left: RPCModel, right: RPCModel) -> None:
    gcp = rpc.virtual_gcp(
        left,
        right,
        lines=(LEFT_SIZE[0], RIGHT_SIZE[0]),
        samples=(LEFT_SIZE[1], RIGHT_SIZE[1]),
        heights=(300.0, 1900.0),
        grid=(15, 15, 5),
        window=_window(2000.0),
    )
    n = len(gcp)
    assert n > 0.9 * 15 * 15 * 5
    assert gcp.points.shape == (n, 3) and gcp.left.shape == gcp.right.shape == (n, 2)
    lon, lat, h = gcp.geodetic.T
    # Recorded image coordinates are the projections of the recorded ground points, exactly.
    assert np.array_equal(np.stack(left.project(lon, lat, h), axis=-1), gcp.left)
    assert np.array_equal(np.stack(right.project(lon, lat, h), axis=-1), gcp.right)
    # ... and of the object points through the local frame, to 1e-6 px.
    geo = np.stack(gcp.frame.to_geodetic(*gcp.points.T), axis=-1)
    assert np.abs(np.stack(left.project(*geo.T), axis=-1) - gcp.left).max() < 1e-6
    assert np.abs(np.stack(right.project(*geo.T), axis=-1) - gcp.right).max() < 1e-6
    # Inside both scenes and on the requested grid.
    for ls, (nl, ns) in ((gcp.left, LEFT_SIZE), (gcp.right, RIGHT_SIZE)):
        assert np.all((ls >= 0) & (ls <= np.array([nl - 1, ns - 1])))
    lo, _, hi, _ = _window(2000.0)
    assert np.all((gcp.left >= lo - 1e-6) & (gcp.left <= hi + 1e-6))
    assert set(np.round(h, 9)) == {300.0, 700.0, 1100.0, 1500.0, 1900.0}
    # The frame has Z up: 100 m higher is 100 m more Z (to the Earth's curvature, < 1e-3 m here).
    _, _, z_up = gcp.frame.to_local(lon, lat, h + 100.0)
    assert np.abs(z_up - gcp.points[:, 2] - 100.0).max() < 1e-3
    assert gcp.points[:, 2].max() - gcp.points[:, 2].min() == pytest.approx(1600.0, abs=1.0)
    # The frame sits at the points' centroid (mean lon, lat, height).
    assert abs(gcp.frame.lat0 - lat.mean()) < 1e-12 and abs(gcp.frame.h0 - h.mean()) < 1e-9


def test_virtual_gcp_keeps_only_common_points(left: RPCModel, right: RPCModel) -> None:
    """A window at the left scene's edge: only points also seen by the right scene remain."""
    gcp = rpc.virtual_gcp(
        left,
        right,
        lines=(LEFT_SIZE[0], RIGHT_SIZE[0]),
        samples=(LEFT_SIZE[1], RIGHT_SIZE[1]),
        heights=(500.0, 1500.0),
        grid=(10, 10, 3),
        window=(LEFT_SIZE[0] - 3000.0, 0.0, LEFT_SIZE[0] - 1.0, 3000.0),
    )
    assert 0 < len(gcp) < 300
    assert np.all(gcp.right[:, 0] <= RIGHT_SIZE[0] - 1)
    frame = rpc.LocalTangentPlane(44.0, 5.0, 0.0)
    with pytest.raises(rpc.RPCError, match="no virtual GCP"):
        rpc.virtual_gcp(
            left,
            right,
            lines=(LEFT_SIZE[0], 10),
            samples=(LEFT_SIZE[1], 10),
            heights=(500.0, 1500.0),
            grid=(3, 3, 2),
            frame=frame,
        )


def test_virtual_gcp_on_dem(left: RPCModel, right: RPCModel, dem: rpc.HeightFunction) -> None:
    common = {
        "lines": (LEFT_SIZE[0], RIGHT_SIZE[0]),
        "samples": (LEFT_SIZE[1], RIGHT_SIZE[1]),
        "heights": dem,
        "window": _window(2000.0),
    }
    on = rpc.virtual_gcp(left, right, grid=(12, 12, 1), **common)
    lon, lat, h = on.geodetic.T
    assert len(on) == 144
    assert np.abs(h - dem(lon, lat)).max() < 1e-2  # rays meet the DEM
    assert h.max() - h.min() > 200.0  # Ventoux foothills
    band = rpc.virtual_gcp(left, right, grid=(12, 12, 3), dem_margin=50.0, **common)
    # Each image point's ray gives DEM - 50, DEM, DEM + 50 (DEM = where the ray meets it).
    d = band.geodetic[:, 2].reshape(-1, 3) - h[:, None]
    np.testing.assert_allclose(d, np.broadcast_to([-50.0, 0.0, 50.0], d.shape), atol=1e-9)
    assert np.abs(band.left[1::3] - on.left).max() < 1e-6


# ---------------------------------------------------------------------------------------------
# Parallel projection fitted to the virtual GCP (ERRATA: about 0.01 px over 1000 px, 0.2 px over
# 5000 px for a single affine model fitted to exact RPC correspondences)


@pytest.mark.parametrize(("size", "errata_px"), [(1000.0, 0.01), (5000.0, 0.2)])
def test_parallel_projection_fit_sigma0(
    left: RPCModel, right: RPCModel, dem: rpc.HeightFunction, size: float, errata_px: float
) -> None:
    gcp = rpc.virtual_gcp(
        left,
        right,
        lines=(LEFT_SIZE[0], RIGHT_SIZE[0]),
        samples=(LEFT_SIZE[1], RIGHT_SIZE[1]),
        heights=dem,
        grid=(21, 21, 1),
        window=_window(size),
    )
    sigmas = []
    for scene in ("left", "right"):
        est, frame = rpc.estimate_scene(
            gcp,
            scene,
            principal_distance=C_PHR,
            pixel_size=PIXEL_PHR,
            principal_point=PP_PHR,
        )
        assert est.psi_estimated
        assert frame.pixel_size == PIXEL_PHR
        sigmas.append(est.sigma0_px)
        # residuals in pixels agree with sigma0
        rms = math.sqrt(float(np.mean(est.residuals**2))) / PIXEL_PHR
        assert rms <= est.sigma0_px
        print(f"window {size:.0f} px, {scene}: sigma0 = {est.sigma0_px:.4f} px, n = {len(gcp)}")
    for s in sigmas:
        assert errata_px / 3.0 <= s <= errata_px * 3.0


def test_sigma0_invariant_to_pixel_size_with_psi_estimated(
    left: RPCModel, right: RPCModel
) -> None:
    """The focal-plane pixel size against c only changes psi when psi is estimated."""
    gcp = rpc.virtual_gcp(
        left,
        right,
        lines=(LEFT_SIZE[0], RIGHT_SIZE[0]),
        samples=(LEFT_SIZE[1], RIGHT_SIZE[1]),
        heights=(900.0, 1100.0),
        grid=(11, 11, 3),
        window=_window(3000.0),
    )
    kw = {"principal_distance": C_PHR, "principal_point": PP_PHR}
    a, _ = rpc.estimate_scene(gcp, "left", pixel_size=PIXEL_PHR, **kw)
    b, _ = rpc.estimate_scene(gcp, "left", pixel_size=PIXEL_PHR * 0.5 / 0.7, **kw)
    assert b.sigma0_px == pytest.approx(a.sigma0_px, rel=1e-4)


# ---------------------------------------------------------------------------------------------
# Independent check: GDAL's RPC transformer (rasterio.transform.RPCTransformer)


def _out_of_domain(left: RPCModel) -> RPCModel:
    """The 500 px crop at (5000, 5000) with the parent's offsets and crop scales (~30 out)."""
    crop = left.shifted(-5000.0, -5000.0)
    return crop.renormalized(
        line_scale=500.0,
        samp_scale=500.0,
        lat_scale=left.lat_scale * 500 / left.line_scale,
        long_scale=left.long_scale * 500 / left.samp_scale,
    )


@pytest.mark.parametrize("which", ["left", "right", "dimap", "out_of_domain"])
def test_against_gdal_rpc_transformer(which: str, left: RPCModel, right: RPCModel) -> None:
    """Projection and localization agree with GDAL's RPC transformer to 1e-3 px / 1e-6 deg.

    GDAL's pixel space is corner-based: its transformer gives RPC00B image coordinates + 0.5
    (rowcol without rounding), and ``xy(..., offset="center")`` takes our coordinates. The
    Ventoux full-scene RPCs over their whole image and height domains; the crop RPC with the
    parent's offsets over the crop, 27..33 scale units outside the declared domain.
    """
    from rasterio.transform import RPCTransformer

    model = {
        "left": left,
        "right": right,
        "dimap": rpc.read_rpc(DIMAP),
        "out_of_domain": _out_of_domain(left),
    }[which]
    rng = np.random.default_rng(5)
    n = 400
    if which == "out_of_domain":
        line, sample = rng.uniform(0, 499, n), rng.uniform(0, 499, n)
        norm = model.normalized_image_range((0.0, 499.0), (0.0, 499.0))
        assert min(abs(v) for r in norm for v in r) > 25  # far outside the declared domain
    else:
        line = rng.uniform(-1, 1, n) * model.line_scale + model.line_off
        sample = rng.uniform(-1, 1, n) * model.samp_scale + model.samp_off
    h = rng.uniform(-1, 1, n) * model.height_scale + model.height_off
    lon, lat = model.localize(line, sample, h)
    with RPCTransformer(_gdal_rpc(model), RPC_PIXEL_ERROR_THRESHOLD=1e-9) as tr:
        g_lon, g_lat = tr.xy(list(line), list(sample), zs=list(h), offset="center")
        g_row, g_col = tr.rowcol(list(lon), list(lat), zs=list(h), op=lambda v: v)
    g_row_a, g_col_a = np.asarray(g_row, float) - 0.5, np.asarray(g_col, float) - 0.5
    p_line, p_sample = model.project(lon, lat, h)
    d_px = float(np.hypot(p_line - g_row_a, p_sample - g_col_a).max())
    d_deg = float(
        np.maximum(np.abs(np.asarray(g_lon) - lon), np.abs(np.asarray(g_lat) - lat)).max()
    )
    print(f"{which}: projection vs GDAL {d_px:.1e} px, localization vs GDAL {d_deg:.1e} deg")
    assert d_px < 1e-3
    assert d_deg < 1e-6


def test_renormalized_is_the_same_mapping(left: RPCModel) -> None:
    """Other offsets / scales, the same ground -> image mapping (pure rescaling: c / k^d)."""
    lon, lat, h = _ground_grid(left, 7, 1.0)
    ref = np.stack(left.project(lon, lat, h), axis=-1)
    k = 3.0
    scaled = left.renormalized(long_scale=left.long_scale * k)
    # a monomial of degree d in L gets its coefficient multiplied by k^d (L = k L')
    powers = np.array([t.count("L") for t in rpc.RPC00B_TERMS])
    np.testing.assert_allclose(
        scaled.line_den_coeff, left.line_den_coeff * k**powers, rtol=1e-12, atol=1e-300
    )
    for model in (
        scaled,
        _out_of_domain(left).shifted(5000.0, 5000.0),
        left.renormalized(line_off=0.0, height_off=0.0, height_scale=1.0, lat_off=45.0),
    ):
        got = np.stack(model.project(lon, lat, h), axis=-1)
        assert np.abs(got - ref).max() < 1e-6


@pytest.mark.parametrize("value", ["1,5", "1.5.2", "12abc", "", "1 2", "nan pixels", "0x10"])
def test_numbers_that_do_not_parse_are_errors(value: str, tmp_path: Path) -> None:
    """Never a partial read ("1,5" is not 1): the error names the file, the key and the value."""
    path = tmp_path / "a_RPC.TXT"
    rpc.write_rpc_txt(path, _random_rpc(0))
    text = path.read_text().splitlines()
    text = [f"SAMP_SCALE: {value}" if t.startswith("SAMP_SCALE") else t for t in text]
    path.write_text("\n".join(text) + "\n")
    with pytest.raises(rpc.RPCFormatError) as err:
        rpc.read_rpc(path)
    assert "a_RPC.TXT" in str(err.value) and "SAMP_SCALE" in str(err.value)
    assert repr(value.strip()) in str(err.value)


# ---- denominators over an image (issue 24 item 6) -----------------------------------------------

MARSEILLE = Path(__file__).resolve().parents[3] / "shared" / "data" / "marseille_triplet"


def _image_lattice(lines: float, samples: float, h: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """The import check's test points: 11 x 11 pixels (edges included) x 3 heights."""
    g_l, g_s = np.meshgrid(
        np.linspace(0.0, lines - 1, 11), np.linspace(0.0, samples - 1, 11), indexing="ij"
    )
    hs = np.linspace(h[0], h[1], 3)
    return np.repeat(g_l.ravel(), 3), np.repeat(g_s.ravel(), 3), np.tile(hs, g_l.size)


def test_image_denominator_check_on_real_rpcs() -> None:
    """No false alarm on real RPCs: the Ventoux scenes (full extent, whole height range) and the
    three Marseille views (their RPCs in GeoTIFF tag 50844, read through GDAL)."""
    from parproj_ros.io.raster import raster_info, rpc_from_metadata

    for geom in (LEFT_GEOM, RIGHT_GEOM):
        m = rpc.read_rpc(geom)
        lines = 2 * m.line_off + 1  # the scene: line_off is its centre
        samples = 2 * m.samp_off + 1
        h = (m.height_off - m.height_scale, m.height_off + m.height_scale)
        assert m.image_denominator_check(*_image_lattice(lines, samples, h)) is None
    for i in (1, 2, 3):
        info = raster_info(MARSEILLE / f"img_0{i}.tif")
        m = rpc_from_metadata(info.rpc_metadata, info.path)
        h = (m.height_off - 0.5 * m.height_scale, m.height_off + 0.5 * m.height_scale)
        assert m.image_denominator_check(*_image_lattice(info.lines, info.samples, h)) is None


def test_image_denominator_check_finds_the_zero() -> None:
    """A sample denominator 1 - P / P0 vanishing at the latitude of the scene's line 3000: named
    with the line of the test point nearest the zero, within one lattice step."""
    m = rpc.read_rpc(LEFT_GEOM)
    lines, samples = 2 * m.line_off + 1, 2 * m.samp_off + 1
    ll, ss, hh = _image_lattice(lines, samples, (m.height_off, m.height_off))
    lon0, lat0 = m.localize(3000.0, m.samp_off, m.height_off)
    _, p0, _ = m.normalize_ground(lon0, lat0, m.height_off)
    v = m.as_vector()
    v[12 + 60 : 12 + 80] = 0.0
    v[12 + 60], v[12 + 62] = 1.0, -1.0 / float(p0)
    bad = RPCModel.from_vector(v)
    why = bad.image_denominator_check(ll, ss, hh)
    assert why is not None and why.startswith("RPC sample denominator changes sign over the image")
    line = float(why.split("at line ")[1].split(",")[0])
    assert abs(line - 3000.0) <= (lines - 1) / 10, why
    v[12 + 60 : 12 + 80] = 0.0
    zero = RPCModel.from_vector(v)
    assert zero.image_denominator_check(ll, ss, hh) == (
        "RPC sample denominator zero everywhere (its 20 SAMP_DEN_COEFF are all 0)"
    )
