"""The ``parproj`` command line: offline work with the parallel projection library."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any


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
    from .paper import reproduce

    result = reproduce(n_sets=args.sets, seed=args.seed)
    _report(args.json, result, _print_paper)
    return 0 if result["tables23_vs_paper"]["all_match"] else 1


def _bags_dir() -> Path:
    return Path(__file__).resolve().parent.parent / "bags"


def cmd_simulate(args: argparse.Namespace) -> int:
    """``parproj simulate``: render scenarios into bags."""
    from .recording import record_scenario
    from .scenarios import SCENARIOS

    names = list(SCENARIOS) if args.scenario == ["all"] else args.scenario
    for name in names:
        if name not in SCENARIOS:
            print(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}", file=sys.stderr)
            return 2
        out = Path(args.output) / name
        if out.exists() and not args.force:
            print(f"{out} exists (use --force to replace)", file=sys.stderr)
            return 2
        if out.exists():
            import shutil

            shutil.rmtree(out)
        record_scenario(SCENARIOS[name](), out, progress=not args.quiet, noise_px=args.noise_px)
    return 0


def cmd_process(args: argparse.Namespace) -> int:
    """``parproj process``: the pipeline over a bag without DDS."""
    from .offline import process_bag

    overrides = {
        "z_avg": args.z_avg,
        "height_range": args.height_range,
        "gcp_roll": args.gcp_roll,
        "interpolation": args.interpolation,
        "scene_lines": args.scene_lines,
        "streaming": not args.no_streaming,
        "tie_points": not args.no_tie_points,
        "segment_max_error_px": args.segment_max_error,
        "output_extent": args.output_extent,
    }
    if args.no_gcp:
        overrides["min_gcp"] = 10**9
    summary = process_bag(
        Path(args.bag), Path(args.output), overrides=overrides, progress=not args.quiet
    )
    for iss in summary.issues:
        print(f"[{iss.level}] {iss.where}: {iss.message}", file=sys.stderr)
    rec = summary.recovery
    lost = "" if rec is None or rec.complete else f"; input cut off: {rec.error}"
    print(
        f"{summary.messages_in} messages in, {summary.scenes} scenes, {summary.pairs} pairs "
        f"-> {args.output}{lost}"
    )
    return 0 if summary.pairs > 0 else 1


def cmd_replay(args: argparse.Namespace) -> int:
    """``parproj replay``: publish a bag into the live graph."""
    import rclpy

    from .live import replay

    rclpy.init()
    node = rclpy.create_node("parproj_replay")
    try:
        res = replay(
            node,
            Path(args.bag),
            rate=args.rate,
            max_gap_s=args.max_gap,
            wait_for=args.wait_for,
            progress=not args.quiet,
        )
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    rec = res["recovery"]
    print(
        f"published {res['sent']} messages in {res['seconds']:.1f} s"
        + ("" if rec.complete else f"; bag cut off: {rec.error}")
    )
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """``parproj evaluate``: y-parallax, x-parallax linearity and object errors of an output."""
    from .evaluate import evaluate_bag

    res = evaluate_bag(
        Path(args.output_bag),
        Path(args.truth) if args.truth else None,
        plots=Path(args.plots) if args.plots else None,
        matching=not args.no_matching,
    )
    _report(args.json, res, _print_evaluation)
    return 0 if res["pair_count"] > 0 else 1


def _print_evaluation(res: dict[str, Any]) -> None:
    print(f"{res['pair_count']} pairs, {res['truth_points']} truth points")
    for p in res["pairs"]:
        print(f"pair {p['pair_id']}: {p['width']} x {p['height']} px")
        g = p.get("geometric")
        if g:
            y = g["y_parallax_px"]
            print(
                f"  geometric y-parallax ({g['points']} truth points): rms {y['rms']:.3f} px, "
                f"mean |y| {y['mean_abs']:.3f}, max {y['max_abs']:.3f}"
            )
            print(
                f"  x-parallax vs height: line rms {g['x_parallax_line_rms_px']:.3f} px, "
                f"{g['disparity_px_per_m']:.4f} px/m (published {g['published_px_per_m']:.4f})"
            )
            h = g["height_from_disparity_error_m"]
            print(f"  height from disparity: rms error {h['rms']:.3f} m")
        o = p.get("object_space_error_m")
        if o:
            print(
                f"  space intersection: xy {o['xy']['mean']:+.3f} +- {o['xy']['std']:.3f} m, "
                f"z {o['z']['mean']:+.3f} +- {o['z']['std']:.3f} m"
            )
        m = p.get("matching")
        if m and m["matches"]:
            y = m["y_parallax_px"]
            print(
                f"  image matches ({m['matches']}): median |y| {y['median_abs']:.3f} px, "
                f"rms {y['rms']:.3f} px"
            )


def cmd_demo(args: argparse.Namespace) -> int:
    """``parproj demo``: the default bag through the live node; pair, anaglyph and evaluation."""
    from .demo import run_demo

    return run_demo(Path(args.bag), Path(args.output), rate=args.rate, progress=not args.quiet)


def _node_params(items: Sequence[str]) -> dict[str, Any] | None:
    """``--node-param KEY=VALUE`` options as parameters (values read as YAML); None if bad."""
    import yaml

    params: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            print(f"--node-param needs KEY=VALUE, got {item!r}", file=sys.stderr)
            return None
        params[key] = yaml.safe_load(value)
    return params


def cmd_longrun(args: argparse.Namespace) -> int:
    """``parproj longrun``: the bag replayed for hours into the live node; memory, queue, pairs."""
    from .longrun import format_report, run_longrun

    params = _node_params(args.node_param)
    if params is None:
        return 2
    report = run_longrun(
        Path(args.bag),
        Path(args.output),
        minutes=args.minutes,
        repetitions=args.repetitions,
        rate=args.rate,
        margin_s=args.margin,
        in_flight=args.in_flight,
        warmup_s=args.warmup,
        node_params=params,
        progress=not args.quiet,
    )
    print(format_report(report))
    print(f"report {Path(args.output) / 'longrun.json'}, plot {Path(args.output) / 'longrun.png'}")
    return 0 if report["ok"] else 1


def cmd_bench(args: argparse.Namespace) -> int:
    """``parproj bench``: resampler against its lower bounds, the live node, memory."""
    from .bench import run_and_report

    params = _node_params(args.node_param)
    if params is None:
        return 2
    res = run_and_report(
        args.quick,
        json_out=args.json,
        markdown=Path(args.markdown) if args.markdown else None,
        include_quick=Path(args.include_quick) if args.include_quick else None,
        workdir=Path(args.workdir) if args.workdir else None,
        live=not args.no_live,
        offline=not args.no_offline,
        domain_id=args.domain_id,
        py_spy=args.py_spy,
        pairs=args.pairs,
        check_fields=args.check_fields,
        node_params=params,
    )
    return 1 if (res.get("live") or {}).get("error") else 0


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


def cmd_import(args: argparse.Namespace) -> int:
    """``parproj import``: two or more images with RPC -> a single-camera bag with virtual GCP."""
    from .multi_import import parse_pairs, scene_ids_of
    from .rpc import RPCError
    from .scene_import import import_scenes

    images = [args.left, args.right, *args.more]
    # a pair selection with more than two images or --pairs; else scenes left, right by order
    select = bool(args.more or args.pairs is not None or (args.ids and len(args.ids) != 2))
    try:
        ids = args.ids or (scene_ids_of(images) if select else ["left", "right"])
        import_scenes(
            images,
            args.output,
            pairs=parse_pairs(args.pairs or "bh", ids) if select else None,
            bh_range=tuple(args.bh_range),
            scene_ids=ids,
            rpcs=_rpc_files(args, images),
            offsets=_crop_origins(args.crop_origin, images),
            dem=args.dem,
            geoid_undulation=args.geoid_undulation,
            heights=tuple(args.heights) if args.heights else None,
            band=args.band,
            principal_distance=args.principal_distance,
            pixel_size=args.pixel_size,
            overwrite=args.force,
        )
    except (RPCError, FileExistsError, OSError, ValueError) as err:
        print(f"parproj import: {err}", file=sys.stderr)
        return 2
    return 0


def cmd_ventoux_eval(args: argparse.Namespace) -> int:
    """``parproj ventoux-eval``: y-parallax of matches, ours vs reference epipolar grids."""
    from .ventoux import evaluate_against_grids, format_table

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


def cmd_segments(args: argparse.Namespace) -> int:
    """``parproj segments``: a full-length RPC strip pair cut under model error bounds."""
    from .long_scene import format_table, run

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


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``parproj`` (one sub-command per offline job)."""
    from .paper import SEED

    parser = argparse.ArgumentParser(prog="parproj", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("paper", help="reproduce paper 1 section 5 (Tables 2-6) and paper 2 checks")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument(
        "--sets",
        type=int,
        default=200,
        help="random point sets for the spread of Tables 4-6 (0 to skip; default 200)",
    )
    p.add_argument("--seed", type=int, default=SEED, help=f"layout seed (default {SEED})")
    p.set_defaults(func=cmd_paper)

    p = sub.add_parser("simulate", help="render simulated scenarios into bags (MCAP)")
    p.add_argument("scenario", nargs="+", help="scenario names, or 'all'")
    p.add_argument("-o", "--output", default=str(_bags_dir()), help="folder for the bags")
    p.add_argument(
        "--noise-px",
        type=float,
        default=None,
        help="GCP measurement noise, px (default: the scenario's)",
    )
    p.add_argument("--force", action="store_true", help="replace existing bags")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("process", help="run the pipeline over a bag offline, write outputs")
    p.add_argument("bag")
    p.add_argument("-o", "--output", required=True, help="output bag folder")
    p.add_argument("--z-avg", type=float, default=0.0, help="average terrain height, m")
    p.add_argument("--height-range", type=float, default=500.0, help="height half range, m")
    p.add_argument("--gcp-roll", choices=["estimate", "navigation", "none"], default="estimate")
    p.add_argument("--interpolation", choices=["linear", "cubic"], default="linear")
    p.add_argument("--no-gcp", action="store_true", help="ignore GCP (navigation only)")
    p.add_argument("--scene-lines", type=int, default=0, help="lines per scene (0: by id/gap)")
    p.add_argument(
        "--no-tie-points",
        action="store_true",
        help="do not refine pairs with tie points matched in the images",
    )
    p.add_argument(
        "--no-streaming",
        action="store_true",
        help="whole images after both scenes, never column blocks",
    )
    p.add_argument(
        "--segment-max-error",
        type=float,
        default=1.0,
        metavar="PX",
        help="cut long GCP/RPC pairs into segments whose model error is within PX (0: never)",
    )
    p.add_argument(
        "--output-extent",
        choices=["overlap", "union"],
        default="overlap",
        help="columns of the normalized pair: the two scenes' overlap (default) or their union",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_process)

    p = sub.add_parser("replay", help="publish a bag into the live ROS 2 graph")
    p.add_argument("bag")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor (0 = unpaced)")
    p.add_argument(
        "--max-gap",
        type=float,
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
    p.add_argument("--plots", help="folder for PNG plots and images")
    p.add_argument("--no-matching", action="store_true", help="skip image matching")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("demo", help="run the default bag through the live node")
    p.add_argument("--bag", default=str(_bags_dir() / "ikonos_agile"))
    p.add_argument("-o", "--output", default="out/demo")
    p.add_argument("--rate", type=float, default=20.0, help="replay speed factor")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "longrun", help="replay a bag for hours into the live node: memory, queue, every pair"
    )
    p.add_argument("--bag", default=str(_bags_dir() / "ikonos_agile"))
    p.add_argument("-o", "--output", default="out/longrun", help="folder for the report")
    p.add_argument("--minutes", type=float, default=20.0, help="wall time to replay (min)")
    p.add_argument("--repetitions", type=int, default=None, help="stop after N repetitions")
    p.add_argument("--rate", type=float, default=0.0, help="speed factor (0 = as acknowledged)")
    p.add_argument("--margin", type=float, default=1.0, help="s between repetitions (simulated)")
    p.add_argument("--in-flight", type=int, default=2, help="repetitions ahead of the pairs")
    p.add_argument("--warmup", type=float, default=120.0, help="s left out of the RSS slope")
    p.add_argument(
        "--node-param", action="append", default=[], metavar="KEY=VALUE", help="node parameter"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_longrun)

    p = sub.add_parser("bench", help="benchmark: resampler, live node over DDS, memory")
    p.add_argument("--quick", action="store_true", help="2048 x 2048 scenes, under a minute")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--markdown", help="write the report (bench/BENCHMARKS.md) to this file")
    p.add_argument("--include-quick", help="JSON of a --quick run to include in the report")
    p.add_argument("--workdir", help="folder for the node's files and bags (default: temporary)")
    p.add_argument("--pairs", type=int, default=None, help="pairs through the live node")
    p.add_argument("--no-live", action="store_true", help="skip the live node over DDS")
    p.add_argument("--no-offline", action="store_true", help="skip the offline process")
    p.add_argument(
        "--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: the environment's)"
    )
    p.add_argument(
        "--check-fields",
        action="store_true",
        help="run the node with ROS_PYTHON_CHECK_FIELDS=1, as the tests do",
    )
    p.add_argument(
        "--node-param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra node parameter (YAML value), e.g. streaming=false; repeatable",
    )
    p.add_argument("--py-spy", help="py-spy executable: sample the node during the live run")
    p.set_defaults(func=cmd_bench)

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
        type=float,
        default=0.0,
        help="metres added to the DEM heights (geoid -> WGS84 ellipsoid; about 50 at Ventoux)",
    )
    p.add_argument(
        "--heights",
        type=float,
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
        type=float,
        default=12.905,
        help="c written in the scanner info, m (not in an RPC; Pleiades-like default)",
    )
    p.add_argument(
        "--pixel-size", type=float, default=13e-6, help="detector pitch, m (default 13 um)"
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
    p.add_argument("--pair", type=int, default=0, help="which stereo_pair of the bag (from 0)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_ventoux_eval)

    p = sub.add_parser(
        "segments",
        help="long scenes: cut a full-length RPC strip pair under model error bounds",
    )
    p.add_argument("left_rpc", help="RPC of the full left scene (.geom, _RPC.TXT, .RPB, XML, tif)")
    p.add_argument("right_rpc", help="RPC of the full right scene")
    p.add_argument("--width", type=int, default=400, help="samples of the strips (default 400)")
    p.add_argument(
        "--heights", type=float, nargs=2, default=[900.0, 1100.0], help="height range, m"
    )
    p.add_argument(
        "--bound", type=float, action="append", help="model error bound, px (repeatable)"
    )
    p.add_argument("--overlap", type=float, default=0.1, help="segment overlap fraction")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_segments, bound=None)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``parproj`` console script."""
    args = build_parser().parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
