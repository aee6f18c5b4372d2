"""A DSM GeoTIFF's heights as a LAS/LAZ point cloud (laspy; lazrs for LAZ), with its CRS.

One point per DSM cell with a height: X, Y the cell centre in the file's CRS (map metres), Z the
height written in the cell (WGS84 ellipsoidal, above a geoid, or the frame's Z for a local
frame, as the GeoTIFF says). LAS 1.4, point format 6, coordinates stored as integers of
:data:`SCALE_M` (1 mm) from an offset at the grid's corner; the CRS is the GeoTIFF's, as an OGC
WKT VLR (global encoding WKT bit set), which laspy, PDAL and CloudCompare read. A ``.laz`` path
is written LAZ-compressed (lazrs). Rows are read and written by blocks: memory stays that of
one block.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["SCALE_M", "write_point_cloud"]

#: Coordinate resolution stored in the LAS file, metres.
SCALE_M = 0.001
#: DSM rows read and written at once.
BLOCK_ROWS = 512


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
        t = src.transform
        header = laspy.LasHeader(point_format=6, version="1.4")
        header.scales = np.array([SCALE_M] * 3)
        header.offsets = np.array([np.floor(t.c), np.floor(t.f + src.height * t.e), 0.0])
        header.add_crs(crs)
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
                    w.write_points(pts)
                    count += int(rows.size)
            os.replace(tmp, out)
        finally:
            tmp.unlink(missing_ok=True)
    return count
