"""``parproj evaluate``: how good the published normalized pairs are.

For every StereoPair of an output bag it reports:

* geometric y-parallax: truth points (exact object points with their exact image positions in
  both scenes) mapped through the *published* transforms (scene frame, PTP roll, 2x3
  normalization affine, output grid) to normalized pixel rows: row_left - row_right;
* image y-parallax: SIFT matches between the two normalized images, each refined to sub-pixel by
  normalized cross-correlation with a parabola fit; their row differences;
* x-parallax against height: disparity (col_left - col_right) of the truth points against their
  height: residual of a straight-line fit, and heights from the published relation;
* object-space errors: least-squares space intersection with the published A1..A8 and roll.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..core import contract
from ..core.results import GroundPoint
from ..geometry import AffineModel, GeometryError, SceneObservation, space_intersection
from ..imaging.matching import match_normalized
from ..imaging.preview import anaglyph, to_uint8
from ..io.files import file_stem
from ..ros.bag import BagError, BagReader
from ..ros.conversions import (
    ConversionError,
    assemble_blocks,
    elevation_grid_from_msg,
    image_to_array,
    stamp_to_ns,
)
from ..ros.inputs import truth_from_bag
from .heights import (
    Surface,
    disparities_by_stamp,
    dsm_accuracy,
    save_height_plots,
    scenario_terrain,
)
from .published import normalized_px

FloatArray = NDArray[np.float64]


def error_stats(v: FloatArray, *, finite_only: bool = False) -> dict[str, float]:
    """Statistics of signed errors (pixels or metres), ``{"n": 0}`` for none.

    n, mean |e|, median |e|, RMS, 95th percentile of |e|, max |e|, signed mean and standard
    deviation (mean removed, ddof 0). With ``finite_only``, NaN and inf are left out first (``n``
    counts the rest): the Ventoux comparison, where a grid may not cover a point. Otherwise a
    non-finite error shows as a non-finite figure, as a defect should.
    """
    v = np.asarray(v, dtype=float)
    if finite_only:
        v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0}
    a = np.abs(v)
    return {
        "n": int(v.size),
        "mean_abs": float(a.mean()),
        "median_abs": float(np.median(a)),
        "rms": float(np.sqrt(np.mean(v**2))),
        "p95_abs": float(np.percentile(a, 95)),
        "max_abs": float(a.max()),
        "mean": float(v.mean()),
        "std": float(v.std()),
    }


def match_y_parallax(
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    *,
    nodata: float = 0.0,
    max_matches: int = 400,
) -> dict[str, Any]:
    """Row differences of image matches between the normalized images, pixels.

    ORB key points (the tie points of the pipeline are SIFT's), refined to sub-pixel by
    correlation (:func:`parproj_ros.imaging.matching.match_normalized`); the best
    ``max_matches`` by correlation peak.
    """
    m = match_normalized(left, right, nodata=nodata, detector="orb")
    if len(m) == 0:
        return {"matches": 0, "y_parallax_px": error_stats(np.zeros(0))}
    best = np.argsort(-m.score)[:max_matches]
    y = (m.yl - m.yr)[best]
    x = (m.xl - m.xr)[best]
    return {
        "matches": int(y.size),
        "detected": len(m),
        "y_parallax_px": error_stats(y),
        "x_disparity_px": error_stats(x),
    }


def first_frame_id(reader: BagReader, topic: str) -> str | None:
    """``header.frame_id`` of the first message on ``topic`` (None: no such topic, or no name)."""
    if topic not in reader.topics():
        return None
    for item in reader.messages(topics=[topic]):
        return str(item.msg.header.frame_id).strip() or None
    return None


def _frame_distance(a: str, b: str) -> str:
    """How far apart the origins of two local tangent plane frames are, as text ("" if not)."""
    from ..io.scene_import import frame_from_id

    try:
        fa, fb = frame_from_id(a), frame_from_id(b)
    except ValueError:
        return ""
    ea = np.array(fa.to_local(fb.lon0, fb.lat0, fb.h0), dtype=np.float64).ravel()
    return (
        f" (origins {float(np.hypot(ea[0], ea[1])):.0f} m apart horizontally, "
        f"{abs(float(ea[2])):.1f} m vertically)"
    )


def check_truth_frame(out_bag: Path, truth_bag: Path) -> None:
    """Refuse truth points in another object frame than the outputs they are to check.

    Compares the ``header.frame_id`` of the truth bag's ``truth/points`` with that of the output
    bag's ``stereo_pair`` messages, as recorded (``map`` for a simulated bag, ``enu_wgs84:lat=..``
    for an imported pair; :mod:`parproj_ros.core.frames`). Object coordinates of two frames
    cannot be compared: a truth bag of another pair, or of the same pair imported again about
    another tangent plane, would give errors of kilometres or pass as a wrong figure.

    Raises:
        InputError: the two frames differ (``--truth`` named, with both frames).
    """
    from ..io.files import InputError

    truth = first_frame_id(BagReader(truth_bag), contract.TRUTH_POINTS)
    out = first_frame_id(BagReader(out_bag), contract.STEREO_PAIR)
    if truth is None or out is None or truth == out:
        return
    raise InputError(
        "--truth",
        f"{truth_bag}: its truth points are in object frame {truth!r}, the outputs of {out_bag} "
        f"in {out!r}{_frame_distance(truth, out)}: their coordinates cannot be compared; give "
        "the bag the outputs were computed from",
    )


def evaluate_bag(
    out_bag: Path,
    truth_bag: Path | None = None,
    *,
    plots: Path | None = None,
    matching: bool = True,
    surface: Surface | None = None,
) -> dict[str, Any]:
    """Evaluate every StereoPair of ``out_bag`` (truth from ``truth_bag`` or ``out_bag``).

    DSMs (``dsm`` topic) are evaluated against ``surface`` (default: the terrain of the
    scenario named like the truth bag, if there is one; else only their completeness).
    """
    if truth_bag:
        from .same_input import check_same_input, truth_bag_lines

        check_truth_frame(Path(out_bag), Path(truth_bag))
        check_same_input(
            Path(out_bag),
            truth_bag_lines(Path(truth_bag)),
            option="--truth",
            source=str(truth_bag),
        )
    reader = BagReader(out_bag)
    if not reader.recovery.complete:
        warnings.warn(
            f"{out_bag}: {reader.recovery.describe()}; the outputs complete in it are evaluated",
            stacklevel=2,
        )
    truth: list[GroundPoint] = (
        truth_from_bag(BagReader(truth_bag))
        if truth_bag
        else (truth_from_bag(reader) if contract.TRUTH_POINTS in reader.topics() else [])
    )
    result: dict[str, Any] = {"pairs": [], "truth_points": len(truth)}
    blocks: dict[tuple[str, str], list[Any]] = {}
    block_topics = [
        t for t in map(contract.normalized_block_topic, contract.SIDES) if t in reader.topics()
    ]
    if block_topics:
        for item in reader.messages(topics=block_topics):
            blocks.setdefault((item.msg.pair_id, item.msg.side), []).append(item.msg)
    for k, item in enumerate(reader.messages(topics=[contract.STEREO_PAIR])):
        sp = item.msg
        try:
            check_pair_message(sp)
            images = None
            if sp.streamed:
                parts = [blocks.get((sp.pair_id, side), []) for side in ("left", "right")]
                images = tuple(assemble_blocks(p) for p in parts) if all(parts) else None
            result["pairs"].append(_evaluate_pair(sp, truth, plots, matching, images))
        except (ConversionError, GeometryError) as err:
            # a message that decodes but cannot be a pair (empty image, singular transform)
            raise BagError(
                f"stereo_pair message {k} ({sp.pair_id or 'no pair id'}) is malformed: {err}",
                out_bag,
            ) from err
    result["pair_count"] = len(result["pairs"])
    if contract.DSM in reader.topics():
        if surface is None and truth_bag is not None:
            surface = scenario_terrain(Path(truth_bag).name)
        result["heights"] = _evaluate_heights(reader, surface, plots)
    return result


def _evaluate_heights(
    reader: BagReader, surface: Surface | None, plots: Path | None
) -> list[dict[str, Any]]:
    """Per ElevationGrid: its figures, and against ``surface`` its errors (eval/heights.py)."""
    # stamps tie a disparity image to its pair's DSM
    disparities = disparities_by_stamp(reader) if plots is not None else {}
    out = []
    for item in reader.messages(topics=[contract.DSM]):
        m = item.msg
        heights, grid, ortho = elevation_grid_from_msg(m)
        row: dict[str, Any] = {
            "pair_id": m.pair_id,
            "frame_id": m.header.frame_id,
            "cells": [grid.width, grid.height],
            "cell_size_m": grid.cell,
            "disparity_range_px": [m.disparity_min, m.disparity_max],
            "matched_share": float(m.matched_share),
            "completeness_published": float(m.completeness),
            "filled_cells": int(m.filled_cells),
            "height_per_disparity_px": float(m.height_per_disparity_px),
        }
        truth = surface
        if truth is not None:
            # which cells were filled is not in the message (their count is): the error
            # figures take every cell with a height
            row["against_truth"] = dsm_accuracy(heights, grid, truth)
        if plots is not None:
            files = save_height_plots(
                plots,
                file_stem(m.pair_id),
                heights,
                grid,
                disparity=disparities.get(stamp_to_ns(m.header.stamp)),
                truth=truth,
                ortho=ortho,
            )
            row["plots"] = [f.name for f in files]
        out.append(row)
    return out


def print_evaluation(res: dict[str, Any]) -> None:
    """Print the result of :func:`evaluate_bag` in words (``parproj evaluate``, the demo)."""
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
    for d in res.get("heights", []):
        print(
            f"DSM {d['pair_id']}: {d['cells'][0]} x {d['cells'][1]} cells of "
            f"{d['cell_size_m']:.3g} m, disparity {d['disparity_range_px'][0]}.."
            f"{d['disparity_range_px'][1]} px, {100 * d['matched_share']:.1f} % matched, "
            f"{100 * d['completeness_published']:.1f} % of cells with a height "
            f"({d['filled_cells']} filled)"
        )
        t = d.get("against_truth")
        if t:
            a = abs(d["height_per_disparity_px"])
            print(
                f"  against the true surface ({t['n']:.0f} cells): NMAD {t['nmad']:.3f} m "
                f"({t['nmad'] / a:.2f} x the {a:.3f} m of one pixel of x-parallax), "
                f"rms {t['rms']:.3f} m, bias {t['mean']:+.3f} m, completeness "
                f"{100 * t['completeness']:.1f} % ({100 * t['completeness_measured']:.1f} % "
                "measured)"
            )


def _observation(p: GroundPoint, params: Any) -> tuple[float, float] | None:
    """A truth point's (line, sample) in a published scene, or None when not observed there.

    A segment of a long scene (``segment_of`` set) counts its lines from
    ``segment_first_line`` of the scene it was cut from; points outside its lines are left out.
    """
    sid = params.segment_of or params.scene_id
    obs = p.observations.get(sid)
    if obs is None:
        return None
    line = obs[0] - params.segment_first_line
    if params.segment_of and not (-0.5 <= line <= params.lines - 0.5):
        return None
    return (line, obs[1])


#: The StereoPair and ParallelProjection fields the evaluation computes with.
_PAIR_FIELDS = (
    "left_to_normalized", "right_to_normalized", "left_x_origin", "right_x_origin", "y_origin",
    "normalized_pixel_size", "height_per_disparity_px", "height_offset_m",
)  # fmt: skip
_PARAM_FIELDS = (
    "affine", "roll_psi", "principal_distance", "pixel_size", "line_mid", "x_per_line",
    "principal_point",
)  # fmt: skip


def check_pair_message(sp: Any) -> None:
    """The fields of a StereoPair that the evaluation uses are finite and consistent.

    Raises:
        ConversionError: naming the first field that is not.
    """
    for name in _PAIR_FIELDS:
        if not np.all(np.isfinite(np.asarray(getattr(sp, name), dtype=float))):
            raise ConversionError(f"{name} is not finite")
    for side in ("left_params", "right_params"):
        prm = getattr(sp, side)
        for name in _PARAM_FIELDS:
            if not np.all(np.isfinite(np.asarray(getattr(prm, name), dtype=float))):
                raise ConversionError(f"{side}.{name} is not finite")
        if not prm.segment_of and prm.segment_first_line != 0:
            raise ConversionError(
                f"{side}.segment_first_line is {prm.segment_first_line} in a whole scene (no "
                "segment_of)"
            )


def _evaluate_pair(
    sp: Any,
    truth: list[GroundPoint],
    plots: Path | None,
    matching: bool,
    images: tuple[Any, Any] | None = None,
) -> dict[str, Any]:
    lp, rp = sp.left_params, sp.right_params
    pix = sp.normalized_pixel_size
    out: dict[str, Any] = {
        "pair_id": sp.pair_id,
        "width": int(sp.width or sp.left.width),
        "height": int(sp.height or sp.left.height),
        "methods": [int(lp.method), int(rp.method)],
        "published_y_parallax_px": {
            "mean": sp.y_parallax_mean_px,
            "rms": sp.y_parallax_rms_px,
            "max": sp.y_parallax_max_px,
            "n": sp.y_parallax_points,
            "source": sp.y_parallax_source,
        },
    }
    obs_l = [_observation(p, lp) for p in truth]
    obs_r = [_observation(p, rp) for p in truth]
    keep = [i for i in range(len(truth)) if obs_l[i] is not None and obs_r[i] is not None]
    pts = [truth[i] for i in keep]
    if pts:
        xyz = np.array([p.xyz for p in pts])
        ol = np.array([obs_l[i] for i in keep])
        orr = np.array([obs_r[i] for i in keep])
        cl, rl = normalized_px(
            lp, sp.left_to_normalized, sp.left_x_origin, sp.y_origin, pix, ol[:, 0], ol[:, 1]
        )
        cr, rr = normalized_px(
            rp, sp.right_to_normalized, sp.right_x_origin, sp.y_origin, pix, orr[:, 0], orr[:, 1]
        )
        ypar = rl - rr
        disp = cl - cr
        coef = np.polyfit(xyz[:, 2], disp, 1)
        line_res = disp - np.polyval(coef, xyz[:, 2])
        z_pub = sp.height_per_disparity_px * disp + sp.height_offset_m
        out["geometric"] = {
            "points": len(pts),
            "y_parallax_px": error_stats(ypar),
            "x_parallax_line_rms_px": float(np.sqrt(np.mean(line_res**2))),
            "x_parallax_line_max_px": float(np.abs(line_res).max()),
            "disparity_px_per_m": float(coef[0]),
            "published_px_per_m": float(1.0 / sp.height_per_disparity_px),
            "height_from_disparity_error_m": error_stats(z_pub - xyz[:, 2]),
        }
        scenes = []
        for prm, obs in ((lp, ol), (rp, orr)):
            x = (obs[:, 0] - prm.line_mid) * prm.x_per_line
            y = (obs[:, 1] - prm.principal_point) * prm.pixel_size
            scenes.append(
                SceneObservation(
                    AffineModel.from_array(prm.affine),
                    np.column_stack([x, y]),
                    prm.roll_psi,
                    prm.principal_distance,
                )
            )
        inter = space_intersection(scenes)
        err = inter.points - xyz
        out["object_space_error_m"] = {
            "xy": {"mean": float(err[:, :2].mean()), "std": float(err[:, :2].std(ddof=1))},
            "z": {"mean": float(err[:, 2].mean()), "std": float(err[:, 2].std(ddof=1))},
        }
        if plots:
            _plot_geometry(plots, sp.pair_id, xyz[:, 2], disp, coef, ypar)
    if images is None and sp.streamed:
        out["images"] = "streamed, but the blocks are not all in the bag"
        return out
    out["streamed"] = bool(sp.streamed)
    if matching or plots:
        left, right = (
            images if images is not None else (image_to_array(sp.left), image_to_array(sp.right))
        )
        if matching:
            out["matching"] = match_y_parallax(left, right)
        if plots:
            plots.mkdir(parents=True, exist_ok=True)
            tag = file_stem(sp.pair_id, plus="__")
            cv2.imwrite(str(plots / f"{tag}_left.png"), to_uint8(left))
            cv2.imwrite(str(plots / f"{tag}_right.png"), to_uint8(right))
            cv2.imwrite(
                str(plots / f"{tag}_anaglyph.png"),
                cv2.cvtColor(anaglyph(left, right), cv2.COLOR_RGB2BGR),
            )
    return out


def _plot_geometry(
    plots: Path, pair_id: str, z: FloatArray, disp: FloatArray, coef: FloatArray, ypar: FloatArray
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plots.mkdir(parents=True, exist_ok=True)
    tag = file_stem(pair_id, plus="__")
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ax[0].plot(z, disp, ".", ms=3)
    zz = np.linspace(z.min(), z.max(), 2)
    ax[0].plot(zz, np.polyval(coef, zz), "-", lw=1)
    ax[0].set(
        xlabel="height Z (m)",
        ylabel="disparity col_left - col_right (px)",
        title="x-parallax against height",
    )
    ax[1].hist(ypar, bins=40)
    ax[1].set(
        xlabel="y-parallax row_left - row_right (px)",
        ylabel="truth points",
        title="geometric y-parallax",
    )
    fig.suptitle(pair_id)
    fig.tight_layout()
    fig.savefig(plots / f"{tag}_geometry.png", dpi=100)
    plt.close(fig)
