"""``parproj import``: images with RPC -> one input bag (:func:`import_scenes`), and which pair up.

The images are read and checked by parproj_ros/io/scene_import.py (windowed strips, import checks,
virtual GCP and check points, truth points; its docstring describes the bag) and written here as
consecutive acquisitions (scenes) of the one view. With a pair selection the bag gets
one more latched topic, ``pairs`` (parproj_msgs/PairSelection), that says which acquisitions pair
up; the node and ``parproj process`` make exactly those pairs (a scene may be in several).
Without one (two images, no ``--pairs``) there is no ``pairs`` topic and the scenes pair up by
order; the bag is then the same as ``parproj import`` of a pair always wrote.

Tie points (issue 24, :func:`parproj_ros.io.rpc_ties.import_ties`; docs/multiview.md): before
any virtual point is made, the original images are matched. With three or more images one
image bias per view is estimated from the tie points seen in three or more views and folded
into each RPC (``adjust``), so that every pair shares one object space; without ``heights`` and
``dem`` the virtual points span the heights the tie points measure (percentiles 1-99 plus a
margin, at least 100 m), else the RPC span with a warning. One line says which heights were used
and where they came from; the bag's ``custom_data`` keeps it (``heights``) and the biases.

Pair selection (``pairs``, :func:`select_pairs`):

* ``"bh"`` (default with three or more images): every pair of images that overlap (at least
  :data:`MIN_COMMON` virtual points seen by both) and whose base-to-height ratio is within
  ``bh_range`` (default :data:`BH_RANGE` = 0.1 .. 1.0: below 0.1 the x-parallax per metre of
  height is too small for useful heights, above 1.0 the views differ so much that image
  matching, and so tie points, fail);
* ``"all"``: every overlapping pair, whatever its B/H;
* a list of (left, right) scene ids: those pairs, in that order; each must overlap
  (:func:`parproj_ros.io.scene_import.check_overlap`, common points).

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

from ..core import contract
from ..io import raster
from ..io.rpc_ties import import_ties
from ..io.scene_import import (
    DEM_MARGIN,
    LINE_PERIOD,
    PIXEL_SIZE,
    PRINCIPAL_DISTANCE,
    SCENE_GAP_S,
    START_NS,
    STRIP_LINES,
    TRUTH_POINTS,
    VIEW,
    Heights,
    ImportedImage,
    SceneImportError,
    VirtualPoints,
    check_image,
    check_options,
    check_overlap,
    default_heights,
    dem_from_path,
    footprints_overlap,
    frame_id_of,
    gcp_points,
    height_range,
    load_image,
    make_frame,
    pair_truth_points,
)
from ..rpc import HeightFunction, LocalTangentPlane

FloatArray = NDArray[np.float64]

#: Default window of useful base-to-height ratios (``pairs="bh"``).
BH_RANGE = (0.1, 1.0)
#: Virtual points both images of a pair must see for it to count as overlapping.
MIN_COMMON = 20
#: Below this B/H two images hold no stereo (the same image twice, or one RPC for both): a
#: pair asked for (by order or by id) is refused, one of ``all`` not selected.
MIN_STEREO_BH = 0.01
#: Height step along a ray for its viewing direction, metres.
DIRECTION_DH = 100.0


def _gdal_type(dtype: Any) -> str:
    """GDAL's name of a numpy pixel type (``uint16`` -> ``UInt16``)."""
    names = {"uint8": "Byte", "uint16": "UInt16", "int16": "Int16", "float32": "Float32"}
    return names.get(np.dtype(dtype).name, "Float32")


#: Characters a scene id may not hold: ``+`` joins a pair's ids, ``:`` and ``,`` separate
#: ``--pairs``, a path separator would take the files named after it out of their folder.
SCENE_ID_FORBIDDEN = "+:,/\\"

#: Longest scene id, characters (the files ``parproj dsm`` names after a pair hold two).
SCENE_ID_MAX = 64


def _not_in_id(ch: str) -> bool:
    """Whether ``ch`` may not be part of a scene id (:data:`SCENE_ID_FORBIDDEN`, control)."""
    return ch in SCENE_ID_FORBIDDEN or not ch.isprintable()


