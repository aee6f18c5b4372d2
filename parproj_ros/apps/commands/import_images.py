"""``parproj import``: images with RPC -> an input bag; the checks of its inputs."""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ...io.dem import add_dem_arguments, dem_from_args
from ...io.files import (
    InputError,
    check_output,
    input_path,
    number,
    staged_output,
)
from .common import check_heights, check_raster, check_rpc, shown


def _image_index(option: str, name: str, images: Sequence[str]) -> int:
    """Which image ``option``'s IMAGE names: its path as given, else its file name.

    Raises:
        ValueError: IMAGE names no image, or several.

    """
    hits = [i for i, p in enumerate(images) if p == name] or [
        i for i, p in enumerate(images) if Path(p).name == Path(name).name
    ]
    if len(hits) != 1:
        raise ValueError(
            f"{option} {name}: names {'no' if not hits else 'more than one'} image "
            f"of {list(images)}"
        )
    return hits[0]


def _rpc_files(args: argparse.Namespace, images: Sequence[str]) -> list[str | None]:
    """``--rpc-left`` / ``--rpc-right`` (images 1, 2) and ``--rpc IMAGE FILE`` -> one per image.

    Raises:
        ValueError: IMAGE names no image (or several), an image given two RPC files.

    """
    out: list[str | None] = [args.rpc_left, args.rpc_right] + [None] * (len(images) - 2)
    for name, path in args.rpc or []:
        i = _image_index("--rpc", name, images)
        if out[i] is not None:
            raise ValueError(f"--rpc {name} {path}: {images[i]} already has RPC file {out[i]}")
        out[i] = path
    return out


def _crop_origins(given: Sequence[Sequence[str]] | None, images: Sequence[str]) -> tuple[Any, ...]:
    """``--crop-origin IMAGE ROW COL`` (repeatable) -> one (row, col) or None per image.

    IMAGE is matched against each image's path as given, then its file name.

    Raises:
        ValueError: IMAGE names no image (or several), ROW / COL not finite numbers.

    """
    out: list[tuple[float, float] | None] = [None] * len(images)
    for name, row, col in given or []:
        i = _image_index("--crop-origin", name, images)
        try:
            r, c = float(row), float(col)
        except ValueError:
            raise ValueError(
                f"--crop-origin {name} {row} {col}: ROW and COL must be numbers"
            ) from None
        if not (math.isfinite(r) and math.isfinite(c)):
            raise ValueError(f"--crop-origin {name} {row} {col}: ROW and COL must be finite")
        out[i] = (r, c)
    return tuple(out)


def run(args: argparse.Namespace) -> int:
    """``parproj import``: two or more images with RPC -> a single-camera bag with virtual GCP."""
    from ..importer import import_scenes, parse_pairs, scene_ids_of

    images = [args.left, args.right, *args.more]
    rpcs = _rpc_files(args, images)
    offsets = _crop_origins(args.crop_origin, images)
    files = [*images, *rpcs, *(args.dem or [])]
    args.inputs = [f for f in files if f]
    for f in args.inputs:
        input_path(f, "file")
    for f in images:
        check_raster(Path(f))
    for img, rpc in zip(images, rpcs, strict=True):
        check_rpc(Path(rpc) if rpc else Path(img), image=not rpc)
    if args.heights:
        check_heights("--heights", args.heights, 1.0)
    seen: dict[Path, str] = {}
    for img in images:
        if Path(img).resolve() in seen:
            raise InputError(
                img,
                f"is the same image as {seen[Path(img).resolve()]}: "
                "a stereo pair needs two different images",
            )
        seen[Path(img).resolve()] = img
    # a pair selection with more than two images or --pairs; else scenes left, right by order
    select = bool(args.more or args.pairs is not None or (args.ids and len(args.ids) != 2))
    ids = args.ids or (scene_ids_of(images) if select else ["left", "right"])
    if len(ids) != len(images) or len(set(ids)) != len(ids) or not all(i.strip() for i in ids):
        raise InputError("--ids", f"one distinct, non-empty scene id per image needed, got {ids}")
    pairs = parse_pairs(args.pairs or "bh", ids) if select else None
    dem = dem_from_args(args)
    out = check_output(args.output, inputs=args.inputs, force=args.force)
    args.outputs = [out]
    with staged_output(out, force=args.force) as work:
        import_scenes(
            images,
            work,
            pairs=pairs,
            bh_range=tuple(args.bh_range),
            scene_ids=ids,
            rpcs=rpcs,
            offsets=offsets,
            dem=dem,
            geoid_undulation=args.geoid_undulation,
            heights=tuple(args.heights) if args.heights else None,
            band=args.band,
            principal_distance=args.principal_distance,
            pixel_size=args.pixel_size,
            adjust=False if args.no_adjust else None,
            tie_points=not args.no_tie_points,
            overwrite=False,
            log=shown(work, out),
        )
    return 0


