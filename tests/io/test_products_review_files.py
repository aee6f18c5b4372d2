"""The products as other tools read them (issue 24, "What to build" 2): the LAS point cloud
through laspy and PDAL's conventions, and the one-band layers written beside a DSM.

A synthetic DSM (a tilted plane, 40 x 50 cells of 0.5 m, a hole) on the tangent plane of the
Marseille pair is written by ``write_dsm_geotiff`` and turned into a point cloud by
``write_point_cloud``; the files are read back as a user would (laspy, rasterio, pyproj).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pytest
import rasterio
from pyproj import CRS, Transformer

from parproj_ros.geometry.geodesy import LocalTangentPlane
from parproj_ros.imaging.heights import DsmGrid
from parproj_ros.io.geotiff import write_dsm_geotiff, write_like, write_plain_tiff
from parproj_ros.io.pointcloud import write_point_cloud
from parproj_ros.io.scene_import import frame_id_of

FID = frame_id_of(LocalTangentPlane(43.2617443, 5.4429502, 188.44))
GRID = DsmGrid.covering(-12.0, 12.5, -10.0, 9.5, 0.5)  # 50 x 40 cells
SOFTWARE = "parproj_ros 9.8.7"
#: laspy stores coordinates as integers of 1 mm: a coordinate read back is within half of it.
LAS_TOL = 0.0005 + 1e-9


def heights() -> np.ndarray[Any, np.dtype[np.float32]]:
    r, c = np.mgrid[0 : GRID.height, 0 : GRID.width].astype(float)
    z = (10.0 + 0.02 * c - 0.01 * r).astype(np.float32)
    z[10:14, 20:26] = np.nan
    return z


def cloud(tmp_path: Path, frame: str, **kw: Any) -> tuple[Path, Path]:
    """(DSM GeoTIFF, LAS) of :func:`heights` in ``frame`` (write_dsm_geotiff options ``kw``)."""
    tif, las = tmp_path / "d_dsm.tif", tmp_path / "d_dsm.las"
    write_dsm_geotiff(tif, heights(), GRID, frame, tags={"TIFFTAG_SOFTWARE": SOFTWARE}, **kw)
    write_point_cloud(tif, las)
    return tif, las


def egm(lon: Any, lat: Any) -> Any:
    return np.full(np.shape(lon), 49.6)


@pytest.mark.parametrize(
    ("frame", "options", "opening"),
    [
        (FID, {}, "COMPD_CS["),  # UTM 31N + WGS 84 ellipsoidal height (a 3-D projected CRS)
        # local transverse Mercator: GDAL reads the GeoTIFF's CRS as a 2-D one (docs/products.md);
        # the band says the heights are ellipsoidal: the LAS's CRS is 3-D
        (FID, {"target": "local"}, "COMPD_CS["),
        (FID, {"geoid": (egm, 3855)}, "COMPD_CS["),  # UTM 31N + EGM2008 height
        ("map", {}, "LOCAL_CS["),  # a simulated bag's frame
    ],
    ids=["utm_ellipsoidal", "local_tm_ellipsoidal", "utm_egm2008", "map"],
)
def test_las_points_are_single_returns_with_a_wkt1_crs(
    tmp_path: Path, frame: str, options: dict[str, Any], opening: str
) -> None:
    """LAS 1.4 formats 6-10 allow no return number 0 (1..15), and the WKT VLR is OGC 01-009
    WKT1 (LAS 1.4 R15, "Georeferencing Information Using WKT"). Before: every point had return
    0 of 0 and the VLR held WKT2 (``PROJCRS[...]``), which WKT1 readers (LAStools) refuse. The
    WKT1 must still read back (pyproj, laspy's parse_crs) as the GeoTIFF's CRS, ellipsoidal
    height axis included; the header names the software of the DSM."""
    tif, path = cloud(tmp_path, frame, **options)
    las = laspy.read(path)
    with rasterio.open(tif) as src:
        z = src.read(1)
        t = src.transform
        tif_crs = CRS.from_wkt(src.crs.to_wkt())
    ok = np.isfinite(z)
    assert len(las.points) == int(ok.sum()) > 0.8 * int(np.isfinite(heights()).sum())
    assert np.all(np.asarray(las.return_number) == 1)
    assert np.all(np.asarray(las.number_of_returns) == 1)
    (vlr,) = [v for v in las.header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)]
    assert vlr.string.startswith(opening), vlr.string[:40]
    assert las.header.global_encoding.wkt
    crs = las.header.parse_crs()
    assert crs is not None
    if frame == "map":
        assert crs.equals(tif_crs) and len(crs.axis_info) == 2
    else:  # the GeoTIFF's map CRS (the same lon, lat at its corners), and its vertical axis
        corners = ([t.c, t.c + 50 * t.a], [t.f, t.f + 40 * t.e])
        lonlat = [
            Transformer.from_crs(c.to_2d(), "EPSG:4326", always_xy=True).transform(*corners)
            for c in (crs, tif_crs)
        ]
        assert np.abs(np.subtract(*lonlat)).max() < 1e-10  # degrees: 1e-5 m
        vertical = "Gravity-related height" if "geoid" in options else "Ellipsoidal height"
        assert [a.name for a in crs.axis_info] == ["Easting", "Northing", vertical]
    assert las.header.generating_software == SOFTWARE
    assert las.header.system_identifier == "PROCESSING"
    # each point at its cell's centre, with its height (pixel-is-area geotransform)
    rows, cols = np.nonzero(ok)
    assert np.abs(np.asarray(las.x) - (t.c + (cols + 0.5) * t.a)).max() <= LAS_TOL
    assert np.abs(np.asarray(las.y) - (t.f + (rows + 0.5) * t.e)).max() <= LAS_TOL
    assert np.abs(np.asarray(las.z) - z[ok]).max() <= LAS_TOL


def test_ellipsoidal_wkt1_is_what_gdal_writes(tmp_path: Path) -> None:
    """The 3-D UTM CRS as GDAL writes it in WKT1: a VERT_CS of datum type 2002 (ellipsoidal)."""
    _, path = cloud(tmp_path, FID)
    wkt = laspy.read(path).header.parse_crs()
    assert wkt is not None
    text = next(
        v.string
        for v in laspy.read(path).header.vlrs
        if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)
    )
    assert 'VERT_DATUM["World Geodetic System 1984",2002]' in text
    assert 'AUTHORITY["EPSG","32631"]' in text
    assert wkt.to_2d().to_epsg() == 32631


def test_layer_beside_a_dsm_has_its_unit_and_tags(tmp_path: Path) -> None:
    """write_like: the band's unit and the dataset's tags as given (a spread layer in metres);
    before, a layer had no unit and no way to say what made it."""
    tif, _ = cloud(tmp_path, FID)
    with rasterio.open(tif) as src:
        shape = (src.height, src.width)
    spread = np.full(shape, 0.25, np.float32)
    write_like(
        tmp_path / "spread.tif",
        tif,
        spread,
        nodata=float("nan"),
        description="spread of the samples, metres",
        unit="m",
        tags={"PARPROJ_PAIR_ID": "fused"},
    )
    with rasterio.open(tmp_path / "spread.tif") as src:
        assert src.units == ("m",)
        assert src.descriptions == ("spread of the samples, metres",)
        assert src.tags()["PARPROJ_PAIR_ID"] == "fused"
        assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert float(src.read(1).mean()) == pytest.approx(0.25)


def test_geoid_heights_band_names_the_geoid(tmp_path: Path) -> None:
    """With a geoid (--heights-geoid egm2008) the band says heights above the EGM2008 geoid;
    before it read "height above EGM2008 height" (the vertical CRS's name taken for a surface),
    and VERTICAL_DATUM held the CRS's name, not its datum's."""
    tif, _ = cloud(tmp_path, FID, geoid=(egm, 3855))
    with rasterio.open(tif) as src:
        assert src.descriptions == ("height above the EGM2008 geoid (EGM2008 height), metres",)
        assert src.tags(1)["VERTICAL_DATUM"] == "EGM2008 geoid" and src.units == ("m",)
        h = src.read(1)
    # the heights are h - N: the plane's ellipsoidal heights less the 49.6 m of egm(); 12 m
    # from the origin the plane leaves the ellipsoid by 1e-5 m, the export grid's cells lie
    # within half a cell (0.01 m of the tilt) of the frame grid's
    z = heights()
    assert abs(float(np.nanmedian(h)) - (188.44 + float(np.nanmedian(z)) - 49.6)) < 0.05


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")  # no CRS: meant
def test_disparity_tiff_has_its_unit_and_tags(tmp_path: Path) -> None:
    """write_plain_tiff (the disparity map): band unit "px" and the tags given (software,
    pair); before, the unit was only in the description and nothing named the pair."""
    d = np.linspace(-40.0, 30.0, 60 * 70, dtype=np.float32).reshape(60, 70)
    d[5:9, 5:9] = np.nan
    write_plain_tiff(
        tmp_path / "disp.tif",
        d,
        nodata=float("nan"),
        description="disparity col_left - col_right, px, left normalized grid",
        unit="px",
        tags={"TIFFTAG_SOFTWARE": SOFTWARE, "PARPROJ_PAIR_ID": "left+right"},
    )
    with rasterio.open(tmp_path / "disp.tif") as src:
        assert src.units == ("px",) and src.tags()["PARPROJ_PAIR_ID"] == "left+right"
        assert src.tags()["TIFFTAG_SOFTWARE"] == SOFTWARE and src.crs is None
        back = src.read(1)
    np.testing.assert_array_equal(back, d)
