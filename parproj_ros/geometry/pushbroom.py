"""Rigorous model of a linear array (pushbroom) scanner moving with constant velocity and attitude.

Sensor frame: x along track (normal to the scan plane), y along the detector line, z up the
principal ray (away from the ground); the detector line lies at image coordinates (0, y, -c).
The scanner rotation R_s maps sensor axes to object axes (papers' convention, see rotation.py).
Object frame: local Cartesian, Z up, metres. Times in seconds.

Image coordinates: ``line`` counts scan lines from the first (line 0 exposed at time ``t0``), and
``sample`` counts detectors; both are continuous (pixel centres at integers). The perspective
scene coordinate along the scan line is ``y = (sample - principal_point) * pixel_size`` metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import DegenerateGeometryError, GeometryError
from .rotation import check_rotation

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LineCamera:
    """Interior orientation of a linear array scanner.

    Attributes:
        principal_distance: c, metres.
        pixel_size: detector pitch, metres.
        detectors: number of detectors in the line.
        line_period: time between two scan lines, seconds.
        principal_point: sample coordinate of the principal point, pixels; None = line centre.

    """

    principal_distance: float
    pixel_size: float
    detectors: int
    line_period: float
    principal_point: float | None = None

    def __post_init__(self) -> None:
        for name in ("principal_distance", "pixel_size", "line_period"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise GeometryError(f"{name} must be a finite number > 0, got {v}")
        if int(self.detectors) < 1:
            raise GeometryError(f"detectors must be >= 1, got {self.detectors}")

    @property
    def pp(self) -> float:
        """Principal point sample coordinate, pixels."""
        if self.principal_point is None:
            return (self.detectors - 1) / 2.0
        return float(self.principal_point)

    def sample_to_y(self, sample: ArrayLike) -> FloatArray:
        """Sample (pixels) -> perspective scene coordinate y (metres from the principal point)."""
        return (np.asarray(sample, dtype=float) - self.pp) * self.pixel_size

    def y_to_sample(self, y: ArrayLike) -> FloatArray:
        """Perspective scene coordinate y (m) -> sample (pixels)."""
        return np.asarray(y, dtype=float) / self.pixel_size + self.pp


@dataclass(frozen=True)
class ConstantMotion:
    """Exterior orientation: constant velocity, constant attitude.

    Attributes:
        position: exposure station at time ``t0`` (line 0), object frame, metres, shape (3,).
        velocity: object frame, metres per second, shape (3,).
        rotation: scanner rotation R_s (sensor -> object axes), shape (3, 3).
        t0: time of line 0, seconds.

    """

    position: FloatArray
    velocity: FloatArray
    rotation: FloatArray
    t0: float = 0.0

    def __post_init__(self) -> None:
        for name in ("position", "velocity"):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise GeometryError(f"{name} must be 3 finite numbers, got {v}")
            object.__setattr__(self, name, v)
        r = np.asarray(self.rotation, dtype=float)
        check_rotation(r)
        object.__setattr__(self, "rotation", r)
        if float(np.linalg.norm(self.velocity)) == 0.0:
            raise GeometryError("velocity is zero: a pushbroom scanner needs motion")

    def station(self, t: ArrayLike) -> FloatArray:
        """Exposure stations at times ``t`` (s), shape (..., 3), metres."""
        tt = np.asarray(t, dtype=float)
        return self.position + (tt[..., None] - self.t0) * self.velocity

    @property
    def crab_angle(self) -> float:
        """Angle (rad) between the velocity and the scan plane normal's plane: asin(v_hat . y_s).

        Zero when the velocity is perpendicular to the scan line (the assumption of Eqs 10-13).
        """
        v = self.velocity / np.linalg.norm(self.velocity)
        return float(np.arcsin(np.clip(v @ self.rotation[:, 1], -1.0, 1.0)))


@dataclass(frozen=True)
class PushbroomModel:
    """Rigorous pushbroom sensor model: camera (IOP) + constant motion (EOP)."""

    camera: LineCamera
    motion: ConstantMotion

    def __post_init__(self) -> None:
        sx = self.motion.rotation[:, 0]
        if abs(float(sx @ self.motion.velocity)) < 1e-9 * np.linalg.norm(self.motion.velocity):
            raise DegenerateGeometryError("velocity lies in the scan plane: lines never advance")

    def line_to_time(self, line: ArrayLike) -> FloatArray:
        """Line coordinate (continuous) -> exposure time, seconds."""
        return self.motion.t0 + np.asarray(line, dtype=float) * self.camera.line_period

    def time_to_line(self, t: ArrayLike) -> FloatArray:
        """Exposure time (s) -> line coordinate."""
        return (np.asarray(t, dtype=float) - self.motion.t0) / self.camera.line_period

    def exposure_time(self, points: ArrayLike) -> FloatArray:
        """Time (s) at which each object point (..., 3) lies in the scan plane (exact, linear)."""
        p = np.asarray(points, dtype=float)
        sx = self.motion.rotation[:, 0]
        return np.asarray(
            self.motion.t0 + ((p - self.motion.position) @ sx) / (sx @ self.motion.velocity),
            dtype=float,
        )

    def project_time_y(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Object points (..., 3) -> (exposure time s, perspective y metres) by collinearity.

        Raises:
            GeometryError: a point lies behind or level with the sensor.

        """
        p = np.asarray(points, dtype=float)
        t = self.exposure_time(p)
        rel = (p - self.motion.station(t)) @ self.motion.rotation  # sensor-frame coordinates
        if np.any(rel[..., 2] >= 0):
            raise GeometryError("a point is not in front of the scanner (sensor z >= 0)")
        y = -self.camera.principal_distance * rel[..., 1] / rel[..., 2]
        return t, np.asarray(y, dtype=float)

    def project(self, points: ArrayLike) -> FloatArray:
        """Object points (..., 3) -> image coordinates (..., 2) as (line, sample), exact."""
        t, y = self.project_time_y(points)
        return np.stack([self.time_to_line(t), self.camera.y_to_sample(y)], axis=-1)

    def ray(self, line: ArrayLike, sample: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Image coordinates -> (station, unit ray direction towards the ground), each (..., 3)."""
        t = self.line_to_time(line)
        y = self.camera.sample_to_y(sample)
        v_sensor = np.stack(
            [np.zeros_like(y), y, np.full_like(y, -self.camera.principal_distance)], axis=-1
        )
        d = v_sensor @ self.motion.rotation.T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return self.motion.station(t), d

    def locate(self, line: ArrayLike, sample: ArrayLike, height: ArrayLike) -> FloatArray:
        """Image coordinates + object height Z (m) -> object point (..., 3) on the plane Z."""
        origin, d = self.ray(line, sample)
        h = np.asarray(height, dtype=float)
        if np.any(np.abs(d[..., 2]) < 1e-12):
            raise DegenerateGeometryError("ray parallel to the horizontal plane")
        lam = (h - origin[..., 2]) / d[..., 2]
        return np.asarray(origin + lam[..., None] * d, dtype=float)
