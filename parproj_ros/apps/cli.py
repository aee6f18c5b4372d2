"""The ``parproj`` command line: offline work with the parallel projection library."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import re
import signal
import sys
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

from ..core.config import PARAMS
from ..io.files import (
    InputError,
    check_output,
    input_path,
    integer,
    number,
    staged_output,
)

#: Exit codes of every ``parproj`` command (README, "Exit codes").
EXIT_OK, EXIT_NOT_MET, EXIT_BAD_INPUT, EXIT_INTERNAL = 0, 1, 2, 3
#: Exit codes after SIGINT and SIGTERM (128 + the signal number, as a shell reports them).
EXIT_SIGINT, EXIT_SIGTERM = 128 + signal.SIGINT, 128 + signal.SIGTERM
#: Largest wait between two messages ``parproj replay`` accepts without --max-gap, s.
MAX_REPLAY_IDLE_S = 3600.0
#: The parameters of parproj_node that ``parproj process`` has options for.
OFFLINE_PARAMS = tuple(p for p in PARAMS if p.offline)
#: Option value names of ``parproj process`` by unit.
METAVARS = {"m": "M", "px": "PX", "s": "S", "lines": "N", "points": "N"}
#: Largest JSON file read (``bench --include-quick``), bytes.
MAX_JSON_BYTES = 16 * 1024 * 1024


def _fmt(v: float) -> str:
    return f"{v:+.3e}" if (v != 0 and (abs(v) < 1e-2 or abs(v) >= 1e4)) else f"{v:+.4f}"


def _print_paper(r: dict[str, Any]) -> None:
    paper = r["paper"]
    print(
        "Paper 1 section 5 reproduced (ours | paper). Layout: seed",
        r["layout"]["seed"],
        "centroid",
        [round(c, 2) for c in r["layout"]["centroid_m"]],
        "m",
    )
    print("\nTables 2 and 3 (printed digits compared cell by cell):")
    for c in r["tables23_vs_paper"]["cells"]:
        flag = "ok " if c["match"] else "BAD"
        print(
            f"  [{flag}] T{c['table']} {c['side']:5s} {c['cell']:9s} ours {_fmt(c['ours']):>12s}"
            f"  paper {c['printed']:>9s}  {c['how']}"
        )
    print("  all cells match:", r["tables23_vs_paper"]["all_match"])
    print("\nTable 4 (direct, navigation-derived A, space intersection of all 25 points), metres:")
    for mode in ("no_ptp", "ptp", "ptp_nominal_roll"):
        o = r["table4"][mode]
        p = paper["table4"].get(mode)
        ps = (
            (
                f"   paper {p['xy_mean_m']:.3f}+-{p['xy_std_m']:.3f}  {p['z_mean_m']:.3f}+-"
                f"{p['z_std_m']:.3f}"
            )
            if p
            else ""
        )
        print(
            f"  {mode:17s} xy {o['xy_mean_m']:+.3f}+-{o['xy_std_m']:.3f}  "
            f"z {o['z_mean_m']:+.3f}+-{o['z_std_m']:.3f}{ps}"
        )
    print("\nTable 5 (A1..A8 and roll from the 16 GCP):")
    for side in ("left", "right"):
        for mode, o in r["table5"][side].items():
            p = paper["table5"][side].get(mode)
            ps = f"  paper sigma0 {p['sigma0_px']:.2f} psi {p['psi_deg']:+.2f}" if p else ""
            print(
                f"  {side:5s} {mode:12s} sigma0 {o['sigma0_px']:.2f} px  psi {o['psi_deg']:+.2f}"
                f"  A5 {o['A'][4]:+.2e} A7 {o['A'][6]:+.2e} A8 {o['A'][7]:+.2e}{ps}"
            )
    print("\nTable 6 (space intersection with the GCP-estimated parameters), metres:")
    for name in ("gcp", "check"):
        for mode, o in r["table6"][name].items():
            p = paper["table6"][name].get(mode)
            ps = (
                (
                    f"   paper {p['xy_mean_m']:.3f}+-{p['xy_std_m']:.3f}  {p['z_mean_m']:.3f}+-"
                    f"{p['z_std_m']:.3f}"
                )
                if p
                else ""
            )
            print(
                f"  {name:5s} {mode:12s} xy {o['xy_mean_m']:+.3f}+-{o['xy_std_m']:.3f}  "
                f"z {o['z_mean_m']:+.3f}+-{o['z_std_m']:.3f}{ps}"
            )
    p2 = r["paper2"]
    print("\nPaper 2 normalization on this geometry:")
    print(
        f"  exact parallel data: max |y-parallax| {p2['exact_parallel_y_parallax_px_max']:.2e} px"
    )
    print(
        f"  rigorous scenes, Eq 8 estimates: |y-parallax| mean {p2['y_parallax_px']['mean']:.3f}"
        f" max {p2['y_parallax_px']['max']:.3f} px (paper 2, real IKONOS: 1.5-2.3 px mean)"
    )
    print(
        f"  x-parallax vs height: rms about a line {p2['x_parallax_line_rms_px']:.4f} px; slope "
        f"{p2['x_parallax_px_per_m']['fitted']:.5f} px/m "
        f"(model {p2['x_parallax_px_per_m']['model']:.5f})"
    )
    if "spread" in r:
        sp = r["spread"]
        print(f"\nSpread over {sp['n_sets']} random point sets (median [5%, 95%]):")
        for k, v in sp["stats"].items():
            print(f"  {k:40s} {v['median']:9.3f} [{v['p05']:9.3f}, {v['p95']:9.3f}]")


def _report(as_json: bool, result: dict[str, Any], show: Callable[[dict[str, Any]], None]) -> None:
    """Print ``result`` as one JSON document, or for a person with ``show``."""
    if as_json:
        json.dump(result, sys.stdout, indent=1, default=float)
        sys.stdout.write("\n")
    else:
        show(result)


def cmd_paper(args: argparse.Namespace) -> int:
    """``parproj paper``: reproduce paper 1 section 5 and paper 2's checks."""
    from ..eval.paper import reproduce

    result = reproduce(n_sets=args.sets, seed=args.seed)
    _report(args.json, result, _print_paper)
    return 0 if result["tables23_vs_paper"]["all_match"] else 1


