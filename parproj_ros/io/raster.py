"""Rasters and their RPC through GDAL (rasterio): what ``parproj import`` reads.

Images: any raster GDAL reads (GeoTIFF, JPEG 2000, NITF, PNG, ...), one band (1-based, as GDAL
counts), read by windows of rows so that a 20k x 20k product is never held whole
(:func:`read_rows`). uint8 and uint16 (11/12-bit data included) and float32 stay as they are
(strip encodings mono8, mono16, 32FC1); other types become float32. Pixels that GDAL's mask
marks as no-data (nodata value, alpha, internal mask, NaN) become 0, the pipeline's no-data.

RPC: GDAL's ``RPC`` metadata domain, which GDAL fills from every source it knows: the GeoTIFF
RPCCoefficientTag (50844), ``.RPB`` and ``_RPC.TXT`` sidecars, NITF RPC00B TREs, DIMAP products,
JPEG 2000 metadata boxes, PAM ``.aux.xml``. The strings are parsed strictly
(:func:`rpc_from_metadata`: a value like ``1,5`` is an error naming file, key and value). The pixel
convention of GDAL's RPC metadata is RPC00B's: (0, 0) = centre of the first pixel, this project's
(GDAL's own pixel space is corner-based: its RPC transformer adds 0.5; tests/rpc/test_rpc.py checks
our projection and localization against it). An explicit ``.RPB`` / ``_RPC.TXT`` file is read by
GDAL too (:func:`read_rpc_file`, as the sidecar of a placeholder raster); OSSIM ``.geom`` keyword
lists and loose DIMAP ``RPC_*.XML`` files (GDAL finds DIMAP RPCs only inside a product's folder
structure) keep this project's readers (parproj_ros/rpc/).

Crop origin (where pixel (0, 0) of the image lies in the RPC's grid): GDAL's geotransform when it
is a pure translation with unit, non-flipped pixels and no CRS: what GDAL makes of a GeoTIFF
ModelTransformationTag (34264) or ModelTiepoint + ModelPixelScale tags, a world file or an
``.aux.xml`` GeoTransform (:func:`crop_origin`). Both the crop and its parent use GDAL's corner
convention, so the translation is also the centre-to-centre offset.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..imaging.encodings import DTYPE_ENCODINGS
from ..rpc import RPCError, RPCFormatError, RPCModel
from ..rpc.formats import _float, _model
from ..rpc.model import _COEFF_NAMES, _SCALARS

FloatArray = NDArray[np.float64]
#: Pixel types kept as they are (those with a strip encoding: mono8, mono16, 32FC1).
KEPT_DTYPES = tuple(d.name for d in DTYPE_ENCODINGS)


class SceneImportError(RPCError):
    """An image or its RPC cannot be imported (the message names the file and the problem)."""


@dataclass(frozen=True)
class RasterInfo:
    """What GDAL says about a raster (no pixels read).

    Attributes:
        path: the file.
        driver: GDAL driver short name (GTiff, JP2OpenJPEG, NITF, PNG, ...).
        lines: rows.
        samples: columns.
        bands: band count.
        dtype: numpy name of the pixel type of band 1.
        nodata: the nodata value of band 1, or None.
        transform: GDAL geotransform as (a, b, c, d, e, f) of rasterio's Affine
            (x = a col + b row + c, y = d col + e row + f).
        has_crs: whether the raster has a coordinate reference system (map georeferencing).
        rpc_metadata: GDAL's ``RPC`` metadata domain (strings), empty when none.
        files: the files GDAL read (the raster and its sidecars).

    """

    path: Path
    driver: str
    lines: int
    samples: int
    bands: int
    dtype: str
    nodata: float | None
    transform: tuple[float, float, float, float, float, float]
    has_crs: bool
    rpc_metadata: dict[str, str]
    files: tuple[str, ...]


#: GDAL's block cache while reading pixels, MB (GDAL's default, 5 % of RAM, would keep every
#: tile of a strip-by-strip pass over a large raster: +120 MB on 2 x 72 MB images).
GDAL_CACHE_MB = 32


def _env() -> Any:
    import rasterio

    return rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB)


def _open(path: str | Path) -> Any:
    import rasterio
    from rasterio.errors import RasterioIOError

    p = Path(path)
    if not p.is_file():
        raise SceneImportError(f"{p}: no such file")
    try:
        return rasterio.open(p)
    except RasterioIOError as err:
        raise SceneImportError(
            f"{p}: not a raster GDAL reads ({str(err).splitlines()[0][:160]}); supported: "
            "GeoTIFF, JPEG 2000, NITF, PNG and the other GDAL raster formats"
        ) from None


def raster_info(path: str | Path) -> RasterInfo:
    """Open a raster with GDAL and describe it (:class:`RasterInfo`).

    Raises:
        SceneImportError: no such file, or not a raster GDAL reads.

    """
    import warnings

    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with _open(path) as src:
            t = src.transform
            return RasterInfo(
                path=Path(path),
                driver=str(src.driver),
                lines=int(src.height),
                samples=int(src.width),
                bands=int(src.count),
                dtype=str(src.dtypes[0]),
                nodata=None if src.nodata is None else float(src.nodata),
                transform=(t.a, t.b, t.c, t.d, t.e, t.f),
                # an engineering (local) CRS, as JPEG 2000 writers leave, is no georeferencing
                has_crs=src.crs is not None and (src.crs.is_geographic or src.crs.is_projected),
                rpc_metadata=dict(src.tags(ns="RPC")),
                files=tuple(str(f) for f in src.files),
            )


def rpc_from_metadata(tags: dict[str, str], source: str | Path) -> RPCModel:
    """An RPC from GDAL's ``RPC`` metadata strings (RPC00B convention: no pixel shift).

    Raises:
        RPCFormatError: a key missing, a value that is not a number (named with the file and the
            key), not 20 coefficients, non-finite or zero-scale values.

    """
    upper = {k.upper(): v for k, v in tags.items()}
    scalars = {
        n: _float(upper[n.upper()], n.upper(), source) for n in _SCALARS if n.upper() in upper
    }
    coeffs: dict[str, FloatArray] = {}
    for name in _COEFF_NAMES:
        text = upper.get(name.upper())
        if text is None:
            continue
        if "," in text:
            raise RPCFormatError(
                f"{source}: {name.upper()}: not 20 numbers separated by spaces: {text[:60]!r} "
                "(a decimal comma?)"
            )
        values = [_float(v, name.upper(), source) for v in text.split()]
        if len(values) != 20:
            raise RPCFormatError(
                f"{source}: {name.upper()}: 20 coefficients needed, got {len(values)}"
            )
        coeffs[name] = np.array(values)
    extra = {
        n: _float(upper[k], k, source)
        for k, n in (("ERR_BIAS", "err_bias"), ("ERR_RAND", "err_rand"))
        if k in upper
    }
    return _model(scalars, coeffs, source, **extra)


def describe_rpc_source(info: RasterInfo) -> str:
    """Where GDAL found the RPC of a raster, for messages and the bag's metadata."""
    name = info.path.name
    for f in info.files[1:]:
        low = f.lower()
        if low.endswith(".rpb") or low.endswith("_rpc.txt"):
            return f"{Path(f).name} (GDAL, sidecar of {name})"
        if Path(low).name.startswith("rpc_") and low.endswith(".xml"):
            return f"{Path(f).name} (DIMAP, GDAL)"
    if info.driver == "GTiff":
        return f"{name} (GeoTIFF tag 50844, GDAL)"
    if info.driver == "NITF" and not any(f.lower().endswith(".aux.xml") for f in info.files):
        return f"{name} (NITF RPC00B, GDAL)"
    return f"{name} (GDAL RPC metadata, {info.driver})"