def scene_id_problem(sid: str) -> str | None:
    """Why ``sid`` cannot be a scene id, or None (:data:`SCENE_ID_FORBIDDEN`, ...)."""
    if not sid or not sid.strip():
        return "is empty"
    bad = sorted({ch for ch in sid if _not_in_id(ch)})
    if bad:
        shown = ", ".join(repr(ch) for ch in bad)
        return f"holds {shown} (not allowed: + : , / \\ and control characters)"
    if sid.startswith("."):
        return "starts with '.' (files named after it would be hidden, or lead out of a folder)"
    if len(sid) > SCENE_ID_MAX:
        return f"has {len(sid)} characters (at most {SCENE_ID_MAX})"
    return None


def scene_ids_of(paths: Sequence[str | Path]) -> list[str]:
    """Unique scene ids from the file stems (repeats get ``_2``, ``_3``, ...).

    A character a scene id may not hold becomes ``_``, a leading ``.`` too, and a stem is cut to
    :data:`SCENE_ID_MAX` characters less room for the repeat's suffix.
    """
    ids: list[str] = []
    for p in paths:
        raw = Path(p).stem or "scene"
        stem = "".join("_" if _not_in_id(ch) else ch for ch in raw)
        stem = ("_" + stem[1:] if stem.startswith(".") else stem)[: SCENE_ID_MAX - 4]
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
        images: the checked images (:func:`parproj_ros.io.scene_import.check_image` done).
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
            (:func:`parproj_ros.io.scene_import.check_overlap`, or no common point); nothing
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
        flat = bool(bh < MIN_STEREO_BH)  # False for NaN (no common point)
        if flat and not isinstance(pairs, str):
            ia, ib = by_id[a], by_id[b]
            raise SceneImportError(
                f"pair {a}:{b}: B/H {bh:.3f}, convergence {conv:.2f} deg: both images look at "
                f"the ground from the same direction, so no heights can come from them (the "
                f"same image twice, or one RPC for both? {ia.path.name} with {ia.rpc_source}, "
                f"{ib.path.name} with {ib.rpc_source})"
            )
        overlap = len(t.ids) >= MIN_COMMON and not flat
        in_window = bool(bh_range[0] <= bh <= bh_range[1])
        if pairs is None:
            row["selected"], row["why"] = True, "by order"
        elif not isinstance(pairs, str):
            row["selected"] = True
            row["why"] = "given" if in_window else "given, B/H outside the useful window"
        else:
            row["selected"] = overlap and (in_window or pairs == "all")
            row["why"] = (
                "no stereo base (B/H under 0.01)"
                if flat
                else "no overlap"
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


def import_scenes(
    paths: Sequence[str | Path],
    output: str | Path,
    *,
    pairs: str | Sequence[tuple[str, str]] | None = "bh",
    bh_range: tuple[float, float] | None = None,
    scene_ids: Sequence[str] | None = None,
    rpcs: Sequence[str | Path | None] | None = None,
    offsets: Sequence[tuple[float, float] | None] | None = None,
    band: int | None = None,
    dem: str | Path | HeightFunction | None = None,
    geoid_undulation: float = 0.0,
    heights: tuple[float, float] | None = None,
    principal_distance: float = PRINCIPAL_DISTANCE,
    pixel_size: float = PIXEL_SIZE,
    line_period: float = LINE_PERIOD,
    dem_margin: float = DEM_MARGIN,
    truth_points: int = TRUTH_POINTS,
    overwrite: bool = False,
    adjust: bool | None = None,
    tie_points: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Write the input bag of two or more images with RPC (module docstring); return a summary.

    Every image is read by windows of :data:`STRIP_LINES` rows (one strip in memory at a time),
    checked (:func:`check_image`; its notes and figures logged), and every pair considered
    must overlap (:func:`check_overlap`; automatic selections leave out those that do not).

    Args:
        paths: the images (any raster GDAL reads), in acquisition order.
        output: bag folder to create.
        pairs: None (no selection: consecutive images pair up, no ``pairs`` topic), ``"bh"``,
            ``"all"`` or (left, right) scene ids
            (:func:`parproj_ros.apps.importer.select_pairs`).
        bh_range: (low, high) B/H of a useful pair for ``pairs="bh"`` (default
            :data:`parproj_ros.apps.importer.BH_RANGE`).
        scene_ids: one per image (default :func:`parproj_ros.apps.importer.scene_ids_of`).
        rpcs: per image, an RPC file of its full scene, or None for :func:`find_rpc`.
        offsets: per image, the crop origin (line, sample) in its RPC's grid, pixels, or None:
            from GDAL's geotransform (:func:`crop_offset`), else (0, 0), a named assumption
            (logged).
        band: the band to import from every image (1-based); None: band 1 (logged when an
            image has more).
        dem: DEM file(s) (any raster GDAL reads, :func:`parproj_ros.io.dem.load_dem`) or a
            height function ``(lon, lat) -> ellipsoidal h`` (m); None: ``heights``.
        geoid_undulation: metres added to the DEM file's heights (geoid -> ellipsoid).
        heights: (hmin, hmax) metres without a DEM (default :func:`default_heights` of the
            first image).
        principal_distance: c written in the scanner info, metres.
        pixel_size: detector pitch written in the scanner info, metres.
        line_period: seconds between lines (stamps).
        dem_margin: half height range of the virtual points about the DEM, metres.
        truth_points: number of truth points per pair.
        overwrite: replace an existing bag.
        adjust: estimate and apply one image bias per view from tie points seen in three or
            more views (:mod:`parproj_ros.io.rpc_ties`); None: with three or more images.
        tie_points: match the original images at all (terrain, biases); False: the RPC span
            (or ``heights`` / ``dem``) and the RPCs as given, as before issue 24.
        log: where to report.

    Returns:
        Summary: sizes, counts, frame_id, per scene the RPC and offset sources, band, checks
        and notes; every candidate pair with its B/H, convergence (deg), common points and
        whether it was selected; the pairs.

    Raises:
        SceneImportError: bad options (NaN, zero height range, scene ids, per-image lists of
            the wrong length), an unreadable image, no RPC, a failed check, pixel types that
            differ, a pair asked for that does not overlap, no pair selected.
        RPCFormatError: a malformed RPC (file, key and value named).

    """
    from parproj_msgs.msg import GroundControlPoints, PairSelection, ScannerInfo
    from sensor_msgs.msg import Image

    from ..ros.bag import BagWriter
    from ..ros.conversions import array_to_image, gcp_to_msg, ns_to_stamp, pairs_to_msg

    n = len(paths)
    if n < 2:
        raise SceneImportError("at least two images are needed")
    ids = list(scene_ids) if scene_ids is not None else scene_ids_of(paths)
    if len(ids) != n or len(set(ids)) != n or not all(ids):
        raise SceneImportError(f"one distinct, non-empty scene id per image needed, got {ids}")
    for sid in ids:
        why = scene_id_problem(sid)
        if why is not None:
            raise SceneImportError(f"scene id {sid!r} {why}")
    rpc_files = list(rpcs) if rpcs is not None else [None] * n
    origins = list(offsets) if offsets is not None else [None] * n
    if len(rpc_files) != n or len(origins) != n:
        raise SceneImportError(
            f"one RPC file and one crop origin (or None) per image needed: {len(rpc_files)} and "
            f"{len(origins)} for {n} images"
        )
    check_options(
        heights, geoid_undulation, principal_distance, pixel_size, line_period, dem_margin
    )
    images = [
        load_image(p, sid, rpc_path=r, offset=o, band=band)
        for p, sid, r, o in zip(paths, ids, rpc_files, origins, strict=True)
    ]
    if len({img.dtype for img in images}) > 1:

        def kind(img: ImportedImage) -> str:
            own = str(img.info.dtype)
            return f"{img.path} {own}" + ("" if own == img.dtype.name else f" (as {img.dtype})")

        raise SceneImportError(
            "pixel types differ: "
            + ", ".join(kind(img) for img in images)
            + ": one pair is matched on one radiometric scale; convert one image to the "
            "other's type first (e.g. gdal_translate -ot "
            + _gdal_type(images[0].dtype)
            + " -scale ...)"
        )
    h: Heights
    if dem is None:
        h = heights if heights is not None else default_heights(images[0])
    elif callable(dem):
        h = dem
    else:
        h = dem_from_path(dem, geoid_undulation=geoid_undulation)
    for img in images:
        check_image(img, height_range(img, h, dem_margin))
        for note in img.notes:
            log(note)
        c = img.checks
        log(
            f"{img.path.name}: RPC {img.rpc_source}, crop origin {img.offset} "
            f"({img.offset_source}); round trip {c['round_trip_px']:.1e} px, "
            f"{c['round_trip_deg']:.1e} deg"
        )
    # issue 24: tie points between the original images -> RPC biases, measured terrain
    images, h, ties = import_ties(
        images, h, measure_terrain=dem is None and heights is None, adjust=adjust,
        tie_points=tie_points, log=log,
    )  # fmt: skip
    frame = make_frame(images[0], h)
    frame_id = frame_id_of(frame)
    gcp = gcp_points(images, h, dem_margin)
    table, truth = select_pairs(
        images, pairs, bh_range or BH_RANGE, h, frame, truth_points, dem_margin, log
    )
    chosen = [(r["left"], r["right"]) for r in table if r["selected"]]

    period_ns = line_period * 1e9
    starts, t = [], START_NS
    for img in images:
        starts.append(t)
        t += round(img.lines * period_ns) + round(SCENE_GAP_S * 1e9)
    t_info = START_NS - 1_000_000_000
    detectors = max(img.samples for img in images)
    custom = {
        "parproj_import": "parproj import (parproj_ros/io/scene_import.py)",
        "object_frame": frame_id,
        "images": ", ".join(f"{img.path.name} ({img.scene_id})" for img in images),
        "rpc": "; ".join(img.rpc_source for img in images),
        "crop_offsets_line_sample": "; ".join(str(img.offset) for img in images),
    }
    if ties.get("heights_note"):
        custom["heights"] = str(ties["heights_note"])
    if ties.get("adjustment"):
        custom["rpc_bias_line_sample_px"] = "; ".join(
            f"{k} ({v['bias_line_sample_px'][0]:+.3f}, {v['bias_line_sample_px'][1]:+.3f})"
            for k, v in ties["adjustment"]["views"].items()
        )
    if pairs is not None:
        custom["pairs"] = ", ".join(
            f"{r['left']}:{r['right']} (B/H {r['base_to_height']:.3f})"
            for r in table
            if r["selected"]
        )
    with BagWriter(
        Path(output), compression="zstd", overwrite=overwrite, custom_data=custom
    ) as bw:
        strips = contract.strip_topic(VIEW)
        bw.add_topics(contract.input_topics([VIEW], navigation=False))
        info = ScannerInfo()
        ns_to_stamp(t_info, info.header.stamp)
        info.header.frame_id = VIEW
        info.camera_name = VIEW
        info.principal_distance = float(principal_distance)
        info.pixel_size = float(pixel_size)
        info.detectors = int(detectors)
        info.principal_point = (images[0].samples - 1) / 2.0
        info.line_period = float(line_period)
        info.mounting.x, info.mounting.y, info.mounting.z, info.mounting.w = 0.0, 0.0, 0.0, 1.0
        bw.write(contract.scanner_info_topic(VIEW), info, t_info)
        for topic, vp in ((contract.GCP, gcp), (contract.TRUTH_POINTS, truth)):
            msg = gcp_to_msg(
                vp.ground_points(frame), GroundControlPoints(), frame_id=frame_id, stamp_ns=t_info
            )
            bw.write(topic, msg, t_info)
        if pairs is not None:
            bw.add_topics([contract.topic(contract.PAIRS)])
            selection = pairs_to_msg(chosen, PairSelection(), stamp_ns=t_info)
            bw.write(contract.PAIRS, selection, t_info)
        for img, t0 in zip(images, starts, strict=True):
            # One camera has one detector count: a narrower crop is padded on the right with
            # no-data (0) columns, which changes no pixel's position.
            # Read by windows of STRIP_LINES rows: one strip in memory at a time.
            masked = 0
            for r0, pixels, n_masked in raster.read_rows(
                img.path, img.band, STRIP_LINES, detectors
            ):
                masked += n_masked
                stamp = t0 + round(r0 * period_ns)
                msg = array_to_image(pixels, Image(), frame_id=img.scene_id, stamp_ns=stamp)
                bw.write(strips, msg, stamp)
            img.checks["nodata_pixels"] = masked
            if masked:
                log(f"{img.path.name}: {masked} no-data pixels (GDAL mask) written as 0")
    size = sum(f.stat().st_size for f in Path(output).iterdir())
    n_gcp = sum(1 for c in gcp.check if not c)
    summary = {
        "output": str(output),
        "size_mb": size / 1e6,
        "frame_id": frame_id,
        "scenes": {
            img.scene_id: {
                "image": str(img.path),
                "lines": img.lines,
                "samples": img.samples,
                "rpc": img.rpc_source,
                "offset_line_sample": list(img.offset),
                "offset_source": img.offset_source,
                "band": img.band,
                "driver": img.info.driver,
                "dtype": str(img.dtype),
                "checks": img.checks,
                "notes": list(img.notes),
                "gcp": sum(
                    1
                    for o, c in zip(gcp.observations, gcp.check, strict=True)
                    if img.scene_id in o and not c
                ),
            }
            for img in images
        },
        "candidates": table,
        "pairs": chosen,
        "gcp": n_gcp,
        "check": len(gcp.ids) - n_gcp,
        "gcp_in_both": sum(1 for o in gcp.observations if len(o) >= 2),
        "truth": len(truth.ids),
        "heights": "DEM" if callable(h) else list(h),
        "tie_points": ties,
    }
    log(
        f"wrote {output} ({size / 1e6:.2f} MB): scenes "
        + ", ".join(f"{img.scene_id} {img.lines}x{img.samples}" for img in images)
        + (f"; pairs {', '.join(a + ':' + b for a, b in chosen)}" if pairs is not None else "")
        + f"; {n_gcp} GCP, {summary['check']} check, {len(truth.ids)} truth points; object "
        f"frame {frame_id}"
    )
    return summary


def import_pair(
    left_path: str | Path,
    right_path: str | Path,
    output: str | Path,
    *,
    rpc_left: str | Path | None = None,
    rpc_right: str | Path | None = None,
    scene_ids: tuple[str, str] = ("left", "right"),
    offsets: tuple[tuple[float, float] | None, tuple[float, float] | None] = (None, None),
    **options: Any,
) -> dict[str, Any]:
    """The bag of a pair: :func:`import_scenes` of two images without a pair selection.

    Args:
        left_path: first image (scene ``scene_ids[0]``, the left scene of the pair).
        right_path: second image.
        output: bag folder to create.
        rpc_left: RPC file of the first image's full scene (default: :func:`find_rpc`).
        rpc_right: RPC file of the second image's full scene.
        scene_ids: the two scene ids.
        offsets: crop origins (line, sample) per image in its RPC's grid, pixels (None: from
            the file, else (0, 0)).
        **options: the other keyword arguments of :func:`import_scenes` (dem, heights, band,
            principal_distance, ..., log).

    Raises:
        SceneImportError, RPCFormatError: as :func:`import_scenes`.

    """
    if scene_ids[0] == scene_ids[1]:
        raise SceneImportError("the two scene ids must differ")
    return import_scenes(
        [left_path, right_path],
        output,
        pairs=None,
        scene_ids=scene_ids,
        rpcs=(rpc_left, rpc_right),
        offsets=offsets,
        **options,
    )


__all__ = [
    "BH_RANGE",
    "base_to_height",
    "import_pair",
    "import_scenes",
    "parse_pairs",
    "scene_ids_of",
    "select_pairs",
    "viewing_direction",
]