def _bags_dir() -> Path:
    return Path(__file__).resolve().parent.parent / "bags"


def _shown(work: Path, out: Path) -> Callable[[str], None]:
    """A ``log`` that prints the output's final name instead of its temporary one."""
    return lambda text: print(text.replace(str(work), str(out)))


def cmd_simulate(args: argparse.Namespace) -> int:
    """``parproj simulate``: render scenarios into bags."""
    from ..sim.recording import record_scenario
    from ..sim.scenarios import SCENARIOS

    names = list(SCENARIOS) if args.scenario == ["all"] else list(dict.fromkeys(args.scenario))
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        raise InputError(unknown[0], f"unknown scenario; known: {', '.join(SCENARIOS)}, all")
    outs = [check_output(Path(args.output) / n, force=args.force) for n in names]
    args.outputs = outs
    for name, out in zip(names, outs, strict=True):
        with staged_output(out, force=args.force) as work:
            record_scenario(
                SCENARIOS[name](),
                work,
                progress=not args.quiet,
                noise_px=args.noise_px,
                log=_shown(work, out),
            )
    return 0


def cmd_process(args: argparse.Namespace) -> int:
    """``parproj process``: the pipeline over a bag without DDS."""
    from ..sim.recording import check_input_bag
    from .process import process_bag

    args.inputs = [args.bag]
    bag = input_path(args.bag, "bag")
    out = check_output(args.output, inputs=[bag], force=args.force)
    args.outputs = [out]
    check_input_bag(bag)
    overrides = {p.field: getattr(args, p.name) for p in OFFLINE_PARAMS if p.field}
    if args.no_gcp:
        overrides["min_gcp"] = 10**9
    with staged_output(out, force=args.force) as work:
        summary = process_bag(bag, work, overrides=overrides, progress=not args.quiet)
    for iss in summary.issues:
        print(f"[{iss.level}] {iss.where}: {iss.message}", file=sys.stderr)
    rec = summary.recovery
    lost = "" if rec is None or rec.complete else f"; input cut off: {rec.error}"
    print(
        f"{summary.messages_in} messages in, {summary.scenes} scenes, {summary.pairs} pairs "
        f"-> {out}{lost}"
    )
    return 0 if summary.pairs > 0 else 1


