"""A DEM's heights over a pair's ground as the pair's terrain (issue 24, What to build 1 and 3).

The front ends read the DEM (``parproj_ros/io/dem.py``: any raster GDAL reads, several tiles, a
geoid) and hand the pipeline a :class:`DemSampler`, ellipsoidal heights by WGS84 lon/lat, with
the object frame of the outputs as it is known at pair time (:class:`DemTerrain`); nothing here
reads a file. Per pair (:meth:`DemTerrain.pair_terrain`):

1. the pair's ground: an image grid of each scene (:data:`FOOTPRINT_GRID` nodes a side), each
   node's ray (its normalized position through the scene's A1..A8 at a height Z) followed down
   to the DEM, and kept when the other scene sees that ground point: the ground both normalized
   images hold (their ``overlap`` extent), wherever the heights assumed so far put it;
2. each ray meets the DEM where the object Z of its point equals the DEM's height:
   ``Z <- Z + (h_dem(lon, lat) - h(X, Y, Z))``, with (lon, lat, h) the geodetic point of the
   object point through the frame's tangent plane (``enu_wgs84:...``, exact: WGS84, the plane's
   curvature included, about d^2 / 2R: 2 m at 5 km from the origin) and h_dem the DEM's height
   made ellipsoidal by its geoid option; a fixed point, as the import's virtual GCP;
3. the DEM's lowest and highest heights over that ground (it has no gross errors to leave out),
   widened by :data:`DEM_PAD_SHARE` of their span and at least :data:`DEM_PAD_M` (what a DEM
   misses: trees, buildings, its own error; SRTM's is 16 m at 90 %) and
   :data:`~.terrain.TERRAIN_PAD_PX` pixels of x-parallax, are a :class:`~.terrain.Terrain` of
   source ``dem`` (combined with the tie points by :func:`~.terrain.with_dem`).

What goes wrong is an :class:`~.results.Issue` in :meth:`DemTerrain.take_issues`, never an
exception, and the pair goes on without the DEM: a DEM that gives heights at fewer than 90 % of
the pair's ground (ERROR when it gives none: a DEM of another place; WARN otherwise), naming the
file, the area needed and the area covered; an object frame with no place on Earth (``map``, a
simulated bag: a WARN once per frame); a DEM that fails to be read (ERROR).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry import Normalization
from ..geometry.geodesy import LocalTangentPlane
from ..imaging.heights import GroundMapping
from ..imaging.resample import OutputGrid, SceneGeometry
from .frames import tangent_plane
from .results import Issue, Level, SceneResult
from .terrain import TERRAIN_PAD_PX, Terrain, TerrainSource, disagreement

FloatArray = NDArray[np.float64]

#: Nodes a side of the image grid of each scene whose ground is sampled.
FOOTPRINT_GRID = 31
#: The DEM's span is widened on each side by this share of it ...
DEM_PAD_SHARE = 0.2
#: ... and by at least this many metres: what the DEM does not hold (trees, buildings, its own
#: error: SRTM 3" is within 16 m at 90 %).
DEM_PAD_M = 20.0
#: Rounds of the fixed point of each ray onto the DEM, and its tolerance, metres.
RAY_ROUNDS = 30
RAY_TOLERANCE_M = 1e-4
#: Fewest ground points both scenes see for them to stand for the pair's ground (fewer: the
#: ground of both scenes whole).
MIN_COMMON = 4
#: The unit grid: a "pixel" of it is a normalized metre (GroundMapping at normalized metres).
_UNIT = OutputGrid(1.0, 0.0, 0.0, 1, 1)


class DemSampler(Protocol):
    """Ellipsoidal heights of a DEM by WGS84 lon/lat (``parproj_ros.io.dem.DemHeights``)."""

    @property
    def name(self) -> str:
        """The DEM's files as given."""
        ...

    @property
    def label(self) -> str:
        """Its file names without their folders (for messages)."""
        ...

    @property
    def reference(self) -> str:
        """Its vertical reference in words (the geoid option)."""
        ...

    def __call__(self, lon: FloatArray, lat: FloatArray) -> FloatArray:
        """Heights above the WGS84 ellipsoid (metres; NaN where it has none)."""
        ...

    def gap_error(self, lon: ArrayLike, lat: ArrayLike, what: str) -> str | None:
        """One line naming the file when it gives heights at under 90 % of the points."""
        ...


