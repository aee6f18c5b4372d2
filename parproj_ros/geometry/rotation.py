"""Rotations in the papers' convention, and quaternions.

Convention (shared/papers/ERRATA.md): ``R = Rx(omega) @ Ry(phi) @ Rz(kappa)`` maps sensor (or
scene) axes to object axes, i.e. its columns are the sensor axes expressed in the object frame.
omega is the roll, phi the pitch and kappa the azimuth, all in radians. The third column of a
scanner's R is the unit vector (L, M, N) pointing from the ground up to the sensor (paper 1 Eq 9).

Quaternions are (x, y, z, w) as in ROS ``geometry_msgs/Quaternion`` and rotate child-frame vectors
into the parent frame, so ``quaternion_to_rotation(q)`` is exactly such an R when the child frame
is the sensor and the parent the object frame.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError

FloatArray = NDArray[np.float64]


def rot_x(angle: float) -> FloatArray:
    """Rotation about the x axis by ``angle`` radians (right-handed, active)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> FloatArray:
    """Rotation about the y axis by ``angle`` radians (right-handed, active)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> FloatArray:
    """Rotation about the z axis by ``angle`` radians (right-handed, active)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_from_angles(omega: float, phi: float, kappa: float) -> FloatArray:
    """``R = Rx(omega) Ry(phi) Rz(kappa)``; angles in radians; maps sensor axes to object axes."""
    return rot_x(omega) @ rot_y(phi) @ rot_z(kappa)


def angles_from_rotation(rot: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_angles`: (omega, phi, kappa) in radians.

    phi is returned in [-pi/2, pi/2]; at phi = +-pi/2 (gimbal lock) kappa is set to 0 and the whole
    rotation about the common axis is put in omega. phi comes from atan2 (not asin, which loses
    half the digits near +-pi/2) and omega from ``R Rz(kappa)^T = Rx(omega) Ry(phi)``, whose
    second column is (0, cos omega, sin omega) whatever phi: accurate to rounding everywhere.
    """
    r = np.asarray(rot, dtype=float)
    check_rotation(r)
    cphi = float(np.hypot(r[0, 0], r[0, 1]))
    phi = float(np.arctan2(r[0, 2], cphi))
    kappa = 0.0 if cphi < 1e-15 else float(np.arctan2(-r[0, 1], r[0, 0]))
    m = r @ rot_z(kappa).T
    omega = float(np.arctan2(m[2, 1], m[1, 1]))
    return omega, phi, kappa


def check_rotation(rot: ArrayLike, tol: float = 1e-6) -> None:
    """Raise :class:`GeometryError` unless ``rot`` is a proper 3x3 rotation (to ``tol``)."""
    r = np.asarray(rot, dtype=float)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise GeometryError(f"rotation must be a finite 3x3 matrix, got shape {r.shape}")
    if np.abs(r.T @ r - np.eye(3)).max() > tol or abs(np.linalg.det(r) - 1.0) > tol:
        raise GeometryError("matrix is not a proper rotation (R^T R != I or det != +1)")


def quaternion_to_rotation(quat: ArrayLike) -> FloatArray:
    """Unit quaternion (x, y, z, w) -> 3x3 rotation matrix (child -> parent frame).

    Raises :class:`GeometryError` for a non-finite or zero-norm quaternion; a non-unit one is
    normalised.
    """
    q = np.asarray(quat, dtype=float).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise GeometryError(f"quaternion must be 4 finite numbers (x, y, z, w), got {q}")
    big = float(np.abs(q).max())
    if big < 1e-9:
        raise GeometryError("quaternion has zero norm: no orientation")
    q = q / big  # first bring it near 1, so that the norm cannot overflow
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quaternion(rot: ArrayLike) -> FloatArray:
    """3x3 rotation matrix -> unit quaternion (x, y, z, w) with w >= 0 (Shepperd's method)."""
    r = np.asarray(rot, dtype=float)
    check_rotation(r)
    tr = np.trace(r)
    if tr > 0:
        k = 2.0 * np.sqrt(1.0 + tr)
        q = [(r[2, 1] - r[1, 2]) / k, (r[0, 2] - r[2, 0]) / k, (r[1, 0] - r[0, 1]) / k, k / 4]
    else:
        i = int(np.argmax(np.diag(r)))
        j, m = (i + 1) % 3, (i + 2) % 3
        k = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[m, m])
        q = [0.0, 0.0, 0.0, (r[m, j] - r[j, m]) / k]
        q[i] = k / 4
        q[j] = (r[j, i] + r[i, j]) / k
        q[m] = (r[m, i] + r[i, m]) / k
    out = np.array(q, dtype=float)
    out /= np.linalg.norm(out)
    return out if out[3] >= 0 else -out
