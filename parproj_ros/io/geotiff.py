"""GeoTIFF export of a DSM and an ortho-image, with a proper coordinate reference system.

The DSM and the ortho-image of a pair live on a north-up :class:`DsmGrid` in the pair's object
frame (``parproj_ros.imaging.heights``). What that frame is decides what is written:

* an imported (real RPC) pair: a local east-north-up tangent plane on WGS84, named by the frame_id
  ``enu_wgs84:lat=...,lon=...,h=...`` (:func:`parproj_ros.io.scene_import.frame_id_of`). That
  plane is not a map projection, and its Z is the height above the plane, not above the ellipsoid
  (the plane leaves the ellipsoid by d^2 / 2R: 8 cm at 1 km, 2 m at 5 km from the origin). The
  export is an exact reprojection onto a regular north-up grid of a real CRS
  (:func:`crs_for_frame`): the UTM zone of the frame origin (EPSG 326xx north, 327xx south) or
  a transverse Mercator centred on the origin (``target="local"``). Each output cell centre
  (E, N) is taken to geodetic (lon, lat); the ellipsoidal height h of the DSM surface on the
  normal through (lon, lat) is found by fixed-point iteration (point (lon, lat, h) -> ENU
  (x, y, z); h += Z_dsm(x, y) - z; the horizontal (x, y) moves by about d / R = 1e-3 m per
  metre of h at 6 km, so 2-3 rounds get below 1e-5 m), Z_dsm bilinear in the DSM. Heights
  written are WGS84 ellipsoidal heights, metres, and the file's CRS is 3-D (:func:`file_crs`):
  the map CRS with an ellipsoidal height axis, written as GeoTIFF 1.1 says (OGC 19-008r4, annex
  D.3: ``ProjectedCSTypeGeoKey`` and ``VerticalGeoKey`` = 4979, WGS 84 geographic 3-D), which
  GDAL reads back as the 3-D projected CRS; or, with a geoid model (``geoid=``), heights above
  that geoid and a compound CRS (map CRS + the geoid's vertical CRS, e.g. EPSG:5773 EGM96).
  The ortho-image is sampled at the same (x, y) (it needs the DSM heights of its cells for
  that), so both files share one grid and CRS.
* any other frame (a simulated bag's ``map``): a local Cartesian engineering frame, metres, with
  no geodetic anchor. The grid is written as it is (geotransform in frame metres, the exact
  values) with a local engineering CRS (WKT ``ENGCRS`` named after the frame, x east, y north,
  metres; :func:`engineering_crs`), which GDAL writes as a ``LOCAL_CS``.

Files are Cloud Optimized GeoTIFFs (GDAL's COG driver: 256 x 256 tiles, deflate with the
predictor, overviews by averaging down to one tile, the IFDs first), written under a temporary
name and renamed when complete; GDAL's ``IMAGE_STRUCTURE`` metadata says ``LAYOUT=COG``.

No data: float rasters use NaN (DSM) and a nodata value (ortho, default 0). An output cell has a
height only where every DSM cell that its bilinear interpolation weighs (non-zero weight) has
one, so a hole grows by less than one cell and nothing is extrapolated (the outer half cell of
the DSM's border is not written either). Files are float32 (DSM) or the image's dtype (ortho).

:func:`write_plain_tiff` writes an array with no georeferencing (e.g. a disparity map, which
lives in the normalized image's pixel grid; a tiled GeoTIFF, not a COG).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import os
import struct
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry.geodesy import LocalTangentPlane
from ..imaging.heights import DsmGrid, bilinear_terms
from .scene_import import FRAME_PREFIX, frame_from_id

if TYPE_CHECKING:
    from pyproj import CRS

__all__ = [
    "Geoid",
    "Ortho",
    "Target",
    "crs_for_frame",
    "engineering_crs",
    "export_grid",
    "file_crs",
    "frame_of",
    "utm_zone",
    "write_dsm_geotiff",
    "write_like",
    "write_ortho_geotiff",
    "write_plain_tiff",
]

FloatArray = NDArray[np.float64]
Target = Literal["utm", "local"]
#: A geoid model: (N(lon deg, lat deg) -> undulation, metres above the WGS84 ellipsoid; the EPSG
#: code of the vertical CRS of heights above it, e.g. 5773 EGM96 height, 3855 EGM2008 height).
Geoid = tuple[Callable[[FloatArray, FloatArray], FloatArray], int]

#: Output rows computed and written at once (a multiple of the tile height).
BLOCK_ROWS = 256
#: Tile side, pixels.
TILE = 256
#: Fixed-point rounds for the ellipsoidal height of an output cell, and the step (m) ending them.
MAX_ROUNDS = 12
HEIGHT_TOL_M = 1e-5
#: Tag and band texts.
ELLIPSOIDAL = "ellipsoidal height above WGS84, metres"
NO_CRS_NOTE = (
    "local engineering frame {frame!r}: Cartesian metres, no geodetic anchor "
    "(X east-like, Y north-like as the frame defines them)"
)
#: EPSG codes of the vertical CRS of heights above a geoid model, by model name.
VERTICAL_EPSG = {"egm2008": 3855, "egm96": 5773}
#: GeoTIFF keys: VerticalGeoKey, and WGS 84 geographic 3-D (the code that says "ellipsoidal
#: heights" there, GeoTIFF 1.1 annex D.3).
VERTICAL_GEO_KEY = 4096
WGS84_3D = 4979
#: The vertical CRS GDAL is handed for an ellipsoidal-height file (its writer encodes no 3-D
#: projected CRS in GeoTIFF keys): the key is then set to :data:`WGS84_3D` in place.
PLACEHOLDER_VERTICAL = 5773
#: COG creation options (GDAL COG driver) besides the compression's predictor.
COG_OPTIONS = {
    "COMPRESS": "DEFLATE",
    "PREDICTOR": "YES",
    "BLOCKSIZE": str(TILE),
    "OVERVIEWS": "AUTO",
    "RESAMPLING": "AVERAGE",
    "BIGTIFF": "IF_SAFER",
}


# ---------------------------------------------------------------------------------------------
# Frames and CRS


def frame_of(frame_id: str) -> LocalTangentPlane | None:
    """The local tangent plane a frame_id names; None for a frame without a geodetic anchor.

    Raises:
        ValueError: a frame_id with the tangent-plane prefix that does not parse.
    """
    if frame_id.strip().startswith(FRAME_PREFIX + ":"):
        return frame_from_id(frame_id)
    return None


def utm_zone(lon_deg: float, lat_deg: float) -> tuple[int, bool]:
    """(zone 1..60, north) of the UTM zone holding a point (Norway and Svalbard exceptions).

    Args:
        lon_deg: longitude, degrees (any turn; normalized to [-180, 180)).
        lat_deg: latitude, degrees, within UTM's [-80, 84].

    Raises:
        ValueError: a latitude outside UTM (polar: use ``target="local"``).
    """
    if not (math.isfinite(lon_deg) and -80.0 <= lat_deg <= 84.0):
        raise ValueError(
            f"no UTM zone at lat {lat_deg}, lon {lon_deg} (UTM spans 80 S to 84 N); "
            "use target='local'"
        )
    lon = (lon_deg + 180.0) % 360.0 - 180.0
    zone = min(math.floor((lon + 180.0) / 6.0) + 1, 60)
    if 56.0 <= lat_deg < 64.0 and 3.0 <= lon < 12.0:
        zone = 32  # 32V covers south-west Norway
    elif lat_deg >= 72.0 and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37  # Svalbard
    return zone, lat_deg >= 0.0


def engineering_crs(frame_id: str) -> CRS:
    """The local engineering CRS of a frame without a geodetic anchor (e.g. ``map``).

    WKT ``ENGCRS`` named after the frame: Cartesian, x east, y north, metres (GDAL writes it as
    a GeoTIFF ``LOCAL_CS``; GIS tools show the grid in metres and place it nowhere on Earth).
    """
    from pyproj import CRS

    name = " ".join(str(frame_id).split()).replace('"', "'") or "unnamed"
    return CRS.from_wkt(
        f'ENGCRS["parproj local frame {name}",EDATUM["{name}"],CS[Cartesian,2],'
        'AXIS["x (E)",east,ORDER[1],LENGTHUNIT["metre",1]],'
        'AXIS["y (N)",north,ORDER[2],LENGTHUNIT["metre",1]]]'
    )


def crs_for_frame(frame_id: str, *, target: Target = "utm") -> CRS:
    """The horizontal CRS an object frame is exported in (the file's is :func:`file_crs`).

    Args:
        frame_id: the object frame; ``enu_wgs84:lat=...,lon=...,h=...`` for an imported pair.
        target: "utm": WGS 84 / UTM zone of the frame origin (EPSG 326zz north, 327zz south);
            "local": a transverse Mercator on WGS84 centred on the origin (scale 1, no false
            easting or northing), metres.

    Returns:
        A 2-D ``pyproj.CRS``: projected for a tangent-plane frame; for any other frame (e.g.
        ``map``: a local frame in metres with no geodetic anchor) its
        :func:`engineering_crs`.

    Raises:
        ValueError: an unknown target, a malformed tangent-plane frame_id, or a UTM target
            outside UTM's latitudes.
    """
    from pyproj import CRS
    from pyproj.crs import ProjectedCRS
    from pyproj.crs.coordinate_operation import TransverseMercatorConversion

    if target not in ("utm", "local"):
        raise ValueError(f"target must be 'utm' or 'local', got {target!r}")
    frame = frame_of(frame_id)
    if frame is None:
        return engineering_crs(frame_id)
    if target == "utm":
        zone, north = utm_zone(frame.lon0, frame.lat0)
        return CRS.from_epsg((32600 if north else 32700) + zone)
    return ProjectedCRS(
        conversion=TransverseMercatorConversion(
            latitude_natural_origin=frame.lat0,
            longitude_natural_origin=frame.lon0,
            false_easting=0.0,
            false_northing=0.0,
            scale_factor_natural_origin=1.0,
        ),
        geodetic_crs=CRS.from_epsg(4326),  # WGS 84
        name=f"WGS 84 / local transverse Mercator (lat {frame.lat0:.7f}, lon {frame.lon0:.7f})",
    )


def file_crs(frame_id: str, *, target: Target = "utm", geoid_epsg: int | None = None) -> CRS:
    """The CRS a DSM file of this frame carries: 3-D for a tangent-plane frame.

    Args:
        frame_id: the object frame.
        target: "utm" or "local" (:func:`crs_for_frame`).
        geoid_epsg: EPSG code of the vertical CRS of the heights (e.g. 5773, EGM96 height);
            None: WGS84 ellipsoidal heights.

    Returns:
        Tangent-plane frame: the map CRS with an ellipsoidal height axis (``to_3d``), or the
        compound CRS map + vertical; any other frame: its 2-D engineering CRS.
    """
    from pyproj import CRS
    from pyproj.crs import CompoundCRS

    horizontal = crs_for_frame(frame_id, target=target)
    if frame_of(frame_id) is None:
        return horizontal
    if geoid_epsg is None:
        return horizontal.to_3d()
    vertical = CRS.from_epsg(int(geoid_epsg))
    if not vertical.is_vertical:
        raise ValueError(f"EPSG:{geoid_epsg} is not a vertical CRS ({vertical.name})")
    return CompoundCRS(
        name=f"{horizontal.name} + {vertical.name}", components=[horizontal, vertical]
    )


# ---------------------------------------------------------------------------------------------
# Sampling a grid at object (x, y)


class _Reprojection:
    """Output cells of a map grid -> object (x, y) and ellipsoidal height on the DSM surface."""

    def __init__(
        self,
        frame: LocalTangentPlane,
        crs: CRS,
        heights: NDArray[np.floating[Any]],
        grid: DsmGrid,
        out: DsmGrid,
    ) -> None:
        from pyproj import CRS as _CRS
        from pyproj import Transformer

        self.frame = frame
        self.heights = heights
        self.grid = grid
        self.out = out
        self.valid = np.isfinite(heights)
        z = heights[self.valid]
        self.z_ref = float(np.median(z)) if z.size else 0.0
        self.to_geodetic = Transformer.from_crs(crs, _CRS.from_epsg(4326), always_xy=True)
        #: (lon, lat) degrees of the cell centres of the last :meth:`rows`.
        self.lonlat: tuple[FloatArray, FloatArray] = (np.zeros(0), np.zeros(0))

    def rows(self, r0: int, r1: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Object (x, y) metres and ellipsoidal height h metres of output rows r0:r1.

        (x, y) is where the DSM surface meets the ellipsoid normal through the cell centre's
        (lon, lat); h is NaN where the DSM has no bilinear height there.
        """
        e, n = self.out.centres((r0, r1))
        lon, lat = self.to_geodetic.transform(e, n)
        lon = np.asarray(lon, dtype=float)
        lat = np.asarray(lat, dtype=float)
        self.lonlat = (lon, lat)
        frame = self.frame
        h = np.full(e.shape, frame.h0 + self.z_ref)
        flat_lon, flat_lat, flat_h = lon.ravel(), lat.ravel(), h.reshape(-1)
        # Only the cells still moving are iterated: a cell stops once its step is below
        # HEIGHT_TOL_M, or has no height around it (NaN: its position no longer changes). A cell
        # on a near-vertical wall (a quarry bench) may have no fixed point and swing for every
        # round; it alone no longer makes the whole block iterate (Marseille: 1 cell of 55,000).
        active = np.arange(flat_h.size)
        for _ in range(MAX_ROUNDS):
            x, y, z = frame.to_local(flat_lon[active], flat_lat[active], flat_h[active])
            total, _, wsum, _ = bilinear_terms(self.heights, self.grid, x, y, self.valid)
            with np.errstate(invalid="ignore", divide="ignore"):
                dh = total / wsum - z  # NaN-tolerant (weights of valid neighbours) while iterating
            step = np.isfinite(dh)
            flat_h[active[step]] += dh[step]
            active = active[step & (np.abs(np.where(step, dh, 0.0)) >= HEIGHT_TOL_M)]
            if active.size == 0:
                break
        x, y, z = frame.to_local(lon, lat, h)
        total, ok, _, _ = bilinear_terms(self.heights, self.grid, x, y, self.valid)
        return x, y, np.where(ok, h + (total - z), np.nan)


# ---------------------------------------------------------------------------------------------
# The output grid


def _edge_points(grid: DsmGrid) -> tuple[FloatArray, FloatArray]:
    """Object (x, y) along the outline of the grid's cells (outer corners included), metres."""
    half = 0.5 * grid.cell
    xa = grid.x0 - half
    xb = grid.x0 + (grid.width - 1) * grid.cell + half
    ya = grid.y0 + half
    yb = grid.y0 - (grid.height - 1) * grid.cell - half
    t = np.linspace(0.0, 1.0, 513)
    xs = np.concatenate(
        [xa + (xb - xa) * t, xa + (xb - xa) * t, np.full(513, xa), np.full(513, xb)]
    )
    ys = np.concatenate(
        [np.full(513, ya), np.full(513, yb), ya + (yb - ya) * t, ya + (yb - ya) * t]
    )
    return xs, ys


def _check_grid(name: str, array: NDArray[Any], grid: DsmGrid) -> None:
    if array.shape != (grid.height, grid.width):
        raise ValueError(
            f"{name} has shape {array.shape}, the grid is {grid.height} x {grid.width} cells"
        )


def export_grid(
    grid: DsmGrid,
    frame_id: str,
    heights: ArrayLike | None = None,
    *,
    target: Target = "utm",
    resolution: float | None = None,
) -> tuple[CRS, DsmGrid]:
    """The horizontal CRS and north-up grid a DSM (and its ortho-image) are exported on.

    For a tangent-plane frame: the grid of cell ``resolution`` (default ``grid.cell``), centres
    on multiples of it in map metres, covering the map position of the grid's outline at the
    lowest and the highest valid height (at Z = 0 without heights). For any other frame: its
    engineering CRS and ``grid`` itself.

    Args:
        grid: the DSM grid in the object frame.
        frame_id: the object frame (see :func:`crs_for_frame`).
        heights: the DSM, Z metres in the object frame, (grid.height, grid.width).
        target: "utm" or "local".
        resolution: output cell side, map metres (tangent-plane frames only).

    Returns:
        (crs, grid): ``DsmGrid`` in map metres (x0 = easting, y0 = northing of the centre of
        the first cell).
    """
    crs = crs_for_frame(frame_id, target=target)
    frame = frame_of(frame_id)
    if frame is None:
        if resolution is not None and resolution != grid.cell:
            raise ValueError(
                f"frame {frame_id!r} is a local frame (no geodetic anchor, no map CRS): its "
                "grid is written as it is "
                f"(cell {grid.cell} m), not resampled to {resolution} m"
            )
        return crs, grid
    from pyproj import CRS as _CRS
    from pyproj import Transformer

    cell = grid.cell if resolution is None else float(resolution)
    if not (cell > 0 and math.isfinite(cell)):
        raise ValueError(f"resolution must be a finite size > 0 m, got {resolution}")
    zs = [0.0]
    if heights is not None:
        z = np.asarray(heights, dtype=float)
        _check_grid("heights", z, grid)
        if np.isfinite(z).any():
            zs = [float(np.nanmin(z)), float(np.nanmax(z))]
    x, y = _edge_points(grid)
    fwd = Transformer.from_crs(_CRS.from_epsg(4326), crs, always_xy=True)
    es, ns = [], []
    for zz in zs:
        lon, lat, _ = frame.to_geodetic(x, y, zz)
        e, n = fwd.transform(lon, lat)
        es.append(np.asarray(e))
        ns.append(np.asarray(n))
    e_all, n_all = np.concatenate(es), np.concatenate(ns)
    half = 0.5 * cell  # the outline is of cell edges: keep cells whose centre is inside it
    return crs, DsmGrid.covering(
        float(e_all.min()) + half,
        float(e_all.max()) - half,
        float(n_all.min()) + half,
        float(n_all.max()) - half,
        cell,
    )


# ---------------------------------------------------------------------------------------------
# Writing


def _spans(n: int) -> Iterator[tuple[int, int]]:
    for s in range(0, n, BLOCK_ROWS):
        yield s, min(n, s + BLOCK_ROWS)


def _written_crs(crs: CRS) -> CRS:
    """The CRS handed to GDAL for a file whose CRS is ``crs`` (see :func:`_set_ellipsoidal`).

    GDAL's GeoTIFF writer keeps a 3-D projected CRS only in a side file (``.aux.xml``): it is
    handed the compound of the map CRS and :data:`PLACEHOLDER_VERTICAL`, whose
    ``VerticalGeoKey`` is then set to :data:`WGS84_3D`.
    """
    from pyproj.crs import CompoundCRS

    if crs.is_projected and len(crs.axis_info) == 3 and not crs.is_compound:
        from pyproj import CRS as _CRS

        horizontal = crs.to_2d()
        return CompoundCRS(
            name=f"{horizontal.name} + WGS 84 ellipsoidal height",
            components=[horizontal, _CRS.from_epsg(PLACEHOLDER_VERTICAL)],
        )
    return crs


def _profile(grid: DsmGrid, dtype: np.dtype[Any], crs: CRS, nodata: float) -> dict[str, Any]:
    """The intermediate tiled GeoTIFF's profile (uncompressed; the COG copy compresses)."""
    from rasterio.crs import CRS as RIO_CRS
    from rasterio.transform import Affine

    half = 0.5 * grid.cell
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": grid.width,
        "height": grid.height,
        "count": 1,
        "dtype": dtype.name,
        "transform": Affine(grid.cell, 0.0, grid.x0 - half, 0.0, -grid.cell, grid.y0 + half),
        "crs": RIO_CRS.from_wkt(_written_crs(crs).to_wkt()),
        "nodata": nodata,
        "tiled": True,
        "blockxsize": TILE,
        "blockysize": TILE,
        "BIGTIFF": "IF_SAFER",
    }
    return profile


