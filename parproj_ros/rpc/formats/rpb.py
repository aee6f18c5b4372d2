"""DigitalGlobe ``.RPB``: read and write.

RPC00B convention: no pixel shift. GDAL reads it too, as the sidecar of a raster
(parproj_ros/io/raster.py).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..model import _SCALARS, RPCModel
from .base import RPCFormatSpec, RPCValues, model_from_values, number

_SCALAR_KEYS = {
    "lineoffset": "line_off", "sampoffset": "samp_off", "latoffset": "lat_off",
    "longoffset": "long_off", "heightoffset": "height_off", "linescale": "line_scale",
    "sampscale": "samp_scale", "latscale": "lat_scale", "longscale": "long_scale",
    "heightscale": "height_scale", "errbias": "err_bias", "errrand": "err_rand",
}  # fmt: skip
_COEFF_KEYS = {
    "linenumcoef": "line_num_coeff", "linedencoef": "line_den_coeff",
    "sampnumcoef": "samp_num_coeff", "sampdencoef": "samp_den_coeff",
}  # fmt: skip
_CAMEL = {
    "errbias": "errBias", "errrand": "errRand", "lineoffset": "lineOffset",
    "sampoffset": "sampOffset", "latoffset": "latOffset", "longoffset": "longOffset",
    "heightoffset": "heightOffset", "linescale": "lineScale", "sampscale": "sampScale",
    "latscale": "latScale", "longscale": "longScale", "heightscale": "heightScale",
    "linenumcoef": "lineNumCoef", "linedencoef": "lineDenCoef",
    "sampnumcoef": "sampNumCoef", "sampdencoef": "sampDenCoef",
}  # fmt: skip


def detect(path: Path, head: bytes) -> bool:
    """``BEGIN_GROUP``, ``lineNumCoef`` or ``lineOffset =`` in the first 4096 bytes."""
    text = head.decode("utf-8", errors="replace")
    return re.search(r"BEGIN_GROUP|lineNumCoef|lineOffset\s*=", text, re.IGNORECASE) is not None


def read(path: Path) -> RPCValues:
    """The values of a ``.RPB`` file.

    Syntax: ``BEGIN_GROUP = IMAGE``, ``lineOffset = ...;``, ``lineNumCoef = ( c1, ..., c20 );``.

    Raises:
        RPCFormatError: a value is malformed (file, key and value named).

    """
    text = Path(path).read_text(encoding="utf-8", errors="replace")
    values: RPCValues = {}
    for m in re.finditer(r"(\w+)\s*=\s*(\([^)]*\)|[^;\n]*)\s*;?", text):
        key, value = m.group(1).lower(), m.group(2).strip()
        if key in _COEFF_KEYS:
            items = [s for s in value.strip("()").replace("\n", " ").split(",") if s.strip()]
            values[_COEFF_KEYS[key]] = np.array([number(s, key, path) for s in items])
        elif key in _SCALAR_KEYS:
            values[_SCALAR_KEYS[key]] = number(value, key, path)
    return values


def read_rpb(path: str | Path) -> RPCModel:
    """Read a DigitalGlobe ``.RPB`` file (:func:`read`).

    Raises:
        RPCFormatError: a value is missing or malformed.

    """
    return model_from_values(read(Path(path)), path)


def write_rpb(path: str | Path, rpc: RPCModel, *, sat_id: str = "UNKNOWN") -> None:
    """Write a DigitalGlobe ``.RPB`` file (17 significant digits: reading gives the same bits)."""
    names = {v: k for k, v in _SCALAR_KEYS.items()}
    out = [f'satId = "{sat_id}";', 'bandId = "P";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE"]
    for n in ("err_bias", "err_rand", *_SCALARS):
        out.append(f"\t{_CAMEL[names[n]]} = {getattr(rpc, n):+.16E};")
    for key, name in _COEFF_KEYS.items():
        vals = ",\n".join(f"\t\t\t{float(c):+.16E}" for c in getattr(rpc, name))
        out.append(f"\t{_CAMEL[key]} = (\n{vals});")
    out += ["END_GROUP = IMAGE", "END;"]
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


FORMAT = RPCFormatSpec(
    name="rpb",
    label=".RPB",
    detect=detect,
    read=read,
    write=write_rpb,
    extensions=(".rpb",),
    gdal=".RPB",
    sidecar_suffixes=(".RPB", ".rpb"),
)
