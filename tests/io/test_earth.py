"""io/earth.py: the object frame's place on Earth, checked against the geodesy it names."""

from __future__ import annotations

import numpy as np
import pytest

from parproj_ros.geometry.geodesy import ecef_from_geodetic
from parproj_ros.geometry.rotation import quaternion_to_rotation
from parproj_ros.io.earth import EARTH_FRAME, earth_transform
from parproj_ros.io.scene_import import frame_from_id


@pytest.mark.parametrize(
    "frame_id",
    [
        "enu_wgs84:lat=44.1234567,lon=5.2345678,h=612.34",  # Ventoux-like
        "enu_wgs84:lat=43.2951000,lon=5.3810000,h=80.00",  # Marseille-like
        "enu_wgs84:lat=-33.8688000,lon=151.2093000,h=0.00",  # southern, eastern hemisphere
    ],
)
def test_transform_places_local_points_where_geodesy_does(frame_id: str) -> None:
    """p_ecef = R(q) p_local + t for points up to 10 km from the origin, within 1 mm."""
    t = earth_transform(frame_id)
    assert t is not None and t.parent == EARTH_FRAME and t.child == frame_id
    plane = frame_from_id(frame_id)
    rng = np.random.default_rng(5)
    local = rng.uniform(-10_000.0, 10_000.0, size=(50, 3)) * [1.0, 1.0, 0.1]
    ours = local @ quaternion_to_rotation(t.rotation).T + np.array(t.translation)
    lon, lat, h = plane.to_geodetic(local[:, 0], local[:, 1], local[:, 2])
    truth = np.stack(ecef_from_geodetic(lon, lat, h), axis=-1)
    assert np.abs(ours - truth).max() < 1e-3
    assert abs(np.linalg.norm(t.rotation) - 1.0) < 1e-12
    assert f"lat {plane.lat0:.7f}" in t.definition


@pytest.mark.parametrize("frame_id", ["map", "", "enu_wgs84:lat=north", "utm31n"])
def test_frames_with_no_place_on_earth(frame_id: str) -> None:
    assert earth_transform(frame_id) is None
