"""RPC file formats: OSSIM .geom, _RPC.TXT, .RPB, DIMAP XML, GeoTIFF tag; reading and writing.

The pixel origin of each format, and the conversion made on reading: :mod:`parproj_ros.rpc`.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from .model import (
    _A_TO_B,
    _COEFF_NAMES,
    _SCALARS,
    RPC_TIFF_TAG,
    FloatArray,
    RPCFormatError,
    RPCModel,
)


def _model(
    scalars: dict[str, float],
    coeffs: dict[str, FloatArray],
    source: str | Path | None = None,
    **extra: float,
) -> RPCModel:
    where = f"{source}: " if source is not None else ""
    missing = [n for n in _SCALARS if n not in scalars] + [
        n for n in _COEFF_NAMES if n not in coeffs
    ]
    if missing:
        raise RPCFormatError(f"{where}missing RPC values: {', '.join(missing)}")
    kwargs: dict[str, float] = {n: scalars[n] for n in _SCALARS}
    try:
        return RPCModel(**kwargs, **coeffs, **extra)  # type: ignore[arg-type]
    except RPCFormatError as err:
        raise RPCFormatError(f"{where}{err}") from None


_NUMBER = re.compile(
    r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eEdD][-+]?\d+)?)"
    r"(?:\s+(?:pixels?|meters?|metres?|degrees?|deg|m))?\s*;?\s*",
    re.IGNORECASE,
)


def _float(text: str, what: str, source: str | Path | None = None) -> float:
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


# ---------------------------------------------------------------------------------------------
# OSSIM keyword list (.geom)


def read_keyword_list(path: str | Path) -> dict[str, str]:
    """An OSSIM keyword list (``key: value`` lines) as a dict of stripped strings."""
    out: dict[str, str] = {}
    for raw in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = raw.partition(":")
        if sep and key.strip():
            out[key.strip()] = value.strip()
    return out


def read_geom(path: str | Path) -> RPCModel:
    """Read an OSSIM ``.geom`` keyword list with an RPC (ossimRpcModel, ossimPleiadesModel, ...).

    Keys ``line_off``, ..., ``height_scale``, ``line_num_coeff_00`` .. ``_19`` etc. (an optional
    ``prefix.`` is accepted); ``polynomial_format: A`` coefficients are reordered to RPC00B.
    OSSIM image coordinates are 0-based with pixel centres at integers: no conversion.

    Raises:
        RPCFormatError: a key is missing or malformed.

    """
    kwl = read_keyword_list(path)
    flat: dict[str, str] = {}
    for key, value in kwl.items():
        flat.setdefault(key.rsplit(".", 1)[-1].lower(), value)
    scalars = {n: _float(flat[n], n, path) for n in _SCALARS if n in flat}
    coeffs: dict[str, FloatArray] = {}
    for name in _COEFF_NAMES:
        keys = [f"{name}_{i:02d}" for i in range(20)]
        if all(k in flat for k in keys):
            coeffs[name] = np.array([_float(flat[k], k, path) for k in keys])
    if flat.get("polynomial_format", "B").strip().upper() == "A":
        coeffs = {k: v[_A_TO_B] for k, v in coeffs.items()}
    extra = {}
    if "bias_error" in flat:
        extra["err_bias"] = _float(flat["bias_error"], "bias_error", path)
    if "rand_error" in flat:
        extra["err_rand"] = _float(flat["rand_error"], "rand_error", path)
    return _model(scalars, coeffs, path, **extra)


def write_geom(
    path: str | Path, rpc: RPCModel, *, lines: int | None = None, samples: int | None = None
) -> None:
    """Write an OSSIM ``.geom`` keyword list (type ossimRpcModel, polynomial_format B).

    Values are written with Python's shortest round-trip repr, so reading gives the same bits.

    Args:
        path: output file.
        rpc: the model.
        lines: image lines (written as ``number_lines`` when given).
        samples: image samples (``number_samples``).

    """
    out = ["type:  ossimRpcModel", "polynomial_format:  B"]
    out += [f"bias_error:  {rpc.err_bias!r}", f"rand_error:  {rpc.err_rand!r}"]
    out += [f"{n}:  {getattr(rpc, n)!r}" for n in _SCALARS]
    for name in _COEFF_NAMES:
        out += [f"{name}_{i:02d}:  {float(c)!r}" for i, c in enumerate(getattr(rpc, name))]
    if lines is not None:
        out.append(f"number_lines:  {int(lines)}")
    if samples is not None:
        out.append(f"number_samples:  {int(samples)}")
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# _RPC.TXT (IKONOS / DigitalGlobe / GDAL text)

_TXT_SCALARS = {n.upper(): n for n in _SCALARS}
_TXT_UNITS = {
    "line_off": "pixels", "samp_off": "pixels", "lat_off": "degrees", "long_off": "degrees",
    "height_off": "meters", "line_scale": "pixels", "samp_scale": "pixels",
    "lat_scale": "degrees", "long_scale": "degrees", "height_scale": "meters",
}  # fmt: skip


def read_rpc_txt(path: str | Path) -> RPCModel:
    """Read an ``_RPC.TXT`` file (``LINE_OFF: +002000.00 pixels`` ..., coefficients 1..20).

    RPC00B convention ((0, 0) = centre of the first pixel): no conversion. ``ERR_BIAS`` and
    ``ERR_RAND`` are read when present.

    Raises:
        RPCFormatError: a value is missing or malformed.

    """
    values: dict[str, str] = {}
    for raw in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = raw.partition(":")
        if sep:
            values[key.strip().upper()] = value
    scalars = {n: _float(values[k], k, path) for k, n in _TXT_SCALARS.items() if k in values}
    coeffs: dict[str, FloatArray] = {}
    for name in _COEFF_NAMES:
        keys = [f"{name.upper()}_{i}" for i in range(1, 21)]
        if all(k in values for k in keys):
            coeffs[name] = np.array([_float(values[k], k, path) for k in keys])
    extra = {
        n: _float(values[k], k, path)
        for k, n in (("ERR_BIAS", "err_bias"), ("ERR_RAND", "err_rand"))
        if k in values
    }
    return _model(scalars, coeffs, path, **extra)


def write_rpc_txt(path: str | Path, rpc: RPCModel) -> None:
    """Write an ``_RPC.TXT`` file (17 significant digits: reading gives the same bits)."""
    out = [f"ERR_BIAS: {rpc.err_bias:+.16E} meters", f"ERR_RAND: {rpc.err_rand:+.16E} meters"]
    out += [f"{n.upper()}: {getattr(rpc, n):+.16E} {_TXT_UNITS[n]}" for n in _SCALARS]
    for name in _COEFF_NAMES:
        out += [
            f"{name.upper()}_{i + 1}: {float(c):+.16E}" for i, c in enumerate(getattr(rpc, name))
        ]
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# .RPB (DigitalGlobe)

_RPB_SCALARS = {
    "lineoffset": "line_off", "sampoffset": "samp_off", "latoffset": "lat_off",
    "longoffset": "long_off", "heightoffset": "height_off", "linescale": "line_scale",
    "sampscale": "samp_scale", "latscale": "lat_scale", "longscale": "long_scale",
    "heightscale": "height_scale", "errbias": "err_bias", "errrand": "err_rand",
}  # fmt: skip
_RPB_COEFFS = {
    "linenumcoef": "line_num_coeff", "linedencoef": "line_den_coeff",
    "sampnumcoef": "samp_num_coeff", "sampdencoef": "samp_den_coeff",
}  # fmt: skip


def read_rpb(path: str | Path) -> RPCModel:
    """Read a DigitalGlobe ``.RPB`` file.

    Syntax: ``BEGIN_GROUP = IMAGE``, ``lineOffset = ...;``, ``lineNumCoef = ( c1, ..., c20 );``.
    RPC00B convention: no conversion.

    Raises:
        RPCFormatError: a value is missing or malformed.

    """
    text = Path(path).read_text(encoding="utf-8", errors="replace")
    found: dict[str, float] = {}
    coeffs: dict[str, FloatArray] = {}
    for m in re.finditer(r"(\w+)\s*=\s*(\([^)]*\)|[^;\n]*)\s*;?", text):
        key, value = m.group(1).lower(), m.group(2).strip()
        if key in _RPB_COEFFS:
            items = [s for s in value.strip("()").replace("\n", " ").split(",") if s.strip()]
            coeffs[_RPB_COEFFS[key]] = np.array([_float(s, key, path) for s in items])
        elif key in _RPB_SCALARS:
            found[_RPB_SCALARS[key]] = _float(value, key, path)
    extra = {k: found.pop(k) for k in ("err_bias", "err_rand") if k in found}
    return _model(found, coeffs, path, **extra)


def write_rpb(path: str | Path, rpc: RPCModel, *, sat_id: str = "UNKNOWN") -> None:
    """Write a DigitalGlobe ``.RPB`` file (17 significant digits: reading gives the same bits)."""
    names = {v: k for k, v in _RPB_SCALARS.items()}
    camel = {
        "errbias": "errBias", "errrand": "errRand", "lineoffset": "lineOffset",
        "sampoffset": "sampOffset", "latoffset": "latOffset", "longoffset": "longOffset",
        "heightoffset": "heightOffset", "linescale": "lineScale", "sampscale": "sampScale",
        "latscale": "latScale", "longscale": "longScale", "heightscale": "heightScale",
        "linenumcoef": "lineNumCoef", "linedencoef": "lineDenCoef",
        "sampnumcoef": "sampNumCoef", "sampdencoef": "sampDenCoef",
    }  # fmt: skip
    out = [f'satId = "{sat_id}";', 'bandId = "P";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE"]
    for n in ("err_bias", "err_rand", *_SCALARS):
        out.append(f"\t{camel[names[n]]} = {getattr(rpc, n):+.16E};")
    for key, name in _RPB_COEFFS.items():
        vals = ",\n".join(f"\t\t\t{float(c):+.16E}" for c in getattr(rpc, name))
        out.append(f"\t{camel[key]} = (\n{vals});")
    out += ["END_GROUP = IMAGE", "END;"]
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# DIMAP RPC XML (Airbus Pleiades / SPOT 6-7 / Pleiades Neo)


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def dimap_pixel_origin(path: str | Path) -> float:
    """Image coordinate of the centre of the first pixel in a DIMAP RPC file.

    DIMAP v3 (Pleiades Neo) states it as ``FIRST_COL`` of ``ImagetoGround_Validity_Domain``
    (GDAL uses that value for lines and samples alike; it is 0 for PNEO); DIMAP v2 (Pleiades
    1A/1B, SPOT 6/7) is 1-based: 1.0.
    """
    root = ET.parse(Path(path)).getroot()
    for node in root.iter():
        if _local(node.tag) == "ImagetoGround_Validity_Domain":
            for child in node:
                if _local(child.tag) == "FIRST_COL" and child.text:
                    return _float(child.text, "FIRST_COL", path)
    return 1.0


def read_dimap_rpc(path: str | Path, *, origin: float | None = None) -> RPCModel:
    """Read the ground -> image RPC of a DIMAP ``RPC_*.XML`` file.

    The coefficients are those of ``Inverse_Model`` (DIMAP v2) or ``GroundtoImage_Values``
    (v3), RPC00B order; offsets and scales from ``RFM_Validity``. The image coordinates are
    converted to this project's convention by subtracting ``origin`` from LINE_OFF and SAMP_OFF.

    Args:
        path: the XML file.
        origin: image coordinate of the centre of the first pixel in the file; None = detect
            (:func:`dimap_pixel_origin`: 1 for DIMAP v2); 0.0 returns the file's raw values.

    Raises:
        RPCFormatError: not a DIMAP RPC file, or a value is missing.

    """
    try:
        root = ET.parse(Path(path)).getroot()
    except ET.ParseError as exc:
        raise RPCFormatError(f"{path}: not XML ({exc})") from exc
    model = None
    for node in root.iter():
        if _local(node.tag) in ("Inverse_Model", "GroundtoImage_Values"):
            model = node
            break
    if model is None:
        raise RPCFormatError(f"{path}: no Inverse_Model / GroundtoImage_Values element")
    values = {_local(c.tag).upper(): (c.text or "") for c in model}
    coeffs: dict[str, FloatArray] = {}
    for name in _COEFF_NAMES:
        keys = [f"{name.upper()}_{i}" for i in range(1, 21)]
        if all(k in values for k in keys):
            coeffs[name] = np.array([_float(values[k], k, path) for k in keys])
    scalars: dict[str, float] = {}
    for node in root.iter():
        tag = _local(node.tag).upper()
        if tag in _TXT_SCALARS and node.text and _TXT_SCALARS[tag] not in scalars:
            scalars[_TXT_SCALARS[tag]] = _float(node.text, tag, path)
    shift = dimap_pixel_origin(path) if origin is None else float(origin)
    if "line_off" in scalars:
        scalars["line_off"] -= shift
    if "samp_off" in scalars:
        scalars["samp_off"] -= shift
    return _model(scalars, coeffs, path)


def write_dimap_rpc(path: str | Path, rpc: RPCModel) -> None:
    """Write a minimal DIMAP v2 RPC XML (Inverse_Model and RFM_Validity; 1-based offsets)."""
    root = ET.Element("Dimap_Document")
    ident = ET.SubElement(root, "Metadata_Identification")
    ET.SubElement(ident, "METADATA_FORMAT", version="2.0").text = "DIMAP"
    ET.SubElement(ident, "METADATA_SUBPROFILE").text = "RPC"
    rfm = ET.SubElement(ET.SubElement(root, "Rational_Function_Model"), "Global_RFM")
    inverse = ET.SubElement(rfm, "Inverse_Model")
    for name in ("samp_num_coeff", "samp_den_coeff", "line_num_coeff", "line_den_coeff"):
        for i, c in enumerate(getattr(rpc, name), start=1):
            ET.SubElement(inverse, f"{name.upper()}_{i}").text = repr(float(c))
    validity = ET.SubElement(rfm, "RFM_Validity")
    for n in reversed(_SCALARS):
        value = getattr(rpc, n) + (1.0 if n in ("line_off", "samp_off") else 0.0)
        ET.SubElement(validity, n.upper()).text = repr(value)
    ET.indent(root)
    ET.ElementTree(root).write(Path(path), encoding="UTF-8", xml_declaration=True)


# ---------------------------------------------------------------------------------------------
# GeoTIFF RPCCoefficientTag


def read_geotiff_rpc(path: str | Path) -> RPCModel:
    """Read the RPCCoefficientTag (50844, 92 doubles) of the first page of a (Geo)TIFF.

    RPC00B convention (GDAL writes the tag from its RPC metadata unchanged): no conversion.

    Raises:
        RPCFormatError: no such tag, or not 92 values.

    """
    import tifffile

    with tifffile.TiffFile(Path(path)) as tif:
        tag = tif.pages.first.tags.get(RPC_TIFF_TAG)
        if tag is None:
            raise RPCFormatError(f"{path}: no RPCCoefficientTag ({RPC_TIFF_TAG})")
        values = np.asarray(tag.value, dtype=np.float64).reshape(-1)
    return RPCModel.from_vector(values)


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


# ---------------------------------------------------------------------------------------------
# Dispatch

RPCFormat = Literal["geom", "rpc_txt", "rpb", "dimap", "geotiff"]


def detect_rpc_format(path: str | Path) -> RPCFormat:
    """Which RPC format a file holds, from its content (the extension only breaks ties).

    Raises:
        RPCFormatError: none of the known formats.

    """
    p = Path(path)
    head = p.read_bytes()[:4096]
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "geotiff"
    text = head.decode("utf-8", errors="replace")
    if text.lstrip().startswith("<") or "Dimap_Document" in text:
        return "dimap"
    if re.search(r"BEGIN_GROUP|lineNumCoef|lineOffset\s*=", text, re.IGNORECASE):
        return "rpb"
    full = p.read_text(encoding="utf-8", errors="replace")
    if re.search(r"^\s*([\w.]*\.)?line_num_coeff_00\s*:", full, re.IGNORECASE | re.MULTILINE):
        return "geom"
    if re.search(r"^\s*LINE_NUM_COEFF_1\s*:", full, re.IGNORECASE | re.MULTILINE):
        return "rpc_txt"
    ext = p.suffix.lower()
    by_ext: dict[str, RPCFormat] = {
        ".geom": "geom",
        ".rpb": "rpb",
        ".xml": "dimap",
        ".tif": "geotiff",
        ".tiff": "geotiff",
    }
    if ext in by_ext:
        return by_ext[ext]
    raise RPCFormatError(f"{p}: not a known RPC format (.geom, _RPC.TXT, .RPB, DIMAP, GeoTIFF)")


def read_rpc(path: str | Path) -> RPCModel:
    """Read an RPC from any supported format (:func:`detect_rpc_format`).

    The returned model is in this project's pixel convention (module docstring).
    """
    readers: dict[RPCFormat, Callable[[str | Path], RPCModel]] = {
        "geom": read_geom,
        "rpc_txt": read_rpc_txt,
        "rpb": read_rpb,
        "dimap": read_dimap_rpc,
        "geotiff": read_geotiff_rpc,
    }
    return readers[detect_rpc_format(path)](path)
