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
import re
import shutil
import tempfile
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from ..imaging.encodings import DTYPE_ENCODINGS
from ..rpc import RPCError, RPCFormatError, RPCFormatSpec, RPCModel
from ..rpc import formats as rpc_formats
from ..rpc.formats import rpc_from_metadata

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
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    p = Path(path)
    if not p.is_file():
        raise SceneImportError(f"{p}: no such file")
    try:
        with warnings.catch_warnings():  # no geotransform is the rule for an image with RPC
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            return rasterio.open(p)
    except RasterioIOError as err:
        cut = truncation(p)
        if cut:
            raise SceneImportError(f"{p}: {cut}; GDAL: {gdal_error(err)}") from None
        raise SceneImportError(
            f"{p}: not a raster GDAL reads ({gdal_error(err)[:160]}); supported: "
            "GeoTIFF, JPEG 2000, NITF, PNG and the other GDAL raster formats"
        ) from None


def gdal_error(err: BaseException) -> str:
    """GDAL's own words for a failed read, from the chain of exceptions rasterio raises.

    rasterio's ``RasterioIOError("Read failed. See previous exception for details.")`` hides
    GDAL's messages in its ``__cause__`` chain: the block that failed (``IReadBlock failed at X
    offset 0, Y offset 31``) and the driver's reason (``TIFFReadEncodedStrip:Read error at
    scanline ...; got 1364 bytes, expected 8000``). Returns the outermost and the innermost of
    them (one line, at most about 300 characters).
    """
    texts: list[str] = []
    seen: set[int] = set()
    e: BaseException | None = err
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        t = " ".join(str(e).split())
        if t and "See previous exception" not in t and t not in texts:
            texts.append(t)
        e = e.__cause__ or e.__context__
    picked = texts[:1] + [t for t in texts[-1:] if texts and t not in texts[0]]
    return "; ".join(picked)[:300] or type(err).__name__


#: GDAL drivers' words for a file that ends too early (libjpeg, libtiff, generic readers).
_CUT_OFF = re.compile(r"premature end|unexpected end|got \d+ bytes, expected \d+", re.I)


def truncation(path: str | Path) -> str | None:
    """``truncated: ...`` when a TIFF's directory points past the end of the file, else None.

    Reads the TIFF directories only (tifffile); None for other formats or an unreadable header.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        with p.open("rb") as fh:
            head = fh.read(16)
        magic = head[:4]
        if magic not in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
            return None
        order: Literal["little", "big"] = "little" if magic[:2] == b"II" else "big"
        # the first directory's offset: bytes 4-7 (classic TIFF) or 8-15 (BigTIFF)
        first = int.from_bytes(
            head[4:8] if magic[2:] in (b"*\x00", b"\x00*") else head[8:16], order
        )
        if first >= size:
            return (
                f"truncated: the file has {size} bytes, its TIFF header puts its first directory "
                f"at byte {first} (copy or download it again)"
            )
        import tifffile

        with tifffile.TiffFile(p) as tif:
            end = max(
                (
                    int(o) + int(c)
                    for page in tif.pages
                    for o, c in zip(page.dataoffsets, page.databytecounts, strict=False)
                ),
                default=0,
            )
    except Exception:  # a damaged header: GDAL's message says it all
        return None
    if end <= size:
        return None
    return (
        f"truncated: the file has {size} bytes, its TIFF directory puts image data up to byte "
        f"{end} ({100.0 * size / end:.0f} % present; copy or download it again)"
    )


def _read_error(path: str | Path, what: str, err: BaseException) -> SceneImportError:
    """The error of a failed pixel read: the file, truncation when found, GDAL's words."""
    words = gdal_error(err)
    cut = truncation(path) or ("truncated (the data ends early)" if _CUT_OFF.search(words) else "")
    head = f"{path}: {cut}; " if cut else f"{path}: damaged or cut off: "
    return SceneImportError(f"{head}GDAL cannot read {what}: {words}")


def raster_info(path: str | Path) -> RasterInfo:
    """Open a raster with GDAL and describe it (:class:`RasterInfo`).

    Raises:
        SceneImportError: no such file, or not a raster GDAL reads.

    """
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


#: Drivers beside whose images GDAL reads RPC sidecars, and which ones (GDAL 3.10, checked by
#: tests/apps/test_import_errors.py on every driver listed there): GeoTIFF and JPEG 2000 read
#: ``.RPB`` and ``_RPC.TXT``, NITF ``_RPC.TXT`` only; PNG, JPEG, BMP, GIF, ENVI, HFA, ... none.
SIDECAR_DRIVERS: dict[str, tuple[str, ...]] = {
    "GTiff": (".RPB", "_RPC.TXT"),
    "COG": (".RPB", "_RPC.TXT"),
    "JP2OpenJPEG": (".RPB", "_RPC.TXT"),
    "JP2KAK": (".RPB", "_RPC.TXT"),
    "JP2ECW": (".RPB", "_RPC.TXT"),
    "JP2MrSID": (".RPB", "_RPC.TXT"),
    "JPEG2000": (".RPB", "_RPC.TXT"),
    "NITF": ("_RPC.TXT",),
}