class _Staged:
    """Write to ``.<name>.partial`` beside ``path``; rename onto ``path`` when complete."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.partial")

    def __enter__(self) -> Path:
        return self.tmp

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)


def _set_ellipsoidal(path: Path) -> None:
    """Set the file's ``VerticalGeoKey`` from :data:`PLACEHOLDER_VERTICAL` to :data:`WGS84_3D`.

    In place (two bytes of the GeoKeyDirectory; nothing moves, the COG layout stays valid).

    Raises:
        ValueError: the file has no such key (GDAL wrote the CRS otherwise).
    """
    import tifffile

    with tifffile.TiffFile(path) as tf:
        tag = tf.pages.first.tags.get(34735)  # GeoKeyDirectoryTag, shorts
        if tag is None:
            raise ValueError(f"{path}: GDAL wrote no GeoTIFF keys")
        values, offset, order = tuple(tag.value), int(tag.valueoffset), tf.byteorder
    for k in range(int(values[3])):
        key, location, _, value = values[4 + 4 * k : 8 + 4 * k]
        if key == VERTICAL_GEO_KEY and location == 0 and value == PLACEHOLDER_VERTICAL:
            with open(path, "r+b") as f:
                f.seek(offset + 2 * (4 + 4 * k + 3))
                f.write(struct.pack(f"{order}H", WGS84_3D))
            return
    raise ValueError(f"{path}: no VerticalGeoKey {PLACEHOLDER_VERTICAL} written by GDAL")


@contextlib.contextmanager
def _c_stderr() -> Iterator[list[str]]:
    """What C code writes to file descriptor 2 inside the block, captured (one string).

    libtiff's own error handler prints ``_tiffWriteProc: No space left on device.`` straight to
    fd 2, past GDAL's and rasterio's handlers: a disk full showed seven such lines before the
    command's one line. Captured into a temporary file; the caller gives it back or uses it.
    Without a usable fd 2 (or temporary file) nothing is captured.
    """
    import sys
    import tempfile

    got: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
        tmp = tempfile.TemporaryFile()
    except (OSError, ValueError):
        yield got
        return
    try:
        os.dup2(tmp.fileno(), 2)
        try:
            yield got
        finally:
            with contextlib.suppress(OSError, ValueError):
                sys.stderr.flush()
            os.dup2(saved, 2)
            tmp.seek(0)
            got.append(tmp.read().decode(errors="replace"))
    finally:
        os.close(saved)
        tmp.close()


def _disk_full(err: BaseException, c_text: str, folder: Path) -> str | None:
    """Why a GeoTIFF write failed, when the reason is a full file system (else None)."""
    import errno
    import shutil

    from .raster import gdal_error

    words = gdal_error(err)
    full = isinstance(err, OSError) and err.errno == errno.ENOSPC
    full = full or "No space left on device" in f"{words} {c_text}"
    if not full:
        return None
    try:
        free = f"{shutil.disk_usage(folder).free / 1e6:.1f} MB free there"
    except OSError:
        free = "its free space unknown"
    return f"No space left on device ({free}; GDAL: {words}): free some space or write elsewhere"


#: How many :func:`_cog` writers are open in this context (a DSM and its ortho-image: 2).
_OPEN_COGS: contextvars.ContextVar[int] = contextvars.ContextVar("_OPEN_COGS", default=0)


@contextlib.contextmanager
def _cog(path: str | os.PathLike[str], profile: dict[str, Any], crs: CRS) -> Iterator[Any]:
    """A writer for ``path`` as a Cloud Optimized GeoTIFF in ``crs``.

    The body writes a tiled GeoTIFF (``.<name>.tiled.partial``); GDAL's COG driver copies it
    (:data:`COG_OPTIONS`) to ``.<name>.partial``, whose vertical key is set for ellipsoidal
    heights, then renamed onto ``path``. Nothing is left behind on an error.

    Raises:
        OSError: ENOSPC, naming ``path``, when the file system fills up ("No space left on
            device", the free space and GDAL's words), instead of rasterio's "Write failed.
            See previous exception for details." and libtiff's lines on stderr. Its folder is
            named instead when the caller's own writes in the body failed while another
            writer is open around this one (a DSM and its ortho-image): the innermost cannot
            tell whose write it was.
    """
    import sys

    from rasterio.shutil import copy as rio_copy

    final = Path(path)
    plain = final.with_name(f".{final.name}.tiled.partial")
    staged = final.with_name(f".{final.name}.partial")
    written = _written_crs(crs)
    failed = in_body = False
    beside = _OPEN_COGS.get()  # writers open around this one
    token = _OPEN_COGS.set(beside + 1)
    c_text: list[str] = []
    try:
        with _c_stderr() as c_text:
            try:
                with _open_writer(plain, profile) as dst:
                    try:
                        yield dst
                    except BaseException:
                        # raised by the caller's writes: maybe into another file open beside
                        # this one (a DSM's ortho-image), so this one is not the one to name
                        in_body = True
                        raise
                with warnings.catch_warnings():
                    from rasterio.errors import NotGeoreferencedWarning

                    warnings.simplefilter("ignore", NotGeoreferencedWarning)
                    rio_copy(plain, staged, driver="COG", **COG_OPTIONS)
                if written is not crs:
                    _set_ellipsoidal(staged)
                os.replace(staged, final)
            except Exception:
                failed = True
                raise
        text = "".join(c_text)
        if text and not failed:
            sys.stderr.write(text)  # nothing of a success is lost
    except Exception as err:
        import errno

        if isinstance(err, OSError) and err.errno == errno.ENOSPC and err.filename:
            raise  # said already (another file of the same write, e.g. the DSM's ortho-image)
        why = _disk_full(err, "".join(c_text), final.parent)
        if why is None:
            sys.stderr.write("".join(c_text))  # another failure: what C code said stays shown
            raise
        # a failure of the caller's writes with another file open beside this one names the
        # folder both fill, not this file
        shared = in_body and beside > 0
        raise OSError(errno.ENOSPC, why, str(final.parent if shared else final)) from None
    except BaseException:  # KeyboardInterrupt, SystemExit: what C code said stays shown
        sys.stderr.write("".join(c_text))
        raise
    finally:
        _OPEN_COGS.reset(token)
        for leftover in (plain, staged):
            leftover.unlink(missing_ok=True)
            Path(f"{leftover}.aux.xml").unlink(missing_ok=True)


def _tags(frame_id: str, crs: CRS, target: Target, what: str) -> dict[str, str]:
    if frame_of(frame_id) is None:
        note = NO_CRS_NOTE.format(frame=frame_id)
    else:
        note = (
            f"{what} reprojected exactly from the local tangent plane {frame_id} "
            f"to {crs.name} ({target})"
        )
    return {
        "TIFFTAG_IMAGEDESCRIPTION": f"parproj_ros {what}: {note}",
        "PARPROJ_SOURCE_FRAME": frame_id,
        "PARPROJ_CRS": crs.name,
    }


def _open_writer(tmp: Path, profile: dict[str, Any]) -> Any:
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        return rasterio.open(tmp, "w", **profile)


@dataclass(frozen=True)
class Ortho:
    """An ortho-image written beside a DSM, on its grid and CRS (:func:`write_dsm_geotiff`).

    Attributes:
        path: the GeoTIFF to write (replaced if it exists).
        image: uint8, uint16, int16, float32 ... (grid.height, grid.width), on the DSM grid.
        nodata: the image's no-data value.
        interpolation: see :func:`write_ortho_geotiff`.
        tags: further dataset tags (e.g. the software and the pair that made it).
    """

    path: str | os.PathLike[str]
    image: NDArray[Any]
    nodata: float = 0
    interpolation: Literal["bilinear", "nearest"] = "bilinear"
    tags: Mapping[str, str] | None = None


def _ortho_header(dst: Any, frame_id: str, crs: CRS, target: Target) -> None:
    dst.update_tags(**_tags(frame_id, crs, target, "ortho-image"))
    dst.set_band_description(1, "ortho-image (left scene on the DSM)")


def _ortho_block(
    ortho: Ortho, grid: DsmGrid, x: FloatArray, y: FloatArray, h: FloatArray
) -> NDArray[Any]:
    """The ortho-image's values at the object (x, y) of output cells with a height ``h``."""
    v = _sample_image(ortho.image, grid, x, y, ortho.nodata, ortho.interpolation)
    return _cast(np.where(np.isfinite(h), v, ortho.nodata), ortho.image.dtype)


def write_dsm_geotiff(
    path: str | os.PathLike[str],
    dsm_heights: ArrayLike,
    grid: DsmGrid,
    frame_id: str,
    *,
    target: Target = "utm",
    nodata: float = math.nan,
    resolution: float | None = None,
    geoid: Geoid | None = None,
    tags: Mapping[str, str] | None = None,
    ortho: Ortho | None = None,
) -> tuple[CRS, DsmGrid]:
    """Write a DSM as a float32 Cloud Optimized GeoTIFF in the CRS of its frame.

    Tangent-plane frame (``enu_wgs84:...``): exact reprojection (module doc) onto
    :func:`export_grid`; values are WGS84 ellipsoidal heights, metres (3-D CRS: map CRS +
    ellipsoidal height), or with ``geoid`` heights above it, h - N (compound CRS). Other
    frames: the grid as it is, values Z in the frame, metres, local engineering CRS.

    Args:
        path: the GeoTIFF to write (replaced if it exists).
        dsm_heights: Z, metres in the object frame, float (grid.height, grid.width), NaN for
            holes (:attr:`parproj_ros.imaging.heights.Dsm.heights`).
        grid: the DSM's grid in the object frame.
        frame_id: the object frame.
        target: "utm" (zone of the frame origin) or "local" (transverse Mercator at it).
        nodata: value written for cells without a height (NaN by default).
        resolution: output cell side, map metres (default: ``grid.cell``).
        geoid: (N(lon, lat) metres, EPSG code of its vertical CRS): heights written above that
            geoid (tangent-plane frames only).
        tags: further dataset tags (e.g. how the heights were made).
        ortho: an ortho-image to write beside it on the same grid and CRS, from the same
            reprojection (as :func:`write_ortho_geotiff` would write it, without computing the
            cells' positions a second time).

    Returns:
        (crs, grid) of the file: :func:`file_crs` and the grid in its horizontal metres.
    """
    z = np.asarray(dsm_heights, dtype=np.float32)
    _check_grid("dsm_heights", z, grid)
    horizontal, out = export_grid(grid, frame_id, z, target=target, resolution=resolution)
    frame = frame_of(frame_id)
    if geoid is not None and frame is None:
        raise ValueError(f"frame {frame_id!r} has no geodetic anchor: no geoid heights")
    crs = file_crs(frame_id, target=target, geoid_epsg=None if geoid is None else geoid[1])
    profile = _profile(out, np.dtype(np.float32), crs, nodata)
    if ortho is not None:
        _check_grid("ortho image", np.asarray(ortho.image), grid)
    with contextlib.ExitStack() as files:
        dst = files.enter_context(_cog(path, profile, crs))
        odst = None
        if ortho is not None:
            oprofile = _profile(out, ortho.image.dtype, crs, ortho.nodata)
            odst = files.enter_context(_cog(ortho.path, oprofile, crs))
            _ortho_header(odst, frame_id, crs, target)
            odst.update_tags(**dict(ortho.tags or {}))
        dst.update_tags(**_tags(frame_id, crs, target, "DSM"), **dict(tags or {}))
        if frame is None:
            dst.set_band_description(1, f"height Z in frame {frame_id}, metres")
            dst.update_tags(1, HEIGHT="Z in the local frame, metres")
            dst.write(np.where(np.isfinite(z), z, np.float32(nodata)).astype(np.float32), 1)
            if odst is not None and ortho is not None:
                odst.write(ortho.image, 1)
        else:
            datum, vertical = "WGS84 ellipsoid", ELLIPSOIDAL
            if geoid is not None:
                vcrs = crs.sub_crs_list[1]
                datum = vcrs.datum.name if vcrs.datum is not None else vcrs.name
                # e.g. "height above the EGM2008 geoid (EGM2008 height), metres"
                vertical = f"height above the {datum} ({vcrs.name}), metres"
            dst.set_band_description(1, vertical)
            dst.update_tags(1, HEIGHT=vertical, VERTICAL_DATUM=datum)
            rep = _Reprojection(frame, horizontal, z, grid, out)
            for r0, r1 in _spans(out.height):
                x, y, h = rep.rows(r0, r1)
                window = ((r0, r1), (0, out.width))
                if odst is not None and ortho is not None:
                    odst.write(_ortho_block(ortho, grid, x, y, h), 1, window=window)
                if geoid is not None:
                    h = h - np.asarray(geoid[0](*rep.lonlat), dtype=float)
                block = np.where(np.isfinite(h), h, nodata).astype(np.float32)
                dst.write(block, 1, window=window)
        # "m": GDAL stores no unit equal to the name of a vertical CRS unit ("metre"), which the
        # ellipsoidal-height key then does not give back
        dst.set_band_unit(1, "m")
    return crs, out


def _sample_image(
    image: NDArray[Any],
    grid: DsmGrid,
    x: FloatArray,
    y: FloatArray,
    nodata: float,
    interpolation: Literal["bilinear", "nearest"],
) -> FloatArray:
    """Image values at object (x, y), metres (float64; nodata where there is none).

    Bilinear where every weighed pixel has data, else the nearest pixel; nodata outside the
    grid's centre box or where (x, y) is NaN.
    """
    valid = image != nodata if image.dtype.kind != "f" else np.isfinite(image) & (image != nodata)
    total, ok, _, nearest = bilinear_terms(image, grid, x, y, valid)
    out = nearest if interpolation == "nearest" else np.where(ok, total, nearest)
    return np.where(np.isfinite(out), out, nodata)


def _cast(values: FloatArray, dtype: np.dtype[Any]) -> NDArray[Any]:
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(dtype)
    return values.astype(dtype)


def write_ortho_geotiff(
    path: str | os.PathLike[str],
    image: ArrayLike,
    grid: DsmGrid,
    frame_id: str,
    *,
    heights: ArrayLike | None = None,
    target: Target = "utm",
    nodata: float = 0,
    resolution: float | None = None,
    interpolation: Literal["bilinear", "nearest"] = "bilinear",
    geoid_epsg: int | None = None,
) -> tuple[CRS, DsmGrid]:
    """Write an ortho-image on a DSM grid as a Cloud Optimized GeoTIFF (its dtype kept).

    Tangent-plane frame: each output cell takes the image at the object (x, y) where the DSM
    surface meets the ellipsoid normal through the cell centre, exactly as
    :func:`write_dsm_geotiff` does with the same ``heights``, ``target`` and ``resolution``:
    the two files share CRS and grid. Other frames: the image as it is, engineering CRS.

    Args:
        path: the GeoTIFF to write (replaced if it exists).
        image: uint8, uint16, int16, float32 ... (grid.height, grid.width), on the DSM grid
            (:func:`parproj_ros.imaging.heights.orthoimage`).
        grid: the DSM grid in the object frame.
        frame_id: the object frame.
        heights: the DSM the ortho-image was made on, Z metres in the object frame; needed
            for a tangent-plane frame (a cell's map position depends on its height by about
            d / R per metre: 0.8 m at 5 km from the origin for 1000 m).
        target: "utm" or "local".
        nodata: the image's no-data value (written as the file's nodata).
        resolution: output cell side, map metres (default: ``grid.cell``).
        interpolation: "bilinear" (where all weighed pixels have data, else the nearest
            pixel; integers rounded) or "nearest".
        geoid_epsg: the DSM's vertical CRS when written with a geoid (:func:`file_crs`).

    Returns:
        (crs, grid) of the file.

    Raises:
        ValueError: shapes that do not match the grid, or no ``heights`` for a tangent-plane
            frame.
    """
    img = np.asarray(image)
    _check_grid("image", img, grid)
    if img.dtype.kind not in "iuf":
        raise ValueError(f"image must be of an integer or float type, got {img.dtype}")
    frame = frame_of(frame_id)
    z: NDArray[np.float32] | None = None
    if heights is not None:
        z = np.asarray(heights, dtype=np.float32)
        _check_grid("heights", z, grid)
    elif frame is not None:
        raise ValueError(
            f"frame {frame_id!r} is a tangent plane: give the DSM heights of the ortho-image's "
            "cells (heights=...), its cells' map positions depend on them"
        )
    horizontal, out = export_grid(grid, frame_id, z, target=target, resolution=resolution)
    crs = file_crs(frame_id, target=target, geoid_epsg=geoid_epsg)
    profile = _profile(out, img.dtype, crs, nodata)
    spec = Ortho(path, img, nodata, interpolation)
    with _cog(path, profile, crs) as dst:
        _ortho_header(dst, frame_id, crs, target)
        if frame is None or z is None:
            dst.write(img, 1)
        else:
            rep = _Reprojection(frame, horizontal, z, grid, out)
            for r0, r1 in _spans(out.height):
                x, y, h = rep.rows(r0, r1)
                dst.write(_ortho_block(spec, grid, x, y, h), 1, window=((r0, r1), (0, out.width)))
    return crs, out


def write_like(
    path: str | os.PathLike[str],
    like: str | os.PathLike[str],
    array: ArrayLike,
    *,
    nodata: float | None = None,
    description: str = "",
    unit: str = "",
    tags: Mapping[str, str] | None = None,
) -> None:
    """Write one band on the grid and CRS of the GeoTIFF ``like`` (e.g. a DSM's count layer).

    A Cloud Optimized GeoTIFF like the others of this module; the CRS read from ``like`` (a
    3-D one included: its ellipsoidal height key is written the same way), its geotransform,
    ``array``'s dtype. ``description``: the band's description and the file's
    ``TIFFTAG_IMAGEDESCRIPTION``; ``unit``: the band's unit (e.g. "m"); ``tags``: further
    dataset tags.

    Raises:
        ValueError: ``array`` is not of ``like``'s shape, or not an integer or float array.
    """
    import rasterio
    from pyproj import CRS as _CRS

    a = np.asarray(array)
    with rasterio.open(like) as src:
        shape, transform = (src.height, src.width), src.transform
        crs = None if src.crs is None else _CRS.from_wkt(src.crs.to_wkt())
    if a.shape != shape or a.dtype.kind not in "iuf":
        raise ValueError(
            f"need a {shape} integer or float array like {like}, got {a.dtype} {a.shape}"
        )
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": shape[1],
        "height": shape[0],
        "count": 1,
        "dtype": a.dtype.name,
        "transform": transform,
        "nodata": nodata,
        "tiled": True,
        "blockxsize": TILE,
        "blockysize": TILE,
        "BIGTIFF": "IF_SAFER",
    }
    if crs is None:
        raise ValueError(f"{like}: no CRS to write {path} in")
    from rasterio.crs import CRS as RIO_CRS

    profile["crs"] = RIO_CRS.from_wkt(_written_crs(crs).to_wkt())
    with _cog(path, profile, crs) as dst:
        if description:
            dst.update_tags(TIFFTAG_IMAGEDESCRIPTION=description)
            dst.set_band_description(1, description)
        dst.update_tags(**dict(tags or {}))
        if unit:
            dst.set_band_unit(1, unit)
        dst.write(a, 1)