def read_rpc_file(path: str | Path) -> tuple[RPCModel, str]:
    """An RPC file given explicitly, and a description of it.

    ``.RPB`` / ``_RPC.TXT`` and rasters through GDAL,
    OSSIM ``.geom`` and DIMAP ``RPC_*.XML`` through parproj_ros/rpc/; and a description.

    Raises:
        RPCFormatError: not an RPC (named), or a malformed one.

    """
    from .. import rpc

    p = Path(path)
    if not p.is_file():
        raise SceneImportError(f"{p}: no such RPC file")
    fmt = rpc.detect_rpc_format(p)
    if fmt in ("rpb", "rpc_txt"):
        # GDAL reads these only as sidecars of a raster: give it a 1 x 1 placeholder.
        import rasterio

        with tempfile.TemporaryDirectory(prefix="parproj_rpc_") as tmp:
            img = Path(tmp) / "x.tif"
            with rasterio.open(
                img, "w", driver="GTiff", width=1, height=1, count=1, dtype="uint8"
            ) as dst:
                dst.write(np.zeros((1, 1, 1), np.uint8))
            shutil.copy(p, Path(tmp) / ("x.RPB" if fmt == "rpb" else "x_RPC.TXT"))
            tags = raster_info(img).rpc_metadata
        if not tags:
            raise RPCFormatError(f"{p}: GDAL reads no RPC from this {fmt.upper()} file")
        return rpc_from_metadata(tags, p), f"{p.name} (GDAL)"
    if fmt == "geotiff":
        info = raster_info(p)
        if not info.rpc_metadata:
            raise RPCFormatError(f"{p}: a TIFF without RPC (no tag 50844, no sidecar)")
        return rpc_from_metadata(info.rpc_metadata, p), describe_rpc_source(info)
    return rpc.read_rpc(p), p.name


