"""``parproj import``, its lower half: images with RPC models, their checks, virtual points.

The bag itself is written by :func:`parproj_ros.apps.importer.import_scenes`
(:func:`~parproj_ros.apps.importer.import_pair` is it with two images), from what this module
reads. The images (e.g. the crops of a Pleiades stereo pair, or more acquisitions) become the
scenes of one view (:data:`VIEW`, single-camera mode), cut into strips of :data:`STRIP_LINES` image
rows with increasing stamps, each scene after the one before. Which scenes pair up: without a
selection (two images, no ``--pairs``) consecutive scenes, as the node pairs them; with one (three
or more images, or ``--pairs``), the pairs chosen by :mod:`parproj_ros.apps.importer` (B/H),
written on the latched ``pairs`` topic. Image rows are scan lines (pushbroom time), columns are
detectors. There is no navigation: the node gets its parameters from the virtual ground control
points on the ``gcp`` topic (Eq 8, roll estimated), exactly as paper 2 did for its IKONOS pair.

Topics written (relative names, as ``parproj_node`` subscribes to them):

| topic | type | content |
|---|---|---|
| pan/image_strip | sensor_msgs/msg/Image | strips of 64 rows; frame_id = the scene id |
| pan/scanner_info | parproj_msgs/msg/ScannerInfo | documented defaults (below), once |
| gcp | parproj_msgs/msg/GroundControlPoints | virtual GCP and check points, once |
| truth/points | parproj_msgs/msg/GroundControlPoints | other virtual points, for evaluation |
| pairs | parproj_msgs/msg/PairSelection | the selected pairs, once (only with a selection) |

Images and RPC are read through GDAL (parproj_ros/io/raster.py: any raster GDAL reads, RPC
from every source GDAL reads, OSSIM ``.geom`` and loose DIMAP XML by parproj_ros/rpc/), pixels
by windows of :data:`STRIP_LINES` rows. Image coordinates of every observation are those of the
*crops* (0, 0 = centre of the crop's first pixel): the RPC is shifted by the crop origin
(``--crop-origin``, else GDAL's geotransform, i.e. the ModelTransformationTag 34264, else (0, 0),
a named assumption: :func:`load_image`) with :meth:`RPCModel.shifted`. Crop origin, RPC file
and band can be given for every image. Before anything is written each image's RPC is checked
over it (:func:`check_image`) and each pair must overlap (:func:`check_overlap`).

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
* truth points: per pair, :data:`TRUTH_POINTS` random positions in its left image that its
  right image also sees, at random heights within the margin of the ground; on
  ``truth/points`` only.

Scanner info: an RPC carries no interior orientation. Defaults (Pleiades-like): principal
distance :data:`PRINCIPAL_DISTANCE` = 12.905 m, detector pitch :data:`PIXEL_SIZE` = 13 um,
line period :data:`LINE_PERIOD` = 1e-4 s (only the stamps use it), principal point at the centre
of the first crop ((width - 1) / 2; the second crop's centre differs by the width difference /
2, which the affine shift absorbs), detectors = the wider crop's width, mounting identity. With
the roll estimated (Eq 8) only tan(psi) / c enters the model, so c and the pitch only rescale
the estimated roll.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.frames import FRAME_PREFIX, frame_from_id, frame_id_of
from ..rpc import (
    DOMAIN_LIMIT,
    RPC_TIFF_TAG,
    HeightFunction,
    LocalTangentPlane,
    RPCFormatError,
    RPCModel,
    read_rpc,
)
from ..rpc.formats import find_sidecar, sidecars_looked_for
from . import raster
from .dem import MIN_COVERAGE, DemError, DemHeights, Geoid, coverage_text, load_dem
from .raster import SceneImportError

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
#: GeoTIFF ModelTransformationTag.
MODEL_TRANSFORMATION_TAG = 34264
#: Fewest rows and columns of an image, pixels: one correlation patch of the tie-point matcher
#: (2 x 10 + 1 px, parproj_ros/imaging/matching.py ``half``) and its +-3 px search; a smaller
#: image (one row, one column) cannot be matched, and leaves the model's terms undetermined.
MIN_IMAGE_SIDE = 2 * (10 + 3) + 1


# ---------------------------------------------------------------------------------------------
# Reading images, offsets and RPC (through GDAL: parproj_ros/io/raster.py)


def read_image(path: str | Path, band: int = 1) -> NDArray[np.generic]:
    """One band of a raster as a 2-D array (rows = lines), no-data as 0 (small images only).

    uint8, uint16 and float32 stay as they are (the strip encodings mono8, mono16, 32FC1); other
    types become float32. The importer never calls this: it reads by windows.
    """
    return raster.read_band(path, band)


def crop_offset(path: str | Path) -> tuple[float, float] | None:
    """(line, sample) of the crop's first pixel in the full scene, from GDAL's geotransform.

    A pure translation with unit, non-flipped pixels and no CRS (what GDAL makes of a GeoTIFF
    ModelTransformationTag 34264 or tie point + pixel scale, a world file, an ``.aux.xml``); None
    when the raster has none or a map georeferencing (:func:`parproj_ros.io.raster.crop_origin`).

    Raises:
        SceneImportError: a geotransform without CRS that is not a unit translation.

    """
    return raster.crop_origin(raster.raster_info(path))


def find_rpc(path: str | Path) -> tuple[RPCModel, str]:
    """The RPC of an image and where it came from.

    First GDAL's RPC metadata (tag 50844, ``.RPB``, ``_RPC.TXT``, NITF RPC00B, JPEG 2000 boxes,
    DIMAP products, ``.aux.xml``); then the sidecars of the RPC format table
    (:func:`parproj_ros.rpc.formats.find_sidecar`): a ``.RPB`` / ``_RPC.TXT`` GDAL skipped is
    an error saying why; same stem with ``.geom`` (OSSIM); ``RPC_*.XML`` (DIMAP) in the folder:
    the only one there, or the one whose name after ``RPC_`` starts the image's stem after
    ``IMG_`` (DIMAP product naming).

    Raises:
        SceneImportError: no RPC found.
        RPCFormatError: an RPC found but malformed (file, key and value named).

    """
    p = Path(path)
    info = raster.raster_info(p)
    if info.rpc_metadata:
        source = raster.describe_rpc_source(info)
        return raster.rpc_from_metadata(info.rpc_metadata, f"{p} [{source}]"), source
    found = find_sidecar(p)
    if found is None:
        raise SceneImportError(
            f"{p}: no RPC (GDAL finds none: no tag {RPC_TIFF_TAG}, "
            f"{sidecars_looked_for(p, gdal=True)}, no NITF RPC00B; "
            f"{sidecars_looked_for(p, gdal=False)}); "
            "pass it with --rpc IMAGE FILE (or --rpc-left / --rpc-right)"
        )
    spec, c = found
    if spec.gdal is None:
        return read_rpc(c), c.name
    # GDAL skips a sidecar it cannot parse: say what is wrong with it
    read_rpc(c)  # raises RPCFormatError naming the file and the key
    suffix = spec.gdal
    if not raster.sidecar_read(info.driver, suffix):
        raise RPCFormatError(
            f"{c}: GDAL reads no {suffix} sidecar beside a {info.driver} image "
            f"(only beside {raster.sidecar_readers(suffix)} images); pass it "
            f"explicitly: --rpc {p.name} {c}"
        )
    raise RPCFormatError(
        f"{c}: GDAL reads no RPC from this sidecar of {p.name}, though it parses as "
        "one; check its syntax against GDAL's .RPB / _RPC.TXT"
    )


#: What the log says when a crop origin is assumed.
ASSUMED_ORIGIN = "assumed (0, 0): the RPC is in the image's own grid, as GDAL assumes"


@dataclass(frozen=True)
class ImportedImage:
    """One image ready to be written as a scene (its pixels stay in the file until then).

    Attributes:
        path: the image file.
        scene_id: scene id (the strips' frame_id, the GCP observations' key).
        rpc: the RPC referred to this image's pixels (crop offset applied).
        rpc_source: where the RPC was read.
        offset: (line, sample) of pixel (0, 0) in the RPC's grid, pixels.
        offset_source: where the offset came from.
        info: what GDAL says about the raster.
        band: the band imported (1-based, GDAL's numbering).
        notes: warnings and named assumptions about this image, in the order found.
        checks: figures of the import checks (round trip, normalized ranges, ...).

    """

    path: Path
    scene_id: str
    rpc: RPCModel
    rpc_source: str
    offset: tuple[float, float]
    offset_source: str
    info: raster.RasterInfo
    band: int = 1
    notes: list[str] = field(default_factory=list)
    checks: dict[str, Any] = field(default_factory=dict)

    @property
    def lines(self) -> int:
        """Rows (scan lines)."""
        return self.info.lines

    @property
    def samples(self) -> int:
        """Columns (detectors)."""
        return self.info.samples

    @property
    def dtype(self) -> np.dtype[Any]:
        """Pixel type of the strips."""
        return raster.out_dtype(self.info.dtype)

    def inside(self, ls: FloatArray) -> NDArray[np.bool_]:
        """Whether (line, sample) rows (n, 2) fall on pixel centres of the image (NaN: no)."""
        with np.errstate(invalid="ignore"):
            return np.asarray(
                (ls[:, 0] >= 0)
                & (ls[:, 0] <= self.lines - 1)
                & (ls[:, 1] >= 0)
                & (ls[:, 1] <= self.samples - 1)
            )


def _finite_pair(value: Sequence[float], what: str) -> tuple[float, float]:
    a, b = (float(v) for v in value)
    if not (math.isfinite(a) and math.isfinite(b)):
        raise SceneImportError(f"{what} must be finite, got ({a}, {b})")
    return a, b


def load_image(
    path: str | Path,
    scene_id: str,
    *,
    rpc_path: str | Path | None = None,
    offset: tuple[float, float] | None = None,
    band: int | None = None,
) -> ImportedImage:
    """Open an image with GDAL, find its RPC (:func:`find_rpc` unless given) and crop origin.

    Args:
        path: the image (any raster GDAL reads).
        scene_id: the scene id to give it.
        rpc_path: RPC file (any format of :func:`parproj_ros.io.raster.read_rpc_file`).
        offset: (line, sample) of the image's first pixel in the RPC's grid, pixels; default
            :func:`crop_offset`, or (0, 0) when the raster has none (a named assumption in
            ``notes``).
        band: band to import (1-based); None: band 1, with a note when there are more.

    Raises:
        SceneImportError: unreadable raster, no RPC, a bad band, a constant band.
        RPCFormatError: a malformed RPC.

    """
    p = Path(path)
    info = raster.raster_info(p)
    if min(info.lines, info.samples) < MIN_IMAGE_SIDE:
        raise SceneImportError(
            f"{p}: image too small: {info.lines} x {info.samples} px (rows x columns), at least "
            f"{MIN_IMAGE_SIDE} x {MIN_IMAGE_SIDE} needed (one tie-point correlation window and "
            "its search); import a larger crop"
        )
    if np.dtype(info.dtype).kind == "c":
        raise SceneImportError(
            f"{p}: complex pixels ({info.dtype}: a SAR or Fourier product): a pushbroom scanner's "
            "image holds real values; give its amplitude (e.g. a VRT band with "
            "PixelFunctionType mod)"
        )
    notes: list[str] = []
    if band is None:
        band = 1
        if info.bands > 1:
            notes.append(
                f"{p.name}: {info.bands} bands, band 1 imported (choose another with --band)"
            )
    if not 1 <= band <= info.bands:
        raise SceneImportError(f"{p}: band {band} asked for, the raster has {info.bands}")
    lo, hi, valid = raster.band_summary(p, band)
    # another band is advice only when there is one
    which = f"band {band}" if info.bands > 1 else "its only band"
    advice = "choose another with --band" if info.bands > 1 else "check the file"
    if valid == 0:
        raise SceneImportError(
            f"{p}: {which} is all no-data (GDAL mask): nothing to import; {advice}"
            + ("" if info.bands > 1 else " and its nodata value")
        )
    if lo == hi:
        raise SceneImportError(f"{p}: {which} is constant ({lo:g}) : nothing to match; {advice}")
    if rpc_path is not None:
        full, source = raster.read_rpc_file(rpc_path)
    else:
        full, source = find_rpc(p)
    if offset is not None:
        off, off_source = _finite_pair(offset, f"{p}: crop origin"), "given (--crop-origin)"
    else:
        found = raster.crop_origin(info)
        if found is not None:
            off, off_source = found, "ModelTransformationTag or tie point (GDAL geotransform)"
        else:
            off, off_source = (0.0, 0.0), ASSUMED_ORIGIN
            notes.append(
                f"{p.name}: no crop origin in the file: {ASSUMED_ORIGIN}; if it is a crop of the "
                f"RPC's scene, give it with --crop-origin {p.name} ROW COL"
            )
    return ImportedImage(
        p,
        scene_id,
        full.shifted(-off[0], -off[1]),
        source,
        off,
        off_source,
        info,
        band,
        notes,
    )


# ---------------------------------------------------------------------------------------------
# The object frame (its frame_id: parproj_ros/core/frames.py, frame_id_of and frame_from_id)


#: How a tangent-plane frame_id is written (for messages refusing one).
TANGENT_PLANE_FORM = (
    f"a tangent plane on WGS84 is {FRAME_PREFIX}:lat=LAT,lon=LON,h=H "
    "(degrees, |LAT| <= 90; metres)"
)


# ---------------------------------------------------------------------------------------------
# Virtual points


Heights = tuple[float, float] | HeightFunction


def _rpc_heights(img: ImportedImage) -> tuple[float, float]:
    """The heights an image's RPC spans, ``height_off`` +- ``height_scale``, metres."""
    rpc = img.rpc
    return rpc.height_off - abs(rpc.height_scale), rpc.height_off + abs(rpc.height_scale)


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
    lo, hi = _rpc_heights(img)
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


#: Share of a scene's DEM heights beyond its RPC's height range above which it is said.
CLIPPED_SHARE_NOTED = 0.01


def _warn_clipped(img: ImportedImage, dem_h: FloatArray, lo: float, hi: float) -> None:
    """A note when the DEM's heights leave the RPC's height range (they are clipped to it)."""
    known = dem_h[np.isfinite(dem_h)]
    out = known[(known < lo) | (known > hi)]
    if known.size and out.size > CLIPPED_SHARE_NOTED * known.size:
        warnings.warn(
            f"{img.scene_id}: the DEM gives {100 * out.size / known.size:.0f} % of its points "
            f"heights beyond the RPC's height range {lo:.0f}..{hi:.0f} m (from "
            f"{known.min():.0f} to {known.max():.0f} m): used clipped to that range; a DEM of "
            "another place, datum or unit? (process measures the terrain from tie points)",
            stacklevel=3,
        )


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

    def extend(self, other: VirtualPoints) -> None:
        """Append the points of ``other`` (their ids must not clash with these)."""
        self.ids += other.ids
        self.geodetic += other.geodetic
        self.observations += other.observations
        self.check += other.check

    def ground_points(self, frame: LocalTangentPlane) -> list[Any]:
        """As pipeline GroundPoints (object coordinates in ``frame``, metres)."""
        from ..core.results import GroundPoint

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


def height_range(img: ImportedImage, heights: Heights, dem_margin: float) -> tuple[float, float]:
    """Heights the virtual points of an image span, metres.

    With a DEM: the ground under a coarse grid +- dem_margin; else the given range.
    """
    if not callable(heights):
        return float(heights[0]), float(heights[1])
    check_dem_coverage(img, heights)
    gl, gs = _grid(img, 5, 5)
    geo = _ground(img, gl, gs, heights, np.zeros(gl.shape))
    dem_h = np.asarray(heights(geo[:, 0], geo[:, 1]), dtype=np.float64)  # before the clip
    _warn_clipped(img, dem_h, *_rpc_heights(img))
    g = geo[:, 2]
    g = g[np.isfinite(g)]
    if g.size == 0:
        mid = img.rpc.height_off
        return mid - dem_margin, mid + dem_margin
    return float(g.min()) - dem_margin, float(g.max()) + dem_margin


def check_image(
    img: ImportedImage, hrange: tuple[float, float], *, grid: int = 11
) -> dict[str, Any]:
    """Check that the RPC is usable over the image; return the figures (also in img.checks).

    Over an ``grid`` x ``grid`` x 3 lattice of pixels and heights (``hrange``, metres):
    localization converges everywhere; the denominators keep their sign; image -> ground ->
    image and ground -> image -> ground close (px, degrees). The image's normalized range
    against the RPC's declared validity domain is noted once when outside (advice only: the RPC
    is evaluated there). With a map georeferencing (a CRS), the image's own footprint must
    agree with the RPC's.

    Raises:
        SceneImportError: a check fails (the message names the file, the figure and what to do).

    """
    rpc = img.rpc
    name = img.path
    g_l, g_s = np.meshgrid(
        np.linspace(0.0, img.lines - 1.0, grid),
        np.linspace(0.0, img.samples - 1.0, grid),
        indexing="ij",
    )  # edges included
    hs = np.linspace(hrange[0], hrange[1], 3)
    ll, ss, hh = np.repeat(g_l.ravel(), 3), np.repeat(g_s.ravel(), 3), np.tile(hs, g_l.size)
    lon, lat = rpc.localize(ll, ss, hh, outside="nan")
    failed = ~(np.isfinite(lon) & np.isfinite(lat))
    if failed.any():
        # the usual cause of a failed localization: a denominator vanishing over the image
        why = rpc.image_denominator_check(ll, ss, hh)
        if why is not None:
            raise SceneImportError(
                f"{name}: {why}: the RPC from {img.rpc_source} is damaged or not this image's "
                "(check --rpc and --crop-origin)"
            )
        k = int(np.flatnonzero(failed)[0])
        raise SceneImportError(
            f"{name}: localization through its RPC does not converge at {int(failed.sum())} of "
            f"{failed.size} test points (e.g. line {ll[k]:.0f}, sample {ss[k]:.0f}, h "
            f"{hh[k]:.0f} m): the RPC does not describe this image, or the crop origin "
            f"{img.offset} ({img.offset_source}) is wrong; check --rpc-* and --crop-origin"
        )
    why = rpc.denominator_check(lon, lat, hh)
    if why is not None:
        raise SceneImportError(
            f"{name}: RPC {why.removeprefix('the ')}: the RPC is unusable over this image "
            f"({img.rpc_source})"
        )
    pl, ps = rpc.project(lon, lat, hh, outside="nan")
    img_err = float(np.nanmax(np.hypot(pl - ll, ps - ss)))
    lon2, lat2 = rpc.localize(pl, ps, hh, outside="nan")
    geo_err = float(np.nanmax(np.maximum(np.abs(lon2 - lon), np.abs(lat2 - lat))))
    if not (img_err < 1e-3 and geo_err < 1e-8):
        raise SceneImportError(
            f"{name}: the RPC round trip misses by {img_err:.3g} px / {geo_err:.3g} deg (limit "
            "1e-3 px, 1e-8 deg): the model is numerically unusable over this image"
        )
    (nl0, nl1), (ns0, ns1) = rpc.normalized_image_range(
        (0.0, img.lines - 1.0), (0.0, img.samples - 1.0)
    )
    L, P, H = rpc.normalize_ground(lon, lat, hh)
    ranges = {
        "line": (nl0, nl1),
        "sample": (ns0, ns1),
        "lon": (float(L.min()), float(L.max())),
        "lat": (float(P.min()), float(P.max())),
        "height": (float(H.min()), float(H.max())),
    }
    outside = {k: v for k, v in ranges.items() if max(abs(v[0]), abs(v[1])) > DOMAIN_LIMIT + 1e-9}
    if outside:
        text = ", ".join(f"{k} {v[0]:.2f}..{v[1]:.2f}" for k, v in outside.items())
        img.notes.append(
            f"warning: {img.path.name} lies outside its RPC's declared validity domain "
            f"(|normalized| <= {DOMAIN_LIMIT}): {text}; the RPC is evaluated there as GDAL, "
            "rpcm and s2p do (a crop that kept its parent's offsets with its own scales is "
            "exact there)"
        )
    foot = raster.map_footprint(img.info, ll[::3], ss[::3])
    if foot is not None:
        c = (0.5 * float(lon.min() + lon.max()), 0.5 * float(lat.min() + lat.max()))
        m_deg = 111_320.0  # metres per degree
        d = np.hypot(
            (foot[:, 0] - lon[::3]) * m_deg * math.cos(math.radians(c[1])),
            (foot[:, 1] - lat[::3]) * m_deg,
        )
        size = float(
            np.hypot(
                (lon.max() - lon.min()) * m_deg * math.cos(math.radians(c[1])),
                (lat.max() - lat.min()) * m_deg,
            )
        )
        if float(np.median(d)) > max(2000.0, 0.5 * size):
            raise SceneImportError(
                f"{name}: the image and its RPC describe different places: the image's map "
                f"georeferencing puts its pixels {float(np.median(d)) / 1000:.1f} km (median) "
                f"from where the RPC puts them ({img.rpc_source}); wrong RPC file?"
            )
    checks = {
        "round_trip_px": img_err,
        "round_trip_deg": geo_err,
        "normalized_ranges": {k: [round(v[0], 3), round(v[1], 3)] for k, v in ranges.items()},
        "outside_declared_domain": sorted(outside),
        "footprint_lon_lat": [
            float(lon.min()),
            float(lat.min()),
            float(lon.max()),
            float(lat.max()),
        ],
    }
    img.checks.update(checks)
    return checks


def footprints_overlap(left: ImportedImage, right: ImportedImage) -> bool:
    """Whether the lon/lat boxes of two images (from :func:`check_image`) intersect."""
    return _boxes_meet(left.checks["footprint_lon_lat"], right.checks["footprint_lon_lat"])


def _box_at(img: ImportedImage, h: float) -> list[float] | None:
    """Lon/lat box of the image's corners localized at height ``h`` (m); None if one fails."""
    ll = np.array([0.0, 0.0, img.lines - 1.0, img.lines - 1.0])
    ss = np.array([0.0, img.samples - 1.0, 0.0, img.samples - 1.0])
    lon, lat = img.rpc.localize(ll, ss, np.full(4, h), outside="nan")
    if not (np.all(np.isfinite(lon)) and np.all(np.isfinite(lat))):
        return None
    return [float(lon.min()), float(lat.min()), float(lon.max()), float(lat.max())]


def _boxes_meet(a: Sequence[float], b: Sequence[float]) -> bool:
    """Whether two lon/lat boxes (min lon, min lat, max lon, max lat) intersect."""
    return not (a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1])


