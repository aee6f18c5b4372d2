"""``parproj import``: two satellite images with RPC models -> a single-camera input bag.

The two images (e.g. the crops of a Pleiades stereo pair) become the scenes of one view
(:data:`VIEW`, single-camera mode: consecutive scenes pair up), cut into strips of
:data:`STRIP_LINES` image rows with increasing stamps, the second scene after the first. Image
rows are scan lines (pushbroom time), columns are detectors. There is no navigation: the node
gets its parameters from the virtual ground control points on the ``gcp`` topic (Eq 8, roll
estimated), exactly as paper 2 did for its IKONOS pair.

Topics written (relative names, as ``parproj_node`` subscribes to them):

| topic | type | content |
|---|---|---|
| pan/image_strip | sensor_msgs/msg/Image | strips of 64 rows; frame_id = the scene id |
| pan/scanner_info | parproj_msgs/msg/ScannerInfo | documented defaults (below), once |
| gcp | parproj_msgs/msg/GroundControlPoints | virtual GCP and check points, once |
| truth/points | parproj_msgs/msg/GroundControlPoints | other virtual points, for evaluation |

Image coordinates of every observation are those of the *crops* (0, 0 = centre of the crop's
first pixel): the RPC of the full scene is shifted by the crop offset (:func:`crop_offset`, from
the GeoTIFF ModelTransformationTag 34264) with :meth:`RPCModel.shifted`.

Object frame: a local east-north-up tangent plane on WGS84 (:class:`LocalTangentPlane`), origin
at the centre of the first image on the mean ground height, rounded to 1e-7 deg and 1 cm so that
the frame is exactly described by the GroundControlPoints ``header.frame_id``, e.g.
``enu_wgs84:lat=44.1234567,lon=5.2345678,h=612.34`` (:func:`frame_id_of`,
:func:`frame_from_id`); heights h are above the WGS84 ellipsoid.

Virtual points (all exact RPC correspondences, projections of one geodetic point):

* GCP: a regular grid (:data:`GCP_GRID`; a long image gets proportionally more rows, up to
  :data:`MAX_GRID_ROWS`, for the segments of a long scene) over each image, localized at the
  ground height (DEM) and ``dem_margin`` above and below it (or at evenly spaced heights
  without a DEM); each point is
  observed in every scene that sees it (inside the crop), so each scene's fit covers the whole
  scene, and points inside both crops also give the pair's y-parallax;
* check points: a sparser grid (:data:`CHECK_GRID`) half a step off the GCP grid, flagged
  ``check_point`` (never used in the estimation);
* truth points: :data:`TRUTH_POINTS` random positions in the first image that the second image
  also sees, at random heights within the margin of the ground; on ``truth/points`` only.

Scanner info: an RPC carries no interior orientation. Defaults (Pleiades-like): principal
distance :data:`PRINCIPAL_DISTANCE` = 12.905 m, detector pitch :data:`PIXEL_SIZE` = 13 um,
line period :data:`LINE_PERIOD` = 1e-4 s (only the stamps use it), principal point at the centre
of the first crop ((width - 1) / 2; the second crop's centre differs by the width difference /
2, which the affine shift absorbs), detectors = the wider crop's width, mounting identity. With
the roll estimated (Eq 8) only tan(psi) / c enters the model, so c and the pitch only rescale
the estimated roll.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .rpc import (
    RPC_TIFF_TAG,
    HeightFunction,
    LocalTangentPlane,
    RPCError,
    RPCModel,
    read_geotiff_rpc,
    read_rpc,
    srtm_height,
)

FloatArray = NDArray[np.float64]

#: The one view (single-camera mode).
VIEW = "pan"
#: Rows per image strip.
STRIP_LINES = 64
#: Default interior orientation (Pleiades-like): principal distance, metres.
PRINCIPAL_DISTANCE = 12.905
#: Default detector pitch, metres.
PIXEL_SIZE = 13e-6
#: Default line period, seconds (stamps only).
LINE_PERIOD = 1e-4
#: Stamp of the first line of the first scene, ns (2013-08-05T10:42:19 UTC, the Ventoux pair).
START_NS = 1_375_699_339_000_000_000
#: Time between the last line of a scene and the first of the next, seconds.
SCENE_GAP_S = 1.0
#: GCP grid per image: (across = columns, along = rows, heights).
GCP_GRID = (7, 7, 3)
#: Most grid rows along a long image (the grids' rows grow with its length / width ratio).
MAX_GRID_ROWS = 400
#: Check-point grid per image (half a GCP step off the GCP grid).
CHECK_GRID = (4, 4, 2)
#: Truth points (random, seen in both images).
TRUTH_POINTS = 300
#: Half height range about the DEM (or about the mid height without a DEM), metres.
DEM_MARGIN = 100.0
#: Object frame_id prefix.
FRAME_PREFIX = "enu_wgs84"
#: GeoTIFF ModelTransformationTag.
MODEL_TRANSFORMATION_TAG = 34264


class SceneImportError(RPCError):
    """An image or its RPC cannot be imported (missing RPC, bad offset, no overlap, ...)."""


# ---------------------------------------------------------------------------------------------
# Reading images, offsets and RPC


def read_image(path: str | Path) -> NDArray[np.generic]:
    """The first band of the first page of a TIFF as a 2-D array (rows = lines).

    uint8, uint16 and float32 stay as they are (the strip encodings mono8, mono16, 32FC1); other
    types become float32.
    """
    import tifffile

    with tifffile.TiffFile(Path(path)) as tif:
        page = tif.pages.first
        data = page.asarray()
        if data.ndim == 3:
            # contiguous (rows, cols, bands) or planar (bands, rows, cols)
            data = data[..., 0] if page.planarconfig == 1 else data[0]
    if data.ndim != 2:
        raise SceneImportError(f"{path}: expected a single-band image, got shape {data.shape}")
    if data.dtype not in (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32)):
        data = data.astype(np.float32)
    return np.ascontiguousarray(data)


def crop_offset(path: str | Path) -> tuple[float, float] | None:
    """(line, sample) of the crop's first pixel in the full scene, from the TIFF's own metadata.

    Read from the GeoTIFF ModelTransformationTag (34264) when it is a pure translation with
    unit, non-flipped pixel scale, as GDAL writes for a crop of a sensor image referenced in
    full-scene pixels (geotransform ``(sample0, 1, 0, line0, 0, 1)``). Since both the crop and
    the full scene use the same corner (PixelIsArea) convention, the translation is also the
    centre-to-centre offset. None when the TIFF has no such tag.

    Raises:
        SceneImportError: the tag is a map georeferencing (scale not 1, rotation), not an offset.

    """
    import tifffile

    with tifffile.TiffFile(Path(path)) as tif:
        tag = tif.pages.first.tags.get(MODEL_TRANSFORMATION_TAG)
        if tag is None:
            return None
        m = np.asarray(tag.value, dtype=np.float64).reshape(4, 4)
    unit = m[0, 0] == 1.0 and m[1, 1] == 1.0 and m[0, 1] == 0.0 and m[1, 0] == 0.0
    if not unit or not np.all(np.isfinite(m[:2, 3])):
        raise SceneImportError(
            f"{path}: ModelTransformationTag {m[:2].ravel().tolist()} is not a crop offset "
            "(unit scale, no rotation); pass the offset explicitly"
        )
    return float(m[1, 3]), float(m[0, 3])


def find_rpc(path: str | Path) -> tuple[RPCModel, str]:
    """The RPC of an image: GeoTIFF tag 50844, else a sidecar file; and where it came from.

    Sidecars, in this order: same stem with ``.geom``, ``_RPC.TXT`` / ``_rpc.txt``, ``.RPB`` /
    ``.rpb``; then ``RPC_*.XML`` (DIMAP) in the folder: the only one there, or the one whose name
    after ``RPC_`` starts the image's stem after ``IMG_`` (DIMAP product naming).

    Raises:
        SceneImportError: no RPC found.

    """
    import tifffile

    p = Path(path)
    with tifffile.TiffFile(p) as tif:
        has_tag = RPC_TIFF_TAG in tif.pages.first.tags
    if has_tag:
        return read_geotiff_rpc(p), f"{p.name} (GeoTIFF tag {RPC_TIFF_TAG})"
    folder, stem = p.parent, p.stem
    candidates = [
        folder / f"{stem}{suffix}"
        for suffix in (".geom", "_RPC.TXT", "_rpc.txt", ".RPB", ".rpb", ".GEOM")
    ]
    for c in candidates:
        if c.is_file():
            return read_rpc(c), c.name
    xmls = sorted(q for q in folder.iterdir() if re.fullmatch(r"(?i)rpc_.*\.xml", q.name))
    key = stem[4:] if stem.upper().startswith("IMG_") else None
    matching = [q for q in xmls if key is not None and key.startswith(q.stem[4:])]
    chosen = matching[0] if len(matching) == 1 else (xmls[0] if len(xmls) == 1 else None)
    if chosen is not None:
        return read_rpc(chosen), chosen.name
    raise SceneImportError(
        f"{p}: no RPC (no tag {RPC_TIFF_TAG}, no {stem}.geom / {stem}_RPC.TXT / {stem}.RPB, "
        f"{'several' if xmls else 'no'} RPC_*.XML in {folder}); pass it explicitly"
    )


@dataclass(frozen=True)
class ImportedImage:
    """One image ready to be written as a scene.

    Attributes:
        path: the image file.
        scene_id: scene id (the strips' frame_id, the GCP observations' key).
        image: (lines, samples) pixels.
        rpc: the RPC referred to this image's pixels (crop offset applied).
        rpc_source: where the RPC was read.
        offset: (line, sample) of pixel (0, 0) in the RPC's full scene, pixels.
        offset_source: where the offset came from.

    """

    path: Path
    scene_id: str
    image: NDArray[np.generic]
    rpc: RPCModel
    rpc_source: str
    offset: tuple[float, float]
    offset_source: str

    @property
    def lines(self) -> int:
        """Rows (scan lines)."""
        return int(self.image.shape[0])

    @property
    def samples(self) -> int:
        """Columns (detectors)."""
        return int(self.image.shape[1])

    def inside(self, ls: FloatArray) -> NDArray[np.bool_]:
        """Whether (line, sample) rows (n, 2) fall on pixel centres of the image (NaN: no)."""
        with np.errstate(invalid="ignore"):
            return np.asarray(
                (ls[:, 0] >= 0)
                & (ls[:, 0] <= self.lines - 1)
                & (ls[:, 1] >= 0)
                & (ls[:, 1] <= self.samples - 1)
            )


def load_image(
    path: str | Path,
    scene_id: str,
    *,
    rpc_path: str | Path | None = None,
    offset: tuple[float, float] | None = None,
) -> ImportedImage:
    """Read an image, its RPC (:func:`find_rpc` unless given) and its crop offset.

    Args:
        path: the image (TIFF / GeoTIFF).
        scene_id: the scene id to give it.
        rpc_path: RPC file of the full scene (any format of :func:`parproj_ros.rpc.read_rpc`).
        offset: (line, sample) of the crop in the full scene; default :func:`crop_offset`, or
            (0, 0) when the TIFF has no offset.

    """
    p = Path(path)
    image = read_image(p)
    if rpc_path is not None:
        full, source = read_rpc(rpc_path), str(rpc_path)
    else:
        full, source = find_rpc(p)
    if offset is not None:
        off, off_source = (float(offset[0]), float(offset[1])), "given"
    else:
        found = crop_offset(p)
        off, off_source = (
            (found, f"ModelTransformationTag {MODEL_TRANSFORMATION_TAG}")
            if found is not None
            else ((0.0, 0.0), "none in the TIFF: (0, 0)")
        )
    return ImportedImage(
        p, scene_id, image, full.shifted(-off[0], -off[1]), source, off, off_source
    )


# ---------------------------------------------------------------------------------------------
# The object frame


def frame_id_of(frame: LocalTangentPlane) -> str:
    """The GroundControlPoints frame_id naming a local tangent plane (exact, see module doc)."""
    return f"{FRAME_PREFIX}:lat={frame.lat0:.7f},lon={frame.lon0:.7f},h={frame.h0:.2f}"


def frame_from_id(frame_id: str) -> LocalTangentPlane:
    """Inverse of :func:`frame_id_of`.

    Raises:
        ValueError: not such a frame_id.

    """
    m = re.fullmatch(
        re.escape(FRAME_PREFIX) + r":lat=([-+0-9.eE]+),lon=([-+0-9.eE]+),h=([-+0-9.eE]+)",
        frame_id.strip(),
    )
    if m is None:
        raise ValueError(f"not a local tangent plane frame_id: {frame_id!r}")
    return LocalTangentPlane(float(m.group(1)), float(m.group(2)), float(m.group(3)))


# ---------------------------------------------------------------------------------------------
# Virtual points


Heights = tuple[float, float] | HeightFunction


def _ground(
    img: ImportedImage,
    line: FloatArray,
    sample: FloatArray,
    heights: Heights,
    offsets: FloatArray,
) -> FloatArray:
    """Geodetic (n, 3) of image points at ground height + offsets (or at fixed heights).

    ``heights`` is a DEM ``(lon, lat) -> h`` (ellipsoidal, m): the point where each ray meets
    the DEM (fixed-point iteration), then + offsets (metres); or (hmin, hmax): offsets in
    [-1, 1] map linearly onto [hmin, hmax]. Rows that fail (outside the RPC domain, no DEM)
    are NaN.
    """
    rpc = img.rpc
    lo = rpc.height_off - abs(rpc.height_scale)
    hi = rpc.height_off + abs(rpc.height_scale)
    if callable(heights):
        h = np.full(line.shape, rpc.height_off)
        for _ in range(30):
            lon, lat = rpc.localize(line, sample, h, outside="nan")
            new = np.clip(np.asarray(heights(lon, lat), dtype=np.float64), lo, hi)
            with np.errstate(invalid="ignore"):
                done = bool(np.all(~(np.abs(new - h) > 1e-3)))
            h = new
            if done:
                break
        h = h + offsets
    else:
        hmin, hmax = (float(v) for v in heights)
        h = 0.5 * (hmin + hmax) + 0.5 * (hmax - hmin) * offsets
    lon, lat = rpc.localize(line, sample, h, outside="nan")
    return np.stack([lon, lat, h], axis=-1)


def _grid(img: ImportedImage, nx: int, ny: int, shift: float = 0.0) -> tuple[FloatArray, ...]:
    """(line, sample) of an nx x ny grid over the image, shifted by ``shift`` grid steps."""
    s = (np.arange(nx) + 0.5 + shift) / nx * (img.samples - 1)
    ln = (np.arange(ny) + 0.5 + shift) / ny * (img.lines - 1)
    gl, gs = np.meshgrid(ln, s, indexing="ij")
    return gl.ravel(), gs.ravel()


@dataclass
class VirtualPoints:
    """Virtual points of an imported pair.

    Attributes:
        ids: point names.
        geodetic: (n, 3) lon deg, lat deg, h m (WGS84 ellipsoid).
        observations: per point, scene id -> (line, sample) pixels (exact RPC projections).
        check: per point, True for a check point.

    """

    ids: list[str] = field(default_factory=list)
    geodetic: list[FloatArray] = field(default_factory=list)
    observations: list[dict[str, tuple[float, float]]] = field(default_factory=list)
    check: list[bool] = field(default_factory=list)

    def add(
        self,
        prefix: str,
        geo: FloatArray,
        images: Sequence[ImportedImage],
        *,
        check: bool,
        min_scenes: int = 1,
    ) -> int:
        """Project ``geo`` (n, 3) into every image; keep points seen by >= min_scenes."""
        obs = []
        for img in images:
            with np.errstate(invalid="ignore"):
                ls = np.stack(img.rpc.project(*geo.T, outside="nan"), axis=-1)
            obs.append((img.scene_id, ls, img.inside(ls)))
        count = 0
        for i in range(len(geo)):
            seen = {sid: (float(ls[i, 0]), float(ls[i, 1])) for sid, ls, ok in obs if ok[i]}
            if len(seen) < min_scenes or not np.all(np.isfinite(geo[i])):
                continue
            self.ids.append(f"{prefix}{len(self.ids):04d}")
            self.geodetic.append(geo[i])
            self.observations.append(seen)
            self.check.append(check)
            count += 1
        return count

    def ground_points(self, frame: LocalTangentPlane) -> list[Any]:
        """As pipeline GroundPoints (object coordinates in ``frame``, metres)."""
        from .pipeline import GroundPoint

        if not self.ids:
            return []
        geo = np.array(self.geodetic)
        xyz = np.stack(frame.to_local(geo[:, 0], geo[:, 1], geo[:, 2]), axis=-1)
        return [
            GroundPoint(i, xyz[k], c, dict(o))
            for k, (i, c, o) in enumerate(
                zip(self.ids, self.check, self.observations, strict=True)
            )
        ]


def make_frame(img: ImportedImage, heights: Heights) -> LocalTangentPlane:
    """Tangent plane at the ground under the image centre, rounded (see :func:`frame_id_of`)."""
    c = np.array([(img.lines - 1) / 2.0]), np.array([(img.samples - 1) / 2.0])
    geo = _ground(img, c[0], c[1], heights, np.zeros(1))[0]
    if not np.all(np.isfinite(geo)):
        raise SceneImportError(f"{img.path}: the image centre does not localize through its RPC")
    return LocalTangentPlane(round(geo[1], 7), round(geo[0], 7), round(geo[2], 2))


def virtual_points(
    left: ImportedImage,
    right: ImportedImage,
    heights: Heights,
    *,
    gcp_grid: tuple[int, int, int] = GCP_GRID,
    check_grid: tuple[int, int, int] = CHECK_GRID,
    truth_points: int = TRUTH_POINTS,
    dem_margin: float = DEM_MARGIN,
    seed: int = 0,
) -> tuple[VirtualPoints, VirtualPoints]:
    """(GCP + check points, truth points) of a pair (see the module docstring).

    Raises:
        SceneImportError: fewer than 5 GCP in a scene, or no truth point seen by both images.

    """
    images = (left, right)
    gcp = VirtualPoints()
    callable_h = callable(heights)

    def levels(n: int) -> FloatArray:
        u = np.linspace(-1.0, 1.0, n) if n > 1 else np.zeros(1)
        return u * dem_margin if callable_h else u

    for grid, check, shift in ((gcp_grid, False, 0.0), (check_grid, True, 0.5)):
        nx, ny, nz = grid
        for img in images:
            # A long image gets as many grid rows per sample of length as a square one, so that
            # each segment of a long scene keeps enough points (up to MAX_GRID_ROWS rows).
            rows = min(max(ny, round(ny * img.lines / max(img.samples, 1))), MAX_GRID_ROWS)
            gl, gs = _grid(img, nx, rows, shift if check else 0.0)
            for dz in levels(nz):
                geo = _ground(img, gl, gs, heights, np.full(gl.shape, dz))
                # a point from the other image's grid that also falls here keeps both observations
                gcp.add(f"{img.scene_id}_{'chk' if check else 'gcp'}", geo, images, check=check)
    for img in images:
        n = sum(
            1
            for o, c in zip(gcp.observations, gcp.check, strict=True)
            if img.scene_id in o and not c
        )
        if n < 5:
            raise SceneImportError(f"only {n} virtual GCP fall in {img.scene_id}: check the RPC")
    truth = VirtualPoints()
    rng = np.random.default_rng(seed)
    for _ in range(20):
        n = 4 * truth_points
        gl = rng.uniform(0, left.lines - 1, n)
        gs = rng.uniform(0, left.samples - 1, n)
        dz = rng.uniform(-1.0, 1.0, n) * (dem_margin if callable_h else 1.0)
        geo = _ground(left, gl, gs, heights, dz)
        truth.add("truth", geo, images, check=True, min_scenes=2)
        if len(truth.ids) >= truth_points:
            break
    del truth.ids[truth_points:], truth.geodetic[truth_points:]
    del truth.observations[truth_points:], truth.check[truth_points:]
    if not truth.ids:
        raise SceneImportError("no virtual point falls in both images: do they overlap?")
    return gcp, truth


# ---------------------------------------------------------------------------------------------
# The bag


def dem_from_path(path: str | Path, *, geoid_undulation: float = 0.0) -> HeightFunction:
    """A DEM file as a height function: an SRTM ``.hgt`` tile (heights + geoid undulation, m)."""
    p = Path(path)
    if p.suffix.lower() != ".hgt":
        raise SceneImportError(f"{p}: only SRTM .hgt tiles are supported as DEM")
    return srtm_height(p, geoid_undulation=geoid_undulation)


def default_heights(img: ImportedImage) -> tuple[float, float]:
    """Heights without a DEM: the RPC's height offset +- half its height scale, metres."""
    r = img.rpc
    return r.height_off - 0.5 * abs(r.height_scale), r.height_off + 0.5 * abs(r.height_scale)