def sidecar_read(driver: str, suffix: str) -> bool:
    """Whether GDAL reads an RPC sidecar ending in ``suffix`` beside an image of ``driver``."""
    return suffix.upper() in SIDECAR_DRIVERS.get(driver, ())


def sidecar_readers(suffix: str) -> str:
    """The image formats beside which GDAL reads an RPC sidecar ending in ``suffix`` (text)."""
    family = {"GTiff": "GeoTIFF", "COG": "GeoTIFF", "NITF": "NITF"}
    names = {family.get(d, "JPEG 2000") for d, s in SIDECAR_DRIVERS.items() if suffix.upper() in s}
    ordered = [n for n in ("GeoTIFF", "JPEG 2000", "NITF") if n in names]
    return " and ".join([", ".join(ordered[:-1]), ordered[-1]] if len(ordered) > 1 else ordered)


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


def _gdal_rpc(path: Path, spec: RPCFormatSpec) -> tuple[dict[str, str], str]:
    """GDAL's RPC metadata of an RPC file of a format GDAL reads, and where GDAL found it.

    A raster (``spec.gdal == "raster"``: the GeoTIFF tag, or a sidecar beside it) is opened as
    it is; a sidecar format (``.RPB``, ``_RPC.TXT``) is read by GDAL only beside a raster, so it
    is copied beside a 1 x 1 placeholder GeoTIFF.

    Raises:
        RPCFormatError: GDAL finds no RPC there.

    """
    if spec.gdal == "raster":
        info = raster_info(path)
        if not info.rpc_metadata:
            raise RPCFormatError(f"{path}: a TIFF without RPC (no tag 50844, no sidecar)")
        return info.rpc_metadata, describe_rpc_source(info)
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with tempfile.TemporaryDirectory(prefix="parproj_rpc_") as tmp:
        img = Path(tmp) / "x.tif"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(
                img, "w", driver="GTiff", width=1, height=1, count=1, dtype="uint8"
            ) as dst:
                dst.write(np.zeros((1, 1, 1), np.uint8))
        shutil.copy(path, Path(tmp) / f"x{spec.gdal}")
        tags = raster_info(img).rpc_metadata
    if not tags:
        raise RPCFormatError(f"{path}: GDAL reads no RPC from this {spec.name.upper()} file")
    return tags, f"{path.name} (GDAL)"


def read_rpc_file(path: str | Path) -> tuple[RPCModel, str]:
    """An RPC file given explicitly, and a description of it.

    :func:`parproj_ros.rpc.formats.read_rpc_file` with GDAL reading the formats it reads
    (``.RPB`` / ``_RPC.TXT`` and rasters); OSSIM ``.geom`` and DIMAP ``RPC_*.XML`` through
    their parsers in parproj_ros/rpc/formats/.

    Raises:
        SceneImportError: no such file.
        RPCFormatError: not an RPC (named), or a malformed one.

    """
    p = Path(path)
    if not p.is_file():
        raise SceneImportError(f"{p}: no such RPC file")
    return rpc_formats.read_rpc_file(p, gdal=_gdal_rpc)


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
        gt = ", ".join(f"{v:g}" for v in (a, b, c, d, e, f))
        if b == 0.0 and d == 0.0 and a > 0 and e > 0 and (a, e) != (1.0, 1.0):
            kind = (
                f"pixels of {a:g} x {e:g} units (a reduced-resolution product, or map units "
                "without a CRS)"
            )
        else:
            kind = "a rotation or a flip (map units without a CRS?)"
        raise SceneImportError(
            f"{info.path}: its geotransform (ModelTransformationTag or tie point) [{gt}] has "
            f"{kind}: not a crop offset (unit scale, no rotation, no CRS), and no --crop-origin "
            "can scale or turn pixels. If its RPC was fitted to this image's own pixels (as GDAL "
            f"rescales the RPC of a reduced-resolution copy), give --crop-origin {info.path.name}"
            " 0 0; if the RPC is the full-resolution scene's, import the full-resolution image "
            "(or an RPC fitted to this grid with --rpc IMAGE FILE)"
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
            raise _read_error(path, f"band {band}", err) from None
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
                raise _read_error(path, f"rows {r0}..{r0 + n - 1} of band {band}", err) from None
            if data.dtype.kind == "f":
                mask |= ~np.isfinite(data)
            out = np.zeros((n, w), dt)
            out[:, : src.width] = np.where(mask, 0, data)
            yield r0, out, int(np.count_nonzero(mask))


def read_band(path: str | Path, band: int = 1) -> NDArray[np.generic]:
    """A whole band (small images, tests), no-data as 0, in its strip pixel type."""
    return np.concatenate([b for _, b, _ in read_rows(path, band, 4096)])


__all__ = [
    "SIDECAR_DRIVERS",
    "RasterInfo",
    "SceneImportError",
    "band_summary",
    "crop_origin",
    "describe_rpc_source",
    "gdal_error",
    "map_footprint",
    "raster_info",
    "read_band",
    "read_rows",
    "read_rpc_file",
    "rpc_from_metadata",
    "sidecar_read",
    "sidecar_readers",
    "truncation",
]
