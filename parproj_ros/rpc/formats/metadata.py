"""GDAL's ``RPC`` metadata domain (strings) -> values: the parser of every format GDAL reads.

GDAL fills that domain from the GeoTIFF tag 50844, ``.RPB`` and ``_RPC.TXT`` sidecars, NITF
RPC00B, DIMAP products, JPEG 2000 boxes and PAM ``.aux.xml`` (parproj_ros/io/raster.py asks
GDAL; this module has no GDAL in it). RPC00B convention: no pixel shift.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model import _COEFF_NAMES, _SCALARS, RPCFormatError, RPCModel
from .base import RPCValues, model_from_values, number


def read(tags: dict[str, str], source: str | Path) -> RPCValues:
    """The values of GDAL's ``RPC`` metadata strings (``LINE_OFF``, ``LINE_NUM_COEFF``, ...).

    Raises:
        RPCFormatError: a value that is not a number (named with ``source`` and the key), not
            20 coefficients.

    """
    upper = {k.upper(): v for k, v in tags.items()}
    values: RPCValues = {
        n: number(upper[n.upper()], n.upper(), source) for n in _SCALARS if n.upper() in upper
    }
    for name in _COEFF_NAMES:
        text = upper.get(name.upper())
        if text is None:
            continue
        if "," in text:
            raise RPCFormatError(
                f"{source}: {name.upper()}: not 20 numbers separated by spaces: {text[:60]!r} "
                "(a decimal comma?)"
            )
        coeffs = [number(v, name.upper(), source) for v in text.split()]
        if len(coeffs) != 20:
            raise RPCFormatError(
                f"{source}: {name.upper()}: 20 coefficients needed, got {len(coeffs)}"
            )
        values[name] = np.array(coeffs)
    for k, n in (("ERR_BIAS", "err_bias"), ("ERR_RAND", "err_rand")):
        if k in upper:
            values[n] = number(upper[k], k, source)
    return values


def rpc_from_metadata(tags: dict[str, str], source: str | Path) -> RPCModel:
    """An RPC from GDAL's ``RPC`` metadata strings (RPC00B convention: no pixel shift).

    Raises:
        RPCFormatError: a key missing, a value that is not a number (named with the file and the
            key), not 20 coefficients, non-finite or zero-scale values.

    """
    return model_from_values(read(tags, source), source)