def check_overlap(left: ImportedImage, right: ImportedImage) -> None:
    """Refuse a pair whose ground footprints (from :func:`check_image`) do not intersect.

    When they would intersect at other heights within the left RPC's height range, the
    heights used (a DEM, ``--heights``) are named as the cause, not the RPCs.
    """
    a, b = left.checks["footprint_lon_lat"], right.checks["footprint_lon_lat"]
    if footprints_overlap(left, right):
        return
    rpc = left.rpc
    lo, hi = _rpc_heights(left)
    meet = []
    for h in np.linspace(lo, hi, 41):
        ba, bb = _box_at(left, float(h)), _box_at(right, float(h))
        if ba is not None and bb is not None and _boxes_meet(ba, bb):
            meet.append(float(h))
    used = left.checks.get("normalized_ranges", {}).get("height")
    if meet and used is not None:
        u0, u1 = (v * rpc.height_scale + rpc.height_off for v in used)
        raise SceneImportError(
            f"{left.path} and {right.path} do not overlap on the ground at the heights used "
            f"({min(u0, u1):.0f}..{max(u0, u1):.0f} m), but do at {meet[0]:.0f}..{meet[-1]:.0f}"
            f" m (within the RPC's height range {lo:.0f}..{hi:.0f} m): the heights are off the "
            "ground: a DEM (--dem) in feet, above another datum (--geoid-undulation, "
            "--dem-ellipsoidal) or of another place, or --heights away from the ground"
        )
    raise SceneImportError(
        f"{left.path} and {right.path} do not overlap on the ground: footprints lon/lat "
        f"{[round(v, 4) for v in a]} and {[round(v, 4) for v in b]}; not a stereo pair, or "
        "a wrong RPC / crop origin"
    )


