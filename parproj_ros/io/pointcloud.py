"""A DSM GeoTIFF's heights as a LAS/LAZ point cloud (laspy; lazrs for LAZ), with its CRS.

One point per DSM cell with a height: X, Y the cell centre in the file's CRS (map metres), Z the
height written in the cell (WGS84 ellipsoidal, above a geoid, or the frame's Z for a local
frame, as the GeoTIFF says; a 2-D map CRS whose band says ellipsoidal heights, as GDAL reads
the ``target="local"`` files, gets its ellipsoidal height axis back). LAS 1.4, point format 6,
coordinates stored as integers of :data:`SCALE_M` (1 mm) from an offset at the grid's corner;
the CRS as an OGC WKT VLR (global encoding WKT bit set) in the WKT the LAS 1.4 specification
names (OGC 01-009, "WKT1", :func:`las_wkt`), which laspy, PDAL, LAStools and CloudCompare
read. Each point is a single return (return 1 of 1: LAS 1.4 allows no return number 0 in
formats 6-10), not classified (class 0). The header names the software that made the DSM (the
GeoTIFF's ``TIFFTAG_SOFTWARE``). A ``.laz`` path is written LAZ-compressed (lazrs). Rows are
read and written by blocks: memory stays that of one block.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .geotiff import ELLIPSOIDAL

if TYPE_CHECKING:
    from pyproj import CRS

__all__ = ["SCALE_M", "las_wkt", "write_point_cloud"]

#: Coordinate resolution stored in the LAS file, metres.
SCALE_M = 0.001
#: DSM rows read and written at once.
BLOCK_ROWS = 512
#: The header's system identifier (LAS 1.4: "PROCESSING" for data made by processing others).
SYSTEM_ID = "PROCESSING"


def las_wkt(crs: CRS) -> str:
    """The CRS as the WKT of a LAS 1.4 WKT VLR: OGC 01-009 ("WKT1", GDAL's dialect).

    A 3-D projected CRS (map CRS with an ellipsoidal height axis) has no WKT1 of its own (PROJ
    refuses it, or drops the height axis when the CRS came from a GeoTIFF): it is written as GDAL
    does (``ALLOW_ELLIPSOIDAL_HEIGHT_AS_VERTICAL_CRS``), a ``COMPD_CS`` of the
    map CRS and a ``VERT_CS`` whose ``VERT_DATUM`` is of type 2002 (ellipsoidal, OGC 01-009),
    which PROJ and GDAL read back as the 3-D CRS. A CRS with no WKT1 at all: its WKT2.
    """
    from pyproj import CRS as _CRS

    if crs.is_projected and len(crs.axis_info) == 3 and not crs.is_compound:
        horizontal = crs.to_2d()
        code = horizontal.to_epsg()
        if code is not None and _CRS.from_epsg(code).equals(horizontal):
            horizontal = _CRS.from_epsg(code)  # its WKT1 then carries AUTHORITY["EPSG", code]
        base = crs.geodetic_crs
        name = base.name if base is not None else "unknown"
        datum = base.datum.name.removesuffix(" ensemble") if base and base.datum else name
        return (
            f'COMPD_CS["{horizontal.name.removesuffix(f" + {name} ellipsoidal height")} + '
            f'{name} ellipsoidal height",'
            f"{horizontal.to_wkt('WKT1_GDAL')},"
            f'VERT_CS["{name} ellipsoidal height",VERT_DATUM["{datum}",2002],'
            'UNIT["metre",1,AUTHORITY["EPSG","9001"]],AXIS["Ellipsoidal height",UP]]]'
        )
    try:
        return str(crs.to_wkt("WKT1_GDAL"))
    except Exception:  # pyproj's CRSError: not expressible in WKT1
        pass
    return str(crs.to_wkt())


def write_point_cloud(dsm_tif: str | os.PathLike[str], path: str | os.PathLike[str]) -> int:
    """Write the cells of ``dsm_tif`` that have a height as points of a LAS/LAZ file.

    Args:
        dsm_tif: a DSM GeoTIFF (:func:`parproj_ros.io.geotiff.write_dsm_geotiff`).
        path: the ``.las`` or ``.laz`` file to write (replaced; written under a temporary
            name and renamed when complete).

    Returns:
        The number of points written.

    Raises:
        ValueError: a path that ends neither in .las nor in .laz, or a DSM without CRS.
    """
    import laspy
    import rasterio
    from pyproj import CRS

    out = Path(path)
    if out.suffix.lower() not in (".las", ".laz"):
        raise ValueError(f"{out}: a point cloud is written as .las or .laz")
    tmp = out.with_name(f".{out.name}.partial")
    with rasterio.open(dsm_tif) as src:
        if src.crs is None:
            raise ValueError(f"{dsm_tif}: no CRS to give the point cloud")
        crs = CRS.from_wkt(src.crs.to_wkt())
        if (
            crs.is_projected
            and len(crs.axis_info) == 2
            and src.tags(1).get("HEIGHT") == (ELLIPSOIDAL)
        ):  # GDAL reads a 3-D CRS it has no code for (target "local") as 2-D: the band tells
            crs = crs.to_3d()
        t = src.transform
        header = laspy.LasHeader(point_format=6, version="1.4")
        header.scales = np.array([SCALE_M] * 3)
        header.offsets = np.array([np.floor(t.c), np.floor(t.f + src.height * t.e), 0.0])
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(las_wkt(crs)))
        header.global_encoding.wkt = True
        header.system_identifier = SYSTEM_ID
        header.generating_software = src.tags().get("TIFFTAG_SOFTWARE", "parproj_ros")[:31]
        count = 0
        try:
            with laspy.open(tmp, mode="w", header=header, do_compress=out.suffix == ".laz") as w:
                for r0 in range(0, src.height, BLOCK_ROWS):
                    r1 = min(src.height, r0 + BLOCK_ROWS)
                    z = src.read(1, window=((r0, r1), (0, src.width)), masked=True)
                    ok = ~np.ma.getmaskarray(z) & np.isfinite(z.filled(np.nan))
                    rows, cols = np.nonzero(ok)
                    if rows.size == 0:
                        continue
                    pts: Any = laspy.ScaleAwarePointRecord.zeros(rows.size, header=header)
                    pts.x = t.c + (cols + 0.5) * t.a
                    pts.y = t.f + (rows + r0 + 0.5) * t.e
                    pts.z = np.asarray(z.data[ok], dtype=float)
                    pts.return_number[:] = 1  # one return of one: a surface point
                    pts.number_of_returns[:] = 1
                    w.write_points(pts)
                    count += int(rows.size)
            os.replace(tmp, out)
        finally:
            tmp.unlink(missing_ok=True)
    return count
