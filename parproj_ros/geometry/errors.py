"""Domain errors of the geometry library: each says what was wrong and what to do about it."""

from __future__ import annotations


class GeometryError(ValueError):
    """Base class of every error raised by :mod:`parproj_ros.geometry`."""


class TooFewPointsError(GeometryError):
    """Fewer points than the model has degrees of freedom (plus the redundancy asked for)."""


class DegeneratePointsError(GeometryError):
    """Points are collinear, coplanar or otherwise leave parameters undetermined."""


class DegenerateGeometryError(GeometryError):
    """A configuration with no unique solution (zero base, parallel vectors, invalid affine)."""


class CrabAngleError(GeometryError):
    """Velocity is not perpendicular to the scan line and no fallback was allowed."""