def make_frame(img: ImportedImage, heights: Heights) -> LocalTangentPlane:
    """Tangent plane at the ground under the image centre, rounded (see :func:`frame_id_of`)."""
    c = np.array([(img.lines - 1) / 2.0]), np.array([(img.samples - 1) / 2.0])
    geo = _ground(img, c[0], c[1], heights, np.zeros(1))[0]
    if not np.all(np.isfinite(geo)):
        raise SceneImportError(
            f"{img.path}: the image centre does not localize through its RPC on the heights "
            f"{heights if not callable(heights) else 'of the DEM'}: check the RPC and the DEM"
        )
    return LocalTangentPlane(round(geo[1], 7), round(geo[0], 7), round(geo[2], 2))


def gcp_points(
    images: Sequence[ImportedImage],
    heights: Heights,
    dem_margin: float = DEM_MARGIN,
    *,
    gcp_grid: tuple[int, int, int] = GCP_GRID,
    check_grid: tuple[int, int, int] = CHECK_GRID,
) -> VirtualPoints:
    """GCP and check points: grids over every image, observed in every image that sees them.

    Raises:
        SceneImportError: fewer than 5 GCP in a scene.

    """
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
                # a point from another image's grid that also falls here keeps every observation
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


def pair_truth_points(
    left: ImportedImage,
    right: ImportedImage,
    heights: Heights,
    count: int = TRUTH_POINTS,
    dem_margin: float = DEM_MARGIN,
    prefix: str = "truth",
    seed: int = 0,
) -> VirtualPoints:
    """Up to ``count`` random points of ``left`` that ``right`` sees too (observed in both).

    Image positions uniform over ``left``; heights uniform within ``dem_margin`` metres of the
    DEM ground, or over (hmin, hmax); ids ``prefix`` + a 4-digit number.
    """
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


