"""Part 5: the heights step on a normalized pair of the benchmark, against a bare SGBM pass.

The pair: the first fore/aft pair of the benchmark's acquisition (:mod:`parproj_ros.sim.synthetic`,
``lines`` x ``detectors`` uint16 scenes, the live run's strips and navigation), normalized by
the :class:`~parproj_ros.core.pipeline.Pipeline` in this process without DDS (whole images,
every other setting the node's default, ``z_avg`` 0 and ``height_range`` 500 m as the live
run); with ``heights_rows`` (the full form: 4096), its central band of that many rows
(:func:`central_band`: the whole IKONOS-size pair took 21.5 GB in the step). On it, in the same
run and on the same OpenCV threads:

* ``heights_full_mpx_s``: the whole heights step,
  :func:`parproj_ros.core.heights.measure_heights` (disparity range, tiled SGBM with the
  left-right check, heights, DSM, ortho-image) with the node's default options and the terrain
  the node would search (:meth:`~parproj_ros.core.heights.HeightsStage.pair_terrain`, not
  timed): left normalized megapixels per second;
* ``sgbm_bare_mpx_s``: one bare ``cv2.StereoSGBM`` pass with the pipeline's own matcher
  (:func:`parproj_ros.imaging.dense.sgbm_matcher`, default :class:`SgbmParams`) over the
  disparity range the step searched, on the pair stretched to uint8 as the step stretches it
  (percentiles of the pixels with data), the whole image in one call (in row bands of at most
  :data:`BARE_BAND_ROWS` rows for a larger pair: OpenCV's buffer size overflows on a whole
  14000 x 13816 px pair): the lower bound of the matching.

Each figure is the best of ``repeats`` runs (the machine is shared).
"""

from __future__ import annotations

import gc
import itertools
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from parproj_ros.core.config import PipelineConfig
from parproj_ros.core.heights import MATCHER_MODES, HeightsStage, measure_heights, options_of
from parproj_ros.core.pipeline import Pipeline
from parproj_ros.core.results import PairResult
from parproj_ros.core.trajectory import NavSample
from parproj_ros.imaging.dense import SgbmParams, sgbm_matcher, to_uint8
from parproj_ros.imaging.resample import OutputGrid
from parproj_ros.sim.synthetic import (
    T0_NS,
    VIEWS,
    acquisition,
    make_platform,
    texture_blocks,
)

from .config import BenchConfig, Log, log_stderr

#: Rows of one bare SGBM call at most (a 14000 x 13816 px pair in one call fails: OpenCV 5.0.0,
#: "Failed to allocate 18446744071950198244 bytes"; 8192 rows passed).
BARE_BAND_ROWS = 4096

#: The live run's prior heights (tools/bench/dds.py: ``z_avg`` 0, ``height_range`` 500 m).
PRIOR: dict[str, Any] = {"z_avg": 0.0, "height_range": 500.0}


def bench_pair(
    cfg: BenchConfig,
) -> tuple[PipelineConfig, PairResult, NDArray[np.generic], NDArray[np.generic]]:
    """The benchmark's first pair, normalized whole in this process: (config, pair, L, R).

    The strips and navigation of the live run (same platform, same random 11-bit blocks per
    strip position), fed to a Pipeline with ``streaming`` off and no heights.
    """
    plat = make_platform(cfg.lines, cfg.detectors)
    config = PipelineConfig(plat.views, scene_lines=cfg.lines, streaming=False, **PRIOR)
    pipe = Pipeline(config)
    dets = cfg.detectors
    blocks: dict[int, NDArray[np.uint16]] = {}
    pairs: list[PairResult] = []
    for ev in acquisition(plat, 1, cfg.strip_lines, cfg.nav_rate_hz):
        if ev.kind == "nav":
            out = pipe.add_navigation(
                NavSample(
                    T0_NS + round(ev.t_s * 1e9), plat.position(ev.t_s), plat.body, plat.velocity
                )
            )
        else:
            if ev.row0 not in blocks:
                (blocks[ev.row0],) = texture_blocks(1, ev.rows, dets, seed=10 + ev.row0)
            out = pipe.add_strip(VIEWS[ev.view], ev.stamp_ns, ev.scene_id, blocks[ev.row0])
        pairs += out.pairs
        if pairs:
            break
    if not pairs:
        pairs += pipe.flush().pairs
    if not pairs or pairs[0].left_image is None or pairs[0].right_image is None:
        raise RuntimeError("the benchmark's pair was not normalized (no pair out of the pipeline)")
    pair = pairs[0]
    assert pair.left_image is not None and pair.right_image is not None
    return config, pair, pair.left_image, pair.right_image


