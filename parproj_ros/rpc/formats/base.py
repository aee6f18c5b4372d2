"""What every RPC format module gives the table: :class:`RPCFormatSpec`, values, numbers.

A format's parser returns :data:`RPCValues`, the keyword arguments of
:class:`~parproj_ros.rpc.model.RPCModel` as found in the file (offsets in the file's own pixel
convention); :func:`model_from_values` turns them into a model, with one check of what is
missing and one error naming the file.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

from ..model import _COEFF_NAMES, _SCALARS, FloatArray, RPCFormatError, RPCModel

#: One parser output: RPCModel's keyword arguments (the 10 offsets and scales: float, pixels /
#: degrees / metres; the 4 coefficient arrays: 20 values each, RPC00B order; optionally
#: ``err_bias`` and ``err_rand``, metres). Offsets are in the file's pixel convention.
RPCValues = dict[str, "float | FloatArray"]

#: How GDAL reads a format: ``"raster"`` (the file is a raster GDAL opens, its RPC metadata
#: domain holds the model) or the suffix of the sidecar GDAL reads beside a raster
#: (``".RPB"``, ``"_RPC.TXT"``); None: GDAL does not read it, this project's parser does.
GdalRoute = Literal["raster", ".RPB", "_RPC.TXT"] | None


def model_from_values(values: RPCValues, source: str | Path | None = None) -> RPCModel:
    """The model of a parser's values; errors name ``source``.

    Raises:
        RPCFormatError: a value is missing (all the missing ones named), or the model refuses
            one (not finite, zero scale, not 20 coefficients).

    """
    where = f"{source}: " if source is not None else ""
    missing = [n for n in (*_SCALARS, *_COEFF_NAMES) if n not in values]
    if missing:
        raise RPCFormatError(f"{where}missing RPC values: {', '.join(missing)}")
    try:
        return RPCModel(**values)  # type: ignore[arg-type]
    except RPCFormatError as err:
        raise RPCFormatError(f"{where}{err}") from None


_NUMBER = re.compile(
    r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eEdD][-+]?\d+)?)"
    r"(?:\s+(?:pixels?|meters?|metres?|degrees?|deg|m))?\s*;?\s*",
    re.IGNORECASE,
)


def number(text: str, what: str, source: str | Path | None = None) -> float:
    """A number as RPC files write it, or an error naming file, key and value.

    Optional sign, decimals, exponent (E or Fortran D), optionally a unit (``+021109.50
    pixels``: pixels, meters, metres, degrees). Anything else (``1,5``, ``12abc3``, two
    numbers) is an error naming the file, the key and the value: never a partial read.
    """
    m = _NUMBER.fullmatch(text)
    if m is None:
        where = f"{source}: " if source is not None else ""
        raise RPCFormatError(
            f"{where}{what}: not a number: {text.strip()[:40]!r} (a decimal point is needed, "
            "e.g. 1.5, not 1,5)"
        )
    return float(m.group(1).replace("d", "e").replace("D", "E"))


def no_shift(path: Path) -> float:
    """Pixel origin of the RPC00B convention: (0, 0) = centre of the first pixel."""
    return 0.0


@dataclass(frozen=True)
class RPCFormatSpec:
    """One RPC file format: the row of :data:`parproj_ros.rpc.formats.FORMATS`.

    Attributes:
        name: short name (``detect_rpc_format``'s answer, e.g. ``"rpb"``).
        label: how messages name it (``".RPB"``).
        detect: whether a file holds this format, from its path and first 4096 bytes
            (content, not the name; the table's order is the order of the questions).
        read: the parser: the file's values (:data:`RPCValues`, offsets as in the file).
        pixel_origin: image coordinate of the centre of the first pixel in the file (0.0 for
            RPC00B's convention; 1.0 for DIMAP v2); subtracted from the offsets on reading.
        write: writes a model to a file (offsets in this project's convention); None if not
            supported.
        extensions: lower-case file extensions that decide when no content matched.
        gdal: how GDAL reads it (:data:`GdalRoute`); None: only ``read`` does.
        sidecar_suffixes: suffixes of an image's same-stem sidecar of this format
            (``image.tif`` -> ``image.RPB``), first one canonical.
        find_in_folder: for a sidecar found by a folder pattern (DIMAP ``RPC_*.XML``): the file
            for an image, or None and the words saying why none (e.g. ``"several RPC_*.XML in
            /data"``).

    """

    name: str
    label: str
    detect: Callable[[Path, bytes], bool]
    read: Callable[[Path], RPCValues]
    pixel_origin: Callable[[Path], float] = no_shift
    write: Callable[[Path, RPCModel], None] | None = None
    extensions: tuple[str, ...] = ()
    gdal: GdalRoute = None
    sidecar_suffixes: tuple[str, ...] = ()
    find_in_folder: Callable[[Path], tuple[Path | None, str]] | None = None


class GdalReader(Protocol):
    """GDAL's reading of an RPC file of a format it reads (given by parproj_ros/io/raster.py).

    Returns GDAL's ``RPC`` metadata strings and where GDAL found them (for messages and the
    bag's metadata); raises :class:`RPCFormatError` when GDAL finds none.
    """

    def __call__(self, path: Path, spec: RPCFormatSpec) -> tuple[dict[str, str], str]:
        """GDAL's ``RPC`` metadata strings of ``path`` (a ``spec`` file) and their source."""
        ...