def surface_z(
    plane: LocalTangentPlane,
    dem: DemSampler,
    x: ArrayLike,
    y: ArrayLike,
    z0: ArrayLike = 0.0,
    rounds: int = 8,
) -> FloatArray:
    """Object Z of the DEM's surface at object (X, Y), metres (NaN where the DEM has none).

    The Z at which the point (X, Y, Z) of the tangent plane has the DEM's ellipsoidal height at
    its own lon/lat (exact to :data:`RAY_TOLERANCE_M`; the plane's curvature included).

    Args:
        plane: the object frame.
        dem: the DEM's heights.
        x: object X (east), metres.
        y: object Y (north), metres.
        z0: the Z to start from, metres.
        rounds: most rounds of ``Z <- Z + (h_dem - h)`` (each gains a factor of some 1e-6).
    """
    xb, yb, z = (np.array(v, dtype=np.float64) for v in np.broadcast_arrays(x, y, z0))
    for _ in range(rounds):
        lon, lat, h = plane.to_geodetic(xb, yb, z)
        dz = np.asarray(dem(lon, lat), dtype=np.float64) - h
        z = z + dz
        if not np.any(np.abs(dz) > RAY_TOLERANCE_M):  # NaN: no DEM there, done
            break
    return z


class _Side:
    """One scene of a pair: its image grid, its rays, and what ground it sees."""

    def __init__(self, res: SceneResult, geom: SceneGeometry, n: int) -> None:
        self.res, self.geom = res, geom
        self.mapping = GroundMapping(_UNIT, geom.to_normalized, res.affine)
        lines, dets = res.scene.lines, res.scene.detectors
        ll, ss = np.meshgrid(np.linspace(0.0, lines - 1.0, n), np.linspace(0.0, dets - 1.0, n))
        xy = geom.image_to_normalized(ll.ravel(), ss.ravel())
        self.xn, self.yn = xy[:, 0], xy[:, 1]

    def ground(self, z: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Object (X, Y) of the grid's rays at heights ``z``."""
        return self.mapping.pixel_to_ground(self.xn, self.yn, z)

    def sees(self, x: FloatArray, y: FloatArray, z: FloatArray) -> NDArray[np.bool_]:
        """Which object points (X, Y, Z) fall inside this scene's image."""
        xn, yn = self.mapping.ground_to_normalized(x, y, z)
        line, sample = self.geom.normalized_to_image(np.asarray(xn), np.asarray(yn))
        lines, dets = self.res.scene.lines, self.res.scene.detectors
        with np.errstate(invalid="ignore"):
            ok: NDArray[np.bool_] = (
                (line >= -0.5) & (line <= lines - 0.5) & (sample >= -0.5) & (sample <= dets - 0.5)
            )
        return ok


def _sides(
    left: SceneResult, right: SceneResult, norm: Normalization, grid: int
) -> tuple[_Side, _Side]:
    """The two scenes of a pair, each with its image grid of ``grid`` nodes a side."""
    return _Side(left, left.geometry(norm.left), grid), _Side(
        right, right.geometry(norm.right), grid
    )


def _onto_dem(
    side: _Side, plane: LocalTangentPlane, dem: DemSampler, z0: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Object (X, Y, Z) where each ray of ``side``'s grid meets the DEM (NaN: no DEM there).

    Fixed point from ``z0``; a ray that does not settle (a slope steeper than the view can
    follow) ends on the DEM next to it, which is all a span of heights needs.
    """
    z = np.full(side.xn.shape, float(z0))
    x, y = side.ground(z)
    for _ in range(RAY_ROUNDS):
        lon, lat, h = plane.to_geodetic(x, y, z)
        dz = np.asarray(dem(lon, lat), dtype=np.float64) - h
        z = z + dz
        x, y = side.ground(z)
        if not np.any(np.abs(dz) > RAY_TOLERANCE_M):
            break
    z = surface_z(plane, dem, x, y, z, rounds=3)  # the DEM's height where the point ended
    return x, y, z


def pair_ground(
    left: SceneResult,
    right: SceneResult,
    norm: Normalization,
    plane: LocalTangentPlane,
    dem: DemSampler,
    *,
    z0: float,
    grid: int = FOOTPRINT_GRID,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Object (X, Y, Z) on the DEM of the ground both scenes of a pair see (module doc, 1-2).

    Points of either scene's image grid whose ground the other scene sees; when fewer than
    :data:`MIN_COMMON` are, those of both scenes whole. NaN rows: no DEM there.

    Args:
        left: the left scene's parameters.
        right: the right scene's.
        norm: the pair's normalization.
        plane: the object frame.
        dem: the DEM's heights.
        z0: the height the rays start from (the pair's prior), metres.
        grid: nodes a side of each image grid.
    """
    sides = _sides(left, right, norm, grid)
    pts = [_onto_dem(s, plane, dem, z0) for s in sides]
    common = [other.sees(*p) for p, other in zip(pts, sides[::-1], strict=True)]
    both = np.concatenate(common)
    xyz = [np.concatenate([p[k] for p in pts]) for k in range(3)]
    if int((both & np.isfinite(xyz[2])).sum()) >= MIN_COMMON:
        xyz = [v[both] for v in xyz]
    return xyz[0], xyz[1], xyz[2]


def footprint_lonlat(
    left: SceneResult,
    right: SceneResult,
    norm: Normalization,
    plane: LocalTangentPlane,
    *,
    z0: float,
    grid: int = FOOTPRINT_GRID,
) -> tuple[FloatArray, FloatArray]:
    """WGS84 lon/lat (degrees) of the ground both scenes see at height ``z0``: the area needed.

    As :func:`pair_ground` without a DEM (the rays at ``z0``): what a DEM must cover.
    """
    sides = _sides(left, right, norm, grid)
    lon, lat, keep = [], [], []
    for s, other in zip(sides, sides[::-1], strict=True):
        z = np.full(s.xn.shape, float(z0))
        x, y = s.ground(z)
        lo, la, _ = plane.to_geodetic(x, y, z)
        lon.append(lo)
        lat.append(la)
        keep.append(other.sees(x, y, z))
    lons, lats, both = np.concatenate(lon), np.concatenate(lat), np.concatenate(keep)
    if int(both.sum()) >= MIN_COMMON:
        return lons[both], lats[both]
    return lons, lats


def dem_span_terrain(z: FloatArray, dem: DemSampler, *, metres_per_px: float) -> Terrain | None:
    """The terrain of DEM heights ``z`` (object frame, m; module doc, 3); None: none finite."""
    z = z[np.isfinite(z)]
    if z.size == 0:
        return None
    lo, hi = float(z.min()), float(z.max())
    pad = max(DEM_PAD_SHARE * (hi - lo), DEM_PAD_M, TERRAIN_PAD_PX * abs(metres_per_px))
    return Terrain(
        lo - pad, hi + pad, TerrainSource.DEM, dem_m=(lo, hi), dem=f"{dem.label}, {dem.reference}"
    )


#: Pairs whose DEM terrain :class:`DemTerrain` remembers (a pair is asked at most twice: at
#: its stream's start and when finished; pairs in flight at once: a few).
SEEN_PAIRS = 16


class DemTerrain:
    """The DEM the front end gave, and the object frame it is placed in at pair time.

    Args:
        dem: the DEM's heights (``parproj_ros.io.dem.DemHeights``).
        frame: the outputs' object frame now (the node: the ``frame_id`` parameter or the
            inputs'; ``parproj process``: the bag's).
    """

    def __init__(self, dem: DemSampler, frame: Callable[[], str]) -> None:
        self.dem = dem
        self.frame = frame
        #: Issues not yet handed to the outputs (:meth:`take_issues`).
        self.issues: list[Issue] = []
        self._frames_said: set[str] = set()
        #: The last pairs' terrains (pair id, frame, its scenes' first line times) -> result: a
        #: streamed pair asked at its start and again when finished is sampled (and its
        #: problems said) once.
        self._seen: dict[tuple[str, str, int, int], Terrain | None] = {}

    def take_issues(self) -> list[Issue]:
        """The issues of the pairs seen since the last call (and forget them)."""
        out, self.issues = self.issues, []
        return out

    def pair_terrain(
        self,
        pair_id: str,
        left: SceneResult,
        right: SceneResult,
        norm: Normalization,
        *,
        z0: float,
        metres_per_px: float,
    ) -> Terrain | None:
        """The DEM's terrain of a pair; None (and an issue) when the DEM cannot give it.

        Args:
            pair_id: the pair, for messages.
            left: its left scene's parameters.
            right: its right scene's.
            norm: its normalization.
            z0: the height its rays start from (its prior), metres.
            metres_per_px: |metres of height per pixel of x-parallax| (the least margin).
        """
        where = f"pair {pair_id}"
        frame_id = self.frame()
        # a pair id may come again (a bag replayed, ids reused): its scenes' first lines too
        key = (pair_id, frame_id, left.scene.first_line_ns, right.scene.first_line_ns)
        if key in self._seen:
            return self._seen[key]
        terrain = self._pair_terrain(
            where, frame_id, left, right, norm, z0=z0, metres_per_px=metres_per_px
        )
        self._seen[key] = terrain
        while len(self._seen) > SEEN_PAIRS:
            del self._seen[next(iter(self._seen))]
        return terrain

    def _pair_terrain(
        self,
        where: str,
        frame_id: str,
        left: SceneResult,
        right: SceneResult,
        norm: Normalization,
        *,
        z0: float,
        metres_per_px: float,
    ) -> Terrain | None:
        """:meth:`pair_terrain` of a pair not seen yet."""
        plane = tangent_plane(frame_id)
        if plane is None:
            if frame_id not in self._frames_said:
                self._frames_said.add(frame_id)
                self.issues.append(
                    Issue(
                        Level.WARN,
                        "dem",
                        f"the DEM {self.dem.name} is not used: the object frame {frame_id!r} "
                        "has no place on Earth (a simulated bag's map; an imported pair's is "
                        "enu_wgs84:lat=..,lon=..,h=..), so the DEM's heights cannot be placed "
                        "in it; the pairs' terrain comes from their tie points (or the prior)",
                    )
                )
            return None
        try:
            lon, lat = footprint_lonlat(left, right, norm, plane, z0=z0)
            gap = self.dem.gap_error(lon, lat, f"{where}'s ground")
            if gap is not None:
                none = not np.isfinite(np.asarray(self.dem(lon, lat))).any()
                self.issues.append(
                    Issue(
                        Level.ERROR if none else Level.WARN,
                        where,
                        f"{gap}; the DEM is not used for this pair: its terrain comes from "
                        "its tie points (or the prior)",
                    )
                )
                return None
            _, _, z = pair_ground(left, right, norm, plane, self.dem, z0=z0)
            terrain = dem_span_terrain(z, self.dem, metres_per_px=metres_per_px)
        except Exception as err:  # a file that fails to be read now: said, the pair goes on
            self.issues.append(
                Issue(
                    Level.ERROR,
                    where,
                    f"the DEM {self.dem.name} could not be sampled ({type(err).__name__}: "
                    f"{err}); the DEM is not used for this pair",
                )
            )
            return None
        if terrain is None:
            self.issues.append(
                Issue(
                    Level.WARN,
                    where,
                    f"the DEM {self.dem.name} gives no height on the pair's ground: not used",
                )
            )
        return terrain


def terrain_issue(pair_id: str, terrain: Terrain, why: str = "") -> Issue:
    """The line saying which heights a pair's terrain holds (with a DEM given).

    OK, or WARN when the DEM's heights and the tie points' disagree
    (:func:`~.terrain.disagreement`). ``why``: what chose it (e.g. too few tie points).
    """
    apart = disagreement(terrain)
    text = f"{terrain.describe()}{why}"
    if apart is not None:
        return Issue(Level.WARN, f"pair {pair_id}", f"{text}; {apart}")
    return Issue(Level.OK, f"pair {pair_id}", text)
