"""``parproj import A B C ...``: which of the imported images pair up (B/H), the ``pairs`` topic.

The images are imported as in :func:`parproj_ros.scene_import.import_scenes` (the one importer:
windowed strips, import checks, virtual GCP and check points, truth points; read that module's
docstring): consecutive acquisitions (scenes) of the one view. With a pair selection the bag gets
one more latched topic, ``pairs`` (parproj_msgs/PairSelection), that says which acquisitions pair
up; the node and ``parproj process`` make exactly those pairs (a scene may be in several).
Without one (two images, no ``--pairs``) there is no ``pairs`` topic and the scenes pair up by
order; the bag is then the same as ``parproj import`` of a pair always wrote.

Pair selection (``pairs``, :func:`select_pairs`):

* ``"bh"`` (default with three or more images): every pair of images that overlap (at least
  :data:`MIN_COMMON` virtual points seen by both) and whose base-to-height ratio is within
  ``bh_range`` (default :data:`BH_RANGE` = 0.1 .. 1.0: below 0.1 the x-parallax per metre of
  height is too small for useful heights, above 1.0 the views differ so much that image
  matching, and so tie points, fail);
* ``"all"``: every overlapping pair, whatever its B/H;
* a list of (left, right) scene ids: those pairs, in that order; each must overlap
  (:func:`parproj_ros.scene_import.check_overlap`, common points).

Each pair's left scene is the earlier image on the command line.

B/H from the RPC geometry: at the pair's scene centre P (the mean of its truth points, on the
ground), each image's viewing direction d is the ray of P's projection, from P to the same
image point localized ``DIRECTION_DH`` metres higher, in the local east-north-up frame. With t =
(d_e / d_u, d_n / d_u) the ray's horizontal displacement per metre of height, B/H = |t_1 - t_2|
(the base on a plane at height H above P over H); the convergence angle is the angle between
d_1 and d_2. Both go into the import summary and its log; B/H also into the bag's metadata
(``custom_data`` "pairs").

Scene ids: the file stems (``left_image.tif`` -> ``left_image``), made unique with ``_2``,
``_3`` ... when repeated; or given (``scene_ids``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .rpc import LocalTangentPlane
from .scene_import import (
    Heights,
    ImportedImage,
    SceneImportError,
    VirtualPoints,
    check_overlap,
    footprints_overlap,
    import_scenes,
    pair_truth_points,
)

FloatArray = NDArray[np.float64]

#: Default window of useful base-to-height ratios (``pairs="bh"``).
BH_RANGE = (0.1, 1.0)
#: Virtual points both images of a pair must see for it to count as overlapping.
MIN_COMMON = 20
#: Height step along a ray for its viewing direction, metres.
DIRECTION_DH = 100.0


def scene_ids_of(paths: Sequence[str | Path]) -> list[str]:
    """Unique scene ids from the file stems (repeats get ``_2``, ``_3``, ...)."""
    ids: list[str] = []
    for p in paths:
        stem = Path(p).stem or "scene"
        sid, k = stem, 2
        while sid in ids:
            sid, k = f"{stem}_{k}", k + 1
        ids.append(sid)
    return ids


def parse_pairs(spec: str, scene_ids: Sequence[str]) -> str | list[tuple[str, str]]:
    """``"all"``, ``"bh"`` or ``"A:B,A:C"`` (scene ids) -> the selection for :func:`import_scenes`.

    Raises:
        SceneImportError: a malformed entry or an unknown scene id.
    """
    if spec in ("all", "bh"):
        return spec
    pairs = []
    for item in spec.split(","):
        parts = item.strip().split(":")
        if len(parts) != 2 or not all(parts):
            raise SceneImportError(f"--pairs: {item!r} is not LEFT:RIGHT")
        unknown = [s for s in parts if s not in scene_ids]
        if unknown:
            raise SceneImportError(
                f"--pairs: unknown scene id {', '.join(unknown)} (scene ids: "
                f"{', '.join(scene_ids)})"
            )
        pairs.append((parts[0], parts[1]))
    return pairs


def viewing_direction(img: ImportedImage, geo: FloatArray, frame: LocalTangentPlane) -> FloatArray:
    """Unit vector (east, north, up) from the geodetic point ``geo`` (lon, lat, h) to the sensor.

    The ray through ``geo``'s image point: the point and the same image point localized
    :data:`DIRECTION_DH` metres higher, in ``frame``.
    """
    lon, lat, h = (np.array([float(v)]) for v in geo)
    line, sample = img.rpc.project(lon, lat, h)
    lon2, lat2 = img.rpc.localize(line, sample, h + DIRECTION_DH)
    a = np.array(frame.to_local(lon, lat, h), dtype=np.float64).ravel()
    b = np.array(frame.to_local(lon2, lat2, h + DIRECTION_DH), dtype=np.float64).ravel()
    d = b - a
    return np.asarray(d / np.linalg.norm(d), dtype=np.float64)


def base_to_height(d1: FloatArray, d2: FloatArray) -> tuple[float, float]:
    """(B/H, convergence angle in degrees) of two viewing directions (east, north, up)."""
    t1, t2 = d1[:2] / d1[2], d2[:2] / d2[2]
    bh = float(np.linalg.norm(t1 - t2))
    conv = float(np.degrees(np.arccos(np.clip(np.dot(d1, d2), -1.0, 1.0))))
    return bh, conv


def _candidates(
    images: Sequence[ImportedImage], pairs: str | Sequence[tuple[str, str]] | None
) -> list[tuple[str, str]]:
    """(left, right) scene ids to consider: by order (None), every two (str), or the given ones.

    Raises:
        SceneImportError: an unknown selection, an odd number of images without a selection, a
            pair with an unknown scene id or the same scene twice.

    """
    ids = [img.scene_id for img in images]
    if pairs is None:
        if len(ids) % 2:
            raise SceneImportError(
                f"{len(ids)} images without a pair selection: they pair up by order (1st with "
                "2nd, 3rd with 4th, ...), so their number must be even; choose pairs with --pairs"
            )
        return list(zip(ids[::2], ids[1::2], strict=True))
    if isinstance(pairs, str):
        if pairs not in ("all", "bh"):
            raise SceneImportError(f"pairs must be 'all', 'bh' or a list, got {pairs!r}")
        return list(itertools.combinations(ids, 2))
    candidates = [(str(a), str(b)) for a, b in pairs]
    for a, b in candidates:
        unknown = [s for s in (a, b) if s not in ids]
        if unknown or a == b:
            raise SceneImportError(
                f"pair {a}:{b}: "
                + (f"unknown scene id {', '.join(unknown)}" if unknown else "same scene twice")
                + f" (scene ids: {', '.join(ids)})"
            )
    return candidates


def select_pairs(
    images: Sequence[ImportedImage],
    pairs: str | Sequence[tuple[str, str]] | None,
    bh_range: tuple[float, float],
    heights: Heights,
    frame: LocalTangentPlane,
    truth_points: int,
    dem_margin: float,
    log: Callable[[str], None],
) -> tuple[list[dict[str, Any]], VirtualPoints]:
    """Each candidate pair's overlap, B/H and convergence; the selected ones' truth points.

    Args:
        images: the checked images (:func:`parproj_ros.scene_import.check_image` done).
        pairs: None (no selection: images pair up by order, as the node pairs scenes without
            a ``pairs`` topic), ``"bh"``, ``"all"`` or (left, right) scene ids.
        bh_range: (low, high) B/H of a useful pair (``pairs="bh"``).
        heights: DEM or (hmin, hmax) metres, as for the virtual points.
        frame: the object frame (viewing directions in east, north, up).
        truth_points: truth points per pair (ids ``t<k>_0000``... for the k-th candidate;
            ``truth0000``... for the first without a selection).
        dem_margin: half height range of the truth points about the DEM, metres.
        log: where each candidate's line goes.

    Returns:
        One row per candidate (left, right, common_points, base_to_height, convergence_deg,
        selected, why) and the truth points of the selected pairs.

    Raises:
        SceneImportError: a pair that is not chosen by B/H (None or given) and does not overlap
            (:func:`parproj_ros.scene_import.check_overlap`, or no common point); nothing
            selected.

    """
    by_id = {img.scene_id: img for img in images}
    candidates = _candidates(images, pairs)
    truth = VirtualPoints()
    table: list[dict[str, Any]] = []
    for k, (a, b) in enumerate(candidates):
        row: dict[str, Any] = {"left": a, "right": b, "common_points": 0}
        bh, conv = float("nan"), float("nan")
        t = VirtualPoints()
        if not isinstance(pairs, str):
            check_overlap(by_id[a], by_id[b])  # a pair asked for must be one
        if not isinstance(pairs, str) or footprints_overlap(by_id[a], by_id[b]):
            prefix = f"t{k}_" if pairs is not None or k else "truth"  # as both importers did
            t = pair_truth_points(by_id[a], by_id[b], heights, truth_points, dem_margin, prefix, k)
            row["common_points"] = len(t.ids)
        if not t.ids and not isinstance(pairs, str):
            raise SceneImportError(
                f"pair {a}:{b}: no virtual point falls in both {by_id[a].path} and "
                f"{by_id[b].path}: do they overlap?"
            )
        if t.ids:
            centre = np.mean(np.array(t.geodetic), axis=0)
            bh, conv = base_to_height(
                viewing_direction(by_id[a], centre, frame),
                viewing_direction(by_id[b], centre, frame),
            )
        row["base_to_height"], row["convergence_deg"] = bh, conv
        overlap = len(t.ids) >= MIN_COMMON
        in_window = bool(bh_range[0] <= bh <= bh_range[1])
        if pairs is None:
            row["selected"], row["why"] = True, "by order"
        elif not isinstance(pairs, str):
            row["selected"] = True
            row["why"] = "given" if in_window else "given, B/H outside the useful window"
        else:
            row["selected"] = overlap and (in_window or pairs == "all")
            row["why"] = (
                "no overlap"
                if not overlap
                else ("B/H in window" if in_window else "B/H outside window")
            )
        if row["selected"]:
            truth.extend(t)
        table.append(row)
        log(
            f"pair {a}:{b}: B/H {bh:.3f}, convergence {conv:.2f} deg, {len(t.ids)} common "
            f"points: "
            + (f"selected ({row['why']})" if row["selected"] else f"not selected ({row['why']})")
        )
    if not any(r["selected"] for r in table):
        raise SceneImportError(
            f"no pair selected ({pairs if isinstance(pairs, str) else 'given'}; B/H window "
            f"{bh_range[0]:g}..{bh_range[1]:g}): "
            + "; ".join(f"{r['left']}:{r['right']} B/H {r['base_to_height']:.3f}" for r in table)
        )
    return table, truth


__all__ = [
    "BH_RANGE",
    "base_to_height",
    "import_scenes",
    "parse_pairs",
    "scene_ids_of",
    "select_pairs",
    "viewing_direction",
]
