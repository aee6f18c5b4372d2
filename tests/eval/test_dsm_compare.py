"""eval/dsm_compare.py: a DSM against a reference, scored as the Marseille data's README does.

Synthetic georeferenced rasters with a known offset and noise give back that offset and noise;
a DSM in a local tangent-plane frame is placed exactly on the reference's UTM grid; and on the
real references, s2p_dsm_12 - cars_dsm_12 gives the README's figures (median -0.08 m, NMAD
0.77 m over 899,873 cells; footprint 1,017,090 cells with the six references).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from pyproj import CRS
from rasterio.transform import Affine

from parproj_ros.eval.dsm_compare import (
    FrameDsm,
    compare,
    difference_stats,
    main,
    read_geotiff_dsm,
)
from parproj_ros.geometry.geodesy import LocalTangentPlane
from parproj_ros.imaging.heights import DsmGrid
from tests.testkit.paths import ROOT

MARSEILLE = ROOT.parent / "shared" / "data" / "marseille_triplet"
UTM31 = CRS.from_epsg(32631)
#: Upper-left corner of the synthetic reference (Marseille, UTM 31N), metres; cell 0.5 m.
E0, N0, CELL = 698000.0, 4793000.0, 0.5


def surface(e: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Smooth ground (ellipsoidal height, m): a tilted plane with gentle hills."""
    return 200.0 + 0.02 * (e - E0) - 0.01 * (n - N0) + 3.0 * np.sin((e - E0) / 40.0)


def write_dsm(
    path: Path, z: np.ndarray, e_left: float, n_top: float, *, crs: CRS | None = UTM31
) -> Path:
    """A float32 GeoTIFF, NaN nodata, ellipsoidal heights as the references are tagged."""
    profile = {
        "driver": "GTiff",
        "width": z.shape[1],
        "height": z.shape[0],
        "count": 1,
        "dtype": "float32",
        "nodata": float("nan"),
        "transform": Affine(CELL, 0.0, e_left, 0.0, -CELL, n_top),
        "crs": None if crs is None else rasterio.crs.CRS.from_wkt(crs.to_wkt()),
    }
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(z.astype(np.float32), 1)
        dst.update_tags(VERTICAL_DATUM="WGS84 ellipsoid")
    return path


