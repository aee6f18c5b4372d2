"""``parproj import A B C ...``: more than two images with RPC -> one single-camera bag + pairs.

The images become consecutive acquisitions (scenes) of the one view, as in
:func:`parproj_ros.scene_import.import_pair` (strips, scanner info, virtual GCP and check
points, truth points; read that module's docstring), and the bag gets one more latched topic,
``pairs`` (parproj_msgs/PairSelection), that says which acquisitions pair up; the node and
``parproj process`` make exactly those pairs (a scene may be in several).

Pair selection (``pairs``):

* ``"bh"`` (default): every pair of images that overlap (at least :data:`MIN_COMMON` virtual
  points seen by both) and whose base-to-height ratio is within ``bh_range`` (default
  :data:`BH_RANGE` = 0.1 .. 1.0: below 0.1 the x-parallax per metre of height is too small for
  useful heights, above 1.0 the views differ so much that image matching, and so tie points,
  fail);
* ``"all"``: every overlapping pair, whatever its B/H;
* a list of (left, right) scene ids: those pairs, in that order.

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

from .rpc import HeightFunction, LocalTangentPlane
from .scene_import import (
    CHECK_GRID,
    DEM_MARGIN,
    GCP_GRID,
    LINE_PERIOD,
    MAX_GRID_ROWS,
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
    _grid,
    _ground,
    default_heights,
    dem_from_path,
    frame_id_of,
    load_image,
    make_frame,
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


def _gcp_points(
    images: Sequence[ImportedImage], heights: Heights, dem_margin: float
) -> VirtualPoints:
    """GCP and check-point grids over every image, observed in every image that sees them."""
    gcp = VirtualPoints()
    callable_h = callable(heights)

    def levels(n: int) -> FloatArray:
        u = np.linspace(-1.0, 1.0, n) if n > 1 else np.zeros(1)
        return u * dem_margin if callable_h else u

    for grid, check, shift in ((GCP_GRID, False, 0.0), (CHECK_GRID, True, 0.5)):
        nx, ny, nz = grid
        for img in images:
            rows = min(max(ny, round(ny * img.lines / max(img.samples, 1))), MAX_GRID_ROWS)
            gl, gs = _grid(img, nx, rows, shift if check else 0.0)
            for dz in levels(nz):
                geo = _ground(img, gl, gs, heights, np.full(gl.shape, dz))
                gcp.add(f"{img.scene_id}_{'chk' if check else 'gcp'}", geo, images, check=check)
    for img in images:
        n = sum(
            1
            for o, c in zip(gcp.observations, gcp.check, strict=True)
            if img.scene_id in o and not c
        )
        if n < 5:
            raise SceneImportError(f"only {n} virtual GCP fall in {img.scene_id}: check the RPC")
    return gcp


def _truth_points(
    left: ImportedImage,
    right: ImportedImage,
    heights: Heights,
    count: int,
    dem_margin: float,
    prefix: str,
    seed: int,
) -> VirtualPoints:
    """Up to ``count`` random points of ``left`` that ``right`` sees too (observed in both)."""
    truth = VirtualPoints()
    rng = np.random.default_rng(seed)
    for _ in range(20):
        n = 4 * count
        gl = rng.uniform(0, left.lines - 1, n)
        gs = rng.uniform(0, left.samples - 1, n)
        dz = rng.uniform(-1.0, 1.0, n) * (dem_margin if callable(heights) else 1.0)
        geo = _ground(left, gl, gs, heights, dz)
        truth.add(prefix, geo, (left, right), check=True, min_scenes=2)
        if len(truth.ids) >= count:
            break
    del truth.ids[count:], truth.geodetic[count:], truth.observations[count:], truth.check[count:]
    return truth


def import_scenes(
    paths: Sequence[str | Path],
    output: str | Path,
    *,
    pairs: str | Sequence[tuple[str, str]] = "bh",
    bh_range: tuple[float, float] = BH_RANGE,
    scene_ids: Sequence[str] | None = None,
    rpcs: Sequence[str | Path | None] | None = None,
    dem: str | Path | HeightFunction | None = None,
    geoid_undulation: float = 0.0,
    heights: tuple[float, float] | None = None,
    principal_distance: float = PRINCIPAL_DISTANCE,
    pixel_size: float = PIXEL_SIZE,
    line_period: float = LINE_PERIOD,
    dem_margin: float = DEM_MARGIN,
    truth_points: int = TRUTH_POINTS,
    overwrite: bool = False,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Write the input bag of two or more images with RPC and their pair selection.

    Args:
        paths: the images (GeoTIFF/TIFF), in acquisition order.
        output: bag folder to create.
        pairs: ``"bh"``, ``"all"`` or (left, right) scene ids (module docstring).
        bh_range: (low, high) B/H of a useful pair (``pairs="bh"``).
        scene_ids: one per image (default :func:`scene_ids_of`).
        rpcs: RPC file of each image's full scene, None for :func:`scene_import.find_rpc`.
        dem: SRTM ``.hgt`` path or a height function ``(lon, lat) -> ellipsoidal h`` (m).
        geoid_undulation: metres added to the SRTM heights.
        heights: (hmin, hmax) metres without a DEM (default: the first image's RPC).
        principal_distance: c written in the scanner info, metres.
        pixel_size: detector pitch written in the scanner info, metres.
        line_period: seconds between lines (stamps).
        dem_margin: half height range of the virtual points about the DEM, metres.
        truth_points: truth points per pair.
        overwrite: replace an existing bag.
        log: where to report.

    Returns:
        Summary: scenes, every candidate pair with its B/H, convergence (deg), common points
        and whether it was selected, the selected pairs.

    Raises:
        SceneImportError: fewer than two images, repeated or unknown scene ids, no pair
            selected, an image without RPC or GCP.
    """
    from parproj_msgs.msg import GroundControlPoints, PairSelection, ScannerInfo
    from sensor_msgs.msg import Image

    from .bag import BagWriter
    from .conversions import array_to_image, gcp_to_msg, ns_to_stamp, pairs_to_msg

    if len(paths) < 2:
        raise SceneImportError("at least two images are needed")
    ids = list(scene_ids) if scene_ids is not None else scene_ids_of(paths)
    if len(ids) != len(paths) or len(set(ids)) != len(ids) or not all(ids):
        raise SceneImportError(f"one distinct, non-empty scene id per image needed, got {ids}")
    rpc_files = list(rpcs) if rpcs is not None else [None] * len(paths)
    images = [
        load_image(p, sid, rpc_path=r) for p, sid, r in zip(paths, ids, rpc_files, strict=True)
    ]
    if len({img.image.dtype for img in images}) > 1:
        raise SceneImportError(f"pixel types differ: {[str(i.image.dtype) for i in images]}")
    h: Heights
    if dem is None:
        h = heights if heights is not None else default_heights(images[0])
    elif callable(dem):
        h = dem
    else:
        h = dem_from_path(dem, geoid_undulation=geoid_undulation)
    frame = make_frame(images[0], h)
    frame_id = frame_id_of(frame)
    gcp = _gcp_points(images, h, dem_margin)

    # Candidate pairs: every two images (earlier one left), or the given ones.
    by_id = {img.scene_id: img for img in images}
    if isinstance(pairs, str):
        if pairs not in ("all", "bh"):
            raise SceneImportError(f"pairs must be 'all', 'bh' or a list, got {pairs!r}")
        candidates = [(a.scene_id, b.scene_id) for a, b in itertools.combinations(images, 2)]
    else:
        candidates = [(str(a), str(b)) for a, b in pairs]
        for a, b in candidates:
            unknown = [s for s in (a, b) if s not in by_id]
            if unknown or a == b:
                raise SceneImportError(
                    f"pair {a}:{b}: "
                    + (f"unknown scene id {', '.join(unknown)}" if unknown else "same scene twice")
                    + f" (scene ids: {', '.join(ids)})"
                )
    truth = VirtualPoints()
    table: list[dict[str, Any]] = []
    for k, (a, b) in enumerate(candidates):
        t = _truth_points(by_id[a], by_id[b], h, truth_points, dem_margin, f"t{k}_", seed=k)
        row: dict[str, Any] = {"left": a, "right": b, "common_points": len(t.ids)}
        if len(t.ids) >= 1:
            centre = np.mean(np.array(t.geodetic), axis=0)
            bh, conv = base_to_height(
                viewing_direction(by_id[a], centre, frame),
                viewing_direction(by_id[b], centre, frame),
            )
        else:
            bh, conv = float("nan"), float("nan")
        row["base_to_height"], row["convergence_deg"] = bh, conv
        overlap = len(t.ids) >= MIN_COMMON
        in_window = bool(bh_range[0] <= bh <= bh_range[1])
        if pairs == "bh":
            row["selected"] = overlap and in_window
        elif pairs == "all":
            row["selected"] = overlap
        else:
            row["selected"] = True
        row["why"] = (
            ("given" if in_window else "given, B/H outside the useful window")
            if not isinstance(pairs, str)
            else (
                "no overlap"
                if not overlap
                else ("B/H in window" if in_window else "B/H outside window")
            )
        )
        if row["selected"]:
            truth.ids += t.ids
            truth.geodetic += t.geodetic
            truth.observations += t.observations
            truth.check += t.check
        table.append(row)
        log(
            f"pair {a}:{b}: B/H {bh:.3f}, convergence {conv:.2f} deg, {len(t.ids)} common "
            f"points: "
            + (f"selected ({row['why']})" if row["selected"] else f"not selected ({row['why']})")
        )
    chosen = [r for r in table if r["selected"]]
    if not chosen:
        raise SceneImportError(
            f"no pair selected ({pairs if isinstance(pairs, str) else 'given'}; B/H window "
            f"{bh_range[0]:g}..{bh_range[1]:g}): "
            + "; ".join(f"{r['left']}:{r['right']} B/H {r['base_to_height']:.3f}" for r in table)
        )

    period_ns = line_period * 1e9
    starts, t = [], START_NS
    for img in images:
        starts.append(t)
        t += round(img.lines * period_ns) + round(SCENE_GAP_S * 1e9)
    t_info = START_NS - 1_000_000_000
    detectors = max(img.samples for img in images)
    custom = {
        "parproj_import": "parproj import (parproj_ros/multi_import.py)",
        "object_frame": frame_id,
        "images": ", ".join(f"{img.path.name} ({img.scene_id})" for img in images),
        "rpc": "; ".join(img.rpc_source for img in images),
        "crop_offsets_line_sample": "; ".join(str(img.offset) for img in images),
        "pairs": ", ".join(
            f"{r['left']}:{r['right']} (B/H {r['base_to_height']:.3f})" for r in chosen
        ),
    }
    with BagWriter(
        Path(output), compression="zstd", overwrite=overwrite, custom_data=custom
    ) as bw:
        bw.add_topic(f"{VIEW}/image_strip", "sensor_msgs/msg/Image", "sensor_data")
        bw.add_topic(f"{VIEW}/scanner_info", "parproj_msgs/msg/ScannerInfo", "transient_local")
        bw.add_topic("gcp", "parproj_msgs/msg/GroundControlPoints", "transient_local")
        bw.add_topic("truth/points", "parproj_msgs/msg/GroundControlPoints", "transient_local")
        bw.add_topic("pairs", "parproj_msgs/msg/PairSelection", "transient_local")
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
        bw.write(f"{VIEW}/scanner_info", info, t_info)
        for topic, vp in (("gcp", gcp), ("truth/points", truth)):
            msg = gcp_to_msg(
                vp.ground_points(frame), GroundControlPoints(), frame_id=frame_id, stamp_ns=t_info
            )
            bw.write(topic, msg, t_info)
        sel = pairs_to_msg(
            [(r["left"], r["right"]) for r in chosen], PairSelection(), stamp_ns=t_info
        )
        bw.write("pairs", sel, t_info)
        for img, t0 in zip(images, starts, strict=True):
            pixels = img.image
            if pixels.shape[1] < detectors:  # one camera: narrower crops padded with no-data
                pad = np.zeros((pixels.shape[0], detectors - pixels.shape[1]), pixels.dtype)
                pixels = np.hstack([pixels, pad])
            for r0 in range(0, img.lines, STRIP_LINES):
                stamp = t0 + round(r0 * period_ns)
                msg = array_to_image(
                    pixels[r0 : r0 + STRIP_LINES], Image(), frame_id=img.scene_id, stamp_ns=stamp
                )
                bw.write(f"{VIEW}/image_strip", msg, stamp)
    size = sum(f.stat().st_size for f in Path(output).iterdir())
    n_gcp = sum(1 for c in gcp.check if not c)
    log(
        f"wrote {output} ({size / 1e6:.2f} MB): {len(images)} scenes, {len(chosen)} pairs "
        f"({', '.join(r['left'] + ':' + r['right'] for r in chosen)}); {n_gcp} GCP, "
        f"{len(gcp.ids) - n_gcp} check, {len(truth.ids)} truth points; object frame {frame_id}"
    )
    return {
        "output": str(output),
        "size_mb": size / 1e6,
        "frame_id": frame_id,
        "scenes": {
            img.scene_id: {"image": str(img.path), "lines": img.lines, "samples": img.samples}
            for img in images
        },
        "candidates": table,
        "pairs": [(r["left"], r["right"]) for r in chosen],
        "gcp": n_gcp,
        "check": len(gcp.ids) - n_gcp,
        "truth": len(truth.ids),
    }


def cmd_import_many(args: Any) -> int:
    """``parproj import A B C ... [--pairs all|bh|A:B,...]`` (called by cli.cmd_import)."""
    import sys

    from .rpc import RPCError

    paths = [args.left, args.right, *args.more]
    try:
        ids = list(args.ids) if args.ids else scene_ids_of(paths)
        spec = parse_pairs(args.pairs or "bh", ids)
        import_scenes(
            paths,
            args.output,
            pairs=spec,
            bh_range=tuple(args.bh_range),
            scene_ids=ids,
            rpcs=[args.rpc_left, args.rpc_right] + [None] * len(args.more),
            dem=args.dem,
            geoid_undulation=args.geoid_undulation,
            heights=tuple(args.heights) if args.heights else None,
            principal_distance=args.principal_distance,
            pixel_size=args.pixel_size,
            overwrite=args.force,
        )
    except (RPCError, FileExistsError, OSError, ValueError) as err:
        print(f"parproj import: {err}", file=sys.stderr)
        return 2
    return 0


__all__ = [
    "BH_RANGE",
    "base_to_height",
    "import_scenes",
    "parse_pairs",
    "scene_ids_of",
    "viewing_direction",
]