def central_band(
    pair: PairResult, left: NDArray[np.generic], right: NDArray[np.generic], rows: int
) -> tuple[PairResult, NDArray[np.generic], NDArray[np.generic]]:
    """The central ``rows`` rows of a normalized pair (copies), and the pair on that band.

    Both grids keep their columns; their row origin moves to the band's first row, so that the
    heights and the DSM of the band are where the whole pair puts them. The pair's own images
    are dropped (the band's are returned).
    """
    r0 = (left.shape[0] - rows) // 2

    def band(g: OutputGrid) -> OutputGrid:
        return replace(g, y_origin=g.y_origin + r0 * g.pixel, height=rows)

    cut = replace(
        pair,
        left_grid=band(pair.left_grid),
        right_grid=band(pair.right_grid),
        left_image=None,
        right_image=None,
    )
    return cut, left[r0 : r0 + rows].copy(), right[r0 : r0 + rows].copy()


def _best(repeats: int, fn: Callable[[], object]) -> float:
    """Shortest wall time of ``repeats`` calls, seconds."""
    best = math.inf
    for _ in range(max(1, repeats)):
        gc.collect()
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _stretch(a: NDArray[Any], nodata: float) -> NDArray[np.uint8]:
    """uint8 of ``a`` between the percentiles of its pixels with data (as the step stretches)."""
    p = SgbmParams()
    data = a[a != nodata] if np.any(a != nodata) else a
    lo, hi = np.percentile(data, p.stretch_percentiles)
    return to_uint8(a, float(lo), float(hi))


