"""Real-pair benchmark: ``python -m tools.bench.realpairs [--json] [-o FILE] [--cases ...]``.

For the real Pleiades data in ``../shared/data`` (the Marseille triplet: pairs 1-2, 1-3, 2-3,
and the triplet through ``parproj import --pairs all`` and ``parproj fuse``; the Ventoux pair)
it runs the documented commands with NO height option::

    parproj import IMAGES -o bag [--pairs all]
    parproj process bag -o out --heights
    parproj dsm out -o dsm            (and for the triplet: parproj fuse out -o fused)

timing each as a separate process (wall clock, what a user waits), and scores every pair DSM
against the s2p and CARS references of the same images, and the fused DSM against
s2p_dsm_123 / cars_dsm_123, with :mod:`parproj_ros.eval.dsm_compare`: one grid (the s2p
reference's), one footprint per case (cells whose ground point projects inside every image of
the case through its RPC, as the data's README scores the references), median, NMAD, RMS,
p95 |d| of ours - reference, completeness (share of footprint cells with a height) and the
horizontal shift of ours (regression of d on the reference's slopes, metres E, N). Our
DSM is read from the output bag (ElevationGrid in its tangent-plane frame, converted exactly);
where ``parproj dsm`` wrote a GeoTIFF with a CRS, that file is scored too (its median must
agree with the bag's: same surface, another path). Beside them, the references' own agreement
(s2p vs CARS on the same images), computed in the same run on the same grid and footprint.

After the three pair cases, ``parproj fuse`` of their three output bags (pairs imported one by
one: three frames, three levels) is timed and scored like the triplet's fused DSM
(``marseille_pairs_fused``). The report ends with the issue's "Done when" bounds, each with
the figure measured (:func:`verdicts`).

The bundled bags (``bags/``) are processed too (``process --heights`` and ``dsm``, no height
option): a simulated bag's DSM against its scenario's terrain, the Ventoux bag's against SRTM.

Ventoux has no reference DSM: its DSM is scored against the SRTM tile (90 m, geoid heights +
50 m undulation, the bags' README): a coarse check of level and completeness only.

Speed of the heights step: ``parproj process --heights`` is run once more in this process
with the heights step (:class:`parproj_ros.core.heights.HeightsStage`) timed; against it, one
bare ``cv2.StereoSGBM`` pass (the settings of :class:`~parproj_ros.imaging.dense.SgbmParams`,
as tools/bench/heights.py) on the same normalized pair (read from the output bag, stretched to
8 bits) over the disparity range the step searched. Figures per left-image megapixel.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from parproj_ros.core import contract
from parproj_ros.eval.dsm_compare import (
    FrameDsm,
    MapDsm,
    compare,
    footprint,
    frame_dsms_from_bag,
    import_bag_frame,
    read_geotiff_dsm,
    to_map_grid,
)

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
MARSEILLE = DATA / "marseille_triplet"
VENTOUX = DATA / "ventoux"
#: Geoid undulation added to the SRTM heights at Ventoux, metres (bags/README.md).
VENTOUX_UNDULATION_M = 50.0

#: s2p vs CARS on pair 1-2 and on the triplet (README of the data), metres: the yardstick.
README_AGREEMENT = {
    "marseille_12": {"median": -0.08, "nmad": 0.77},
    "marseille_123": {"median": 0.00, "nmad": 0.52},
}


@dataclass(frozen=True)
class Case:
    """One benchmark case.

    Attributes:
        name: its key.
        images: the images imported (in order).
        refs: pair id -> {reference name: GeoTIFF}; the DSM of that pair is scored against
            each ("fused" for the fused DSM). CARS made no DSM of pairs 1-3 and 2-3: theirs
            are scored against cars_dsm_123 too (the triplet's level, 2.4 m from each of
            those pairs': compare its NMAD, not its median), so that a change is seen by
            both pipelines' references, not tuned to one.
        footprints: pair id -> the images whose common footprint is scored.
        pairs_all: import with ``--pairs all`` and fuse the pairs' DSMs.
        srtm: an SRTM tile to score against when there is no reference DSM.
    """

    name: str
    images: tuple[Path, ...]
    refs: dict[str, dict[str, Path]]
    footprints: dict[str, tuple[Path, ...]]
    pairs_all: bool = False
    srtm: Path | None = None


def _img(i: int) -> Path:
    return MARSEILLE / f"img_0{i}.tif"


def _ref(name: str) -> Path:
    return MARSEILLE / "reference" / f"{name}.tif"


CASES: dict[str, Case] = {
    "marseille_12": Case(
        "marseille_12",
        (_img(1), _img(2)),
        {"left+right": {"s2p": _ref("s2p_dsm_12"), "cars": _ref("cars_dsm_12")}},
        {"left+right": (_img(1), _img(2))},
    ),
    "marseille_13": Case(
        "marseille_13",
        (_img(1), _img(3)),
        {"left+right": {"s2p": _ref("s2p_dsm_13"), "cars": _ref("cars_dsm_123")}},
        {"left+right": (_img(1), _img(3))},
    ),
    "marseille_23": Case(
        "marseille_23",
        (_img(2), _img(3)),
        {"left+right": {"s2p": _ref("s2p_dsm_23"), "cars": _ref("cars_dsm_123")}},
        {"left+right": (_img(2), _img(3))},
    ),
    "marseille_123": Case(
        "marseille_123",
        (_img(1), _img(2), _img(3)),
        {
            "img_01+img_02": {"s2p": _ref("s2p_dsm_12"), "cars": _ref("cars_dsm_12")},
            "img_01+img_03": {"s2p": _ref("s2p_dsm_13")},
            "img_02+img_03": {"s2p": _ref("s2p_dsm_23")},
            "fused": {"s2p": _ref("s2p_dsm_123"), "cars": _ref("cars_dsm_123")},
        },
        {
            "img_01+img_02": (_img(1), _img(2)),
            "img_01+img_03": (_img(1), _img(3)),
            "img_02+img_03": (_img(2), _img(3)),
            "fused": (_img(1), _img(2), _img(3)),
        },
        pairs_all=True,
    ),
    "ventoux": Case(
        "ventoux",
        (VENTOUX / "left_image.tif", VENTOUX / "right_image.tif"),
        {},
        {"left+right": (VENTOUX / "left_image.tif", VENTOUX / "right_image.tif")},
        srtm=VENTOUX / "dem" / "N44E005.hgt",
    ),
}


# ---------------------------------------------------------------------------------------------
# Scoring


def score(
    ours: MapDsm | FrameDsm,
    refs: dict[str, MapDsm],
    images: Sequence[Path],
    *,
    label: str,
    also: dict[str, MapDsm | FrameDsm] | None = None,
) -> list[dict[str, Any]]:
    """Rows of ours (and ``also``) against each reference, and of the references' agreement.

    ``also``: other DSMs scored the same way (e.g. the GeoTIFF of ours). All on one grid and
    one footprint.

    The grid is the first reference's; the footprint the cells whose ground point (at the
    median height of all the DSMs scored) projects inside every image (the whole grid's cells
    where the first reference has a height when no image is given).
    """
    names = list(refs)
    first = refs[names[0]]
    g, crs = first.grid, first.crs
    on = {n: to_map_grid(r, g, crs) for n, r in refs.items()}
    mine = to_map_grid(ours, g, crs, start=on[names[0]])
    if images:
        mask = footprint(g, crs, [mine, *on.values()], images)
    else:
        mask = np.isfinite(on[names[0]])
    rows: list[dict[str, Any]] = []
    dsms: dict[str, MapDsm | FrameDsm] = {label: ours, **(also or {})}
    for dname, dsm in dsms.items():
        for ref in refs.values():
            c = compare(dsm, ref, grid=(g, crs), mask=mask, images=images)
            rows.append({**c.as_dict(), "dsm": dname, "vs": ref.name})
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            c = compare(refs[a], refs[b], grid=(g, crs), mask=mask, images=images)
            rows.append({**c.as_dict(), "dsm": f"{refs[a].name} (reference)", "vs": refs[b].name})
    return rows


def srtm_reference(path: Path, ours: FrameDsm, undulation_m: float) -> MapDsm:
    """The SRTM tile (+ undulation: ellipsoidal heights) on a UTM grid covering our DSM."""
    from pyproj import CRS, Transformer

    from parproj_ros.imaging.heights import DsmGrid
    from parproj_ros.io.dem import srtm_height
    from parproj_ros.io.geotiff import crs_for_frame, frame_of

    frame = frame_of(ours.frame_id)
    crs = crs_for_frame(ours.frame_id)
    if frame is None or crs is None:
        raise ValueError(f"{ours.name}: frame {ours.frame_id!r} is not a tangent plane")
    x, y = ours.grid.centres()
    z = ours.heights
    lon, lat, _ = frame.to_geodetic(x, y, np.where(np.isfinite(z), z, 0.0))
    fwd = Transformer.from_crs(CRS.from_epsg(4326), crs, always_xy=True)
    e, n = (np.asarray(v) for v in fwd.transform(lon, lat))
    cell = ours.grid.cell
    grid = DsmGrid.covering(float(e.min()), float(e.max()), float(n.min()), float(n.max()), cell)
    ge, gn = grid.centres()
    inv = Transformer.from_crs(crs, CRS.from_epsg(4326), always_xy=True)
    glon, glat = inv.transform(ge, gn)
    dem = srtm_height(path, geoid_undulation=undulation_m)
    h = np.asarray(dem(np.asarray(glon), np.asarray(glat)), dtype=np.float32)
    return MapDsm(h, grid, crs, f"SRTM+{undulation_m:g}m")


# ---------------------------------------------------------------------------------------------
# Running the commands


def _parproj() -> list[str]:
    return [sys.executable, "-m", "parproj_ros.apps.cli"]


def run_step(args: Sequence[str], log: Callable[[str], None]) -> tuple[float, int, str]:
    """Run ``parproj ARGS``; (wall seconds, exit code, its stderr's last lines)."""
    t0 = time.perf_counter()
    p = subprocess.run([*_parproj(), *args], capture_output=True, text=True, check=False)
    dt = time.perf_counter() - t0
    tail = "\n".join((p.stderr or "").strip().splitlines()[-3:])
    log(f"  parproj {' '.join(str(a) for a in args[:1])}: {dt:.1f} s, exit {p.returncode}")
    if p.returncode != 0:
        log("    " + tail.replace("\n", "\n    "))
    return dt, p.returncode, tail


@contextmanager
def _timed_heights(times: list[float]) -> Any:
    """Time every call of the pipeline's heights step (HeightsStage.__call__) in this process."""
    from parproj_ros.core import heights as core_heights

    stage = getattr(core_heights, "HeightsStage", None)
    if stage is None:
        yield
        return
    original = stage.__call__

    def wrapped(self: Any, out: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return original(self, out)
        finally:
            if getattr(out, "pairs", None):
                times.append(time.perf_counter() - t0)

    stage.__call__ = wrapped
    try:
        yield
    finally:
        stage.__call__ = original


@contextmanager
def _captured_steps(calls: list[tuple[Any, ...]]) -> Any:
    """Keep the arguments of every ``measure_heights`` call of the heights stage."""
    from parproj_ros.core import heights as core_heights

    original = core_heights.measure_heights

    def spy(*args: Any) -> Any:
        calls.append(args)
        return original(*args)

    core_heights.measure_heights = spy  # type: ignore[assignment]
    try:
        yield
    finally:
        core_heights.measure_heights = original


def step_best_s(
    calls: list[tuple[Any, ...]],
    bare: Callable[[Any], float] | None = None,
    repeat: int = 5,
) -> tuple[float, float]:
    """The heights step on the inputs the pipeline gave it, and the bare pass, in turns.

    Each call of the step again on its own inputs, alternated with ``bare(pair)`` (one bare
    pass of that call's pair, seconds), ``repeat`` times; the best of each, summed over the
    calls. Alternated, both meet the same load of a shared machine; neither is the first
    call in the process (first touches of memory, thread starts).

    Returns:
        (step seconds, bare pass seconds; NaN without ``bare``).
    """
    from parproj_ros.core.heights import measure_heights

    step_total = bare_total = 0.0
    for args in calls:
        best_step = best_bare = math.inf
        for _ in range(repeat):
            if bare is not None:
                best_bare = min(best_bare, bare(args[0]))
            t0 = time.perf_counter()
            measure_heights(*args)
            best_step = min(best_step, time.perf_counter() - t0)
        step_total += best_step
        bare_total += best_bare if bare is not None else math.nan
    return step_total, bare_total


class _TimedMatcher:
    """A cv2.StereoSGBM whose ``compute`` calls add their seconds to ``spent[0]``."""

    def __init__(self, matcher: Any, spent: list[float]) -> None:
        self._matcher, self._spent = matcher, spent

    def compute(self, left: NDArray[Any], right: NDArray[Any]) -> NDArray[Any]:
        t0 = time.perf_counter()
        try:
            return cast("NDArray[Any]", self._matcher.compute(left, right))
        finally:
            self._spent[0] += time.perf_counter() - t0


def step_parts_s(calls: list[tuple[Any, ...]], repeat: int = 5) -> tuple[float, float]:
    """The heights step's seconds inside OpenCV's SGBM ``compute`` and outside it.

    Each call of the step again on its own inputs, ``repeat`` times, with every matcher the
    step builds (``imaging.dense.sgbm_matcher``) timing its ``compute`` calls; of each call,
    the run of least total time, summed over the calls.

    Returns:
        (seconds in SGBM, seconds of everything else: checks, sub-pixel refinement, DSM
        gridding and fill, ortho-image, bookkeeping).
    """
    from parproj_ros.core.heights import measure_heights
    from parproj_ros.imaging import dense

    original = dense.sgbm_matcher
    spent = [0.0]

    def timed(*args: Any) -> Any:
        return _TimedMatcher(original(*args), spent)

    in_sgbm = rest = 0.0
    dense.sgbm_matcher = timed  # type: ignore[assignment]
    try:
        for args in calls:
            best = (math.inf, math.inf)
            for _ in range(repeat):
                spent[0] = 0.0
                t0 = time.perf_counter()
                measure_heights(*args)
                total = time.perf_counter() - t0
                if total < sum(best):
                    best = (spent[0], total - spent[0])
            in_sgbm += best[0]
            rest += best[1]
    finally:
        dense.sgbm_matcher = original
    return in_sgbm, rest


def narrowest_pass(left: NDArray[Any], right: NDArray[Any], d_range: tuple[int, int]) -> float:
    """Seconds of one bare pass searching 16 disparities (the fewest SGBM takes), best of 5.

    Centred on ``d_range``, on the same images and settings as :func:`bare_pass`: what any
    full-resolution SGBM pass of the pair costs at least, however narrow its range.
    """
    mid = (d_range[0] + d_range[1]) // 2
    run = bare_pass(left, right, (mid - 8, mid + 7))
    return min(run() for _ in range(5))


def normalized_pairs(
    out_bag: Path,
) -> dict[str, tuple[NDArray[Any], NDArray[Any], tuple[int, int]]]:
    """Pair id -> (left, right normalized images, searched disparity range) of an output bag."""
    from parproj_ros.ros.bag import BagReader
    from parproj_ros.ros.conversions import image_to_array

    reader = BagReader(out_bag)
    images: dict[str, tuple[NDArray[Any], NDArray[Any]]] = {}
    ranges: dict[str, tuple[int, int]] = {}
    left = right = None
    left_topic, right_topic = map(contract.normalized_image_topic, contract.SIDES)
    topics = [left_topic, right_topic, contract.STEREO_PAIR, contract.DSM]
    for item in reader.messages(topics=topics):
        m = item.msg
        if item.topic == left_topic:
            left = image_to_array(m)
        elif item.topic == right_topic:
            right = image_to_array(m)
        elif item.topic == contract.STEREO_PAIR and left is not None and right is not None:
            images[str(m.pair_id)] = (left, right)
            left = right = None
        elif item.topic == contract.DSM:
            ranges[str(m.pair_id)] = (int(m.disparity_min), int(m.disparity_max))
    return {k: (*images[k], ranges[k]) for k in images if k in ranges}


def bare_pass(
    left: NDArray[Any], right: NDArray[Any], d_range: tuple[int, int]
) -> Callable[[], float]:
    """One bare cv2.StereoSGBM pass (uint8, SgbmParams' settings), made ready: seconds per call.

    The images are stretched and the matcher built once; each call times one ``compute``.
    """
    from parproj_ros.imaging.dense import SgbmParams, sgbm_matcher, to_uint8

    p = SgbmParams()

    def stretch(a: NDArray[Any]) -> NDArray[Any]:
        data = a[a != 0] if np.any(a != 0) else a
        lo, hi = np.percentile(data, p.stretch_percentiles)
        return to_uint8(a, float(lo), float(hi))

    l8, r8 = stretch(left), stretch(right)
    ndisp = int(np.ceil((d_range[1] - d_range[0] + 1) / 16)) * 16
    sgbm = sgbm_matcher(p, d_range[0], ndisp)

    def timed() -> float:
        t0 = time.perf_counter()
        sgbm.compute(l8, r8)
        return time.perf_counter() - t0

    return timed


def bare_sgbm_s(
    left: NDArray[Any], right: NDArray[Any], d_range: tuple[int, int], repeat: int = 3
) -> float:
    """Seconds of one bare cv2.StereoSGBM pass (:func:`bare_pass`), best of ``repeat``."""
    run = bare_pass(left, right, d_range)
    return min(run() for _ in range(repeat))


def match_pair_s(left: NDArray[Any], right: NDArray[Any], d_range: tuple[int, int]) -> float:
    """Seconds of a :func:`~parproj_ros.imaging.dense.match_pair` call, best of two.

    The step's matching: default settings and tiles, as the heights step calls it.
    """
    from parproj_ros.imaging.dense import match_pair

    best = math.inf
    for _ in range(2):
        t0 = time.perf_counter()
        match_pair(left, right, d_range=d_range, nodata=0.0)
        best = min(best, time.perf_counter() - t0)
    return best


def _cv2_threads() -> int:
    import cv2

    return int(cv2.getNumThreads())


def heights_speed(bag: Path, work: Path, log: Callable[[str], None]) -> dict[str, Any]:
    """The heights step against one bare SGBM pass on the same normalized pairs.

    The step is timed in an in-process ``parproj process --heights`` run.
    """
    from parproj_ros.apps.cli import main as cli_main
    from parproj_ros.core.heights import measure_heights

    times: list[float] = []
    calls: list[tuple[Any, ...]] = []
    out = work / "speed_out"
    said = io.StringIO()
    with _timed_heights(times), _captured_steps(calls), redirect_stdout(said):
        with redirect_stderr(said):
            rc = cli_main(["process", str(bag), "-o", str(out), "--heights", "-q", "--force"])
    if rc != 0 or not times:
        return {"error": f"in-process process exit {rc}, heights step timed {len(times)} times"}
    pairs = normalized_pairs(out)
    mpx = sum(lft.size for lft, _, _ in pairs.values()) / 1e6
    per_pair = {k: bare_sgbm_s(lft, rgt, rng) for k, (lft, rgt, rng) in pairs.items()}
    sgbm = sum(per_pair.values())
    matched = {k: match_pair_s(lft, rgt, rng) for k, (lft, rgt, rng) in pairs.items()}
    match = sum(matched.values())
    step = float(sum(times))
    by_id = {str(args[0].pair_id): args for args in calls}
    ready = {k: bare_pass(*v) for k, v in pairs.items() if k in by_id}

    def bare_of(pair: Any) -> float:
        return ready[str(pair.pair_id)]()

    known = [args for k, args in by_id.items() if k in pairs]
    best, bare_alt = step_best_s(known, bare_of) if known else (math.nan, math.nan)
    # the same step matching at half resolution (heights_scale 2), in turns with the bare pass
    half = [(*args[:4], replace(args[4], scale=2)) for args in known]
    best2, bare2 = step_best_s(half, bare_of) if half else (math.nan, math.nan)
    in_sgbm, rest = step_parts_s(known) if known else (math.nan, math.nan)
    narrow = sum(narrowest_pass(*pairs[k]) for k in by_id if k in pairs)
    floor = (narrow + rest) / bare_alt if bare_alt else math.nan
    res = {
        "pairs": len(pairs),
        "mpx": mpx,
        "heights_s": step,
        "sgbm_s": sgbm,
        "heights_s_per_mpx": step / mpx if mpx else None,
        "sgbm_s_per_mpx": sgbm / mpx if mpx else None,
        "ratio": step / sgbm if sgbm else None,
        "heights_best_s": best,
        "sgbm_alternated_s": bare_alt,
        "ratio_best": best / bare_alt if bare_alt and math.isfinite(best / bare_alt) else None,
        "heights_best_s_scale2": best2,
        "ratio_best_scale2": best2 / bare2 if bare2 and math.isfinite(best2 / bare2) else None,
        "step_sgbm_s": in_sgbm,
        "step_rest_s": rest,
        "rest_over_sgbm": rest / bare_alt if bare_alt else None,
        "narrowest_over_sgbm": narrow / bare_alt if bare_alt else None,
        "floor_over_sgbm": floor if math.isfinite(floor) else None,
        "ranges": {k: list(v[2]) for k, v in pairs.items()},
        "sgbm_s_by_pair": per_pair,
        "match_pair_s": match,
        "match_pair_over_sgbm": match / sgbm if sgbm else None,
        "heights_s_by_call": times,
        "cv2_threads": _cv2_threads(),
        # pair id -> the heights_scale 2 step's result (scored by run_case, then dropped)
        "_scale2": {str(args[0].pair_id): measure_heights(*args)[0] for args in half},
    }
    log(
        f"  heights step {step:.2f} s for {mpx:.2f} Mpx ({res['heights_s_per_mpx']:.2f} s/Mpx), "
        f"bare SGBM {sgbm:.2f} s: x{res['ratio']:.2f} (the two in turns, best of 5: "
        f"{best:.2f} s and {bare_alt:.2f} s, x{res['ratio_best'] or math.nan:.2f}); "
        f"match_pair alone {match:.2f} s"
    )
    log(
        f"  heights_scale 2: the step {best2:.2f} s against {bare2:.2f} s in turns, "
        f"x{res['ratio_best_scale2'] or math.nan:.2f}"
    )
    log(
        f"  of the step, {in_sgbm:.3f} s in SGBM and {rest:.3f} s outside it "
        f"(x{rest / bare_alt:.2f} the bare pass alone); a pass of 16 disparities "
        f"x{narrow / bare_alt:.2f}: with one such pass and the rest as it is, x{floor:.2f}"
    )
    return res


#: The bundled bags (bags/README.md): each processed with --heights and no height option.
BAGS = ("airborne_foreaft", "crab_foreaft", "ikonos_agile", "ventoux")


def run_bag_case(name: str, work: Path, log: Callable[[str], None]) -> dict[str, Any]:
    """``process --heights`` and ``dsm`` on a bundled bag; its DSM against the truth.

    The truth: a simulated bag's terrain (its scenario, rebuilt from its seed:
    :func:`parproj_ros.eval.heights.scenario_terrain`), scored by
    :func:`~parproj_ros.eval.heights.dsm_accuracy` (completeness over the convex hull of the
    DSM's cells); the Ventoux bag's SRTM tile (+ 50 m undulation), a coarse check.
    """
    from parproj_ros.eval.heights import dsm_accuracy, scenario_terrain

    log(f"bag {name}:")
    bag = ROOT / "bags" / name
    out, dsm_dir = work / "out", work / "dsm"
    res: dict[str, Any] = {"bag": name, "seconds": {}, "exit": {}}
    for step, args in (
        ("process", ["process", str(bag), "-o", str(out), "--heights", "-q", "--force"]),
        ("dsm", ["dsm", str(out), "-o", str(dsm_dir), "--force"]),
    ):
        dt, rc, tail = run_step(args, log)
        res["seconds"][step], res["exit"][step] = dt, rc
        if rc != 0:
            res.setdefault("errors", {})[step] = tail
            if step == "process":
                return res
    try:
        dsms = frame_dsms_from_bag(out)
    except ValueError as err:
        res.setdefault("errors", {})["dsm"] = str(err)
        return res
    res["dsms"] = []
    truth = scenario_terrain(name)
    for d in dsms:
        row: dict[str, Any] = {
            "pair_id": d.name,
            "cells_with_height": int(np.isfinite(d.heights).sum()),
        }
        if truth is not None:
            acc = dsm_accuracy(d.heights, d.grid, truth)
            row.update(vs="truth", nmad=acc["nmad"], rms=acc["rms"],
                       median=acc.get("mean"), completeness=acc["completeness"])  # fmt: skip
        elif name == "ventoux":
            ref = srtm_reference(VENTOUX / "dem" / "N44E005.hgt", d, VENTOUX_UNDULATION_M)
            c = compare(d, ref, images=CASES["ventoux"].images)
            row.update(vs=ref.name, nmad=c.stats["nmad"], rms=c.stats["rms"],
                       median=c.stats["median"], completeness=c.completeness)  # fmt: skip
        res["dsms"].append(row)
        log(f"  {d.name}: {row.get('vs', '-')}: NMAD {row.get('nmad', math.nan):.3f} m, "
            f"completeness {100 * row.get('completeness', math.nan):.1f} %")  # fmt: skip
    return res


#: The pair cases whose separately imported DSMs are fused (``parproj fuse`` of three bags).
SEPARATE = ("marseille_12", "marseille_13", "marseille_23")


def run_separate_fusion(base: Path, log: Callable[[str], None]) -> dict[str, Any]:
    """``parproj fuse`` of the three pairs imported one by one (three frames, three levels).

    Timed as a process; scored like the triplet's fused DSM (against s2p_dsm_123 and
    cars_dsm_123 on the footprint of the three images), with the three pair DSMs beside it.
    """
    from parproj_ros.apps.fuse import fuse_bags

    name = "marseille_pairs_fused"
    log(f"{name}:")
    outs = [base / c / "out" for c in SEPARATE]
    res: dict[str, Any] = {"case": name, "images": [f"img_0{i}.tif" for i in (1, 2, 3)]}
    dt, rc, tail = run_step(["fuse", *map(str, outs), "-o", str(base / name), "--force"], log)
    res["seconds"] = {"fuse": dt}
    res["exit"] = {"fuse": rc}
    if rc != 0:
        res["errors"] = {"fuse": tail}
        return res
    frames = [import_bag_frame(base / c / "bag") for c in SEPARATE]
    # the pairs' own frames (a DSM labelled 'map' takes its import bag's)
    dsms = [frame_dsms_from_bag(o, frame_id=f)[0] for o, f in zip(outs, frames, strict=True)]
    fr = fuse_bags(outs, frame_id=frames[0])  # what parproj fuse computed
    f = fr.fused
    fused = FrameDsm(f.heights, f.grid, fr.frame_id, "fused")
    res["fusion"] = {
        "pairs": [f"{c}:{d.name}" for c, d in zip(SEPARATE, dsms, strict=True)],
        "weights": fr.weights,
        "median_before_m": [[round(float(v), 3) for v in r] for r in f.median_before],
        "median_after_m": [[round(float(v), 3) for v in r] for r in f.median_after],
        "offsets_m": [round(float(v), 3) for v in f.offsets],
    }
    case = CASES["marseille_123"]
    refs = {k: read_geotiff_dsm(p, name=p.stem) for k, p in case.refs["fused"].items()}
    also: dict[str, MapDsm | FrameDsm] = {
        f"{c} pair": d for c, d in zip(SEPARATE, dsms, strict=True)
    }
    res["rows"] = score(fused, refs, case.footprints["fused"], label="fused", also=also)
    for r in res["rows"]:
        log(f"  {r['dsm']} - {r['vs']}: median {r['median']:+.2f} NMAD {r['nmad']:.2f} m")
    return res


def run_case(case: Case, work: Path, log: Callable[[str], None]) -> dict[str, Any]:
    """Import, process, dsm (and fuse) one case; time, score, measure the heights speed."""
    log(f"{case.name}:")
    bag, out, dsm_dir = work / "bag", work / "out", work / "dsm"
    res: dict[str, Any] = {"case": case.name, "images": [p.name for p in case.images]}
    imp = ["import", *map(str, case.images), "-o", str(bag), "--force"]
    if case.pairs_all:
        imp += ["--pairs", "all"]
    steps: list[tuple[str, list[str]]] = [
        ("import", imp),
        ("process", ["process", str(bag), "-o", str(out), "--heights", "-q", "--force"]),
        ("dsm", ["dsm", str(out), "-o", str(dsm_dir), "--force"]),
    ]
    if case.pairs_all:
        steps.append(("fuse", ["fuse", str(out), "-o", str(work / "fused"), "--force"]))
    res["seconds"] = {}
    res["exit"] = {}
    for name, args in steps:
        dt, rc, tail = run_step(args, log)
        res["seconds"][name] = dt
        res["exit"][name] = rc
        if rc != 0:
            res.setdefault("errors", {})[name] = tail
            if name in ("import", "process"):
                return res
    frame = import_bag_frame(bag)
    dsms = {d.name: d for d in frame_dsms_from_bag(out, frame_id=frame)}
    res["dsm_frame"] = sorted({d.frame_id for d in dsms.values()})
    rows: list[dict[str, Any]] = []
    for pair_id, d in dsms.items():
        imgs = case.footprints.get(pair_id, case.images)
        also: dict[str, MapDsm | FrameDsm] = {}
        tif = dsm_dir / f"{pair_id.replace('+', '_')}_dsm.tif"
        if tif.is_file():
            try:
                also[f"{pair_id} (GeoTIFF)"] = read_geotiff_dsm(tif)
            except ValueError as err:  # no CRS yet: the bag's frame is what we score
                res.setdefault("notes", []).append(f"{tif.name}: {err}")
        refs = {k: read_geotiff_dsm(p, name=p.stem) for k, p in case.refs.get(pair_id, {}).items()}
        if not refs and case.srtm is not None:
            refs = {"srtm": srtm_reference(case.srtm, d, VENTOUX_UNDULATION_M)}
        if refs:
            rows += score(d, refs, imgs, label=pair_id, also=also)
    if case.pairs_all and len(dsms) >= 2:
        from parproj_ros.apps.fuse import fuse_bags

        fr = fuse_bags([out], frame_id=frame)  # what parproj fuse computes
        f = fr.fused
        fused = FrameDsm(f.heights, f.grid, fr.frame_id, "fused")
        res["fusion"] = {
            "pairs": list(dsms),
            "weights": fr.weights,
            "median_before_m": [[round(float(v), 3) for v in r] for r in f.median_before],
            "median_after_m": [[round(float(v), 3) for v in r] for r in f.median_after],
            "offsets_m": [round(float(v), 3) for v in f.offsets],
        }
        refs = {k: read_geotiff_dsm(p, name=p.stem) for k, p in case.refs["fused"].items()}
        also = {}
        tif = work / "fused" / "fused_dsm.tif"
        if tif.is_file():
            try:
                also["fused (GeoTIFF)"] = read_geotiff_dsm(tif)
            except ValueError as err:
                res.setdefault("notes", []).append(f"{tif.name}: {err}")
        # the pipeline's own fusion (process publishes dsm_fused): its last, all-pair DSM
        try:
            piped = frame_dsms_from_bag(out, frame_id=frame, topic=contract.DSM_FUSED)
        except ValueError:
            piped = []
        if piped:
            last = piped[-1]
            also["fused (process, dsm_fused)"] = FrameDsm(
                last.heights, last.grid, last.frame_id, "fused (process)"
            )
        # the pairs too, against the same references on the same footprint: like with like
        also.update(dsms)
        rows += score(fused, refs, case.footprints["fused"], label="fused", also=also)
    res["speed"] = speed = heights_speed(bag, work, log)
    # the same pairs matched at half resolution (heights_scale 2), scored the same way
    for pair_id, h2 in speed.pop("_scale2", {}).items():
        refs = {k: read_geotiff_dsm(p, name=p.stem) for k, p in case.refs.get(pair_id, {}).items()}
        if h2.dsm is None or not refs or frame is None:
            continue
        d2 = FrameDsm(h2.dsm.heights, h2.dsm.grid, frame, f"{pair_id} (heights_scale 2)")
        rows += score(d2, refs, case.footprints.get(pair_id, case.images), label=d2.name)
    res["rows"] = rows
    for r in rows:
        log(
            f"  {r['dsm']} - {r['vs']}: median {r['median']:+.2f} NMAD {r['nmad']:.2f} m, "
            f"completeness {100 * r['completeness']:.1f} %"
        )
    return res


# ---------------------------------------------------------------------------------------------
# Report


def _git() -> dict[str, Any]:
    def git(*a: str) -> str:
        p = subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True, check=False)
        return p.stdout.strip()

    dirty = [ln for ln in git("status", "--porcelain", "--", "parproj_ros").splitlines() if ln]
    return {"commit": git("rev-parse", "--short", "HEAD"), "uncommitted_files": len(dirty)}


def _f(v: Any, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


#: The issue's "Done when" bounds: NMAD vs s2p at most s2p vs CARS on pair 1-2 (README), metres;
#: completeness; the triplet pairs' levels; the GeoTIFF's level and shift against s2p (half a
#: cell); the heights step against one bare SGBM pass.
BOUNDS = {
    "nmad_m": 0.77,
    "completeness": 0.90,
    "pair_levels_m": 0.5,
    "geotiff_median_m": 0.5,
    "geotiff_shift_m": 0.25,
    "heights_over_sgbm": 1.25,
}


def _row(case: dict[str, Any], dsm: str, vs_prefix: str) -> dict[str, Any] | None:
    for r in case.get("rows", []):
        if r["dsm"] == dsm and str(r["vs"]).startswith(vs_prefix):
            return dict(r)
    return None


def verdicts(doc: dict[str, Any]) -> list[tuple[str, str, str, bool]]:
    """(criterion, measured, bound, met) of the issue's "Done when" items this run measures."""
    out: list[tuple[str, str, str, bool]] = []
    b = BOUNDS
    for bag in doc.get("bags", []):
        n = len(bag.get("dsms") or [])
        cells = sum(r["cells_with_height"] for r in bag.get("dsms") or [])
        out.append(
            (
                f"bag {bag['bag']}: a DSM",
                f"{n} DSM, {cells} cells",
                ">= 1 DSM",
                n >= 1 and cells > 0,
            )
        )
    for case in doc["cases"]:
        name = case["case"]
        if name in ("marseille_12", "marseille_13", "marseille_23"):
            r = _row(case, "left+right", "s2p")
            if r is None:
                out.append((f"{name}: a DSM", "none", "a DSM", False))
                continue
            out.append(
                (
                    f"{name}: NMAD vs s2p",
                    f"{r['nmad']:.2f} m",
                    f"<= {b['nmad_m']} m",
                    r["nmad"] <= b["nmad_m"],
                )
            )
            out.append(
                (
                    f"{name}: completeness",
                    f"{100 * r['completeness']:.1f} %",
                    f">= {100 * b['completeness']:.0f} %",
                    r["completeness"] >= b["completeness"],
                )
            )
            r2 = _row(case, "left+right (heights_scale 2)", "s2p")
            if r2 is not None:
                out.append(
                    (
                        f"{name}: with heights_scale 2, NMAD vs s2p; completeness",
                        f"{r2['nmad']:.2f} m; {100 * r2['completeness']:.1f} %",
                        f"<= {b['nmad_m']} m; >= {100 * b['completeness']:.0f} %",
                        r2["nmad"] <= b["nmad_m"] and r2["completeness"] >= b["completeness"],
                    )
                )
            t = _row(case, "left+right (GeoTIFF)", "s2p")
            if t is not None:
                shift = math.hypot(t.get("shift_e_m", math.nan), t.get("shift_n_m", math.nan))
                ok = abs(t["median"]) < b["geotiff_median_m"] and shift < b["geotiff_shift_m"]
                out.append(
                    (
                        f"{name}: GeoTIFF lands on s2p",
                        f"median {t['median']:+.2f} m, shift {shift:.2f} m",
                        f"< {b['geotiff_median_m']} m, < {b['geotiff_shift_m']} m",
                        ok,
                    )
                )
        if name in ("marseille_123", "marseille_pairs_fused"):
            fused = _row(case, "fused", "s2p")
            pairs = [
                r
                for r in case.get("rows", [])
                if r["dsm"] != "fused" and "(" not in r["dsm"] and str(r["vs"]) == "s2p_dsm_123"
            ]
            if fused is None or not pairs:
                out.append((f"{name}: fused DSM", "none", "a fused DSM", False))
                continue
            best_c = max(r["completeness"] for r in pairs)
            best_n = min(r["nmad"] for r in pairs)
            out.append(
                (
                    f"{name}: fused completeness vs best pair",
                    f"{100 * fused['completeness']:.1f} %",
                    f">= {100 * best_c:.1f} %",
                    fused["completeness"] >= best_c,
                )
            )
            out.append(
                (
                    f"{name}: fused NMAD vs best pair (s2p_dsm_123)",
                    f"{fused['nmad']:.2f} m",
                    f"<= {best_n:.2f} m",
                    fused["nmad"] <= best_n,
                )
            )
            if name != "marseille_123":  # pairs imported one by one keep their own levels
                continue
            meds = [r["median"] for r in pairs]
            span = max(meds) - min(meds)
            out.append(
                (
                    f"{name}: pair levels agree",
                    f"{span:.2f} m",
                    f"<= {b['pair_levels_m']} m",
                    span <= b["pair_levels_m"],
                )
            )
        sp = case.get("speed", {})
        for key, how in (("ratio", "(first call) / bare SGBM"),
                         ("ratio_best", "/ bare SGBM (in turns, best of 5)"),
                         ("ratio_best_scale2",
                          "with heights_scale 2 / bare SGBM (in turns, best of 5)")):  # fmt: skip
            if sp.get(key) is not None:
                out.append(
                    (
                        f"{name}: heights step {how}",
                        f"{sp[key]:.2f}",
                        f"<= {b['heights_over_sgbm']}",
                        sp[key] <= b["heights_over_sgbm"],
                    )
                )
    return out


def markdown(doc: dict[str, Any]) -> str:
    """The results as markdown tables (accuracy, then speed)."""
    g = doc.get("git", {})
    dirty = f" + {g['uncommitted_files']} uncommitted files" if g.get("uncommitted_files") else ""
    lines = [
        f"Real pairs, commit {g.get('commit', '?')}{dirty}, {doc.get('date', '')}, "
        f"{doc.get('machine', '')}",
        "",
        "| case | DSM | vs | median m | NMAD m | RMS m | p95 abs m | cells | complete % "
        "| ref complete % | shift E, N m |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in doc["cases"]:
        for r in case.get("rows", []):
            lines.append(
                f"| {case['case']} | {r['dsm']} | {r['vs']} | {_f(r['median'], '+.2f')} "
                f"| {_f(r['nmad'], '.2f')} | {_f(r['rms'], '.2f')} | {_f(r['p95_abs'], '.2f')} "
                f"| {r['cells']} | {_f(100 * r['completeness'], '.1f')} "
                f"| {_f(100 * r['reference_completeness'], '.1f')} "
                f"| {_f(r.get('shift_e_m'), '+.2f')}, {_f(r.get('shift_n_m'), '+.2f')} |"
            )
        if case.get("errors"):
            for step, tail in case["errors"].items():
                lines.append(f"| {case['case']} | {step} failed | {' '.join(tail.split())} |")
    lines += [
        "",
        "| case | import s | process s | dsm s | fuse s | heights step s/Mpx | bare SGBM s/Mpx "
        "| heights / SGBM (first call) | heights / SGBM (in turns, best of 5) "
        "| with heights_scale 2 (in turns) "
        "| match_pair / SGBM | step outside SGBM / SGBM | 16-disparity pass + outside / SGBM |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in doc["cases"]:
        s = case.get("seconds", {})
        sp = case.get("speed", {})
        lines.append(
            f"| {case['case']} | {_f(s.get('import'), '.1f')} | {_f(s.get('process'), '.1f')} "
            f"| {_f(s.get('dsm'), '.1f')} | {_f(s.get('fuse'), '.1f')} "
            f"| {_f(sp.get('heights_s_per_mpx'), '.2f')} | {_f(sp.get('sgbm_s_per_mpx'), '.2f')} "
            f"| {_f(sp.get('ratio'), '.2f')} | {_f(sp.get('ratio_best'), '.2f')} "
            f"| {_f(sp.get('ratio_best_scale2'), '.2f')} "
            f"| {_f(sp.get('match_pair_over_sgbm'), '.2f')} "
            f"| {_f(sp.get('rest_over_sgbm'), '.2f')} | {_f(sp.get('floor_over_sgbm'), '.2f')} |"
        )
    for case in doc["cases"]:
        fu = case.get("fusion")
        if fu:
            names = fu["pairs"]
            offs = ", ".join(
                f"{a} - {b} {fu['median_before_m'][i][j]:+.2f}"
                for i, a in enumerate(names)
                for j, b in enumerate(names)
                if j > i
            )
            lines += ["", f"{case['case']}: pair level offsets before fusion (m): {offs}"]
    if doc.get("bags"):
        lines += [
            "",
            "| bundled bag | pair | vs | NMAD m | RMS m | complete % | process s | dsm s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for b in doc["bags"]:
            s = b.get("seconds", {})
            for r in b.get("dsms") or [{"pair_id": "no DSM"}]:
                lines.append(
                    f"| {b['bag']} | {r['pair_id']} | {r.get('vs', '-')} "
                    f"| {_f(r.get('nmad'), '.3f')} | {_f(r.get('rms'), '.3f')} "
                    f"| {_f(100 * r['completeness'] if 'completeness' in r else None, '.1f')} "
                    f"| {_f(s.get('process'), '.1f')} | {_f(s.get('dsm'), '.1f')} |"
                )
    lines += ["", "| Done when | measured | bound | met |", "|---|---|---|---|"]
    for crit, value, bound, met in verdicts(doc):
        lines.append(f"| {crit} | {value} | {bound} | {'yes' if met else 'NO'} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the cases; print the markdown tables (or JSON); exit 1 if a case made no DSM."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--bags", nargs="*", default=list(BAGS), choices=list(BAGS),
                    help="bundled bags to process (none: --bags with no name)")  # fmt: skip
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    ap.add_argument("-o", "--output", help="also write the report (markdown, or JSON) here")
    ap.add_argument("--keep", help="folder for the bags and DSMs (default: a temporary one)")
    args = ap.parse_args(argv)
    missing = [p for c in args.cases for p in CASES[c].images if not p.is_file()]
    if missing:
        print(f"realpairs: missing data: {', '.join(map(str, missing))}", file=sys.stderr)
        return 2
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    doc: dict[str, Any] = {
        "git": _git(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "readme_agreement": README_AGREEMENT,
        "cases": [],
    }
    with tempfile.TemporaryDirectory(prefix="realpairs_") as tmp:
        base = Path(args.keep) if args.keep else Path(tmp)
        for name in args.cases:
            work = base / name
            work.mkdir(parents=True, exist_ok=True)
            doc["cases"].append(run_case(CASES[name], work, log))
        done = {c["case"] for c in doc["cases"] if c.get("rows")}
        if set(SEPARATE) <= done:
            doc["cases"].append(run_separate_fusion(base, log))
        doc["bags"] = []
        for name in args.bags:
            work = base / f"bag_{name}"
            work.mkdir(parents=True, exist_ok=True)
            doc["bags"].append(run_bag_case(name, work, log))
    text = json.dumps(doc, indent=1, default=float) if args.json else markdown(doc)
    print(text)
    if args.output:
        Path(args.output).write_text(text)
    failed = [c["case"] for c in doc["cases"] if not c.get("rows")]
    failed += [f"bag {b['bag']}" for b in doc["bags"] if not b.get("dsms")]
    if failed:
        print(f"realpairs: no DSM scored for {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
