"""What the ``parproj`` commands share: result output, the bags folder, input checks."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ...io.files import InputError

FORCE_HELP = (
    "replace an existing output of the same kind (a bag where a bag is written, or a folder "
    "parproj wrote)"
)


def report(as_json: bool, result: dict[str, Any], show: Callable[[dict[str, Any]], None]) -> None:
    """Print ``result`` as one JSON document, or for a person with ``show``."""
    if as_json:
        json.dump(result, sys.stdout, indent=1, default=float)
        sys.stdout.write("\n")
    else:
        show(result)


def bags_dir() -> Path:
    """The repository's bags/ folder (the bundled bags)."""
    return Path(__file__).resolve().parents[3] / "bags"


def shown(work: Path, out: Path) -> Callable[[str], None]:
    """A ``log`` that prints the output's final name instead of its temporary one."""
    return lambda text: print(text.replace(str(work), str(out)))


def why(err: BaseException) -> str:
    """``<type>: <message>`` of an exception, on one line of at most about 300 characters."""
    text = " ".join(str(err).split())[:300]
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def check_tiff(path: Path) -> None:
    """A TIFF whose first image reads whole, else :class:`InputError` naming it."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            if not tif.pages:
                raise InputError(path, "a TIFF without images")
            tif.pages[0].asarray()
    except InputError:
        raise
    except Exception as err:  # tifffile raises assorted types for a damaged file
        raise InputError(path, f"not a readable TIFF ({why(err)})") from None


def check_raster(path: Path) -> None:
    """A raster GDAL opens (header, size, bands), else :class:`InputError` naming it.

    Pixels are read later, strip by strip; a file damaged further in is then reported with the
    rows GDAL could not read (``raster_io.read_rows``).
    """
    from ...io.raster import SceneImportError, raster_info

    try:
        raster_info(path)
    except SceneImportError as err:  # names the file and GDAL's error already
        raise InputError(path, str(err).removeprefix(f"{path}: ")) from None
    except Exception as err:  # GDAL and rasterio raise assorted types for a damaged file
        raise InputError(path, f"not a raster GDAL can read ({why(err)})") from None


def check_rpc(path: Path, image: bool = False) -> None:
    """An RPC that reads, else :class:`InputError` naming the file.

    From the file ``path``; with ``image``, the RPC of the image ``path`` (GeoTIFF tag or
    sidecar file).

    The readers (rpc.py, scene_import.py) signal a bad file with assorted exceptions, not all
    naming it: reading here first is what lets the message name the right file.
    """
    from ...io.raster import read_rpc_file
    from ...io.scene_import import find_rpc

    try:
        if image:
            find_rpc(path)
        else:
            read_rpc_file(path)
    except Exception as err:
        if image and "--rpc " in str(err):  # the message says what to pass already
            text = " ".join(str(err).split()).removeprefix(f"{path}: ")
            why_not = text if text.startswith("no RPC") else f"no usable RPC: {text}"
            raise InputError(path, why_not) from None
        if image:
            raise InputError(
                path,
                f"no usable RPC for this image ({why(err)}); give the RPC file with "
                "--rpc IMAGE FILE (or --rpc-left / --rpc-right)",
            ) from None
        raise InputError(path, f"not a readable RPC file ({why(err)})") from None


def check_heights(option: str, heights: Sequence[float], min_width: float) -> None:
    """Refuse a height range (m) that is inverted or narrower than ``min_width`` (exit 2)."""
    lo, hi = heights
    if not hi > lo:
        raise InputError(option, f"HI ({hi:g}) must be above LO ({lo:g})")
    if hi - lo < min_width:
        raise InputError(
            option,
            f"range {hi - lo:g} m is narrower than {min_width:g} m: points at nearly one height "
            "leave the model's height terms undetermined, and the check would mean nothing",
        )