def centres(e_left: float, n_top: float, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    e = e_left + CELL * (np.arange(cols) + 0.5)
    n = n_top - CELL * (np.arange(rows) + 0.5)
    return np.meshgrid(e, n)


def test_stats_of_known_differences() -> None:
    rng = np.random.default_rng(1)
    d = rng.normal(0.3, 0.5, 200_000)
    s = difference_stats(np.concatenate([d, [np.nan] * 10]))
    assert s["cells"] == 200_000
    assert abs(s["median"] - 0.3) < 0.01
    assert abs(s["nmad"] - 0.5) < 0.01  # NMAD of a normal law is its sigma
    assert abs(s["rms"] - math.hypot(0.3, 0.5)) < 0.01
    assert abs(s["p95_abs"] - np.percentile(np.abs(d), 95)) < 1e-9
    assert difference_stats(np.array([np.nan]))["cells"] == 0


def test_offset_noise_and_holes_recovered(tmp_path: Path) -> None:
    """Ours = reference + 1.25 m + N(0, 0.4 m), on another extent of the same lattice."""
    rows, cols = 300, 400
    e, n = centres(E0, N0, rows, cols)
    ref = surface(e, n)
    ref[100:120, 50:90] = np.nan  # a hole in the reference: out of the statistics
    ref_path = write_dsm(tmp_path / "ref.tif", ref, E0, N0)
    # ours: shifted by (+10, -6) cells, 20 % of its cells empty at random
    oe, on = E0 + 10 * CELL, N0 - 6 * CELL
    e2, n2 = centres(oe, on, rows, cols)
    rng = np.random.default_rng(7)
    ours = surface(e2, n2) + 1.25 + rng.normal(0.0, 0.4, e2.shape)
    holes = rng.random(e2.shape) < 0.2
    ours[holes] = np.nan
    ours_path = write_dsm(tmp_path / "ours.tif", ours, oe, on)
    res = compare(read_geotiff_dsm(ours_path), read_geotiff_dsm(ref_path))
    s = res.stats
    assert res.footprint == "reference cells"
    assert res.footprint_cells == rows * cols - 20 * 40
    # ours covers the reference's cells from column 10 and row 6 on: 20 % holes there
    covered = (rows - 6) * (cols - 10) - 20 * 40
    assert res.completeness == pytest.approx(0.8 * covered / res.footprint_cells, abs=0.01)
    assert s["cells"] == pytest.approx(0.8 * covered, rel=0.01)
    assert s["median"] == pytest.approx(1.25, abs=0.01)
    assert s["nmad"] == pytest.approx(0.4, abs=0.01)
    assert res.reference_completeness == 1.0


def test_half_cell_shift_of_a_plane_is_exact(tmp_path: Path) -> None:
    """Bilinear resampling of a plane onto a grid half a cell off loses nothing."""
    rows, cols = 120, 160
    e, n = centres(E0, N0, rows, cols)
    plane = 150.0 + 0.03 * (e - E0) + 0.02 * (n - N0)
    ref_path = write_dsm(tmp_path / "ref.tif", plane, E0, N0)
    oe, on = E0 + 0.25, N0 - 0.25
    e2, n2 = centres(oe, on, rows, cols)
    ours = 150.0 + 0.03 * (e2 - E0) + 0.02 * (n2 - N0) - 0.7
    ours[40:50, 40:50] = np.nan
    res = compare(
        read_geotiff_dsm(write_dsm(tmp_path / "ours.tif", ours, oe, on)),
        read_geotiff_dsm(ref_path),
    )
    assert res.stats["median"] == pytest.approx(-0.7, abs=1e-4)
    assert res.stats["nmad"] < 1e-4 and res.stats["p95_abs"] == pytest.approx(0.7, abs=1e-4)
    # missing: the reference's first row and column (outside our centres' box: 279 cells)
    # and the points all of whose neighbours of non-zero weight are in our 10 x 10 hole (9 x 9):
    # a sample needs half of its bilinear support, so the hole shrinks by half a cell a side
    missing = res.footprint_cells * (1.0 - res.completeness)
    assert round(missing) == (rows + cols - 1) + 9 * 9


def test_frame_dsm_is_placed_exactly_on_the_map_grid(tmp_path: Path) -> None:
    """A DSM in a tangent plane 600 m from its origin: converted to UTM + ellipsoidal h.

    The frame's Z is the height above the plane; 600 m from the origin it leaves the
    ellipsoidal height by d^2 / 2R = 3 cm plus the tilt of the normal. The comparison must
    convert, not subtract Z from h: the offset given (+2.0 m) comes back to 1 mm.
    """
    from pyproj import Transformer

    rows, cols = 200, 200
    e, n = centres(E0, N0, rows, cols)
    ref_path = write_dsm(tmp_path / "ref.tif", surface(e, n), E0, N0)
    to_ll = Transformer.from_crs(UTM31, CRS.from_epsg(4326), always_xy=True)
    to_utm = Transformer.from_crs(CRS.from_epsg(4326), UTM31, always_xy=True)
    # frame origin 600 m west and 400 m north of the reference's centre, 100 m below the ground
    lon0, lat0 = to_ll.transform(E0 + 50.0 - 600.0, N0 - 50.0 + 400.0)
    frame = LocalTangentPlane(lat0, lon0, 100.0)
    frame_id = f"enu_wgs84:lat={lat0:.9f},lon={lon0:.9f},h=100.0"
    # our grid in the frame covers the reference; Z on the surface + 2 m, found by iteration
    x0, y0, _ = frame.to_local(*to_ll.transform(E0 - 5.0, N0 + 5.0), 200.0)
    grid = DsmGrid(float(np.round(x0)), float(np.round(y0)), 0.5, 240, 240)
    gx, gy = grid.centres()
    z = np.full(gx.shape, 100.0)
    for _ in range(6):
        lon, lat, h = frame.to_geodetic(gx, gy, z)
        ee, nn = to_utm.transform(lon, lat)
        z += surface(np.asarray(ee), np.asarray(nn)) + 2.0 - h
    lon, lat, h = frame.to_geodetic(gx, gy, z)
    ee, nn = to_utm.transform(lon, lat)
    assert np.abs(surface(np.asarray(ee), np.asarray(nn)) + 2.0 - h).max() < 1e-6
    # the plane's Z is not the ellipsoidal height here: a naive Z + h0 is off by > 2 cm
    assert np.abs(z + 100.0 - h).max() > 0.02
    ours = FrameDsm(z.astype(np.float32), grid, frame_id, "ours")
    res = compare(ours, read_geotiff_dsm(ref_path))
    assert res.completeness > 0.99
    assert res.stats["median"] == pytest.approx(2.0, abs=0.005)
    # what is left is bilinear interpolation of the hills (3 m amplitude over 40 m) and float32
    assert res.stats["nmad"] < 0.005


def test_file_without_crs_is_refused_by_the_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    z = np.full((10, 10), 100.0)
    ref = write_dsm(tmp_path / "ref.tif", z, E0, N0)
    bare = write_dsm(tmp_path / "bare.tif", z, 0.0, 10.0, crs=None)
    assert main([str(bare), str(ref)]) == 2
    assert "bare.tif: no CRS" in capsys.readouterr().err
    assert main([str(ref), str(ref)]) == 0
    assert "median +0.00 m" in capsys.readouterr().out


@pytest.mark.slow  # about 5 s: six 1.2-Mpx rasters and two RPC footprints
def test_marseille_references_reproduce_the_readme() -> None:
    """s2p_dsm_12 - cars_dsm_12 on s2p_dsm_12's grid, footprint of img_01 + img_02 (README)."""
    ref = MARSEILLE / "reference"
    s2p = read_geotiff_dsm(ref / "s2p_dsm_12.tif")
    cars = read_geotiff_dsm(ref / "cars_dsm_12.tif")
    others = [
        read_geotiff_dsm(ref / f"{n}.tif")
        for n in ("s2p_dsm_13", "s2p_dsm_23", "s2p_dsm_123", "cars_dsm_123")
    ]
    res = compare(
        s2p,
        cars,
        images=[MARSEILLE / "img_01.tif", MARSEILLE / "img_02.tif"],
        grid=(s2p.grid, s2p.crs),
        footprint_layers=others,
    )
    s = res.stats
    assert s["median"] == pytest.approx(-0.08, abs=0.01)
    assert s["nmad"] == pytest.approx(0.77, abs=0.01)
    assert s["rms"] == pytest.approx(1.13, abs=0.01)
    assert s["p95_abs"] == pytest.approx(1.69, abs=0.01)
    assert s["cells"] == pytest.approx(899_873, abs=200)
    # footprint 1,017,090 cells; s2p_dsm_12 90.6 %, cars_dsm_12 96.7 % complete in it
    assert res.footprint_cells == pytest.approx(1_017_090, abs=200)
    assert res.completeness == pytest.approx(0.906, abs=0.001)
    assert res.reference_completeness == pytest.approx(0.967, abs=0.001)


def test_horizontal_shift_recovered(tmp_path: Path) -> None:
    """Ours = the hills moved 0.30 m east and 0.20 m south, 0.5 m up: the shift comes back."""
    rows, cols = 240, 240
    e, n = centres(E0, N0, rows, cols)

    def hills(ee: np.ndarray, nn: np.ndarray) -> np.ndarray:
        return 100.0 + 5.0 * np.sin((ee - E0) / 9.0) * np.cos((nn - N0) / 11.0)

    ref_path = write_dsm(tmp_path / "ref.tif", hills(e, n), E0, N0)
    ours_path = write_dsm(tmp_path / "ours.tif", hills(e - 0.30, n + 0.20) + 0.5, E0, N0)
    res = compare(read_geotiff_dsm(ours_path), read_geotiff_dsm(ref_path))
    # first order in the shift: the curvature of 9-11 m hills leaves a few cm
    assert res.extra["shift_e_m"] == pytest.approx(0.30, abs=0.03)
    assert res.extra["shift_n_m"] == pytest.approx(-0.20, abs=0.03)
    assert res.extra["shift_dz_m"] == pytest.approx(0.5, abs=0.03)
    same = compare(read_geotiff_dsm(ref_path), read_geotiff_dsm(ref_path))
    assert abs(same.extra["shift_e_m"]) < 1e-9 and abs(same.extra["shift_n_m"]) < 1e-9
    assert "shift E +0.3" in res.line()


def test_shift_beyond_the_linear_range_is_not_reported(tmp_path: Path) -> None:
    """A DSM 20 m off against 9-11 m hills: no first-order fit; no shift is reported."""
    rows, cols = 200, 200
    e, n = centres(E0, N0, rows, cols)

    def hills(ee: np.ndarray, nn: np.ndarray) -> np.ndarray:
        return 100.0 + 5.0 * np.sin((ee - E0) / 9.0) * np.cos((nn - N0) / 11.0)

    ref = write_dsm(tmp_path / "ref.tif", hills(e, n), E0, N0)
    ours = write_dsm(tmp_path / "ours.tif", hills(e - 20.0, n), E0, N0)
    res = compare(read_geotiff_dsm(ours), read_geotiff_dsm(ref))
    assert math.isnan(res.extra["shift_e_m"]) and res.extra["shift_cells"] == 0
    assert "shift" not in res.line()