# ---------------------------------------------------------------------------------------------
# The bag


def dem_from_path(
    path: str | Path | Sequence[str | Path],
    *,
    geoid_undulation: float = 0.0,
    geoid: Geoid = None,
) -> HeightFunction:
    """DEM files (any raster GDAL reads, see :func:`parproj_ros.io.dem.load_dem`) as heights.

    ``geoid`` (a grid file, a model name, a constant) if given, else ``geoid_undulation``
    (metres added to the DEM's heights; 0: used as they are).
    """
    return load_dem(path, geoid=geoid if geoid is not None else float(geoid_undulation))


def check_dem_coverage(img: ImportedImage, heights: HeightFunction) -> None:
    """Refuse a DEM that gives no ground under :data:`MIN_COVERAGE` of an image's 11 x 11 grid.

    The points whose localization at the RPC's height offset fails are left to
    :func:`check_image` (the RPC's fault, not the DEM's).

    Raises:
        DemError: one line naming the DEM (or geoid grid), the area needed and covered.

    """
    gl, gs = _grid(img, 11, 11)
    rpc = img.rpc
    lon, lat = rpc.localize(gl, gs, np.full(gl.shape, rpc.height_off), outside="nan")
    ok = np.isfinite(lon) & np.isfinite(lat)
    if not ok.any():
        return
    g = _ground(img, gl[ok], gs[ok], heights, np.zeros(int(ok.sum())))[:, 2]
    fraction = float(np.isfinite(g).mean())
    if fraction >= MIN_COVERAGE:
        return
    what = f"{img.path.name}'s ground"
    if isinstance(heights, DemHeights):
        heights.check_covers(lon, lat, what)  # names the geoid grid when it is at fault
        name, box = heights.name, heights.bounds_lonlat()
    else:
        name, box = "the DEM", None
    need = (float(lon[ok].min()), float(lat[ok].min()), float(lon[ok].max()), float(lat[ok].max()))
    raise DemError(name, coverage_text(fraction, what, need, box))