def cmd_replay(args: argparse.Namespace) -> int:
    """``parproj replay``: publish a bag into the live graph."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from ..ros.bag import BagReader
    from ..ros.live import largest_idle_s, replay

    args.inputs = [args.bag]
    bag = input_path(args.bag, "bag")
    reader = BagReader(bag)
    unknown = [t for t in args.wait_for if t not in reader.topics()]
    if unknown:
        raise InputError(
            "--wait-for", f"{unknown[0]} is not a topic of {bag} ({', '.join(reader.topics())})"
        )
    if args.rate > 0:
        idle, where = largest_idle_s(reader, args.max_gap)
        if idle / args.rate > MAX_REPLAY_IDLE_S:
            raise InputError(
                bag,
                f"log time jumps ahead by {idle:.6g} s at message {where} (a clock jump?): "
                f"more than {MAX_REPLAY_IDLE_S:g} s of waiting; shorten it with --max-gap S, "
                "or replay unpaced with --rate 0",
            )
    print(f"replay {bag}: rate {args.rate:g}" + (" (unpaced)" if args.rate == 0 else ""))
    sys.stdout.flush()
    # Our own SIGINT/SIGTERM handlers (main) stop the replay at once; rclpy's would not.
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node("parproj_replay")
        try:
            res = replay(
                node,
                bag,
                rate=args.rate,
                max_gap_s=args.max_gap,
                wait_for=args.wait_for,
                progress=not args.quiet,
            )
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    rec = res["recovery"]
    print(
        f"published {res['sent']} messages in {res['seconds']:.1f} s"
        + ("" if rec.complete else f"; bag cut off: {rec.error}")
    )
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """``parproj evaluate``: y-parallax, x-parallax linearity and object errors of an output."""
    from ..eval.evaluate import evaluate_bag, print_evaluation
    from ..sim.recording import check_output_bag, check_truth_bag

    args.inputs = [args.output_bag, args.truth]
    out_bag = input_path(args.output_bag, "bag")
    truth = input_path(args.truth, "bag") if args.truth else None
    plots = None
    if args.plots:
        plots = check_output(args.plots, inputs=[out_bag, truth], force=args.force, kind="folder")
    args.outputs = [plots]
    check_output_bag(out_bag)
    if truth is not None:
        check_truth_bag(truth)
    with contextlib.ExitStack() as stack:
        work = (
            stack.enter_context(staged_output(plots, force=args.force, kind="folder"))
            if plots
            else None
        )
        res = evaluate_bag(out_bag, truth, plots=work, matching=not args.no_matching)
    _report(args.json, res, print_evaluation)
    return 0 if res["pair_count"] > 0 else 1


def cmd_demo(args: argparse.Namespace) -> int:
    """``parproj demo``: the default bag through the live node; pair, anaglyph and evaluation."""
    from ..sim.recording import check_input_bag
    from .demo import run_demo

    args.inputs = [args.bag]
    bag = input_path(args.bag, "bag")
    out = check_output(args.output, inputs=[bag], force=args.force, kind="folder")
    args.outputs = [out]
    check_input_bag(bag)
    with staged_output(out, force=args.force, kind="folder") as work:
        code = run_demo(bag, work, rate=args.rate, progress=not args.quiet, shown_as=out)
    return code


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


def _why(err: BaseException) -> str:
    text = " ".join(str(err).split())[:300]
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def _check_tiff(path: Path) -> None:
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
        raise InputError(path, f"not a readable TIFF ({_why(err)})") from None


def _check_raster(path: Path) -> None:
    """A raster GDAL opens (header, size, bands), else :class:`InputError` naming it.

    Pixels are read later, strip by strip; a file damaged further in is then reported with the
    rows GDAL could not read (``raster_io.read_rows``).
    """
    from ..io.raster import raster_info

    try:
        raster_info(path)
    except Exception as err:  # GDAL and rasterio raise assorted types for a damaged file
        raise InputError(path, f"not a raster GDAL can read ({_why(err)})") from None


def _check_rpc(path: Path, image: bool = False) -> None:
    """An RPC that reads, else :class:`InputError` naming the file.

    From the file ``path``; with ``image``, the RPC of the image ``path`` (GeoTIFF tag or
    sidecar file).

    The readers (rpc.py, scene_import.py) signal a bad file with assorted exceptions, not all
    naming it: reading here first is what lets the message name the right file.
    """
    from ..io.raster import read_rpc_file
    from ..io.scene_import import find_rpc

    try:
        if image:
            find_rpc(path)
        else:
            read_rpc_file(path)
    except Exception as err:
        if image:
            raise InputError(
                path,
                f"no usable RPC for this image ({_why(err)}); give the RPC file with "
                "--rpc IMAGE FILE (or --rpc-left / --rpc-right)",
            ) from None
        raise InputError(path, f"not a readable RPC file ({_why(err)})") from None


def cmd_import(args: argparse.Namespace) -> int:
    """``parproj import``: two or more images with RPC -> a single-camera bag with virtual GCP."""
    from .importer import import_scenes, parse_pairs, scene_ids_of

    images = [args.left, args.right, *args.more]
    rpcs = _rpc_files(args, images)
    offsets = _crop_origins(args.crop_origin, images)
    files = [*images, *rpcs, args.dem]
    args.inputs = [f for f in files if f]
    for f in args.inputs:
        input_path(f, "file")
    for f in images:
        _check_raster(Path(f))
    for img, rpc in zip(images, rpcs, strict=True):
        _check_rpc(Path(rpc) if rpc else Path(img), image=not rpc)
    if args.heights:
        _check_heights("--heights", args.heights, 1.0)
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
            dem=args.dem,
            geoid_undulation=args.geoid_undulation,
            heights=tuple(args.heights) if args.heights else None,
            band=args.band,
            principal_distance=args.principal_distance,
            pixel_size=args.pixel_size,
            overwrite=False,
            log=_shown(work, out),
        )
    return 0


def cmd_ventoux_eval(args: argparse.Namespace) -> int:
    """``parproj ventoux-eval``: y-parallax of matches, ours vs reference epipolar grids."""
    from ..eval.reference_grids import evaluate_against_grids, format_table
    from ..sim.recording import check_output_bag

    args.inputs = [args.output_bag, args.left, args.right, args.grids, args.truth]
    check_output_bag(input_path(args.output_bag, "bag"))
    for f in (args.left, args.right):
        _check_tiff(input_path(f, "file"))
    input_path(args.grids, "dir")
    if args.truth:
        input_path(args.truth, "bag")
    res = evaluate_against_grids(
        args.output_bag,
        args.left,
        args.right,
        args.grids,
        truth_bag=args.truth,
        pair_index=args.pair,
    )
    _report(args.json, res, lambda r: print(format_table(r)))
    return 0 if res["methods"]["ours"].get("n", 0) > 0 else 1


#: Smallest height range of ``parproj segments``, m: the virtual GCP and check points need
#: relief to fix the model's height terms (A3, A7, roll); a flat set leaves them undetermined,
#: and check points at the same heights then cannot show it.
MIN_SEGMENT_HEIGHT_RANGE_M = 10.0


def _check_heights(option: str, heights: Sequence[float], min_width: float) -> None:
    lo, hi = heights
    if not hi > lo:
        raise InputError(option, f"HI ({hi:g}) must be above LO ({lo:g})")
    if hi - lo < min_width:
        raise InputError(
            option,
            f"range {hi - lo:g} m is narrower than {min_width:g} m: points at nearly one height "
            "leave the model's height terms undetermined, and the check would mean nothing",
        )


def cmd_segments(args: argparse.Namespace) -> int:
    """``parproj segments``: a full-length RPC strip pair cut under model error bounds."""
    from ..eval.long_scene import format_table, run

    args.inputs = [args.left_rpc, args.right_rpc]
    for f in args.inputs:
        _check_rpc(input_path(f, "file"))
    _check_heights("--heights", args.heights, MIN_SEGMENT_HEIGHT_RANGE_M)
    res = run(
        args.left_rpc,
        args.right_rpc,
        width=args.width,
        heights=tuple(args.heights),
        bounds=tuple(args.bound or (1.0, 0.5, 0.3)),
        overlap=args.overlap,
    )
    _report(args.json, res, lambda r: print(format_table(r)))
    return 0 if all(r["reached"] for r in res["runs"]) else 1


def _add_parameter_options(p: argparse.ArgumentParser) -> None:
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


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``parproj <command>: <option>: <problem>``, exit 2.

    ``-1e4``, ``-.5e-3`` and ``-inf`` are taken as (negative) values, not as options (argparse
    only knows ``-1`` and ``-1.5``), so that ``--z-avg -1e4`` works and ``--rate -inf`` is
    refused for what it is.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(
            r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE
        )

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: {message} (see {self.prog} --help)\n")


FORCE_HELP = "replace an existing output (a bag, or a folder parproj wrote)"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``parproj`` (one sub-command per offline job)."""
    from ..eval.paper import SEED

    parser = _Parser(prog="parproj", description=__doc__)
    parser.add_argument(
        "--debug",
        action="store_true",
        help="on an error, show the Python traceback instead of the one-line message",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("paper", help="reproduce paper 1 section 5 (Tables 2-6) and paper 2 checks")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument(
        "--sets",
        type=integer(0, 100_000),
        default=200,
        help="random point sets for the spread of Tables 4-6 (0 to skip; default 200)",
    )
    p.add_argument(
        "--seed", type=integer(0, 2**32 - 1), default=SEED, help=f"layout seed (default {SEED})"
    )
    p.set_defaults(func=cmd_paper)

    p = sub.add_parser("simulate", help="render simulated scenarios into bags (MCAP)")
    p.add_argument("scenario", nargs="+", help="scenario names, or 'all'")
    p.add_argument("-o", "--output", default=str(_bags_dir()), help="folder for the bags")
    p.add_argument(
        "--noise-px",
        type=number(0.0, 1e3),
        default=None,
        help="GCP measurement noise, px (default: the scenario's)",
    )
    p.add_argument("--force", action="store_true", help="replace existing bags")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("process", help="run the pipeline over a bag offline, write outputs")
    p.add_argument("bag")
    p.add_argument("-o", "--output", required=True, help="output bag folder")
    p.add_argument("--force", action="store_true", help="replace an existing output bag")
    p.add_argument("--no-gcp", action="store_true", help="ignore GCP (navigation only)")
    _add_parameter_options(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_process)

    p = sub.add_parser("replay", help="publish a bag into the live ROS 2 graph")
    p.add_argument("bag")
    p.add_argument("--rate", type=number(0.0, 1e6), default=1.0, help="speed factor (0 = unpaced)")
    p.add_argument(
        "--max-gap",
        type=number(0.0, 1e9, lo_open=True),
        default=None,
        help="shorten idle stretches longer than this many seconds",
    )
    p.add_argument("--wait-for", nargs="*", default=[], help="topics to wait subscribers on")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("evaluate", help="evaluate the normalized pairs of an output bag")
    p.add_argument("output_bag")
    p.add_argument("--truth", help="bag with truth/points (default: the output bag)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--plots", help="folder to create for PNG plots and images")
    p.add_argument("--force", action="store_true", help="replace an existing --plots folder")
    p.add_argument("--no-matching", action="store_true", help="skip image matching")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("demo", help="run the default bag through the live node")
    p.add_argument("--bag", default=str(_bags_dir() / "ikonos_agile"))
    p.add_argument("-o", "--output", default="out/demo", help="folder to create for results")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.add_argument(
        "--rate", type=number(0.0, 1e6), default=20.0, help="replay speed factor (0 = unpaced)"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_demo)

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
    p.add_argument("--dem", help="SRTM .hgt tile: virtual points on the ground +- 100 m")
    p.add_argument(
        "--geoid-undulation",
        type=number(-200.0, 200.0),
        default=0.0,
        help="metres added to the DEM heights (geoid -> WGS84 ellipsoid; about 50 at Ventoux)",
    )
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
    p.set_defaults(func=cmd_import)

    p = sub.add_parser(
        "ventoux-eval",
        help="y-parallax of image matches: published transforms vs reference epipolar grids",
    )
    p.add_argument("output_bag", help="output bag of parproj process (a stereo_pair)")
    p.add_argument("--left", required=True, help="original left image (the pair's left scene)")
    p.add_argument("--right", required=True, help="original right image")
    p.add_argument("--grids", required=True, help="folder of the reference grids (OTB, shareloc)")
    p.add_argument("--truth", help="the imported input bag: evaluate its RPC-exact truth points")
    p.add_argument(
        "--pair", type=integer(0, 10**6), default=0, help="which stereo_pair of the bag (from 0)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_ventoux_eval)

    p = sub.add_parser(
        "segments",
        help="long scenes: cut a full-length RPC strip pair under model error bounds",
    )
    p.add_argument("left_rpc", help="RPC of the full left scene (.geom, _RPC.TXT, .RPB, XML, tif)")
    p.add_argument("right_rpc", help="RPC of the full right scene")
    p.add_argument(
        "--width",
        type=integer(2, 10**6),
        default=400,
        help="samples of the strips (default 400)",
    )
    p.add_argument(
        "--heights",
        type=number(-1e4, 1e5),
        nargs=2,
        default=[900.0, 1100.0],
        metavar=("LO", "HI"),
        help=f"height range, m (HI - LO >= {MIN_SEGMENT_HEIGHT_RANGE_M:g})",
    )
    p.add_argument(
        "--bound",
        type=number(0.0, 1e6, lo_open=True),
        action="append",
        help="model error bound, px (> 0; repeatable)",
    )
    p.add_argument(
        "--overlap", type=number(0.0, 0.5), default=0.1, help="segment overlap fraction (0-0.5)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_segments, bound=None)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like SIGINT's KeyboardInterrupt so that outputs in progress are undone."""


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    raise Terminated


#: What the commands raise for input a user can fix (exit 2): domain errors of the readers,
#: and the operating system's errors on the files named.
def _input_errors(command: str) -> tuple[type[BaseException], ...]:
    import yaml

    from ..io.gcp_file import GcpFileError
    from ..ros.bag import BagError

    kinds: list[type[BaseException]] = [InputError, BagError, GcpFileError, OSError]
    kinds += [UnicodeDecodeError, yaml.YAMLError]
    with contextlib.suppress(ImportError):
        from ..rpc import RPCError

        kinds.append(RPCError)
    if command in ("import", "ventoux-eval"):
        # their readers (scene_import, rpc, ventoux, tifffile) report bad files as ValueError
        kinds.append(ValueError)
    return tuple(kinds)


def describe(err: BaseException, inputs: Sequence[Any] = (), outputs: Sequence[Any] = ()) -> str:
    """One line ``<file>: <problem>`` for a bad-input exception.

    The file is the one the exception names; failing that, for an operating-system error
    (disk full, ...) the outputs being written, and for any other error the inputs.
    """
    if isinstance(err, OSError):
        if err.filename is not None:
            names = f"{err.filename}" + (f" -> {err.filename2}" if err.filename2 else "")
            return f"{names}: {err.strerror or err}"
        inputs = outputs or inputs
    text = " ".join(str(err).split()) or type(err).__name__
    path = getattr(err, "path", None)
    if path and not text.startswith(str(path)):
        return f"{path}: {text}"
    if path or any(f and str(f) in text for f in inputs):
        return text
    named = ", ".join(str(f) for f in inputs if f)
    return f"{named}: {text}" if named else text


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``parproj`` console script; returns the exit code (README)."""
    args = build_parser().parse_args(argv)
    name = f"parproj {args.command}"
    previous = signal.getsignal(signal.SIGTERM)
    with contextlib.suppress(ValueError):  # not the main thread: leave SIGTERM alone
        signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return int(args.func(args))
    except KeyboardInterrupt as err:
        if args.debug:
            traceback.print_exc()
        which = "SIGTERM" if isinstance(err, Terminated) else "SIGINT"
        outs = [str(o) for o in getattr(args, "outputs", []) if o]
        undone = f"; {', '.join(outs)} not written" if outs else ""
        print(f"{name}: stopped by {which}{undone}", file=sys.stderr)
        return EXIT_SIGTERM if isinstance(err, Terminated) else EXIT_SIGINT
    except MemoryError as err:
        if args.debug:
            raise
        print(f"{name}: out of memory ({err})", file=sys.stderr)
        return EXIT_INTERNAL
    except _input_errors(args.command) as err:
        if args.debug:
            raise
        where = describe(err, getattr(args, "inputs", []), getattr(args, "outputs", []))
        print(f"{name}: {where}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as err:
        if args.debug:
            raise
        print(
            f"{name}: internal error (a bug, not your input): {type(err).__name__}: "
            f"{' '.join(str(err).split())[:300]}; rerun with --debug for the traceback",
            file=sys.stderr,
        )
        return EXIT_INTERNAL
    finally:
        with contextlib.suppress(ValueError, TypeError):
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