def write_plain_tiff(
    path: str | os.PathLike[str],
    array: ArrayLike,
    *,
    nodata: float | None = None,
    description: str = "",
    unit: str = "",
    tags: Mapping[str, str] | None = None,
) -> None:
    """Write one 2-D array as a TIFF with no georeferencing (deflate, tiled), dtype kept.

    For rasters in an image's pixel grid, e.g. a disparity map (float32, pixels, NaN where
    invalid): row 0 is the image's first row, no geotransform, no CRS. ``unit``: the band's
    unit (e.g. "px"); ``tags``: further dataset tags.
    """
    a = np.asarray(array)
    if a.ndim != 2 or a.dtype.kind not in "iuf":
        raise ValueError(f"need a 2-D integer or float array, got {a.dtype} {a.shape}")
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": a.shape[1],
        "height": a.shape[0],
        "count": 1,
        "dtype": a.dtype.name,
        "nodata": nodata,
        "compress": "deflate",
        "predictor": 3 if a.dtype.kind == "f" else 2,
        "tiled": True,
        "blockxsize": TILE,
        "blockysize": TILE,
        "BIGTIFF": "IF_SAFER",
    }
    with _Staged(path) as tmp, _open_writer(tmp, profile) as dst:
        if description:
            dst.update_tags(TIFFTAG_IMAGEDESCRIPTION=description)
            dst.set_band_description(1, description)
        dst.update_tags(**dict(tags or {}))
        if unit:
            dst.set_band_unit(1, unit)
        dst.write(a, 1)