def crop_origin(info: RasterInfo) -> tuple[float, float] | None:
    """(line, sample) of the raster's first pixel in its RPC's grid, from GDAL's geotransform.

    None when the raster has no geotransform (identity) or a map georeferencing (a CRS).

    Raises:
        SceneImportError: a geotransform without CRS that is not a unit translation.

    """
    a, b, c, d, e, f = info.transform
    if info.has_crs or (a, b, c, d, e, f) == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0):
        return None
    if (a, b, d, e) != (1.0, 0.0, 0.0, 1.0) or not (math.isfinite(c) and math.isfinite(f)):
        raise SceneImportError(
            f"{info.path}: its geotransform (ModelTransformationTag or tie point) "
            f"{[a, b, c, d, e, f]} is not a crop offset (unit scale, no rotation, no CRS); "
            "give the crop origin with --crop-origin"
        )
    return float(f), float(c)


def map_footprint(info: RasterInfo, rows: FloatArray, cols: FloatArray) -> FloatArray | None:
    """(n, 2) lon, lat (degrees) of pixel centres by the raster's map georeferencing, or None."""
    if not info.has_crs:
        return None
    from rasterio.warp import transform as warp

    with _open(info.path) as src:
        crs = src.crs
    a, b, c, d, e, f = info.transform
    x = a * (cols + 0.5) + b * (rows + 0.5) + c
    y = d * (cols + 0.5) + e * (rows + 0.5) + f
    lon, lat = warp(crs, "EPSG:4326", list(map(float, x)), list(map(float, y)))
    return np.column_stack([lon, lat])


def out_dtype(dtype: str) -> np.dtype[Any]:
    """The strip pixel type of a GDAL band type."""
    return np.dtype(dtype) if dtype in KEPT_DTYPES else np.dtype(np.float32)


def band_summary(path: str | Path, band: int, max_side: int = 1024) -> tuple[float, float, int]:
    """(min, max, valid count) of a band on a decimated read (at most max_side^2 pixels)."""
    from rasterio.errors import RasterioError

    with _env(), _open(path) as src:
        if not 1 <= band <= src.count:
            raise SceneImportError(f"{path}: band {band} asked for, the raster has {src.count}")
        k = max(1, math.ceil(max(src.height, src.width) / max_side))
        shape = (max(1, src.height // k), max(1, src.width // k))
        try:
            data = src.read(band, out_shape=shape, masked=True).astype(np.float64)
        except RasterioError as err:
            raise SceneImportError(
                f"{path}: GDAL cannot read band {band}: {str(err).splitlines()[0][:160]}"
            ) from None
    valid = np.ma.masked_invalid(data).compressed()
    if valid.size == 0:
        return math.nan, math.nan, 0
    return float(valid.min()), float(valid.max()), int(valid.size)


def read_rows(
    path: str | Path, band: int, rows_per_block: int, width: int | None = None
) -> Iterator[tuple[int, NDArray[np.generic], int]]:
    """Yield (first row, pixels, masked count) blocks of ``rows_per_block`` rows of one band.

    Pixels GDAL masks (nodata, alpha, NaN) become 0; with ``width`` larger than the raster the
    block is padded on the right with 0 (no-data) columns. Only one block is held at a time.
    """
    from rasterio.errors import RasterioError
    from rasterio.windows import Window

    with _env(), _open(path) as src:
        dt = out_dtype(str(src.dtypes[band - 1]))
        w = src.width if width is None else max(width, src.width)
        for r0 in range(0, src.height, rows_per_block):
            n = min(rows_per_block, src.height - r0)
            win = Window(0, r0, src.width, n)
            try:
                data = src.read(band, window=win)
                mask = src.read_masks(band, window=win) == 0
            except RasterioError as err:  # a truncated or corrupt file, found while reading
                raise SceneImportError(
                    f"{path}: GDAL cannot read rows {r0}..{r0 + n - 1} of band {band}: "
                    f"{str(err).splitlines()[0][:160]}"
                ) from None
            if data.dtype.kind == "f":
                mask |= ~np.isfinite(data)
            out = np.zeros((n, w), dt)
            out[:, : src.width] = np.where(mask, 0, data)
            yield r0, out, int(np.count_nonzero(mask))


def read_band(path: str | Path, band: int = 1) -> NDArray[np.generic]:
    """A whole band (small images, tests), no-data as 0, in its strip pixel type."""
    return np.concatenate([b for _, b, _ in read_rows(path, band, 4096)])


__all__ = [
    "RasterInfo",
    "SceneImportError",
    "band_summary",
    "crop_origin",
    "describe_rpc_source",
    "map_footprint",
    "raster_info",
    "read_band",
    "read_rows",
    "read_rpc_file",
    "rpc_from_metadata",
]
