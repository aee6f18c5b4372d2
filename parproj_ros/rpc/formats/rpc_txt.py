"""``_RPC.TXT`` (IKONOS / DigitalGlobe / GDAL text): read and write.

RPC00B convention ((0, 0) = centre of the first pixel): no pixel shift. GDAL reads it too, as
the sidecar of a raster (parproj_ros/io/raster.py).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..model import _COEFF_NAMES, _SCALARS, RPCModel
from .base import RPCFormatSpec, RPCValues, model_from_values, number

#: Upper-case key -> RPCModel name of the 10 offsets and scales (DIMAP XML uses the same keys).
KEYS = {n.upper(): n for n in _SCALARS}
_UNITS = {
    "line_off": "pixels", "samp_off": "pixels", "lat_off": "degrees", "long_off": "degrees",
    "height_off": "meters", "line_scale": "pixels", "samp_scale": "pixels",
    "lat_scale": "degrees", "long_scale": "degrees", "height_scale": "meters",
}  # fmt: skip


def detect(path: Path, head: bytes) -> bool:
    """A ``LINE_NUM_COEFF_1:`` key starts a line."""
    full = path.read_text(encoding="utf-8", errors="replace")
    return re.search(r"^\s*LINE_NUM_COEFF_1\s*:", full, re.IGNORECASE | re.MULTILINE) is not None


def read(path: Path) -> RPCValues:
    """The values of an ``_RPC.TXT`` file (``LINE_OFF: +002000.00 pixels``, coefficients 1..20).

    ``ERR_BIAS`` and ``ERR_RAND`` are read when present.

    Raises:
        RPCFormatError: a value is malformed (file, key and value named).

    """
    lines: dict[str, str] = {}
    for raw in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = raw.partition(":")
        if sep:
            lines[key.strip().upper()] = value
    values: RPCValues = {n: number(lines[k], k, path) for k, n in KEYS.items() if k in lines}
    for name in _COEFF_NAMES:
        keys = [f"{name.upper()}_{i}" for i in range(1, 21)]
        if all(k in lines for k in keys):
            values[name] = np.array([number(lines[k], k, path) for k in keys])
    for k, n in (("ERR_BIAS", "err_bias"), ("ERR_RAND", "err_rand")):
        if k in lines:
            values[n] = number(lines[k], k, path)
    return values


def read_rpc_txt(path: str | Path) -> RPCModel:
    """Read an ``_RPC.TXT`` file (:func:`read`).

    Raises:
        RPCFormatError: a value is missing or malformed.

    """
    return model_from_values(read(Path(path)), path)


def write_rpc_txt(path: str | Path, rpc: RPCModel) -> None:
    """Write an ``_RPC.TXT`` file (17 significant digits: reading gives the same bits)."""
    out = [f"ERR_BIAS: {rpc.err_bias:+.16E} meters", f"ERR_RAND: {rpc.err_rand:+.16E} meters"]
    out += [f"{n.upper()}: {getattr(rpc, n):+.16E} {_UNITS[n]}" for n in _SCALARS]
    for name in _COEFF_NAMES:
        out += [
            f"{name.upper()}_{i + 1}: {float(c):+.16E}" for i, c in enumerate(getattr(rpc, name))
        ]
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


FORMAT = RPCFormatSpec(
    name="rpc_txt",
    label="_RPC.TXT",
    detect=detect,
    read=read,
    write=write_rpc_txt,
    gdal="_RPC.TXT",
    sidecar_suffixes=("_RPC.TXT", "_rpc.txt"),
)