def default_heights(img: ImportedImage) -> tuple[float, float]:
    """Heights without a DEM: the RPC's height offset +- half its height scale, metres."""
    r = img.rpc
    return r.height_off - 0.5 * abs(r.height_scale), r.height_off + 0.5 * abs(r.height_scale)


def check_options(
    heights: tuple[float, float] | None,
    geoid_undulation: float,
    principal_distance: float,
    pixel_size: float,
    line_period: float,
    dem_margin: float,
) -> None:
    """Refuse NaN / infinite options, a zero-width height range, non-positive sizes."""
    named = {
        "geoid_undulation": geoid_undulation,
        "principal_distance": principal_distance,
        "pixel_size": pixel_size,
        "line_period": line_period,
        "dem_margin": dem_margin,
    }
    for key, value in named.items():
        if not math.isfinite(float(value)):
            raise SceneImportError(f"{key} must be finite, got {value}")
    for key in ("principal_distance", "pixel_size", "line_period"):
        if not float(named[key]) > 0:
            raise SceneImportError(f"{key} must be > 0, got {named[key]}")
    if heights is not None:
        lo, hi = _finite_pair(heights, "--heights")
        if not hi > lo:
            raise SceneImportError(
                f"--heights {lo:g} {hi:g}: the height range must have HMAX > HMIN (the virtual "
                "points need a height spread to fit a parallel projection)"
            )


def geodetic_of(points: Sequence[Any], frame_id: str) -> FloatArray:
    """(n, 3) lon deg, lat deg, h m of GroundPoints given in the frame named ``frame_id``."""
    frame = frame_from_id(frame_id)
    xyz = np.array([p.xyz for p in points]).reshape(-1, 3)
    return np.stack(frame.to_geodetic(*xyz.T), axis=-1)


__all__ = [
    "FRAME_PREFIX",
    "ImportedImage",
    "SceneImportError",
    "check_image",
    "check_overlap",
    "crop_offset",
    "find_rpc",
    "frame_from_id",
    "frame_id_of",
    "load_image",
]
