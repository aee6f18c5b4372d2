"""Where the outputs' object frame lies on Earth: its transform from the Earth-fixed frame.

An imported real pair's object frame is a local east-north-up plane on WGS84, named
``enu_wgs84:lat=...,lon=...,h=...`` (:func:`parproj_ros.io.scene_import.frame_id_of`): a map-aware
tool (a viewer, a map server) places the node's outputs on Earth with the rigid transform from
ECEF (WGS84 Earth-centred, Earth-fixed, metres; REP 105's ``earth`` frame) to that plane. A
simulated ``map`` frame has no place on Earth: None.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rotation import rotation_to_quaternion
from .scene_import import FRAME_PREFIX, frame_from_id

#: The Earth-fixed parent frame of the transform (REP 105).
EARTH_FRAME = "earth"


@dataclass(frozen=True)
class EarthTransform:
    """The object frame's pose in ECEF: ``p_ecef = R(q) p_local + t``.

    Attributes:
        parent: the Earth-fixed frame (:data:`EARTH_FRAME`).
        child: the object frame's frame_id.
        translation: the frame's origin in ECEF, metres (x, y, z).
        rotation: the quaternion (x, y, z, w) turning local east-north-up axes into ECEF.
        definition: the frame in words (origin latitude, longitude, ellipsoidal height).
    """

    parent: str
    child: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    definition: str


def earth_transform(frame_id: str) -> EarthTransform | None:
    """The transform from ECEF to the object frame ``frame_id``; None: no place on Earth."""
    if not frame_id.strip().startswith(FRAME_PREFIX + ":"):
        return None
    try:
        plane = frame_from_id(frame_id)
    except ValueError:
        return None
    # plane.rotation's rows are the local axes in ECEF: its transpose maps local to ECEF.
    q = rotation_to_quaternion(np.asarray(plane.rotation).T)
    t = plane.origin_ecef
    return EarthTransform(
        EARTH_FRAME,
        frame_id.strip(),
        (float(t[0]), float(t[1]), float(t[2])),
        (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
        f"local east-north-up plane on WGS84, origin lat {plane.lat0:.7f} deg, "
        f"lon {plane.lon0:.7f} deg, h {plane.h0:.2f} m (ellipsoidal); X east, Y north, Z up, m",
    )
