"""Rendering of pushbroom scenes of a :class:`~.terrain.Terrain` through the rigorous model.

Every pixel (line, sample) of a :class:`~parproj_ros.geometry.pushbroom.PushbroomModel` is traced
to the terrain surface: its ray (station and unit direction, object frame, metres) is intersected
with the bilinear height field, the texture is sampled at the intersection, and ``supersample^2``
sub-pixel rays are averaged (a box filter over one detector pitch and one line period).

Ray / height-field intersection (:func:`intersect_terrain`). Along a ray ``P(l) = O + l d``
(``|d| = 1``, pointing down) the vertical gap ``f(l) = Z(l) - h(X(l), Y(l))`` is positive above
the terrain. With G the terrain's Lipschitz bound on |grad h| (``Terrain.max_slope``), f cannot
fall faster than ``K = -d_z + G |d_xy|`` per metre of ray, so:

1. *Conservative march*: from the ray's crossing of the highest terrain height, ``l += f / K``
   never passes the first intersection, whatever the slopes and occlusions, and converges to it
   linearly; it runs until the gap is below ``0.05 * spacing``.
2. *Bracket*: a Newton probe (twice the Newton step, capped at half a grid cell horizontally)
   finds a point below the surface; if the probe is still above, one more conservative step is
   taken and the probe repeated.
3. *Illinois regula falsi* in the bracket until ``|f| <= tol`` (default 0.1 mm).

So the first surface along the ray is found (hidden ground is never imaged), except where the ray
pierces a ridge less than half a grid cell thick within the last ``0.05 * spacing`` of its
descent. The result satisfies ``|Z - h(X, Y)| <= tol`` exactly as tested; it lies on the ray to
rounding (about 1e-10 m at 700 km range), so projecting it back through the model returns the
pixel to about 1e-9 px. The position error along the ray is ``tol / |f'|``, larger only where
the ray grazes the surface.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

from ..geometry.errors import DegenerateGeometryError, GeometryError
from ..geometry.pushbroom import PushbroomModel
from .terrain import Terrain

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.intp]

#: Full-scale DN of each output type (uint16 is 11-bit, as IKONOS).
FULL_SCALE: dict[np.dtype[np.generic], float] = {
    np.dtype(np.uint8): 255.0,
    np.dtype(np.uint16): 2047.0,
    np.dtype(np.float32): 1.0,
}

_MAX_RAYS_PER_BLOCK = 1 << 18
_MAX_BLOCK_LINES = 64


class _Rays:
    """Flat ray arrays and the gap function f(l) = Z - h(X, Y) on index subsets (internal)."""

    def __init__(self, origins: FloatArray, directions: FloatArray, terrain: Terrain) -> None:
        self.ox, self.oy, self.oz = (np.ascontiguousarray(origins[:, k]) for k in range(3))
        self.dx, self.dy, self.dz = (np.ascontiguousarray(directions[:, k]) for k in range(3))
        self.terrain = terrain

    def gap(self, idx: IndexArray, lam: FloatArray) -> FloatArray:
        x = self.ox[idx] + lam * self.dx[idx]
        y = self.oy[idx] + lam * self.dy[idx]
        z = self.oz[idx] + lam * self.dz[idx]
        return z - self.terrain.height(x, y)

    def gap_and_slope(self, idx: IndexArray, lam: FloatArray) -> tuple[FloatArray, FloatArray]:
        dx, dy, dz = self.dx[idx], self.dy[idx], self.dz[idx]
        h, gx, gy = self.terrain.height_and_gradient(
            self.ox[idx] + lam * dx, self.oy[idx] + lam * dy
        )
        return self.oz[idx] + lam * dz - h, dz - gx * dx - gy * dy


def _intersect_flat(
    origins: FloatArray,
    directions: FloatArray,
    terrain: Terrain,
    tol: float,
    max_iter: int,
) -> tuple[FloatArray, FloatArray]:
    """Ray parameters (n,) and final gaps (n,) of flat (n, 3) rays with unit directions."""
    n = origins.shape[0]
    rays = _Rays(origins, directions, terrain)
    down = -rays.dz
    if np.any(down <= 1e-12):
        raise DegenerateGeometryError("a ray does not point downwards: it never meets the terrain")
    horiz = np.hypot(rays.dx, rays.dy)
    k_rate = down + terrain.max_slope * horiz * (1.0 + 1e-9)
    lam = np.maximum((rays.oz - terrain.max_height) / down, 0.0)
    lam_end = (rays.oz - terrain.min_height) / down
    if np.any(lam_end < 0):
        raise GeometryError("a ray starts below the lowest terrain point")
    everything = np.arange(n)
    f = rays.gap(everything, lam)
    if np.any(f < -tol):
        raise GeometryError("a ray starts below the terrain surface")

    # 1. conservative march: l += f / K never passes the first root.
    zone = max(0.05 * terrain.spacing, 20.0 * tol)
    idx = everything[f > zone]
    fi = f[idx]
    for _ in range(max_iter):
        if idx.size == 0:
            break
        lam[idx] += fi / k_rate[idx]
        fi = rays.gap(idx, lam[idx])
        keep = fi > zone
        idx, fi = idx[keep], fi[keep]

    # 2. bracket with a capped Newton probe, conservative steps when the probe stays above.
    f_lo, fp_lo = rays.gap_and_slope(everything, lam)
    hi = lam_end.copy()
    f_hi = np.zeros(n)
    cap = np.where(horiz > 0, 0.5 * terrain.spacing / np.maximum(horiz, 1e-300), np.inf)
    done = np.abs(f_lo) <= tol
    bracketed = np.zeros(n, dtype=bool)
    idx = everything[~done]
    for _ in range(max_iter):
        if idx.size == 0:
            break
        fl, fp = f_lo[idx], fp_lo[idx]
        newton = np.where(fp < 0, fl / np.maximum(-fp, 1e-300), np.inf)
        step = np.minimum(np.minimum(2.0 * newton, cap[idx]), lam_end[idx] - lam[idx])
        probe = lam[idx] + step
        fpb = rays.gap(idx, probe)
        ok = fpb <= 0
        got = idx[ok]
        hi[got], f_hi[got] = probe[ok], fpb[ok]
        bracketed[got] = True
        nb = idx[~ok]
        lam[nb] += f_lo[nb] / k_rate[nb]
        f_lo[nb], fp_lo[nb] = rays.gap_and_slope(nb, lam[nb])
        small = np.abs(f_lo[nb]) <= tol
        done[nb[small]] = True
        idx = nb[~small]
    # Rays left without a bracket (extreme grazing): the bracket ending at the lowest terrain
    # height is always valid.
    bracketed[idx] = True

    # 3. Illinois regula falsi in [lam (f >= 0), hi (f <= 0)].
    idx = everything[bracketed & ~done]
    a, fa, b, fb = lam[idx], f_lo[idx], hi[idx], f_hi[idx]
    side = np.zeros(idx.size, dtype=np.int8)
    for _ in range(max_iter):
        if idx.size == 0:
            break
        den = fa - fb
        c = np.where(den > 0, (a * -fb + b * fa) / np.where(den > 0, den, 1.0), a)
        c = np.clip(c, a, b)
        fc = rays.gap(idx, c)
        conv = (np.abs(fc) <= tol) | (b - a <= 1e-13 * np.maximum(np.abs(b), 1.0))
        lam[idx[conv]], f_lo[idx[conv]] = c[conv], fc[conv]
        above = fc > 0
        fb = np.where(above & (side == 1), fb * 0.5, fb)
        fa = np.where(~above & (side == -1), fa * 0.5, fa)
        a = np.where(above, c, a)
        fa = np.where(above, fc, fa)
        b = np.where(above, b, c)
        fb = np.where(above, fb, fc)
        side = np.where(above, 1, -1).astype(np.int8)
        keep = ~conv
        if not keep.all():
            idx, a, fa, b, fb, side = idx[keep], a[keep], fa[keep], b[keep], fb[keep], side[keep]
    if idx.size:
        lam[idx] = 0.5 * (a + b)
        f_lo[idx] = rays.gap(idx, lam[idx])
    return lam, f_lo


def intersect_terrain(
    origins: ArrayLike,
    directions: ArrayLike,
    terrain: Terrain,
    *,
    tol: float = 1e-4,
    max_iter: int = 200,
) -> FloatArray:
    """First intersection of rays with the terrain surface (see the module docstring).

    Args:
        origins: ray origins (stations), object frame, metres, shape (..., 3).
        directions: ray directions (need not be unit), pointing down, shape (..., 3);
            broadcast with ``origins``.
        terrain: the surface.
        tol: vertical tolerance |Z - h(X, Y)| of the result, metres.
        max_iter: iteration limit of each stage (reached only by rays grazing the surface).

    Returns:
        Object points, metres, float64 of the broadcast shape (..., 3).

    Raises:
        DegenerateGeometryError: a direction does not point downwards.
        GeometryError: an origin is below the terrain.

    """
    o = np.asarray(origins, dtype=float)
    d = np.asarray(directions, dtype=float)
    shape = np.broadcast_shapes(o.shape, d.shape)
    if shape[-1:] != (3,):
        raise ValueError(f"origins and directions must have shape (..., 3), got {shape}")
    of = np.broadcast_to(o, shape).reshape(-1, 3)
    df = np.broadcast_to(d, shape).reshape(-1, 3)
    norm = np.linalg.norm(df, axis=1, keepdims=True)
    if np.any(norm == 0) or not (np.all(np.isfinite(of)) and np.all(np.isfinite(df))):
        raise ValueError("origins and directions must be finite and directions non-zero")
    df = df / norm
    if of.shape[0] == 0:
        return np.zeros(shape)
    lam, _ = _intersect_flat(of, df, terrain, tol, max_iter)
    return np.asarray((of + lam[:, None] * df).reshape(shape), dtype=np.float64)


def locate_on_terrain(
    model: PushbroomModel,
    terrain: Terrain,
    line: ArrayLike,
    sample: ArrayLike,
    *,
    tol: float = 1e-4,
) -> FloatArray:
    """Image coordinates -> the object point the pixel sees (ground truth of the simulator).

    Args:
        model: the rigorous scanner model.
        terrain: the surface.
        line: line coordinates (continuous, pixel centres at integers), any shape.
        sample: sample coordinates, broadcast with ``line``.
        tol: vertical tolerance |Z - h(X, Y)| of the result, metres.

    Returns:
        Object points, metres, float64 (..., 3) of the broadcast shape; ``model.project`` of
        them returns (line, sample) to about 1e-9 px.

    """
    origin, direction = model.ray(line, sample)
    return intersect_terrain(origin, direction, terrain, tol=tol)


def _neighbour_spacing(points: FloatArray, axis: int) -> FloatArray | None:
    """Distance from each point of a (L, S, 3) grid to its nearer neighbour along an axis."""
    if points.shape[axis] < 2:
        return None
    gaps = np.linalg.norm(np.diff(points, axis=axis), axis=-1)
    first = np.take(gaps, [0], axis=axis)
    last = np.take(gaps, [-1], axis=axis)
    lo = np.concatenate([first, gaps], axis=axis)
    hi = np.concatenate([gaps, last], axis=axis)
    return np.asarray(np.minimum(lo, hi), dtype=np.float64)


def _render_block(
    model: PushbroomModel,
    terrain: Terrain,
    line0: float,
    rows: int,
    n: int,
    tol: float,
) -> NDArray[np.float32]:
    """Mean reflectance of ``rows`` image rows starting at line ``line0``: float32 (rows, det)."""
    det = model.camera.detectors
    offsets = (np.arange(n) + 0.5) / n - 0.5
    samples = (np.arange(det)[:, None] + offsets[None, :]).ravel()  # (det * n,)
    ls = (line0 + np.arange(rows)[:, None] + offsets[None, :]).ravel()  # (rows * n,)
    origin, direction = model.ray(ls[:, None], samples[None, :])
    pts = intersect_terrain(origin, direction, terrain, tol=tol)  # (rows * n, det * n, 3)
    # Ground spacing of the sub-pixel samples: across track from the neighbours on the same
    # sub-line, along track from the neighbours within the same pixel (so that the result does
    # not depend on how lines are grouped into blocks).
    res_s = _neighbour_spacing(pts, 1)
    if res_s is None:
        dist = np.linalg.norm(pts - origin, axis=-1)
        res_s = dist * model.camera.pixel_size / model.camera.principal_distance / n
    res_l = _neighbour_spacing(pts.reshape(rows, n, det * n, 3), 1)
    if res_l is None:
        along = float(np.linalg.norm(model.motion.velocity)) * model.camera.line_period
        res = np.maximum(res_s, along)
    else:
        res = np.maximum(res_s, res_l.reshape(rows * n, det * n))
    refl = terrain.texture(pts[..., 0], pts[..., 1], res)
    return np.asarray(refl.reshape(rows, n, det, n).mean(axis=(1, 3)), dtype=np.float32)


def render_reflectance(
    model: PushbroomModel,
    terrain: Terrain,
    first_line: int,
    lines: int,
    *,
    supersample: int = 2,
    tol: float = 1e-3,
    workers: int | None = None,
) -> NDArray[np.float32]:
    """Mean texture reflectance seen by each pixel, float32 (lines, detectors) in [0, 1].

    Sub-pixel rays sit at ``(k + 0.5) / n - 0.5`` pixel offsets (k = 0..n-1, n = supersample) in
    line and sample. The texture is asked for detail down to the local spacing of the sub-pixel
    footprints on the ground (from neighbouring intersections, so slopes that stretch the
    footprint get a smoother texture rather than aliasing; with supersample 1 the along-track
    spacing is the nominal ``|V| line_period``). Each pixel depends only on its own line, so any
    split of a scene into strips renders identically. Blocks of at most 64 lines and 2^18 rays
    keep memory bounded (some 50 MB per worker).

    Args:
        model: the rigorous scanner model.
        terrain: the surface.
        first_line: line coordinate of the first output row.
        lines: number of output rows (>= 1).
        supersample: sub-pixel rays per pixel along each axis (>= 1).
        tol: vertical tolerance of the ray / terrain intersections, metres.
        workers: threads rendering blocks in parallel (numpy releases the GIL in the heavy
            loops); None = min(4, CPU count). The result does not depend on it.

    """
    n = int(supersample)
    if n < 1 or int(lines) < 1:
        raise ValueError("supersample and lines must be >= 1")
    det = model.camera.detectors
    block = int(np.clip(_MAX_RAYS_PER_BLOCK // (det * n * n), 1, _MAX_BLOCK_LINES))
    starts = list(range(0, int(lines), block))
    nthreads = min(4, os.cpu_count() or 1) if workers is None else max(1, int(workers))

    def one(r0: int) -> NDArray[np.float32]:
        return _render_block(model, terrain, first_line + r0, min(block, lines - r0), n, tol)

    if nthreads == 1 or len(starts) == 1:
        parts = [one(r0) for r0 in starts]
    else:
        with ThreadPoolExecutor(max_workers=nthreads) as pool:
            parts = list(pool.map(one, starts))
    return np.concatenate(parts, axis=0)


def render_scene(
    model: PushbroomModel,
    terrain: Terrain,
    first_line: int,
    lines: int,
    *,
    dtype: DTypeLike = np.uint16,
    supersample: int = 2,
    gain: float | None = None,
    offset: float = 0.0,
    noise_sigma: float = 0.0,
    seed: int = 0,
    workers: int | None = None,
) -> NDArray[np.generic]:
    """Render lines ``first_line .. first_line + lines - 1`` of a scene, all detectors.

    ``DN = offset + gain * reflectance + noise``; for the integer types rounded and clipped to
    [0, full scale]. Full scale is 255 for uint8, 2047 for uint16 (11-bit, as IKONOS) and 1.0 for
    float32 (reflectance; not clipped).

    Args:
        model: the rigorous scanner model; image coordinates as in
            :mod:`parproj_ros.geometry.pushbroom`.
        terrain: the surface.
        first_line: line coordinate of the first output row.
        lines: number of output rows.
        dtype: np.uint8, np.uint16 or np.float32.
        supersample: sub-pixel rays per pixel along each axis (supersample^2 per pixel).
        gain: DN per unit reflectance (default: the type's full scale).
        offset: DN of zero reflectance.
        noise_sigma: standard deviation of additive Gaussian noise, DN.
        seed: seed of the noise (the texture's seed is the terrain's).
        workers: rendering threads (None = min(4, CPU count)); the result does not depend on it.

    Returns:
        Image of shape (lines, detectors) and type ``dtype``; row i is line first_line + i,
        column j is sample j.

    """
    dt = np.dtype(dtype)
    if dt not in FULL_SCALE:
        raise ValueError(f"dtype must be uint8, uint16 or float32, got {dt}")
    full = FULL_SCALE[dt]
    g = full if gain is None else float(gain)
    dn = render_reflectance(
        model, terrain, first_line, lines, supersample=supersample, workers=workers
    )
    img = dn.astype(np.float64) * g + float(offset)
    if noise_sigma > 0:
        img += np.random.default_rng(seed).normal(0.0, float(noise_sigma), img.shape)
    if dt == np.dtype(np.float32):
        return img.astype(np.float32)
    return np.clip(np.rint(img), 0.0, full).astype(dt)
