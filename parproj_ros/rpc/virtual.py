"""Virtual ground control points of a stereo pair from its RPC models and a DEM (paper 2)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..geometry.estimation import AffineEstimate, estimate_affine
from ..geometry.geodesy import LocalTangentPlane
from ..geometry.navigation import SceneFrame
from .model import DOMAIN_LIMIT, FloatArray, HeightFunction, RPCError, RPCModel

# ---------------------------------------------------------------------------------------------
# Virtual GCP


@dataclass(frozen=True)
class VirtualGCP:
    """Virtual ground control points of a stereo pair (from :func:`virtual_gcp`).

    Attributes:
        points: (n, 3) object coordinates in ``frame`` (X east, Y north, Z up), metres.
        left: (n, 2) (line, sample) in the left scene, pixels (this project's convention):
            exactly ``left_rpc.project(*geodetic.T)``.
        right: (n, 2) (line, sample) in the right scene, pixels.
        geodetic: (n, 3) (lon deg, lat deg, h m above the WGS84 ellipsoid).
        frame: the local tangent plane of ``points``.

    """

    points: FloatArray
    left: FloatArray
    right: FloatArray
    geodetic: FloatArray
    frame: LocalTangentPlane

    def __len__(self) -> int:
        return len(self.points)


def _dem_heights(
    rpc: RPCModel, line: FloatArray, sample: FloatArray, dem: HeightFunction
) -> FloatArray:
    """Height where each image ray meets the DEM (fixed point h = dem(localize(h)))."""
    h = np.full(line.shape, rpc.height_off)
    lo = rpc.height_off - DOMAIN_LIMIT * abs(rpc.height_scale)
    hi = rpc.height_off + DOMAIN_LIMIT * abs(rpc.height_scale)
    for _ in range(30):
        lon, lat = rpc.localize(line, sample, h, outside="nan", domain="limit")
        new = np.clip(np.asarray(dem(lon, lat), dtype=np.float64), lo, hi)
        with np.errstate(invalid="ignore"):
            done = np.all(~(np.abs(new - h) > 1e-3))
        h = new
        if done:
            break
    return h


def virtual_gcp(
    left: RPCModel,
    right: RPCModel,
    *,
    lines: tuple[int, int],
    samples: tuple[int, int],
    heights: tuple[float, float] | HeightFunction,
    grid: tuple[int, int, int] = (11, 11, 5),
    frame: LocalTangentPlane | None = None,
    window: tuple[float, float, float, float] | None = None,
    dem_margin: float = 100.0,
) -> VirtualGCP:
    """Virtual GCP of a pair on a 3-D grid over the left scene (paper 2's experiment).

    A regular grid of (line, sample) over ``window`` of the left image is localized at ``nz``
    heights: evenly from hmin to hmax, or, with a DEM, from DEM - dem_margin to DEM + dem_margin
    (the height where each ray meets the DEM; nz = 1: on the DEM). The ground points are
    projected into both scenes; those inside both images (pixel centres between 0 and size - 1)
    and in both validity domains are kept.

    Args:
        left: RPC of the left scene.
        right: RPC of the right scene.
        lines: number of lines of the (left, right) image.
        samples: number of samples of the (left, right) image.
        heights: (hmin, hmax) metres above the WGS84 ellipsoid, or a DEM function
            ``(lon deg, lat deg) -> ellipsoidal height m`` (e.g. ``io.dem.load_dem``).
        grid: (nx, ny, nz): grid points across (samples), along (lines), in height.
        frame: object frame; default: tangent plane at the kept points' mean lon, lat, height.
        window: (first_line, first_sample, last_line, last_sample) of the left image to cover;
            default the whole image.
        dem_margin: half height range about the DEM, metres.

    Returns:
        The points, their image coordinates in both scenes, geodetic coordinates and frame.

    Raises:
        RPCError: no point falls inside both scenes; bad arguments.

    """
    nx, ny, nz = (int(v) for v in grid)
    if nx < 1 or ny < 1 or nz < 1:
        raise RPCError(f"grid sizes must be >= 1, got {grid}")
    if window is None:
        window = (0.0, 0.0, lines[0] - 1.0, samples[0] - 1.0)
    l0, s0, l1, s1 = (float(v) for v in window)
    grid_l, grid_s = np.meshgrid(np.linspace(l0, l1, ny), np.linspace(s0, s1, nx), indexing="ij")
    gl, gs = grid_l.ravel(), grid_s.ravel()
    if callable(heights):
        h_dem = _dem_heights(left, gl, gs, heights)
        offsets = np.linspace(-dem_margin, dem_margin, nz) if nz > 1 else np.zeros(1)
        hh = h_dem[:, None] + offsets[None, :]
    else:
        hmin, hmax = (float(v) for v in heights)
        hh = np.broadcast_to(np.linspace(hmin, hmax, nz), (len(gl), nz))
    ll = np.repeat(gl, nz)
    ss = np.repeat(gs, nz)
    hh = hh.ravel()
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(hh)
    ll, ss, hh = ll[ok], ss[ok], hh[ok]
    lon, lat = left.localize(ll, ss, hh, outside="nan", domain="limit")
    ok = np.isfinite(lon) & np.isfinite(lat)
    lon, lat, hh = lon[ok], lat[ok], hh[ok]
    left_ls = np.stack(left.project(lon, lat, hh, outside="nan", domain="limit"), axis=-1)
    right_ls = np.stack(right.project(lon, lat, hh, outside="nan", domain="limit"), axis=-1)
    with np.errstate(invalid="ignore"):
        keep = (
            np.all(np.isfinite(left_ls), axis=1)
            & np.all(np.isfinite(right_ls), axis=1)
            & (left_ls[:, 0] >= 0) & (left_ls[:, 0] <= lines[0] - 1)
            & (left_ls[:, 1] >= 0) & (left_ls[:, 1] <= samples[0] - 1)
            & (right_ls[:, 0] >= 0) & (right_ls[:, 0] <= lines[1] - 1)
            & (right_ls[:, 1] >= 0) & (right_ls[:, 1] <= samples[1] - 1)
        )  # fmt: skip
    if not np.any(keep):
        raise RPCError("no virtual GCP falls inside both scenes: check the window and heights")
    geo = np.stack([lon[keep], lat[keep], hh[keep]], axis=-1)
    if frame is None:
        frame = LocalTangentPlane(
            float(geo[:, 1].mean()), float(geo[:, 0].mean()), float(geo[:, 2].mean())
        )
    pts = np.stack(frame.to_local(geo[:, 0], geo[:, 1], geo[:, 2]), axis=-1)
    return VirtualGCP(
        points=pts, left=left_ls[keep], right=right_ls[keep], geodetic=geo, frame=frame
    )


def estimate_scene(
    gcp: VirtualGCP,
    scene: Literal["left", "right"],
    *,
    principal_distance: float,
    pixel_size: float,
    principal_point: float,
    line_mid: float | None = None,
    psi: float | None = None,
) -> tuple[AffineEstimate, SceneFrame]:
    """Parallel projection parameters of one scene fitted to virtual GCP (paper 1 Eq 8).

    Scene coordinates: ``x = (line - line_mid) * pixel_size`` (one line = one pixel along track;
    the affine absorbs the real along-track scale), ``y = (sample - principal_point) *
    pixel_size``, metres. With psi estimated, sigma0 in pixels does not depend on the choice of
    pixel_size against principal_distance (only psi does).

    Args:
        gcp: virtual GCP.
        scene: which scene's image coordinates to fit.
        principal_distance: c, metres (Pleiades: 12.905 m).
        pixel_size: metres per pixel in the focal plane (Pleiades: 13e-6 m).
        principal_point: sample of the principal point, pixels (e.g. the line centre).
        line_mid: origin line; default the middle of the points' lines.
        psi: None to estimate the roll (Eq 8); radians to hold it; 0.0 for no PTP.

    Returns:
        The estimate (sigma0 in metres and pixels, residuals) and the scene frame used.

    """
    ls = gcp.left if scene == "left" else gcp.right
    if line_mid is None:
        line_mid = 0.5 * float(ls[:, 0].min() + ls[:, 0].max())
    frame = SceneFrame(
        line_mid=float(line_mid),
        x_per_line=float(pixel_size),
        pixel_size=float(pixel_size),
        principal_point=float(principal_point),
    )
    xy = frame.to_scene(ls[:, 0], ls[:, 1])
    est = estimate_affine(
        gcp.points, xy, principal_distance=principal_distance, pixel_size=pixel_size, psi=psi
    )
    return est, frame
