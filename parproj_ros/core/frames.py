"""The object frame of a run's outputs: the one given, or the one its inputs are in.

The outputs (ParallelProjection, StereoPair, DSM ...) are labelled with the object frame of the
navigation and the GCP they were computed from: ``header.frame_id`` of those messages (``map``
for a simulated bag, ``enu_wgs84:lat=...,lon=...,h=...`` for an imported real pair, see
:mod:`parproj_ros.io.scene_import`). ``parproj dsm`` reads it to choose the CRS of the products.

The rule (the same for ``parproj process`` and parproj_node):

* a frame given by the user (the node's ``frame_id`` parameter, ``process_bag(frame_id=...)``)
  labels the outputs; an input in another frame is a WARN naming both;
* given none (""), the outputs are in the frame of the first input that names one (GCP, truth
  points or navigation, in the order they come); a later input in another frame is a WARN naming
  both (the outputs stay in the first); before any input names one, and if none ever does,
  :data:`DEFAULT_FRAME`.

A frame with a place on Earth is a local east-north-up tangent plane on WGS84, named
``enu_wgs84:lat=...,lon=...,h=...`` (:func:`frame_id_of`, :func:`frame_from_id`,
:func:`tangent_plane`): the frame of an imported real pair, in which a DEM's heights can be
placed (:mod:`parproj_ros.core.dem_terrain`).

Nothing here imports ROS.
"""

from __future__ import annotations

import re
import threading

from ..geometry.geodesy import LocalTangentPlane
from .results import Issue, Level

__all__ = [
    "DEFAULT_FRAME",
    "FRAME_PREFIX",
    "ObjectFrame",
    "frame_from_id",
    "frame_id_of",
    "tangent_plane",
]

#: The outputs' frame when neither the user nor any input names one.
DEFAULT_FRAME = "map"

#: The frame_id prefix of a local tangent plane on WGS84 (an imported pair's object frame).
FRAME_PREFIX = "enu_wgs84"


def frame_id_of(frame: LocalTangentPlane) -> str:
    """The frame_id naming a local tangent plane (1e-7 deg, 1 cm: exact for a rounded origin)."""
    return f"{FRAME_PREFIX}:lat={frame.lat0:.7f},lon={frame.lon0:.7f},h={frame.h0:.2f}"


def frame_from_id(frame_id: str) -> LocalTangentPlane:
    """Inverse of :func:`frame_id_of`.

    Raises:
        ValueError: not such a frame_id (or an origin that cannot be: latitude beyond +-90 deg,
            a figure not finite).

    """
    m = re.fullmatch(
        re.escape(FRAME_PREFIX) + r":lat=([-+0-9.eE]+),lon=([-+0-9.eE]+),h=([-+0-9.eE]+)",
        frame_id.strip(),
    )
    if m is None:
        raise ValueError(f"not a local tangent plane frame_id: {frame_id!r}")
    return LocalTangentPlane(float(m.group(1)), float(m.group(2)), float(m.group(3)))


def tangent_plane(frame_id: str) -> LocalTangentPlane | None:
    """The tangent plane a frame_id names; None for a frame with no place on Earth (``map``).

    A frame_id of the ``enu_wgs84:`` form that does not parse has no place on Earth either.
    """
    if not frame_id.strip().startswith(FRAME_PREFIX + ":"):
        return None
    try:
        return frame_from_id(frame_id)
    except ValueError:
        return None


class ObjectFrame:
    """Chooses the outputs' frame_id from the one given and the inputs' (thread-safe).

    Args:
        given: the frame the user asked for; "" (or blanks) = the inputs' frame.
    """

    def __init__(self, given: str = "") -> None:
        self.given = given.strip()
        self.seen: str | None = None
        self.source = ""
        self._warned: set[tuple[str, str]] = set()
        self._lock = threading.Lock()

    @property
    def frame_id(self) -> str:
        """The outputs' frame: the given one, else the inputs' first, else ``map``."""
        return self.given or self.seen or DEFAULT_FRAME

    def observe(self, where: str, frame_id: str) -> list[Issue]:
        """Note that the input ``where`` (a topic) is in ``frame_id``.

        Returns:
            A WARN (once per input and frame) when it is not the outputs' frame; [] otherwise,
            and for an input that names no frame ("").
        """
        frame = str(frame_id).strip()
        if not frame:
            return []
        with self._lock:
            if not self.given and self.seen is None:
                self.seen, self.source = frame, where
                return []
            current = self.frame_id
            if frame == current or (where, frame) in self._warned:
                return []
            self._warned.add((where, frame))
            why = (
                "given by the user"
                if self.given
                else f"the frame of {self.source}, which came first"
            )
        return [
            Issue(
                Level.WARN,
                where,
                f"input in frame {frame!r}, the outputs are in {current!r} ({why}): its "
                "coordinates are taken as they are; give inputs in one frame",
            )
        ]