def bench_heights_step(
    cfg: BenchConfig, log: Log = log_stderr, repeats: int = 2
) -> dict[str, Any]:
    """The heights step and one bare SGBM pass on the benchmark's normalized pair (module doc).

    Returns ``heights_full_mpx_s`` and ``sgbm_bare_mpx_s`` (left normalized Mpx per second,
    best of ``repeats``), their seconds and ratio, the pair's size, the disparity range, the
    matched share and the OpenCV thread count; ``error`` (and None figures) when the pair or
    its heights could not be made.
    """
    res: dict[str, Any] = {
        "heights_full_mpx_s": None,
        "sgbm_bare_mpx_s": None,
        "cv2_threads": int(cv2.getNumThreads()),
        "error": None,
    }
    t0 = time.perf_counter()
    try:
        config, pair, left, right = bench_pair(cfg)
    except (RuntimeError, ValueError) as err:
        res["error"] = str(err)
        return res
    res["normalize_s"] = time.perf_counter() - t0
    res["whole_pair_size"] = [int(left.shape[1]), int(left.shape[0])]
    if 0 < cfg.heights_rows < left.shape[0]:
        pair, left, right = central_band(pair, left, right, cfg.heights_rows)
        gc.collect()
    options = options_of(config)
    terrain, _ = HeightsStage(options).pair_terrain(pair, left, right)
    mpx = left.shape[0] * left.shape[1] / 1e6
    last: list[Any] = []

    def step() -> None:
        last[:] = [measure_heights(pair, left, right, terrain, options)[0]]

    t_step = _best(repeats, step)
    hr = last[0]
    log(f"heights step: {mpx:.1f} Mpx in {t_step:.2f} s ({mpx / t_step:.2f} Mpx/s)")
    res.update(
        {
            "pair_id": pair.pair_id,
            "pair_size": [int(left.shape[1]), int(left.shape[0])],
            "mpx": mpx,
            "terrain": terrain.describe(),
            "status": str(hr.status),
            "d_range": [int(hr.d_range[0]), int(hr.d_range[1])],
            "matched_share": float(hr.valid_share),
            "heights_s": t_step,
            "matcher": options.matcher,
            "tile_px": options.tile_px,
        }
    )
    if not hr.ok:
        res["error"] = f"no heights on the benchmark's pair ({hr.status}): {hr.message}"
        return res
    p = SgbmParams(mode=MATCHER_MODES[options.matcher])  # the step's settings
    l8, r8 = _stretch(left, options.nodata), _stretch(right, options.nodata)
    dmin, dmax = hr.d_range
    ndisp = int(np.ceil((dmax - dmin + 1) / 16)) * 16
    sgbm = sgbm_matcher(p, dmin, ndisp)
    n_bands = -(-l8.shape[0] // BARE_BAND_ROWS)
    cuts = np.linspace(0, l8.shape[0], n_bands + 1).round().astype(int)

    def bare() -> None:
        for r0, r1 in itertools.pairwise(cuts):
            sgbm.compute(l8[r0:r1], r8[r0:r1])

    t_bare = _best(repeats, bare)
    res.update(
        {
            "sgbm_s": t_bare,
            "sgbm_disparities": ndisp,
            "sgbm_row_bands": n_bands,
            "heights_full_mpx_s": mpx / t_step,
            "sgbm_bare_mpx_s": mpx / t_bare,
            "heights_over_sgbm": t_step / t_bare,
        }
    )
    log(
        f"heights step: pair {left.shape[1]} x {left.shape[0]} px, disparities {dmin}..{dmax}, "
        f"{100 * hr.valid_share:.1f} % matched: step {t_step:.2f} s ({mpx / t_step:.2f} Mpx/s), "
        f"bare SGBM {t_bare:.2f} s ({mpx / t_bare:.2f} Mpx/s), x{t_step / t_bare:.2f}, "
        f"{res['cv2_threads']} OpenCV threads"
    )
    return res


#: The quick-look the benchmark runs the node with (issue 26: "of your choice"): -4, the tiles
#: of the normalized blocks reduced by 4 (a 16th of the pixels, a quarter of the disparities)
#: instead of the full-resolution tiles; 4 would make both. Given to the node as its
#: ``heights_quicklook`` value (a level -3..3 there, reduction 2^|level|: -2).
QUICKLOOK_FACTOR = -4
#: The streamed DSM tiles' topic (issue 26, item 1).
TILE_TOPIC = "dsm_tile"


def quicklook_setup(factor: int = QUICKLOOK_FACTOR) -> tuple[dict[str, Any], list[str]] | str:
    """(node parameters, tile topics) of the quick-look run, or why it cannot run (yet).

    Detects the streamed tiles by the contract (:data:`TILE_TOPIC` among the outputs; a
    quick-look topic: an output with "quick" in its name) and the quick-look parameter (a
    parameter with "quick" and "look" in its name, preferring one with "factor").
    """
    from parproj_ros.core import contract, params

    outputs = [t.name for t in contract.OUTPUTS]
    if TILE_TOPIC not in outputs:
        return (
            f"not measured yet: no topic {TILE_TOPIC} in parproj_ros/core/contract.py OUTPUTS "
            "(streamed DSM tiles, issue 26 item 1, not built)"
        )
    found = [p for p in params.PARAMS if "quick" in p.name and "look" in p.name]
    found.sort(key=lambda p: "factor" not in p.name)
    if not found:
        return (
            "not measured yet: no quick-look parameter (a name with 'quick' and 'look') in "
            "parproj_ros/core/params.py"
        )
    param = found[0]
    value: Any = factor
    if param.high is not None and param.high < 8 and abs(factor) > 1:
        # A level (heights_quicklook -3..3: reduction 2^|level|, negative: instead).
        level = round(math.log2(abs(factor)))
        if 2**level != abs(factor) or level > param.high:
            return f"no level of {param.name} ({param.low}..{param.high}) reduces by {factor}"
        value = level if factor > 0 else -level
    elif param.type == "string" or param.choices:
        value = str(factor)
        if param.choices and value not in param.choices:
            return f"the quick-look parameter {param.name} has no choice {factor}: {param.choices}"
    elif param.type == "double":
        value = float(factor)
    topics = [n for n in outputs if "quick" in n]
    return {"heights": True, param.name: value}, [TILE_TOPIC, *topics]


def bench_quicklook(
    cfg: BenchConfig,
    workdir: Any,
    *,
    domain_id: int | None = None,
    node_params: dict[str, Any] | None = None,
    factor: int = QUICKLOOK_FACTOR,
    log: Log = log_stderr,
) -> dict[str, Any]:
    """The live run again with ``heights`` on and the quick-look at ``factor``: its tiles.

    Every other parameter the node's default (plus ``node_params``). Returns the live run's
    figures (:func:`~tools.bench.dds.bench_live`, tiles per topic) under ``live``, and
    ``available`` False with ``reason`` when the node has no tiles yet.
    """
    setup = quicklook_setup(factor)
    if isinstance(setup, str):
        log(f"quick-look: {setup}")
        return {"available": False, "reason": setup, "factor": factor}
    params, topics = setup
    from .dds import bench_live

    log(f"quick-look: live run with {params}, tiles on {topics}")
    live = bench_live(
        cfg,
        workdir,
        domain_id=domain_id,
        node_params={**(node_params or {}), **params},
        tile_topics=topics,
        log=log,
    )
    return {"available": True, "reason": None, "factor": factor, "params": params, "live": live}


def quicklook_keys(ql: dict[str, Any] | None) -> dict[str, Any]:
    """The quick-look's ``--json`` keys, each None with a ``<key>_reason`` when not measured.

    A live run that ended early (the node killed above its memory limit, a stall) gives None
    too, its reason quoting the figure over the tiles that came before.

    ``heights_quicklook_realtime_factor``: of the quick-look tiles (the topic with "quick" in
    its name, else the ``@<factor>`` tiles of ``dsm_tile``); ``heights_tile_latency_max_s``:
    the longest latency of any DSM tile, from its last strip's publication to the tile's
    (every tile topic), and ``heights_tile_received_latency_max_s`` to its reception by the
    bench; and the CPU seconds per sensor second of the node and its render process in that
    run.
    """
    out: dict[str, Any] = {
        "heights_quicklook_realtime_factor": None,
        "heights_quicklook_realtime_factor_reason": None,
        "heights_tile_latency_max_s": None,
        "heights_tile_latency_max_s_reason": None,
        "heights_tile_received_latency_max_s": None,
        "heights_quicklook_node_cpu_per_sensor_s": None,
        "heights_quicklook_render_cpu_per_sensor_s": None,
        "heights_quicklook_factor": None,
    }
    if not ql:
        why = "the live part was not run (--no-live, or a test's form)"
        out["heights_quicklook_realtime_factor_reason"] = why
        out["heights_tile_latency_max_s_reason"] = why
        return out
    out["heights_quicklook_factor"] = ql.get("factor")
    if not ql.get("available"):
        out["heights_quicklook_realtime_factor_reason"] = ql.get("reason")
        out["heights_tile_latency_max_s_reason"] = ql.get("reason")
        return out
    live = ql.get("live") or {}
    cpu = live.get("cpu_per_sensor_s") or {}
    out["heights_quicklook_node_cpu_per_sensor_s"] = cpu.get("node")
    out["heights_quicklook_render_cpu_per_sensor_s"] = cpu.get("render")
    tiles: dict[str, Any] = live.get("tiles") or {}
    level = f"@{abs(int(ql.get('factor') or 0))}"
    quick = [k for k in tiles if "quick" in k and "@" not in k] or [
        k for k in tiles if k.endswith(level)
    ]
    err = f" (live run: {live['error']})" if live.get("error") else ""
    said = [i for i in live.get("node_issues") or [] if "quicklook" in i]
    err += f" (node: {said[0]})" if said else ""
    got = (tiles[quick[0]] or {}).get("tiles") if quick else 0
    if not got:
        where = quick[0] if quick else list(tiles)
        out["heights_quicklook_realtime_factor_reason"] = (
            f"no quick-look tiles received on {where}{err}"
        )
    else:
        f = (tiles[quick[0]] or {}).get("realtime_factor")
        out["heights_quicklook_realtime_factor"] = f
        if f is None:
            out["heights_quicklook_realtime_factor_reason"] = (
                f"fewer than 2 quick-look tiles placed on {quick[0]}{err}"
            )
    maxima = [
        v["latency_s"]["max"]
        for k, v in tiles.items()
        if "@" not in k and v and v["latency_s"]["max"] is not None
    ]
    received = [
        v["latency_s"]["max"]
        for v in (live.get("tiles_received") or {}).values()
        if v and v["latency_s"]["max"] is not None
    ]
    out["heights_tile_received_latency_max_s"] = max(received) if received else None
    if maxima:
        out["heights_tile_latency_max_s"] = max(maxima)
    else:
        out["heights_tile_latency_max_s_reason"] = f"no DSM tile placed on {list(tiles)}{err}"
    if live.get("error"):
        # A run that ended early measured its first tiles only: no figure of the pass.
        for key in ("heights_quicklook_realtime_factor", "heights_tile_latency_max_s"):
            if out[key] is not None:
                out[f"{key}_reason"] = (
                    f"the live run ended early ({live['error']}); {got} quick-look tiles came "
                    f"before, this figure over them: {out[key]:.3g}"
                )
                out[key] = None
    return out


#: The stages :func:`tile_stages` times, (attribute of parproj_ros.core.tiles, label).
TILE_STAGES = (
    ("reduce_block", "reduce blocks"),
    ("_window_terrain", "terrain (tie points)"),
    ("match_pair", "match_pair"),
    ("make_dsm", "make_dsm"),
    ("orthoimage", "orthoimage"),
    ("to_uint8", "stretch"),
)


def tile_stages(
    cfg: BenchConfig, quicklook: int = -3, *, log: Log = log_stderr, line_rate_hz: float = 6500.0
) -> dict[str, Any]:
    """CPU of the streamed tiles of the benchmark's first pair, by stage (issue 26).

    The pair normalized whole in this process (:func:`bench_pair`), then fed as 256-column
    blocks to a :class:`~parproj_ros.core.tiles.TileStage` with ``heights`` on and
    ``heights_quicklook`` ``quicklook`` (:func:`~parproj_ros.core.tiles.tiles_of_pair`: a
    contiguous copy of each block, as the pipeline keeps one), every stage's CPU seconds
    (``time.process_time``: every thread of this process) counted once (outermost call).

    Returns the tiles, CPU and wall seconds, CPU per sensor second (one pair per scene of
    ``cfg.lines`` lines at ``line_rate_hz``), ms of CPU per tile, and ``stages``: seconds per
    stage label, ``other`` the rest (block copies, windows, cell bookkeeping).
    """
    from parproj_ros.core import tiles as core_tiles

    config, pair, left, right = bench_pair(cfg)
    config = replace(config, dense=replace(config.dense, enabled=True, quicklook=quicklook))
    spent: dict[str, float] = {}
    depth = [0]
    saved = {name: getattr(core_tiles, name) for name, _ in TILE_STAGES}

    def timed(fn: Callable[..., Any], label: str) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            if depth[0]:
                return fn(*args, **kwargs)
            depth[0] += 1
            c0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[label] = spent.get(label, 0.0) + time.process_time() - c0
                depth[0] -= 1

        return call

    for name, label in TILE_STAGES:
        setattr(core_tiles, name, timed(saved[name], label))
    try:
        gc.collect()
        c0, t0 = time.process_time(), time.perf_counter()
        got = core_tiles.tiles_of_pair(config, pair, left, right)
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    finally:
        for name, fn in saved.items():
            setattr(core_tiles, name, fn)
    sensor_s = cfg.lines / line_rate_hz
    n = max(1, len(got))
    spent["other"] = cpu - sum(spent.values())
    stages = dict(sorted(spent.items(), key=lambda kv: -kv[1]))
    res: dict[str, Any] = {
        "quicklook": quicklook,
        "pair_size": [int(left.shape[1]), int(left.shape[0])],
        "tiles": len(got),
        "tiles_ok": sum(t.ok for _, t in got),
        "cpu_s": cpu,
        "wall_s": wall,
        "sensor_s": sensor_s,
        "cpu_per_sensor_s": cpu / sensor_s,
        "cpu_ms_per_tile": 1000 * cpu / n,
        "stages": stages,
    }
    log(
        f"tiles (heights_quicklook {quicklook}): {len(got)} of pair {left.shape[1]} x "
        f"{left.shape[0]} px, CPU {cpu:.2f} s ({cpu / sensor_s:.2f} per sensor s, "
        f"{1000 * cpu / n:.0f} ms a tile), wall {wall:.2f} s; "
        + ", ".join(f"{k} {v:.3f} s" for k, v in stages.items())
    )
    return res


def main(argv: list[str] | None = None) -> int:
    """``python -m tools.bench.dsm [--quick] [--quicklook L] [--live [--pairs N]]``.

    :func:`tile_stages` as JSON; ``--live``: instead, the live quick-look run of the full
    benchmark (:func:`bench_quicklook` with the form's own quick-look factor, ``--pairs``
    pairs, default the form's) and its ``--json`` keys (:func:`quicklook_keys`), with the
    tiles' latencies; exit 1 when the run gave no figure.
    """
    import argparse
    import dataclasses
    import json
    import os
    import tempfile
    from pathlib import Path

    from .config import FULL, QUICK

    p = argparse.ArgumentParser(prog="python -m tools.bench.dsm", description=tile_stages.__doc__)
    p.add_argument("--quick", action="store_true", help="the quick form's pair (2048 px)")
    p.add_argument(
        "--quicklook",
        type=int,
        default=-3,
        choices=range(-3, 4),
        help="heights_quicklook of the tiles (default -3: 1/8 only; 0: full resolution)",
    )
    p.add_argument("--live", action="store_true", help="the live quick-look run over DDS")
    p.add_argument("--pairs", type=int, default=0, help="with --live: pairs (default: the form's)")
    args = p.parse_args(argv)
    cfg = QUICK if args.quick else FULL
    if not args.live:
        res = tile_stages(cfg, args.quicklook)
        print(json.dumps(res, indent=1))
        return 0 if res["tiles_ok"] else 1
    if args.pairs > 0:
        cfg = dataclasses.replace(cfg, pairs=args.pairs)
    domain = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0) or None
    with tempfile.TemporaryDirectory() as wd:
        ql = bench_quicklook(cfg, Path(wd), domain_id=domain, factor=cfg.quicklook_factor)
    keys = quicklook_keys(ql)
    live = ql.get("live") or {}
    keys["pairs"] = cfg.pairs
    keys["pairs_shed"] = live.get("pairs_shed")
    keys["node_peak_rss_mb"] = live.get("node_peak_rss_mb")
    keys["node_queue_max"] = live.get("node_queue_max")
    keys["node_render"] = live.get("node_render")
    keys["node_cpu"] = live.get("cpu_per_sensor_s")
    keys["tiles"] = {
        k: {"tiles": v["tiles"], "latency_s": v["latency_s"]}
        for k, v in (live.get("tiles") or {}).items()
        if v
    }
    print(json.dumps(keys, indent=1))
    return 0 if keys["heights_quicklook_realtime_factor"] is not None else 1


if __name__ == "__main__":
    raise SystemExit(main())
