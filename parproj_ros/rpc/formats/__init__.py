"""RPC file formats: one module each, one table (:data:`FORMATS`), one entrance.

Every reader of an RPC file goes through :func:`read_rpc_file` (:func:`read_rpc` is it without
the description); every search for the RPC file beside an image through :func:`find_sidecar`.
A format is a module with ``detect``, ``read`` (-> :data:`~.base.RPCValues`), ``pixel_origin``
and ``write`` gathered in a :class:`~.base.RPCFormatSpec` ``FORMAT``, plus its line in
:data:`FORMATS` (docs/extending.md). The formats GDAL reads (``gdal`` of the row) are read by
GDAL when the caller gives a :class:`~.base.GdalReader` (parproj_ros/io/raster.py does), with
GDAL's strings parsed by :mod:`.metadata`; without one, by the format's own parser.

The pixel origin of each format, and the conversion made on reading: :mod:`parproj_ros.rpc`.
"""

from __future__ import annotations

from pathlib import Path

from ..model import RPCFormatError, RPCModel
from . import dimap, geom, geotiff, rpb, rpc_txt
from .base import (
    GdalReader,
    GdalRoute,
    RPCFormatSpec,
    RPCValues,
    model_from_values,
    number,
)
from .dimap import dimap_pixel_origin, read_dimap_rpc, write_dimap_rpc
from .geom import read_geom, read_keyword_list, write_geom
from .geotiff import read_geotiff_rpc, write_geotiff_rpc
from .metadata import rpc_from_metadata
from .rpb import read_rpb, write_rpb
from .rpc_txt import read_rpc_txt, write_rpc_txt

#: The name of a row of :data:`FORMATS` (``"geom"``, ``"rpc_txt"``, ``"rpb"``, ...).
RPCFormat = str

#: The RPC file formats, in the order :func:`detect_rpc_format` asks them (a TIFF header first:
#: a TIFF's text may hold anything).
FORMATS: dict[str, RPCFormatSpec] = {
    spec.name: spec
    for spec in (geotiff.FORMAT, dimap.FORMAT, rpb.FORMAT, geom.FORMAT, rpc_txt.FORMAT)
}


def detect_rpc_format(path: str | Path) -> RPCFormat:
    """Which RPC format a file holds, from its content (the extension only breaks ties).

    Raises:
        RPCFormatError: none of the known formats.

    """
    p = Path(path)
    head = p.read_bytes()[:4096]
    for spec in FORMATS.values():
        if spec.detect(p, head):
            return spec.name
    ext = p.suffix.lower()
    for spec in FORMATS.values():
        if ext in spec.extensions:
            return spec.name
    labels = ", ".join(spec.label for spec in FORMATS.values())
    raise RPCFormatError(f"{p}: not a known RPC format ({labels})")


def read_rpc_file(path: str | Path, *, gdal: GdalReader | None = None) -> tuple[RPCModel, str]:
    """The RPC of a file of any format in :data:`FORMATS`, and where it was read.

    The format's parser gives the file's values, its pixel origin is subtracted from
    LINE_OFF / SAMP_OFF, and the model is in this project's convention (:mod:`parproj_ros.rpc`).
    With ``gdal``, a format GDAL reads (its row's ``gdal``) is read by GDAL instead and GDAL's
    metadata strings parsed by :func:`.metadata.read` (RPC00B convention).

    Args:
        path: the RPC file.
        gdal: GDAL's reading (parproj_ros/io/raster.py), or None for this package's parsers.

    Returns:
        The model and a description of the source (the file name, or GDAL's words).

    Raises:
        RPCFormatError: not a known format, or a value missing or malformed (file and key
            named).

    """
    p = Path(path)
    spec = FORMATS[detect_rpc_format(p)]
    if gdal is not None and spec.gdal is not None:
        tags, source = gdal(p, spec)
        return rpc_from_metadata(tags, p), source
    values = spec.read(p)
    origin = spec.pixel_origin(p)
    if origin != 0.0:
        for key in ("line_off", "samp_off"):
            if key in values:
                values[key] = float(values[key]) - origin
    return model_from_values(values, p), p.name


def read_rpc(path: str | Path) -> RPCModel:
    """Read an RPC from any format of :data:`FORMATS` with this package's parsers.

    :func:`read_rpc_file` without GDAL and without the description. The returned model is in
    this project's pixel convention (:mod:`parproj_ros.rpc`).
    """
    return read_rpc_file(path)[0]


