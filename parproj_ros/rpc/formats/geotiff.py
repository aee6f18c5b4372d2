"""The GeoTIFF RPCCoefficientTag (50844, 92 doubles): read and write with tifffile.

RPC00B convention (GDAL writes the tag from its RPC metadata unchanged): no pixel shift. GDAL
reads the tag too (and the raster's sidecars with it: parproj_ros/io/raster.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ..model import _COEFF_NAMES, _SCALARS, RPC_TIFF_TAG, RPCFormatError, RPCModel
from .base import RPCFormatSpec, RPCValues, model_from_values

#: The first bytes of a TIFF or BigTIFF, little- or big-endian.
TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def detect(path: Path, head: bytes) -> bool:
    """A TIFF header."""
    return head[:4] in TIFF_MAGIC


def read(path: Path) -> RPCValues:
    """The values of the RPCCoefficientTag of the first page of a (Geo)TIFF.

    Order of the 92 values: :meth:`RPCModel.as_vector`.

    Raises:
        RPCFormatError: no such tag, or not 92 values.

    """
    import tifffile

    with tifffile.TiffFile(Path(path)) as tif:
        tag = tif.pages.first.tags.get(RPC_TIFF_TAG)
        if tag is None:
            raise RPCFormatError(f"{path}: no RPCCoefficientTag ({RPC_TIFF_TAG})")
        v = np.asarray(tag.value, dtype=np.float64).reshape(-1)
    if v.shape != (92,):
        raise RPCFormatError(f"an RPC vector has 92 values, got {v.size}")
    values: RPCValues = {"err_bias": float(v[0]), "err_rand": float(v[1])}
    values.update({name: float(v[2 + i]) for i, name in enumerate(_SCALARS)})
    values.update({name: v[12 + 20 * i : 32 + 20 * i] for i, name in enumerate(_COEFF_NAMES)})
    return values


def read_geotiff_rpc(path: str | Path) -> RPCModel:
    """Read the RPCCoefficientTag (50844, 92 doubles) of the first page of a (Geo)TIFF.

    Raises:
        RPCFormatError: no such tag, or not 92 values.

    """
    return model_from_values(read(Path(path)), path)


def write_geotiff_rpc(path: str | Path, rpc: RPCModel, image: ArrayLike | None = None) -> None:
    """Write a TIFF carrying the RPC in tag 50844 (DOUBLE x 92).

    Args:
        path: output file.
        rpc: the model (offsets in this project's convention = RPC00B).
        image: pixels to store (default a 1 x 1 uint8 placeholder).

    """
    import tifffile

    data = np.zeros((1, 1), np.uint8) if image is None else np.asarray(image)
    vec = tuple(float(v) for v in rpc.as_vector())
    tifffile.imwrite(Path(path), data, extratags=[(RPC_TIFF_TAG, 12, 92, vec, True)])


FORMAT = RPCFormatSpec(
    name="geotiff",
    label="GeoTIFF",
    detect=detect,
    read=read,
    write=write_geotiff_rpc,
    extensions=(".tif", ".tiff"),
    gdal="raster",
)