def add_parser(sub: Any) -> None:
    """Add ``parproj import`` to the sub-command parsers ``sub``."""
    p = sub.add_parser(
        "import",
        help="two or more images with RPC -> a single-camera bag with virtual GCP, no navigation",
    )
    p.add_argument("left", help="left image (any raster GDAL reads; first scene)")
    p.add_argument("right", help="right image (second scene)")
    p.add_argument("more", nargs="*", help="further images (scenes 3, 4, ...; see --pairs)")
    p.add_argument(
        "--pairs",
        help="which acquisitions pair up, written on the bag's `pairs` topic: 'bh' (default with "
        "3+ images: overlapping pairs with B/H in --bh-range), 'all', or LEFT:RIGHT,... "
        "scene ids; without it two images pair up by order",
    )
    p.add_argument(
        "--bh-range",
        type=float,
        nargs=2,
        default=[0.1, 1.0],
        metavar=("LO", "HI"),
        help="useful base-to-height ratios for --pairs bh (default 0.1 1.0)",
    )
    p.add_argument("-o", "--output", required=True, help="bag folder to create")
    p.add_argument("--rpc-left", help="RPC of the left full scene (default: tag 50844, sidecars)")
    p.add_argument("--rpc-right", help="RPC of the right full scene (see also --rpc)")
    add_dem_arguments(p, "virtual points on the ground +- 100 m")
    p.add_argument(
        "--heights",
        type=number(-1e4, 1e5),
        nargs=2,
        metavar=("HMIN", "HMAX"),
        help="ellipsoidal heights without a DEM (default: RPC height_off +- height_scale / 2)",
    )
    p.add_argument(
        "--ids",
        nargs="+",
        default=None,
        metavar="ID",
        help="scene ids, one per image (default: left right for two images, else file stems)",
    )
    p.add_argument(
        "--principal-distance",
        type=number(1e-4, 100.0),
        default=12.905,
        help="c written in the scanner info, m (not in an RPC; Pleiades-like default)",
    )
    p.add_argument(
        "--pixel-size",
        type=number(0.0, 1e-2, lo_open=True),
        default=13e-6,
        help="detector pitch, m (default 13 um)",
    )
    p.add_argument("--force", action="store_true", help="replace an existing bag")
    # issue 10: crop origins and band (kept apart from the image list: merge-friendly)
    p.add_argument(
        "--crop-origin",
        nargs=3,
        action="append",
        metavar=("IMAGE", "ROW", "COL"),
        help="pixel (0, 0) of IMAGE (its path or file name) is pixel (ROW, COL) of its RPC's "
        "grid; repeatable; default: the file's GDAL geotransform (ModelTransformationTag), "
        "else (0, 0) (the RPC is in the image's own grid, as GDAL assumes)",
    )
    p.add_argument("--band", type=int, help="band to import from each image, 1-based (default 1)")
    p.add_argument(
        "--rpc",
        nargs=2,
        action="append",
        metavar=("IMAGE", "FILE"),
        help="RPC file of IMAGE's full scene (its path or file name; any image; repeatable); "
        "--rpc-left / --rpc-right are the same for the first two images",
    )
    # issue 24: tie points between the original images (parproj_ros/io/rpc_ties.py)
    p.add_argument(
        "--no-adjust",
        action="store_true",
        help="keep the RPCs as given (default with 3+ images: one image bias per view estimated "
        "from tie points seen in 3+ views, so that every pair shares one object space)",
    )
    p.add_argument(
        "--no-tie-points",
        action="store_true",
        help="match nothing at import: no bias adjustment, and without --heights / --dem the "
        "virtual points span the RPC's height range instead of the measured terrain",
    )
    p.set_defaults(func=run)