def import_pair(
    left_path: str | Path,
    right_path: str | Path,
    output: str | Path,
    *,
    rpc_left: str | Path | None = None,
    rpc_right: str | Path | None = None,
    dem: str | Path | HeightFunction | None = None,
    geoid_undulation: float = 0.0,
    heights: tuple[float, float] | None = None,
    scene_ids: tuple[str, str] = ("left", "right"),
    offsets: tuple[tuple[float, float] | None, tuple[float, float] | None] = (None, None),
    principal_distance: float = PRINCIPAL_DISTANCE,
    pixel_size: float = PIXEL_SIZE,
    line_period: float = LINE_PERIOD,
    dem_margin: float = DEM_MARGIN,
    truth_points: int = TRUTH_POINTS,
    overwrite: bool = False,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Write the input bag of a pair of images with RPC (module docstring); return a summary.

    Args:
        left_path: first image (scene ``scene_ids[0]``, the left scene of the pair).
        right_path: second image.
        output: bag folder to create.
        rpc_left: RPC file of the first image's full scene (default: :func:`find_rpc`).
        rpc_right: RPC file of the second image's full scene.
        dem: SRTM ``.hgt`` path or a height function ``(lon, lat) -> ellipsoidal h`` (m); None:
            ``heights``.
        geoid_undulation: metres added to the SRTM heights (geoid -> ellipsoid).
        heights: (hmin, hmax) metres without a DEM (default :func:`default_heights`).
        scene_ids: the two scene ids.
        offsets: crop offsets (line, sample) per image; None: from the TIFF (:func:`crop_offset`).
        principal_distance: c written in the scanner info, metres.
        pixel_size: detector pitch written in the scanner info, metres.
        line_period: seconds between lines (stamps).
        dem_margin: half height range of the virtual points about the DEM, metres.
        truth_points: number of truth points.
        overwrite: replace an existing bag.
        log: where to report.

    Returns:
        Summary (sizes, counts, frame_id, RPC and offset sources).

    """
    from parproj_msgs.msg import GroundControlPoints, ScannerInfo
    from sensor_msgs.msg import Image

    from .bag import BagWriter
    from .conversions import array_to_image, gcp_to_msg, ns_to_stamp

    if scene_ids[0] == scene_ids[1]:
        raise SceneImportError("the two scene ids must differ")
    left = load_image(left_path, scene_ids[0], rpc_path=rpc_left, offset=offsets[0])
    right = load_image(right_path, scene_ids[1], rpc_path=rpc_right, offset=offsets[1])
    if left.image.dtype != right.image.dtype:
        raise SceneImportError(f"pixel types differ: {left.image.dtype} and {right.image.dtype}")
    h: Heights
    if dem is None:
        h = heights if heights is not None else default_heights(left)
    elif callable(dem):
        h = dem
    else:
        h = dem_from_path(dem, geoid_undulation=geoid_undulation)
    frame = make_frame(left, h)
    frame_id = frame_id_of(frame)
    gcp, truth = virtual_points(left, right, h, truth_points=truth_points, dem_margin=dem_margin)
    gcp_points = gcp.ground_points(frame)
    truth_points_ = truth.ground_points(frame)

    period_ns = line_period * 1e9
    starts = [START_NS]
    starts.append(START_NS + round(left.lines * period_ns) + round(SCENE_GAP_S * 1e9))
    t_info = START_NS - 1_000_000_000
    detectors = max(left.samples, right.samples)
    custom = {
        "parproj_import": "parproj import (parproj_ros/scene_import.py)",
        "object_frame": frame_id,
        "images": f"{left.path.name} ({scene_ids[0]}), {right.path.name} ({scene_ids[1]})",
        "rpc": f"{left.rpc_source}; {right.rpc_source}",
        "crop_offsets_line_sample": f"{left.offset}; {right.offset}",
    }
    with BagWriter(
        Path(output), compression="zstd", overwrite=overwrite, custom_data=custom
    ) as bw:
        bw.add_topic(f"{VIEW}/image_strip", "sensor_msgs/msg/Image", "sensor_data")
        bw.add_topic(f"{VIEW}/scanner_info", "parproj_msgs/msg/ScannerInfo", "transient_local")
        bw.add_topic("gcp", "parproj_msgs/msg/GroundControlPoints", "transient_local")
        bw.add_topic("truth/points", "parproj_msgs/msg/GroundControlPoints", "transient_local")
        info = ScannerInfo()
        ns_to_stamp(t_info, info.header.stamp)
        info.header.frame_id = VIEW
        info.camera_name = VIEW
        info.principal_distance = float(principal_distance)
        info.pixel_size = float(pixel_size)
        info.detectors = int(detectors)
        info.principal_point = (left.samples - 1) / 2.0
        info.line_period = float(line_period)
        info.mounting.x, info.mounting.y, info.mounting.z, info.mounting.w = 0.0, 0.0, 0.0, 1.0
        bw.write(f"{VIEW}/scanner_info", info, t_info)
        for topic, pts in (("gcp", gcp_points), ("truth/points", truth_points_)):
            msg = gcp_to_msg(pts, GroundControlPoints(), frame_id=frame_id, stamp_ns=t_info)
            bw.write(topic, msg, t_info)
        for img, t0 in zip((left, right), starts, strict=True):
            # One camera has one detector count: a narrower crop is padded on the right with
            # no-data (0) columns, which changes no pixel's position.
            pixels = img.image
            if pixels.shape[1] < detectors:
                pad = np.zeros((pixels.shape[0], detectors - pixels.shape[1]), pixels.dtype)
                pixels = np.hstack([pixels, pad])
            for r0 in range(0, img.lines, STRIP_LINES):
                stamp = t0 + round(r0 * period_ns)
                msg = array_to_image(
                    pixels[r0 : r0 + STRIP_LINES],
                    Image(),
                    frame_id=img.scene_id,
                    stamp_ns=stamp,
                )
                bw.write(f"{VIEW}/image_strip", msg, stamp)
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
                "gcp": sum(
                    1
                    for o, c in zip(gcp.observations, gcp.check, strict=True)
                    if img.scene_id in o and not c
                ),
            }
            for img in (left, right)
        },
        "gcp": n_gcp,
        "check": len(gcp.ids) - n_gcp,
        "gcp_in_both": sum(1 for o in gcp.observations if len(o) == 2),
        "truth": len(truth.ids),
        "heights": "DEM" if callable(h) else list(h),
    }
    log(
        f"wrote {output} ({size / 1e6:.2f} MB): scenes {scene_ids[0]} {left.lines}x{left.samples}"
        f", {scene_ids[1]} {right.lines}x{right.samples}; {n_gcp} GCP, {summary['check']} check,"
        f" {len(truth.ids)} truth points; object frame {frame_id}"
    )
    return summary


def geodetic_of(points: Sequence[Any], frame_id: str) -> FloatArray:
    """(n, 3) lon deg, lat deg, h m of GroundPoints given in the frame named ``frame_id``."""
    frame = frame_from_id(frame_id)
    xyz = np.array([p.xyz for p in points]).reshape(-1, 3)
    return np.stack(frame.to_geodetic(*xyz.T), axis=-1)


__all__ = [
    "ImportedImage",
    "SceneImportError",
    "crop_offset",
    "find_rpc",
    "frame_from_id",
    "frame_id_of",
    "import_pair",
    "load_image",
]