def write_rpc(path: str | Path, rpc: RPCModel, fmt: RPCFormat) -> None:
    """Write ``rpc`` to ``path`` in format ``fmt`` (a name of :data:`FORMATS`).

    Raises:
        RPCFormatError: an unknown format, or one that cannot be written.

    """
    spec = FORMATS.get(fmt)
    if spec is None or spec.write is None:
        known = ", ".join(n for n, s in FORMATS.items() if s.write is not None)
        raise RPCFormatError(f"cannot write RPC format {fmt!r} (written: {known})")
    spec.write(Path(path), rpc)


def sidecar_formats() -> list[RPCFormatSpec]:
    """The formats that sit beside an image, in the order :func:`find_sidecar` looks for them.

    Same-stem sidecars GDAL reads first (found, they mean GDAL skipped them: an error to
    explain), then same-stem sidecars only this package reads, then folder patterns; the
    table's order within each.
    """
    rank = {
        s.name: (0 if s.gdal is not None else 1) if s.sidecar_suffixes else 2
        for s in FORMATS.values()
        if s.sidecar_suffixes or s.find_in_folder is not None
    }
    return sorted((FORMATS[n] for n in rank), key=lambda s: rank[s.name])


def find_sidecar(image: str | Path) -> tuple[RPCFormatSpec, Path] | None:
    """The first RPC file beside an image (:func:`sidecar_formats`' order) and its format.

    A same-stem sidecar is the image's stem plus one of the row's ``sidecar_suffixes``
    (``a.tif`` -> ``a.RPB``); a folder sidecar is what the row's ``find_in_folder`` chooses.
    """
    p = Path(image)
    for spec in sidecar_formats():
        for suffix in spec.sidecar_suffixes:
            c = p.parent / f"{p.stem}{suffix}"
            if c.is_file():
                return spec, c
        if spec.find_in_folder is not None:
            chosen, _ = spec.find_in_folder(p)
            if chosen is not None:
                return spec, chosen
    return None


def sidecars_looked_for(image: str | Path, *, gdal: bool) -> str:
    """What :func:`find_sidecar` looked for beside an image, in words, for a "no RPC" message.

    Args:
        image: the image.
        gdal: the sidecars GDAL reads (``"no a.RPB / a_RPC.TXT"``), else the others (``"no
            a.geom; no RPC_*.XML in /data"``).

    """
    p = Path(image)
    specs = [s for s in sidecar_formats() if (s.gdal is not None) == gdal]
    if gdal:
        return "no " + " / ".join(f"{p.stem}{s.sidecar_suffixes[0]}" for s in specs)
    words = [f"no {p.stem}{s.sidecar_suffixes[0]}" for s in specs if s.sidecar_suffixes]
    words += [s.find_in_folder(p)[1] for s in specs if s.find_in_folder is not None]
    return "; ".join(words)


def formats_markdown() -> str:
    """The format table as markdown (docs/extending.md holds it; a test compares)."""
    rows = [
        "| format | module | written | read by GDAL | sidecar of an image "
        "| extension (no content match) |",
        "|---|---|---|---|---|---|",
    ]
    for s in FORMATS.values():
        module = s.read.__module__.replace(".", "/") + ".py"
        gdal = {None: "no", "raster": "yes (the raster)"}.get(s.gdal, f"yes (sidecar {s.gdal})")
        beside = " ".join(f"`<stem>{x}`" for x in s.sidecar_suffixes[:1])
        if s.find_in_folder is not None:
            beside = (beside + " " if beside else "") + "folder pattern"
        exts = ", ".join(f"`{e}`" for e in s.extensions) or "-"
        rows.append(
            f"| `{s.name}` ({s.label}) | `{module}` | {'yes' if s.write else 'no'} | {gdal} "
            f"| {beside or '-'} | {exts} |"
        )
    return "\n".join(rows)


__all__ = [
    "FORMATS",
    "GdalReader",
    "GdalRoute",
    "RPCFormat",
    "RPCFormatSpec",
    "RPCValues",
    "detect_rpc_format",
    "dimap_pixel_origin",
    "find_sidecar",
    "formats_markdown",
    "model_from_values",
    "number",
    "read_dimap_rpc",
    "read_geom",
    "read_geotiff_rpc",
    "read_keyword_list",
    "read_rpb",
    "read_rpc",
    "read_rpc_file",
    "read_rpc_txt",
    "rpc_from_metadata",
    "sidecar_formats",
    "sidecars_looked_for",
    "write_dimap_rpc",
    "write_geom",
    "write_geotiff_rpc",
    "write_rpb",
    "write_rpc",
    "write_rpc_txt",
]
