"""``parproj process``: the pipeline over a bag without DDS; one option per offline parameter."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from ...core.params import PARAMS
from ...io.dem import add_dem_arguments
from ...io.files import (
    check_output,
    input_path,
    integer,
    number,
    staged_output,
)

if TYPE_CHECKING:
    from ..process import ProcessSummary

#: The parameters of parproj_node that ``parproj process`` has options for.
OFFLINE_PARAMS = tuple(p for p in PARAMS if p.offline)


#: Option value names of ``parproj process`` by unit.
METAVARS = {"m": "M", "px": "PX", "s": "S", "lines": "N", "points": "N"}


def add_parameter_options(p: argparse.ArgumentParser) -> None:
    """One option per parameter of parproj_node that makes sense offline (config.PARAMS).

    The same name with dashes (``--z-avg``), default and range (numbers are checked: finite, in
    range, else exit 2), and the description; booleans have ``--no-<name>`` as well.
    """
    for prm in OFFLINE_PARAMS:
        unit = f" [{prm.unit}]" if prm.unit else ""
        rng = f"; {prm.option_range_text}" if prm.option_range_text else ""
        shown = "on" if prm.default is True else "off" if prm.default is False else prm.default
        text = f"{prm.description}{unit}{rng}; default {shown}".replace("%", "%%")
        names = [prm.option, *prm.aliases]
        kw: dict[str, Any] = {"dest": prm.name, "default": prm.default, "help": text}
        if prm.type == "bool":
            p.add_argument(*names, action=argparse.BooleanOptionalAction, **kw)
            continue
        if prm.choices:
            kw["choices"] = list(prm.choices)
        elif prm.type == "integer":
            lo, hi = (None if b is None else int(b) for b in (prm.low, prm.high))
            kw["type"] = integer(lo, hi)
        elif prm.type == "double":
            kw["type"] = number(prm.low, prm.high, lo_open=prm.low_open)
        if not prm.choices:
            kw["metavar"] = METAVARS.get(prm.unit, "N" if prm.type == "integer" else "X")
        p.add_argument(*names, **kw)


def overrides_from(args: argparse.Namespace) -> dict[str, Any]:
    """PipelineConfig fields from the parameter options (and ``--no-gcp``)."""
    overrides = {p.field: getattr(args, p.name) for p in OFFLINE_PARAMS if p.field}
    if args.no_gcp:
        overrides["min_gcp"] = 10**9
    return overrides


def run(args: argparse.Namespace) -> int:
    """``parproj process``: the pipeline over a bag without DDS."""
    from ...io.dem import dem_from_args
    from ...ros.inputs import check_input_bag
    from ..process import process_bag

    args.inputs = [args.bag]
    bag = input_path(args.bag, "bag")
    out = check_output(args.output, inputs=[bag], force=args.force)
    args.outputs = [out]
    check_input_bag(bag)
    _check_frame_id(args.frame_id)
    overrides = overrides_from(args)
    dem = dem_from_args(args)  # read now: a DEM that cannot serve is refused before the run
    with staged_output(out, force=args.force) as work:
        summary = process_bag(
            bag,
            work,
            overrides=overrides,
            progress=not args.quiet,
            direct=args.direct,
            frame_id=args.frame_id,
            dem=dem,
        )
    for iss in summary.issues:
        print(f"[{iss.level}] {iss.where}: {iss.message}", file=sys.stderr)
    rec = summary.recovery
    lost = "" if rec is None or rec.complete else f"; input cut off: {rec.error}"
    print(
        f"{summary.messages_in} messages in, {summary.scenes} scenes, {summary.pairs} pairs "
        f"-> {out}{lost}"
    )
    return verdict(summary, heights=bool(overrides.get("heights")))


def _check_frame_id(frame_id: str) -> None:
    """Refuse a ``--frame-id`` naming a tangent plane that does not parse or cannot be.

    Raises:
        InputError: ``enu_wgs84:...`` with a latitude outside +-90 deg, a non-finite figure,
            or another form (``parproj dsm`` could not place the outputs).
    """
    from ...io.files import InputError
    from ...io.geotiff import frame_of
    from ...io.scene_import import TANGENT_PLANE_FORM

    try:
        frame_of(frame_id)
    except ValueError as err:
        raise InputError("--frame-id", f"{frame_id!r}: {err}; {TANGENT_PLANE_FORM}") from None


def verdict(summary: ProcessSummary, *, heights: bool) -> int:
    """Exit code of a run: 1 when the result is not what was asked for, else 0.

    Each shortfall is one line on stderr saying what is missing and what to try: no pair, a
    pair whose images share almost no ground, a pair without a DSM when heights were asked.
    """
    problems = []
    if summary.pairs == 0:
        problems.append("no pair was made (see the lines above)")
    if summary.unusable:
        problems.append(
            f"pair {', '.join(summary.unusable)}: the normalized images share almost no ground "
            "(ERROR above); check that the scenes overlap, or, if no DEM was given, import with "
            "--dem"
        )
    missing = [p for p, ok in summary.heights if not ok]
    tiled = {p for p, ok in summary.tiles if ok}  # quick-look tiles only: they are the heights
    if heights and summary.pairs and (missing or not (summary.heights or tiled)):
        which = ", ".join(missing) if missing else "every pair"
        problems.append(
            f"--heights: no DSM for {which} (the WARN above says why: e.g. textureless "
            "images, no overlap, a disparity range too wide; try --terrain tie_points, or "
            "--z-avg / --height-range around the ground)"
        )
    for text in problems:
        print(f"parproj process: {text}", file=sys.stderr)
    return 1 if problems else 0


def add_parser(sub: Any) -> None:
    """Add ``parproj process`` to the sub-command parsers ``sub``."""
    p = sub.add_parser("process", help="run the pipeline over a bag offline, write outputs")
    p.add_argument("bag")
    p.add_argument("-o", "--output", required=True, help="output bag folder")
    p.add_argument("--force", action="store_true", help="replace an existing output bag")
    p.add_argument("--no-gcp", action="store_true", help="ignore GCP (navigation only)")
    p.add_argument(
        "--frame-id",
        default="",
        metavar="FRAME",
        help="object frame the outputs are labelled with; default: that of the bag's GCP, "
        "truth or navigation messages (an imported pair's enu_wgs84:..., which parproj dsm "
        "turns into a CRS), else map",
    )
    add_parameter_options(p)
    add_dem_arguments(
        p,
        "the pairs' ground (parameter dem): its heights over each pair join the tie points' as "
        "the terrain searched (an enu_wgs84 object frame only)",
    )
    p.add_argument(
        "--direct",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="write the output bag past the page cache (O_DIRECT, where the file system allows "
        "it): no memory taken for its pages; --no-direct keeps it in the cache, for a reader "
        "right after; default on",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
