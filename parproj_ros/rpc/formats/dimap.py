"""DIMAP RPC XML (Airbus Pleiades 1A/1B, SPOT 6/7, Pleiades Neo) ``RPC_*.XML``: read and write.

Pixel origin: (1, 1) = centre of the first pixel in DIMAP v2; ``FIRST_COL`` of
``ImagetoGround_Validity_Domain`` in DIMAP v3 (0 for Pleiades Neo); subtracted on reading
(:mod:`parproj_ros.rpc`, evidence there). GDAL reads DIMAP RPCs only inside a product's folder
structure, so a loose ``RPC_*.XML`` is read here.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..model import _COEFF_NAMES, _SCALARS, RPCFormatError, RPCModel
from .base import RPCFormatSpec, RPCValues, model_from_values, number
from .rpc_txt import KEYS


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def detect(path: Path, head: bytes) -> bool:
    """XML (the first non-blank character is ``<``) or ``Dimap_Document`` in the head."""
    text = head.decode("utf-8", errors="replace")
    return text.lstrip().startswith("<") or "Dimap_Document" in text


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
                    return number(child.text, "FIRST_COL", path)
    return 1.0


def read(path: Path) -> RPCValues:
    """The ground -> image values of a DIMAP ``RPC_*.XML`` file, offsets as in the file.

    The coefficients are those of ``Inverse_Model`` (DIMAP v2) or ``GroundtoImage_Values``
    (v3), RPC00B order; offsets and scales from ``RFM_Validity``.

    Raises:
        RPCFormatError: not XML, no ground -> image model, or a value is malformed.

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
    found = {_local(c.tag).upper(): (c.text or "") for c in model}
    values: RPCValues = {}
    for name in _COEFF_NAMES:
        keys = [f"{name.upper()}_{i}" for i in range(1, 21)]
        if all(k in found for k in keys):
            values[name] = np.array([number(found[k], k, path) for k in keys])
    for node in root.iter():
        tag = _local(node.tag).upper()
        if tag in KEYS and node.text and KEYS[tag] not in values:
            values[KEYS[tag]] = number(node.text, tag, path)
    return values


def read_dimap_rpc(path: str | Path, *, origin: float | None = None) -> RPCModel:
    """Read the ground -> image RPC of a DIMAP ``RPC_*.XML`` file (:func:`read`).

    The image coordinates are converted to this project's convention by subtracting ``origin``
    from LINE_OFF and SAMP_OFF.

    Args:
        path: the XML file.
        origin: image coordinate of the centre of the first pixel in the file; None = detect
            (:func:`dimap_pixel_origin`: 1 for DIMAP v2); 0.0 returns the file's raw values.

    Raises:
        RPCFormatError: not a DIMAP RPC file, or a value is missing.

    """
    values = read(Path(path))
    shift = dimap_pixel_origin(path) if origin is None else float(origin)
    for key in ("line_off", "samp_off"):
        if key in values:
            values[key] = float(values[key]) - shift
    return model_from_values(values, path)


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


def find_in_folder(image: Path) -> tuple[Path | None, str]:
    """The ``RPC_*.XML`` of an image in its folder, or None and why none.

    The only one there, or the one whose name after ``RPC_`` starts the image's stem after
    ``IMG_`` (DIMAP product naming).
    """
    folder, stem = image.parent, image.stem
    xmls = sorted(q for q in folder.iterdir() if re.fullmatch(r"(?i)rpc_.*\.xml", q.name))
    key = stem[4:] if stem.upper().startswith("IMG_") else None
    matching = [q for q in xmls if key is not None and key.startswith(q.stem[4:])]
    chosen = matching[0] if len(matching) == 1 else (xmls[0] if len(xmls) == 1 else None)
    return chosen, f"{'several' if xmls else 'no'} RPC_*.XML in {folder}"


FORMAT = RPCFormatSpec(
    name="dimap",
    label="DIMAP",
    detect=detect,
    read=read,
    pixel_origin=dimap_pixel_origin,
    write=write_dimap_rpc,
    extensions=(".xml",),
    find_in_folder=find_in_folder,
)
