"""Scene parallel projection parameters from navigation data (paper 1, section 4, Eqs 9-13).

Eqs 10-13 assume the velocity is perpendicular to the scan line. With a crab angle they give a
model that misses the rigorous one by up to ``s |V . y_s| T / 2`` (T the scene duration); when that
exceeds a tolerance, :func:`parameters_from_navigation` fits the affine model to virtual ground
points projected through the rigorous model instead, and says so.

Scene coordinates (metres in the focal plane): ``x = s |V_perp| (t - t_mid)`` along track, with
V_perp the velocity component normal to the scan line and t_mid the time of the scene's middle
line, and ``y`` the perspective coordinate from the principal point (ERRATA, "conventions").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import CrabAngleError, DegenerateGeometryError, GeometryError
from .parallel import AffineModel, ParallelProjection, affine_to_nonlinear, nonlinear_to_affine
from .ptp import ptp_forward, roll_from_rotation
from .pushbroom import PushbroomModel
from .rotation import angles_from_rotation

FloatArray = NDArray[np.float64]

Method = Literal["navigation", "navigation_virtual_gcp"]


@dataclass(frozen=True)
class SceneFrame:
    """How a scene's image coordinates map to scene coordinates in metres.

    ``x = x_per_line * (line - line_mid)`` and ``y = pixel_size * (sample - principal_point)``
    (perspective, before PTP).

    Attributes:
        line_mid: line coordinate of the scene's origin (its middle line), lines.
        x_per_line: scene metres per line along track (s |V_perp| line_period for navigation).
        pixel_size: scene metres per sample across track.
        principal_point: sample coordinate of the principal point, pixels.

    """

    line_mid: float
    x_per_line: float
    pixel_size: float
    principal_point: float

    def to_scene(self, line: ArrayLike, sample: ArrayLike) -> FloatArray:
        """(line, sample) pixels -> (x, y) metres, stacked on the last axis."""
        x = (np.asarray(line, dtype=float) - self.line_mid) * self.x_per_line
        y = (np.asarray(sample, dtype=float) - self.principal_point) * self.pixel_size
        return np.stack([x, y], axis=-1)

    def to_image(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """(x, y) metres -> (line, sample) pixels, stacked on the last axis."""
        line = np.asarray(x, dtype=float) / self.x_per_line + self.line_mid
        sample = np.asarray(y, dtype=float) / self.pixel_size + self.principal_point
        return np.stack([line, sample], axis=-1)


@dataclass(frozen=True)
class NavigationParameters:
    """Result of :func:`parameters_from_navigation`.

    Attributes:
        params: non-linear parallel projection parameters of the scene.
        affine: the same as A1..A8 (Eq 3).
        psi: roll for the PTP correction, radians (tan psi = r_s32 / r_s33).
        frame: mapping of image coordinates to scene metres.
        method: "navigation" (Eqs 9-13) or "navigation_virtual_gcp" (fit to rigorous points).
        crab_angle: angle between velocity and the scan-plane normal, radians.
        crab_error_px: predicted worst error of Eqs 10-13 from the crab angle, pixels.
        fit_rms_px: RMS misfit of the model against the rigorous scanner over the virtual
            points on the mean-height plane (where PTP is exact), pixels.
        note: why the method was chosen, in words.

    """

    params: ParallelProjection
    affine: AffineModel
    psi: float
    frame: SceneFrame
    method: Method
    crab_angle: float
    crab_error_px: float
    fit_rms_px: float
    note: str


def _eqs_9_to_13(model: PushbroomModel, t_mid: float, z_avg: float) -> ParallelProjection:
    rs = model.motion.rotation
    vel = model.motion.velocity
    d = rs[:, 2]  # Eq 9
    if d[2] <= 0:
        raise DegenerateGeometryError("scanner looks upwards (r_s33 <= 0): no ground in view")
    y_axis = rs[:, 1]  # Eq 11
    zc = np.cross(vel, y_axis)
    nz = float(np.linalg.norm(zc))
    if nz < 1e-12 * np.linalg.norm(vel):
        raise DegenerateGeometryError("velocity is parallel to the scan line")
    z_axis = zc / nz
    x_axis = np.cross(y_axis, z_axis)
    r = np.column_stack([x_axis, y_axis, z_axis])  # Eq 10
    station = model.motion.station(t_mid)
    height = station[2] - z_avg
    if height <= 0:
        raise DegenerateGeometryError("sensor is not above the mean terrain height")
    s = rs[2, 2] * model.camera.principal_distance / height  # Eq 12
    rd = r.T @ d
    u, v = rd[0] / rd[2], rd[1] / rd[2]
    dx = s * (
        (r[0, 2] * u - r[0, 0]) * station[0]
        + (r[1, 2] * u - r[1, 0]) * station[1]
        + (r[2, 2] * u - r[2, 0]) * station[2]
    )  # Eq 13
    dy = s * (
        (r[0, 2] * v - r[0, 1]) * station[0]
        + (r[1, 2] * v - r[1, 1]) * station[1]
        + (r[2, 2] * v - r[2, 1]) * station[2]
    )
    om, ph, ka = angles_from_rotation(r)
    return ParallelProjection(float(d[0]), float(d[1]), om, ph, ka, float(s), dx, dy)


def virtual_points(
    model: PushbroomModel,
    lines: tuple[float, float],
    heights: ArrayLike,
    *,
    grid: int = 9,
) -> FloatArray:
    """Object points (n, 3) on a grid of image positions at each of ``heights`` (m).

    The grid spans ``lines`` (first, last) and every detector, ``grid`` x ``grid`` per height.
    """
    ll = np.linspace(lines[0], lines[1], grid)
    ss = np.linspace(0.0, model.camera.detectors - 1.0, grid)
    lg, sg = np.meshgrid(ll, ss, indexing="ij")
    pts = [
        model.locate(lg.ravel(), sg.ravel(), np.full(lg.size, float(h)))
        for h in np.atleast_1d(np.asarray(heights, dtype=float))
    ]
    return np.concatenate(pts, axis=0)


def scene_observations(model: PushbroomModel, frame: SceneFrame, points: ArrayLike) -> FloatArray:
    """Rigorous scene coordinates (x, y) in metres (perspective y) of object points (n, 3)."""
    lsamp = model.project(points)
    return frame.to_scene(lsamp[..., 0], lsamp[..., 1])


def parameters_from_navigation(
    model: PushbroomModel,
    *,
    line_mid: float,
    z_avg: float,
    scene_lines: float,
    height_range: float = 500.0,
    crab_tolerance_px: float = 0.05,
    allow_fallback: bool = True,
) -> NavigationParameters:
    """Paper 1 Eqs 9-13: parameters of a scene from its rigorous model and navigation.

    Args:
        model: the rigorous scanner model (camera + constant motion).
        line_mid: line coordinate of the scene's middle line; its station is (X0s, Y0s, Z0s).
        z_avg: average terrain elevation, metres (Eq 12).
        scene_lines: number of lines in the scene (for the crab error and the virtual points).
        height_range: half-range of the virtual ground points around z_avg, metres.
        crab_tolerance_px: largest acceptable predicted crab error of Eqs 10-13, pixels.
        allow_fallback: if False, a crab error above tolerance raises CrabAngleError.

    """
    if not (np.isfinite(z_avg) and np.isfinite(line_mid) and scene_lines > 0):
        raise GeometryError("line_mid, z_avg must be finite and scene_lines > 0")
    cam = model.camera
    t_mid = float(model.line_to_time(line_mid))
    nav = _eqs_9_to_13(model, t_mid, z_avg)
    vel = model.motion.velocity
    y_axis = model.motion.rotation[:, 1]
    v_perp = vel - (vel @ y_axis) * y_axis
    frame = SceneFrame(
        line_mid, nav.s * float(np.linalg.norm(v_perp)) * cam.line_period, cam.pixel_size, cam.pp
    )
    psi = roll_from_rotation(model.motion.rotation)
    duration = scene_lines * cam.line_period
    crab = model.motion.crab_angle
    crab_err = nav.s * abs(float(vel @ y_axis)) * duration / 2.0 / cam.pixel_size
    half = scene_lines / 2.0
    span = (line_mid - half, line_mid + half)
    flat = virtual_points(model, span, [z_avg])
    nav_aff = nonlinear_to_affine(nav)

    def rms_px(aff: AffineModel) -> float:
        obs = scene_observations(model, frame, flat)
        obs[:, 1] = ptp_forward(obs[:, 1], cam.principal_distance, psi)
        return float(np.sqrt(np.mean((aff.project(flat) - obs) ** 2)) / cam.pixel_size)

    if crab_err <= crab_tolerance_px:
        return NavigationParameters(
            nav,
            nav_aff,
            psi,
            frame,
            "navigation",
            crab,
            crab_err,
            rms_px(nav_aff),
            f"Eqs 9-13; crab angle {np.degrees(crab):.4g} deg within tolerance",
        )
    if not allow_fallback:
        raise CrabAngleError(
            f"crab angle {np.degrees(crab):.4g} deg: Eqs 10-13 would err by up to "
            f"{crab_err:.3g} px (> {crab_tolerance_px} px)"
        )
    pts = virtual_points(model, span, [z_avg - height_range, z_avg, z_avg + height_range])
    obs = scene_observations(model, frame, pts)
    obs[:, 1] = ptp_forward(obs[:, 1], cam.principal_distance, psi)
    design = np.column_stack([pts, np.ones(len(pts))])
    sol, *_ = np.linalg.lstsq(design, obs, rcond=None)
    aff = AffineModel.from_array(np.concatenate([sol[:, 0], sol[:, 1]]))
    inv = affine_to_nonlinear(aff, rule="reference", reference=nav)
    return NavigationParameters(
        inv.chosen,
        aff,
        psi,
        frame,
        "navigation_virtual_gcp",
        crab,
        crab_err,
        rms_px(aff),
        f"crab angle {np.degrees(crab):.4g} deg: Eqs 10-13 would err by up to {crab_err:.3g} px, "
        f"so A1..A8 were fitted to {len(pts)} virtual points of the rigorous model "
        f"({inv.rule})",
    )
