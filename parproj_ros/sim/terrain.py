"""Simulated ground: a height field on a regular grid and a procedural reflectance texture.

Object frame: local Cartesian, metres, X east, Y north, Z up (the frame of
:mod:`parproj_ros.geometry.pushbroom`). A :class:`Terrain` is a regular grid DEM, interpolated
bilinearly and clamped to its edge values outside the grid, plus a texture that is a pure function
of (X, Y) and a seed: no raster, so it is defined everywhere, never repeats, and is the same in
every scene rendered over it (what stereo matching needs).

The texture is built for feature matching at ground sample distances of 0.3 m to 2 m:

* smooth value noise in ten octaves, lattice cells 0.5 m to 256 m (wavelengths about 1 m to
  500 m), each on its own rotated, shifted lattice so that no grid direction dominates;
* two patchworks of rotated rectangular "fields" (sharp edges and corners at 45 m to 110 m);
* a network of bright 6 m "roads", gently curved by low-frequency noise;
* three layers of small dark and bright "buildings / trees": squares and discs 1.2 m to 15 m
  across with random orientation, one per cell of a jittered grid (10 m, 24 m and 37 m cells),
  about half of the cells occupied. These give detectors such as ORB, FAST or SIFT their corners.

Anti-aliasing: :meth:`Terrain.texture` takes the sample spacing r on the ground; a noise octave
fades out as its lattice cell shrinks from 2 r to r, and a blob as its half-size shrinks from
1.5 r to 0.5 r, so that a renderer averaging sub-pixel samples (``simulate.render_scene``) sees
no detail it cannot represent, apart from the hard edges themselves (which supersampling
smooths). The texture therefore depends slightly on r, but only in detail below the resolution.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..io.dem import read_hgt, tile_origin_of

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]
UIntArray = NDArray[np.uint32]

# ---------------------------------------------------------------------------------------------
# Hash-based random numbers on integer lattices (deterministic, platform independent, no period)

_HX = np.uint32(0x9E3779B1)
_HY = np.uint32(0x85EBCA77)
_M1 = np.uint32(0x7FEB352D)
_M2 = np.uint32(0x846CA68B)
_S15 = np.uint32(15)
_S16 = np.uint32(16)
_TO_UNIT = np.float32(2.0**-24)
_BYTE = np.float32(1.0 / 255.0)


def _mix32(h: UIntArray) -> UIntArray:
    """Avalanche a uint32 array in place (a murmur3-style finalizer) and return it."""
    h ^= h >> _S16
    h *= _M1
    h ^= h >> _S15
    h *= _M2
    h ^= h >> _S16
    return h


def _cell_hash(i: NDArray[np.int64], j: NDArray[np.int64], salt: int) -> UIntArray:
    """A well-mixed uint32 for each integer lattice cell (i, j) and a salt."""
    h = i.astype(np.uint32) * _HX
    h ^= j.astype(np.uint32) * _HY
    h ^= np.uint32(salt & 0xFFFFFFFF)
    return _mix32(h)


def _unit(h: UIntArray) -> Float32Array:
    """uint32 hash -> float32 uniform in [0, 1) (24 bits)."""
    return (h >> np.uint32(8)).astype(np.float32) * _TO_UNIT


def _byte(h: UIntArray, k: int) -> Float32Array:
    """Byte ``k`` (0..3) of a hash as float32 in [0, 1]."""
    return ((h >> np.uint32(8 * k)) & np.uint32(0xFF)).astype(np.float32) * _BYTE


def _value_noise(u: FloatArray, v: FloatArray, salt: int) -> Float32Array:
    """Smooth value noise in [-1, 1] on the unit lattice of (u, v) (smoothstep interpolation).

    Args:
        u: lattice coordinates, any shape, float64.
        v: lattice coordinates, same shape.
        salt: selects an independent noise field.

    Returns:
        float32 array of the same shape; mean 0, standard deviation about 0.33.

    """
    fu = np.floor(u)
    fv = np.floor(v)
    tu = (u - fu).astype(np.float32)
    tv = (v - fv).astype(np.float32)
    hu0 = fu.astype(np.int64).astype(np.uint32) * _HX
    hv0 = fv.astype(np.int64).astype(np.uint32) * _HY
    hv0 ^= np.uint32(salt & 0xFFFFFFFF)
    hu1 = hu0 + _HX
    hv1 = (fv.astype(np.int64) + 1).astype(np.uint32) * _HY
    hv1 ^= np.uint32(salt & 0xFFFFFFFF)
    c00 = _unit(_mix32(hu0 ^ hv0))
    c10 = _unit(_mix32(hu1 ^ hv0))
    c01 = _unit(_mix32(hu0 ^ hv1))
    c11 = _unit(_mix32(hu1 ^ hv1))
    su = tu * tu * (np.float32(3.0) - np.float32(2.0) * tu)
    sv = tv * tv * (np.float32(3.0) - np.float32(2.0) * tv)
    a = c00 + su * (c10 - c00)
    b = c01 + su * (c11 - c01)
    out: Float32Array = (a + sv * (b - a)) * np.float32(2.0) - np.float32(1.0)
    return out


# ---------------------------------------------------------------------------------------------
# Texture


@dataclass(frozen=True)
class _Frame:
    """Rotated, shifted, scaled 2-D frame: u = (c x + s y) / su + ou, v = (c y - s x) / sv + ov."""

    cos: float
    sin: float
    su: float
    sv: float
    ou: float
    ov: float
    salt: int

    def uv(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        u = (self.cos * x + self.sin * y) / self.su + self.ou
        v = (self.cos * y - self.sin * x) / self.sv + self.ov
        return u, v


#: Value noise octaves: (lattice cell in metres, amplitude in reflectance).
_OCTAVES: tuple[tuple[float, float], ...] = (
    (256.0, 0.10),
    (128.0, 0.08),
    (64.0, 0.07),
    (32.0, 0.06),
    (16.0, 0.06),
    (8.0, 0.06),
    (4.0, 0.06),
    (2.0, 0.06),
    (1.0, 0.055),
    (0.5, 0.05),
)
#: Field patchworks: (cell along u, cell along v in metres, amplitude).
_FIELDS: tuple[tuple[float, float, float], ...] = ((70.0, 45.0, 0.13), (110.0, 60.0, 0.11))
#: Blob layers: jittered-grid cell in metres.
_BLOB_CELLS: tuple[float, ...] = (10.0, 24.0, 37.0)
_BLOB_JITTER = 0.17  # max centre offset, fraction of the cell
_BLOB_HALF = (0.06, 0.20)  # half-size range, fraction of the cell (reach <= 0.45 cell)
_BLOB_PRESENCE = 0.55
_ROAD_SPACING = (190.0, 260.0)  # m between candidate road lines along u and v
_ROAD_HALF_WIDTH = 3.0  # m
_ROAD_WARP = (30.0, 150.0)  # m of lateral wander, noise cell in m
_ROAD_KEEP = 0.5  # fraction of candidate lines that are roads
_ROAD_VALUE = 0.78
_BASE = 0.45


@dataclass(frozen=True)
class ProceduralTexture:
    """Deterministic reflectance texture over the object plane (see the module docstring).

    Attributes:
        seed: selects the texture; equal seeds give identical textures.

    """

    seed: int = 0
    _octaves: tuple[tuple[_Frame, float, float], ...] = field(init=False, repr=False)
    _fields: tuple[tuple[_Frame, float], ...] = field(init=False, repr=False)
    _blobs: tuple[tuple[_Frame, float], ...] = field(init=False, repr=False)
    _roads: tuple[_Frame, _Frame] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng([int(self.seed) & 0xFFFFFFFF, 0x7E57])

        def frame(su: float, sv: float) -> _Frame:
            ang = float(rng.uniform(0.0, np.pi))
            return _Frame(
                float(np.cos(ang)),
                float(np.sin(ang)),
                su,
                sv,
                float(rng.uniform(0.0, 1000.0)),
                float(rng.uniform(0.0, 1000.0)),
                int(rng.integers(0, 2**32)),
            )

        octaves = tuple((frame(c, c), c, a) for c, a in _OCTAVES)
        fields = tuple((frame(cu, cv), a) for cu, cv, a in _FIELDS)
        blobs = tuple((frame(c, c), c) for c in _BLOB_CELLS)
        roads = (frame(_ROAD_SPACING[0], _ROAD_SPACING[1]), frame(_ROAD_WARP[1], _ROAD_WARP[1]))
        object.__setattr__(self, "_octaves", octaves)
        object.__setattr__(self, "_fields", fields)
        object.__setattr__(self, "_blobs", blobs)
        object.__setattr__(self, "_roads", roads)

    def __call__(self, x: ArrayLike, y: ArrayLike, resolution: ArrayLike = 0.0) -> Float32Array:
        """Reflectance at object points.

        Args:
            x: object X, metres, any shape (broadcast with ``y`` and ``resolution``).
            y: object Y, metres.
            resolution: ground spacing of the samples, metres (0 = no anti-alias fading).

        Returns:
            float32 reflectance in [0, 1], the broadcast shape.

        """
        xb, yb, rb = np.broadcast_arrays(
            np.asarray(x, dtype=float), np.asarray(y, dtype=float), np.asarray(resolution, float)
        )
        shape = xb.shape
        # 1-d work arrays: numpy warns on uint32 wrap-around for scalars but not for arrays
        xa, ya = xb.reshape(-1), yb.reshape(-1)
        res = np.maximum(rb.reshape(-1), 1e-6).astype(np.float32)
        out = np.full(xa.shape, _BASE, dtype=np.float32)
        for fr, amp in self._fields:
            u, v = fr.uv(xa, ya)
            h = _cell_hash(np.floor(u).astype(np.int64), np.floor(v).astype(np.int64), fr.salt)
            out += (_unit(h) - np.float32(0.5)) * np.float32(2.0 * amp)
        for fr, cell, amp in self._octaves:
            fade = np.clip(np.float32(cell) / res - np.float32(1.0), 0.0, 1.0)
            if not np.any(fade):
                continue
            u, v = fr.uv(xa, ya)
            out += _value_noise(u, v, fr.salt) * (np.float32(amp) * fade)
        self._add_roads(xa, ya, out)
        finest = float(res.min()) if res.size else 1.0
        for fr, cell in self._blobs:
            if _BLOB_HALF[1] * cell / finest <= 0.5:
                continue  # every blob of this layer is below the resolution
            self._add_blobs(xa, ya, res, fr, cell, out)
        np.clip(out, 0.0, 1.0, out=out)
        return out.reshape(shape)

    def _add_roads(self, x: FloatArray, y: FloatArray, out: Float32Array) -> None:
        grid, warp = self._roads
        wu, wv = warp.uv(x, y)
        wander = _value_noise(wu, wv, warp.salt).astype(np.float64) * _ROAD_WARP[0]
        u, v = grid.uv(x, y)
        on = np.zeros(x.shape, dtype=bool)
        for coord, spacing, salt in ((u, grid.su, grid.salt), (v, grid.sv, grid.salt ^ 0x55AA)):
            c = coord + wander / spacing
            k = np.floor(c + 0.5)
            near = np.abs(c - k) * spacing < _ROAD_HALF_WIDTH
            kk = k.astype(np.int64)
            keep = _unit(_cell_hash(kk, kk, salt)) < _ROAD_KEEP
            on |= near & keep
        out[on] = np.float32(_ROAD_VALUE) + np.float32(0.5) * (out[on] - np.float32(_BASE))

    def _add_blobs(
        self,
        x: FloatArray,
        y: FloatArray,
        res: Float32Array,
        fr: _Frame,
        cell: float,
        out: Float32Array,
    ) -> None:
        u, v = fr.uv(x, y)
        fu = np.floor(u)
        fv = np.floor(v)
        h1 = _cell_hash(fu.astype(np.int64), fv.astype(np.int64), fr.salt)
        h2 = _mix32(h1 ^ np.uint32(fr.salt ^ 0x3C3C3C3C))
        present = _byte(h1, 0) < np.float32(_BLOB_PRESENCE)
        du = (u - fu - 0.5).astype(np.float32) - (_byte(h1, 1) - np.float32(0.5)) * np.float32(
            2 * _BLOB_JITTER
        )
        dv = (v - fv - 0.5).astype(np.float32) - (_byte(h1, 2) - np.float32(0.5)) * np.float32(
            2 * _BLOB_JITTER
        )
        half = np.float32(_BLOB_HALF[0]) + _byte(h1, 3) * np.float32(_BLOB_HALF[1] - _BLOB_HALF[0])
        ang = _byte(h2, 0) * np.float32(np.pi / 2)
        ca, sa = np.cos(ang), np.sin(ang)
        a = ca * du + sa * dv
        b = ca * dv - sa * du
        square = _byte(h2, 1) < np.float32(0.7)
        inside = np.where(
            square, np.maximum(np.abs(a), np.abs(b)) < half, a * a + b * b < half * half
        )
        inside &= present
        shade = _byte(h2, 3)
        value = np.where(
            _byte(h2, 2) < np.float32(0.5),
            np.float32(0.05) + np.float32(0.2) * shade,
            np.float32(0.65) + np.float32(0.3) * shade,
        )
        alpha = np.clip(half * np.float32(cell) / res - np.float32(0.5), 0.0, 1.0) * inside
        out += alpha * (value - out)


# ---------------------------------------------------------------------------------------------
# Terrain


@dataclass(frozen=True, eq=False)
class Terrain:
    """A height field on a regular grid plus a reflectance texture, in the object frame.

    Grid node (row j, column i) is at X = x0 + i * spacing, Y = y0 + j * spacing (rows go north,
    +Y). Heights are interpolated bilinearly inside the grid and clamped to the nearest edge value
    outside it (the grid extends as a flat skirt).

    Attributes:
        x0: X of grid node (0, 0), metres.
        y0: Y of grid node (0, 0), metres.
        spacing: grid spacing, metres (same in X and Y).
        heights: Z of the grid nodes, metres, float64 array of shape (ny, nx), ny, nx >= 2
            (stored as a read-only copy).
        texture_seed: seed of the procedural texture.
        min_height: lowest node height, metres (derived).
        max_height: highest node height, metres (derived).
        max_slope: upper bound of |grad Z| anywhere (a Lipschitz constant of the surface,
            dimensionless; derived from the largest node differences along X and along Y).

    """

    x0: float
    y0: float
    spacing: float
    heights: FloatArray
    texture_seed: int = 0
    min_height: float = field(init=False)
    max_height: float = field(init=False)
    max_slope: float = field(init=False)
    _texture: ProceduralTexture = field(init=False, repr=False)

    def __post_init__(self) -> None:
        h = np.array(self.heights, dtype=np.float64, order="C", copy=True)
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise ValueError(f"heights must be a 2-D array of at least 2 x 2, got {h.shape}")
        if not np.all(np.isfinite(h)):
            raise ValueError("heights must be finite")
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise ValueError(f"spacing must be a finite number > 0, got {self.spacing}")
        if not (np.isfinite(self.x0) and np.isfinite(self.y0)):
            raise ValueError("x0, y0 must be finite")
        h.setflags(write=False)
        gx = float(np.max(np.abs(np.diff(h, axis=1)))) / self.spacing
        gy = float(np.max(np.abs(np.diff(h, axis=0)))) / self.spacing
        object.__setattr__(self, "x0", float(self.x0))
        object.__setattr__(self, "y0", float(self.y0))
        object.__setattr__(self, "spacing", float(self.spacing))
        object.__setattr__(self, "heights", h)
        object.__setattr__(self, "min_height", float(h.min()))
        object.__setattr__(self, "max_height", float(h.max()))
        object.__setattr__(self, "max_slope", float(np.hypot(gx, gy)))
        object.__setattr__(self, "_texture", ProceduralTexture(int(self.texture_seed)))

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape (ny, nx)."""
        ny, nx = self.heights.shape
        return int(ny), int(nx)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the grid nodes, metres."""
        ny, nx = self.shape
        return (
            self.x0,
            self.x0 + (nx - 1) * self.spacing,
            self.y0,
            self.y0 + (ny - 1) * self.spacing,
        )

    def _cells(
        self, x: ArrayLike, y: ArrayLike
    ) -> tuple[FloatArray, FloatArray, NDArray[np.intp], FloatArray, FloatArray]:
        """Cell corner heights, fractions and flags for bilinear interpolation (internal)."""
        ny, nx = self.shape
        fx = (np.asarray(x, dtype=float) - self.x0) / self.spacing
        fy = (np.asarray(y, dtype=float) - self.y0) / self.spacing
        fx, fy = np.broadcast_arrays(fx, fy)
        cx = np.clip(fx, 0.0, nx - 1.0)
        cy = np.clip(fy, 0.0, ny - 1.0)
        i = np.minimum(cx.astype(np.intp), nx - 2)
        j = np.minimum(cy.astype(np.intp), ny - 2)
        tx = cx - i
        ty = cy - j
        k = j * nx + i
        return fx, fy, k, tx, ty

    def height(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Terrain height Z at (X, Y), bilinear, clamped to the edge outside the grid.

        Args:
            x: object X, metres, any shape (broadcast with ``y``).
            y: object Y, metres.

        Returns:
            Z in metres, float64, the broadcast shape.

        """
        _, _, k, tx, ty = self._cells(x, y)
        flat = self.heights.ravel()
        nx = self.shape[1]
        h00 = flat[k]
        h10 = flat[k + 1]
        h01 = flat[k + nx]
        h11 = flat[k + nx + 1]
        a = h00 + tx * (h10 - h00)
        b = h01 + tx * (h11 - h01)
        return np.asarray(a + ty * (b - a), dtype=np.float64)

    def height_and_gradient(
        self, x: ArrayLike, y: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Height (m) and its partial derivatives dZ/dX, dZ/dY (dimensionless), broadcast shape.

        The gradient is that of the bilinear patch (one-sided on cell edges) and zero across the
        clamped skirt outside the grid.
        """
        fx, fy, k, tx, ty = self._cells(x, y)
        ny, nx = self.shape
        flat = self.heights.ravel()
        h00 = flat[k]
        h10 = flat[k + 1]
        h01 = flat[k + nx]
        h11 = flat[k + nx + 1]
        dx0 = h10 - h00
        dx1 = h11 - h01
        a = h00 + tx * dx0
        b = h01 + tx * dx1
        h = a + ty * (b - a)
        inx = (fx >= 0.0) & (fx <= nx - 1.0)
        iny = (fy >= 0.0) & (fy <= ny - 1.0)
        gx = np.where(inx, (dx0 + ty * (dx1 - dx0)) / self.spacing, 0.0)
        gy = np.where(iny, (b - a) / self.spacing, 0.0)
        return h, gx, gy

    def texture(self, x: ArrayLike, y: ArrayLike, resolution: ArrayLike = 0.0) -> Float32Array:
        """Reflectance at (X, Y): float32 in [0, 1], the broadcast shape.

        Args:
            x: object X, metres, any shape (broadcast with ``y`` and ``resolution``).
            y: object Y, metres.
            resolution: ground spacing of the caller's samples, metres, scalar or per point;
                detail finer than about two sample spacings is faded out (0 = keep everything).

        """
        return self._texture(x, y, resolution)


# ---------------------------------------------------------------------------------------------
# Terrain sources


def procedural_terrain(
    extent_m: float, spacing_m: float, relief_m: float, seed: int = 0
) -> Terrain:
    """Smooth fractal hills on a square grid centred on the object origin.

    Sum of cubic-spline interpolated random lattices (octaves with cells from extent/2 down to
    four grid spacings, amplitude proportional to cell^1.5, so that fine octaves add detail but
    little slope), shifted to mean 0 and scaled so that the largest |Z| equals ``relief_m``.
    Example: 4 km, 10 m spacing, 800 m relief gives median slopes of about 0.45 (24 deg) and a
    steepest bilinear facet of about 1.7 (60 deg).

    Args:
        extent_m: side of the square, metres (the grid covers [-extent/2, extent/2] in X and Y).
        spacing_m: grid spacing, metres.
        relief_m: largest |Z| about 0, metres (0 gives a flat plane).
        seed: seeds both the heights and the texture.

    Returns:
        The terrain; heights float64 (n, n) with n = round(extent / spacing) + 1.

    """
    from scipy.ndimage import map_coordinates

    if not (extent_m > 0 and spacing_m > 0 and relief_m >= 0):
        raise ValueError("extent_m and spacing_m must be > 0 and relief_m >= 0")
    n = round(extent_m / spacing_m) + 1
    if n < 2:
        raise ValueError("extent_m must cover at least one grid spacing")
    half = (n - 1) * spacing_m / 2.0
    coords = np.arange(n, dtype=float) * spacing_m
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x4E16])
    z = np.zeros((n, n))
    cell = max(extent_m / 2.0, 4.0 * spacing_m)
    while cell >= 4.0 * spacing_m or not z.any():
        m = int(np.ceil(extent_m / cell)) + 4
        lattice = rng.standard_normal((m, m))
        off = rng.uniform(0.0, 1.0, 2)
        gy, gx = np.meshgrid(
            coords / cell + 1.5 + off[1], coords / cell + 1.5 + off[0], indexing="ij"
        )
        z += cell**1.5 * map_coordinates(lattice, [gy, gx], order=3, mode="mirror")
        cell /= 2.0
    z -= z.mean()
    peak = float(np.max(np.abs(z)))
    z = z * (relief_m / peak) if peak > 0 else z * 0.0
    return Terrain(-half, -half, spacing_m, z, texture_seed=seed)


#: WGS84 ellipsoid.
_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563


def _radii(lat_rad: float) -> tuple[float, float]:
    """Meridional (M) and prime-vertical (N) radii of curvature of WGS84 at a latitude, metres."""
    e2 = _WGS84_F * (2.0 - _WGS84_F)
    w2 = 1.0 - e2 * np.sin(lat_rad) ** 2
    return _WGS84_A * (1.0 - e2) / w2**1.5, _WGS84_A / np.sqrt(w2)


def srtm_terrain(
    hgt_path: str | Path,
    lat0: float,
    lon0: float,
    size_m: float,
    spacing_m: float,
    *,
    seed: int = 0,
    tile_origin: tuple[float, float] | None = None,
    order: int = 1,
) -> Terrain:
    """A square of an SRTM tile, resampled into a local east-north-up frame.

    The object frame has its origin at (lat0, lon0) at height 0 (the geoid), X east, Y north,
    Z = the SRTM height (above the geoid). The mapping is equirectangular about the centre with
    the WGS84 radii of curvature M, N at lat0: ``lat = lat0 + Y / M``,
    ``lon = lon0 + X / (N cos lat0)``; heights are not corrected for Earth curvature.

    Accuracy against a true tangent-plane (ENU) frame at (lat0, lon0, 0), near 45 deg latitude
    (checked against the exact geodetic -> ECEF -> ENU conversion): for a point at distance d
    from the centre and height h, horizontal errors up to about ``1.1 d^2 / (2 R) + h d / R``
    (meridian convergence, the change of the east scale with latitude, the tilt of the vertical)
    and the neglected curvature drop ``d^2 / (2 R)`` in Z: at 1 km 0.09 m horizontal (0.35 m for
    h = 2000 m) and 0.08 m vertical; at 5 km 2.2 m (3.1 m) and 2.0 m; at 10 km 8.8 m (10.3 m) and
    7.9 m. Over the few-kilometre squares used for simulation that is inside the SRTM's own
    accuracy (about 10 m), and the terrain is, by definition, exact in the frame it is rendered
    in.

    Args:
        hgt_path: the tile (see :func:`read_hgt`), named like ``N44E005.hgt`` unless
            ``tile_origin`` is given.
        lat0: latitude of the square's centre, degrees.
        lon0: longitude of the square's centre, degrees.
        size_m: side of the square, metres.
        spacing_m: grid spacing of the result, metres.
        seed: texture seed.
        tile_origin: (lat, lon) of the tile's south-west corner, degrees (default: from the
            file name).
        order: spline order of the resampling (1 bilinear, 3 cubic).

    Returns:
        Terrain with heights float64 (n, n), n = round(size / spacing) + 1, centred on the origin.

    Raises:
        ValueError: the square is not inside the tile, or bad arguments.

    """
    from scipy.ndimage import map_coordinates

    path = Path(hgt_path)
    if not (size_m > 0 and spacing_m > 0):
        raise ValueError("size_m and spacing_m must be > 0")
    lat_sw, lon_sw = tile_origin if tile_origin is not None else tile_origin_of(path)
    data = read_hgt(path)
    n_tile = data.shape[0]
    per_deg = n_tile - 1
    m_rad, n_rad = _radii(np.radians(lat0))
    n = round(size_m / spacing_m) + 1
    half = (n - 1) * spacing_m / 2.0
    xs = np.arange(n) * spacing_m - half
    lat = lat0 + np.degrees(xs / m_rad)  # per row (Y)
    lon = lon0 + np.degrees(xs / (n_rad * np.cos(np.radians(lat0))))  # per column (X)
    rows = (lat_sw + 1.0 - lat) * per_deg
    cols = (lon - lon_sw) * per_deg
    lim = n_tile - 1
    if rows.min() < 0 or rows.max() > lim or cols.min() < 0 or cols.max() > lim:
        raise ValueError(
            f"the {size_m} m square at ({lat0}, {lon0}) is not inside the tile "
            f"({lat_sw}..{lat_sw + 1} N, {lon_sw}..{lon_sw + 1} E)"
        )
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    z = map_coordinates(data, [rr, cc], order=order, mode="nearest")
    return Terrain(-half, -half, spacing_m, z, texture_seed=seed)
