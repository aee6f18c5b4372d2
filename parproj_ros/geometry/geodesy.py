"""WGS84 geodesy: geodetic <-> ECEF, and the local tangent plane (east, north, up) frame.

The object frame of the parallel projection model of a real scene is a local tangent plane (Z up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: WGS84 semi-major axis (m) and flattening.
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
_B = WGS84_A * (1.0 - WGS84_F)
_E2 = WGS84_F * (2.0 - WGS84_F)
_EP2 = _E2 / (1.0 - _E2)


def ecef_from_geodetic(
    lon_deg: ArrayLike, lat_deg: ArrayLike, h_m: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """WGS84 geodetic (lon, lat degrees; h metres above the ellipsoid) -> ECEF X, Y, Z metres."""
    lon, lat, h = np.broadcast_arrays(
        np.radians(np.asarray(lon_deg, dtype=np.float64)),
        np.radians(np.asarray(lat_deg, dtype=np.float64)),
        np.asarray(h_m, dtype=np.float64),
    )
    s, c = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - _E2 * s * s)
    return (
        (n + h) * c * np.cos(lon),
        (n + h) * c * np.sin(lon),
        (n * (1.0 - _E2) + h) * s,
    )


def geodetic_from_ecef(
    x: ArrayLike, y: ArrayLike, z: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """ECEF X, Y, Z metres -> WGS84 (lon deg, lat deg, h metres above the ellipsoid).

    Bowring's iteration on the parametric latitude, four rounds: errors below 1e-13 deg and 1e-7 m
    from 6000 km below the surface out to geostationary distances (undefined at the centre).
    """
    xb, yb, zb = np.broadcast_arrays(
        np.asarray(x, dtype=np.float64),
        np.asarray(y, dtype=np.float64),
        np.asarray(z, dtype=np.float64),
    )
    p = np.hypot(xb, yb)
    beta = np.arctan2(zb, (1.0 - WGS84_F) * p)
    for _ in range(4):
        lat = np.arctan2(zb + _EP2 * _B * np.sin(beta) ** 3, p - _E2 * WGS84_A * np.cos(beta) ** 3)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    lat = np.arctan2(zb + _EP2 * _B * np.sin(beta) ** 3, p - _E2 * WGS84_A * np.cos(beta) ** 3)
    s = np.sin(lat)
    h = p * np.cos(lat) + zb * s - WGS84_A * np.sqrt(1.0 - _E2 * s * s)
    return np.degrees(np.arctan2(yb, xb)), np.degrees(lat), h


@dataclass(frozen=True)
class LocalTangentPlane:
    """A local east-north-up Cartesian frame on WGS84 (the object frame, Z up, metres).

    Origin at geodetic (lat0, lon0, h0); X east, Y north, Z along the ellipsoid normal at the
    origin. Exact (a rotation and a translation of ECEF).

    Attributes:
        lat0: origin latitude, degrees.
        lon0: origin longitude, degrees.
        h0: origin height above the WGS84 ellipsoid, metres.

    """

    lat0: float
    lon0: float
    h0: float = 0.0
    origin_ecef: FloatArray = field(init=False, repr=False)
    rotation: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("lat0", "lon0", "h0"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if not (-90.0 <= self.lat0 <= 90.0 and math.isfinite(self.lon0 + self.h0)):
            raise ValueError(f"bad origin ({self.lat0}, {self.lon0}, {self.h0})")
        o = np.array([float(v) for v in ecef_from_geodetic(self.lon0, self.lat0, self.h0)])
        lat, lon = math.radians(self.lat0), math.radians(self.lon0)
        sl, cl, sp, cp = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
        r = np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])
        o.setflags(write=False)
        r.setflags(write=False)
        object.__setattr__(self, "origin_ecef", o)
        object.__setattr__(self, "rotation", r)  # rows: east, north, up in ECEF

    def to_local(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, h_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Geodetic (lon deg, lat deg, h m ellipsoidal) -> (X east, Y north, Z up), metres."""
        x, y, z = ecef_from_geodetic(lon_deg, lat_deg, h_m)
        d = np.stack([x, y, z], axis=-1) - self.origin_ecef
        e = d @ self.rotation.T
        return e[..., 0], e[..., 1], e[..., 2]

    def to_geodetic(
        self, x: ArrayLike, y: ArrayLike, z: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(X east, Y north, Z up) metres -> geodetic (lon deg, lat deg, h m ellipsoidal)."""
        xb, yb, zb = np.broadcast_arrays(
            np.asarray(x, dtype=np.float64),
            np.asarray(y, dtype=np.float64),
            np.asarray(z, dtype=np.float64),
        )
        ecef = np.stack([xb, yb, zb], axis=-1) @ self.rotation + self.origin_ecef
        return geodetic_from_ecef(ecef[..., 0], ecef[..., 1], ecef[..., 2])
