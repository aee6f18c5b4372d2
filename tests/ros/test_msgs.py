"""parproj_msgs (msg_defs/): declared fields, CDR round trips, constants, field checks, comments.

The package is built into the venv by `./dev setup`; these tests need no ROS graph (no rclpy.init,
no DDS traffic): rclpy.serialization works on the type support alone.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from typing import TypeVar

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Quaternion
from parproj_msgs.msg import (
    ElevationGrid,
    GroundControlPoint,
    GroundControlPoints,
    ImageObservation,
    NormalizedBlock,
    ParallelProjection,
    ScannerInfo,
    StereoPair,
)
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Header
from testkit.paths import MSG_DIR

pytestmark = pytest.mark.ros  # the built parproj_msgs interfaces

M = TypeVar("M")

ALL_TYPES = (
    ScannerInfo,
    ImageObservation,
    GroundControlPoint,
    GroundControlPoints,
    ParallelProjection,
    StereoPair,
    NormalizedBlock,
    ElevationGrid,
)

# The interface contract (issue brief): field name -> rosidl type, in declaration order.
EXPECTED_FIELDS: dict[type, dict[str, str]] = {
    ScannerInfo: {
        "header": "std_msgs/Header",
        "camera_name": "string",
        "principal_distance": "double",
        "pixel_size": "double",
        "detectors": "uint32",
        "principal_point": "double",
        "line_period": "double",
        "mounting": "geometry_msgs/Quaternion",
    },
    ImageObservation: {"scene_id": "string", "line": "double", "sample": "double"},
    GroundControlPoint: {
        "id": "string",
        "position": "geometry_msgs/Point",
        "check_point": "boolean",
        "observations": "sequence<parproj_msgs/ImageObservation>",
    },
    GroundControlPoints: {
        "header": "std_msgs/Header",
        "points": "sequence<parproj_msgs/GroundControlPoint>",
    },
    ParallelProjection: {
        "header": "std_msgs/Header",
        "scene_id": "string",
        "view": "string",
        "first_line_time": "builtin_interfaces/Time",
        "last_line_time": "builtin_interfaces/Time",
        "lines": "uint32",
        "detectors": "uint32",
        **dict.fromkeys(["l", "m", "n", "omega", "phi", "kappa", "s", "dx", "dy"], "double"),
        "affine": "double[8]",
        "roll_psi": "double",
        "principal_distance": "double",
        "pixel_size": "double",
        "line_mid": "double",
        "x_per_line": "double",
        "principal_point": "double",
        "method": "uint8",
        "method_note": "string",
        "sigma0_px": "double",
        "residual_rms_px": "double",
        "residual_max_px": "double",
        "gcp_count": "uint32",
        "check_count": "uint32",
        "check_rms_px": "double",
        "covariance": "double[81]",
        "crab_angle": "double",
        "segment_of": "string",
        "segment_first_line": "uint32",
        "model_error_bound_px": "double",
    },
    StereoPair: {
        "header": "std_msgs/Header",
        "pair_id": "string",
        "left": "sensor_msgs/Image",
        "right": "sensor_msgs/Image",
        "width": "uint32",
        "height": "uint32",
        "streamed": "boolean",
        "left_params": "parproj_msgs/ParallelProjection",
        "right_params": "parproj_msgs/ParallelProjection",
        "left_to_normalized": "double[6]",
        "right_to_normalized": "double[6]",
        "kappa_n": "double",
        "s_n": "double",
        "normalized_pixel_size": "double",
        "left_x_origin": "double",
        "right_x_origin": "double",
        "y_origin": "double",
        "parallax_per_height": "double",
        "parallax_offset": "double",
        "height_per_disparity_px": "double",
        "height_offset_m": "double",
        "y_parallax_mean_px": "double",
        "y_parallax_rms_px": "double",
        "y_parallax_max_px": "double",
        "y_parallax_points": "uint32",
        "y_parallax_source": "string",
    },
    NormalizedBlock: {
        "header": "std_msgs/Header",
        "pair_id": "string",
        "side": "string",
        "col0": "uint32",
        "full_width": "uint32",
        "full_height": "uint32",
        "pixel_size": "double",
        "x_origin": "double",
        "y_origin": "double",
        "index": "uint32",
        "last": "boolean",
        "image": "sensor_msgs/Image",
    },
    ElevationGrid: {
        "header": "std_msgs/Header",
        "pair_id": "string",
        "x0": "double",
        "y0": "double",
        "cell_size": "double",
        "heights": "sensor_msgs/Image",
        "ortho": "sensor_msgs/Image",
        "filled_cells": "uint32",
        "max_fill_cells": "float",
        "completeness": "float",
        "disparity_min": "int32",
        "disparity_max": "int32",
        "matched_share": "float",
        "height_per_disparity_px": "double",
        "height_offset_m": "double",
        "terrain_min_m": "double",
        "terrain_max_m": "double",
        "terrain_source": "string",
        "terrain_points": "uint32",
    },
}


def round_trip(msg: M) -> M:
    data = serialize_message(msg)
    assert isinstance(data, bytes) and len(data) > 0
    return deserialize_message(data, type(msg))


def header(frame: str, sec: int = 1_700_000_000, nanosec: int = 123_456_789) -> Header:
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame)


def scanner_info() -> ScannerInfo:
    return ScannerInfo(
        header=header("ikonos_pan"),
        camera_name="ikonos_pan",
        principal_distance=10.0,
        pixel_size=12e-6,
        detectors=13816,
        principal_point=6907.5,
        line_period=1.0 / 6500.0,
        mounting=Quaternion(x=0.0, y=0.0, z=0.7071067811865476, w=0.7071067811865476),
    )


def ground_control_points() -> GroundControlPoints:
    points = []
    for i in range(3):
        obs = [
            ImageObservation(scene_id=f"scene_{k}", line=100.25 + 7 * i + k, sample=5000.5 - i)
            for k in range(i)  # 0, 1 and 2 observations: empty and non-empty nested arrays
        ]
        points.append(
            GroundControlPoint(
                id=f"P{i}",
                position=Point(x=-5500.0 + i, y=3.25 * i, z=-58.4 + 1000.0 * i),
                check_point=(i == 2),
                observations=obs,
            )
        )
    return GroundControlPoints(header=header("local_enu"), points=points)


def parallel_projection(scene_id: str, view: str, seed: int) -> ParallelProjection:
    rng = np.random.default_rng(seed)
    return ParallelProjection(
        header=header("local_enu", 1_000, 500),
        scene_id=scene_id,
        view=view,
        first_line_time=Time(sec=1_000, nanosec=500),
        last_line_time=Time(sec=1_002, nanosec=999_999_999),
        lines=17_000,
        detectors=13816,
        l=0.0,
        m=-0.0871557427476582,
        n=0.9961946980917455,
        omega=0.0872664625997165,
        phi=-1e-3,
        kappa=3.0,
        s=1.47e-5,
        dx=3.26e-4,
        dy=-2.5e-3,
        affine=rng.normal(size=8),
        roll_psi=-0.1,
        principal_distance=10.0,
        pixel_size=12e-6,
        line_mid=8500.5,
        x_per_line=1.2e-5,
        principal_point=6907.5,
        method=ParallelProjection.METHOD_GCP_ROLL_ESTIMATED,
        method_note="Eq 8, 16 GCP, 9 check points",
        sigma0_px=1.41,
        residual_rms_px=1.2,
        residual_max_px=2.9,
        gcp_count=16,
        check_count=9,
        check_rms_px=1.7,
        covariance=rng.normal(size=81),
        crab_angle=-2e-4,
        segment_of="pan_scene_0000",
        segment_first_line=12000,
        model_error_bound_px=0.5,
    )


def image(seed: int) -> Image:
    rng = np.random.default_rng(seed)
    pixels = rng.integers(0, 65535, size=(4, 5), dtype=np.uint16)
    return Image(
        header=header("normalized", 42, 7),
        height=4,
        width=5,
        encoding="mono16",
        is_bigendian=0,
        step=10,
        data=pixels.tobytes(),
    )


def stereo_pair() -> StereoPair:
    return StereoPair(
        header=header("normalized", 42, 7),
        pair_id="ikonos_fore_aft",
        left=image(1),
        right=image(2),
        left_params=parallel_projection("left_scene", "left", 3),
        right_params=parallel_projection("right_scene", "right", 4),
        left_to_normalized=[0.9, -0.1, 1e-3, 0.1, 0.9, -2e-3],
        right_to_normalized=np.array([1.1, 0.2, -1e-3, -0.2, 1.1, 2e-3]),
        kappa_n=1.2,
        s_n=1.47e-5,
        normalized_pixel_size=12e-6,
        left_x_origin=-0.08,
        right_x_origin=-0.07,
        y_origin=-0.06,
        parallax_per_height=1.15e-5,
        parallax_offset=3e-4,
        height_per_disparity_px=1.043,
        height_offset_m=-26.1,
        y_parallax_mean_px=0.01,
        y_parallax_rms_px=0.059,
        y_parallax_max_px=0.188,
        y_parallax_points=25,
        y_parallax_source="gcp",
    )


@pytest.mark.parametrize("msg_type", ALL_TYPES, ids=lambda t: t.__name__)
def test_declared_fields_match_the_contract(msg_type: type) -> None:
    declared = msg_type.get_fields_and_field_types()  # type: ignore[attr-defined]
    assert list(declared.items()) == list(EXPECTED_FIELDS[msg_type].items())


def test_scanner_info_round_trip() -> None:
    msg = scanner_info()
    back = round_trip(msg)
    assert back == msg
    assert back.detectors == 13816 and back.pixel_size == 12e-6
    assert back.mounting.z == msg.mounting.z and back.header.frame_id == "ikonos_pan"


def test_image_observation_round_trip() -> None:
    msg = ImageObservation(scene_id="left_scene", line=-0.5, sample=13815.499)
    assert round_trip(msg) == msg


def test_ground_control_points_round_trip_with_nested_observations() -> None:
    msg = ground_control_points()
    back = round_trip(msg)
    assert back == msg
    assert [len(p.observations) for p in back.points] == [0, 1, 2]
    assert [p.check_point for p in back.points] == [False, False, True]
    last = back.points[2].observations[1]
    assert (last.scene_id, last.line, last.sample) == ("scene_1", 115.25, 4998.5)
    assert back.points[1].position == Point(x=-5499.0, y=3.25, z=941.6)
    assert round_trip(GroundControlPoint(id="alone")) == GroundControlPoint(id="alone")


def test_parallel_projection_round_trip_with_fixed_arrays() -> None:
    msg = parallel_projection("left_scene", "left", 0)
    back = round_trip(msg)
    assert back == msg
    assert back.affine.shape == (8,) and back.covariance.shape == (81,)
    np.testing.assert_array_equal(back.affine, msg.affine)  # bit-exact
    np.testing.assert_array_equal(back.covariance.reshape(9, 9), msg.covariance.reshape(9, 9))
    assert back.first_line_time == Time(sec=1_000, nanosec=500)
    assert back.header.stamp == back.first_line_time


def test_parallel_projection_nan_fields_survive() -> None:
    msg = parallel_projection("s", "aft", 1)
    msg.check_rms_px = math.nan  # no check points
    msg.sigma0_px = math.nan  # navigation: not adjusted
    msg.check_count = 0
    back = round_trip(msg)
    assert math.isnan(back.check_rms_px) and math.isnan(back.sigma0_px)
    assert back.check_count == 0 and back.crab_angle == msg.crab_angle


def test_parallel_projection_defaults_are_zero_arrays() -> None:
    msg = ParallelProjection()
    assert msg.affine.shape == (8,) and not msg.affine.any()
    assert msg.covariance.shape == (81,) and not msg.covariance.any()
    assert msg.method == ParallelProjection.METHOD_NAVIGATION


def test_stereo_pair_round_trip() -> None:
    msg = stereo_pair()
    back = round_trip(msg)
    assert back == msg
    np.testing.assert_array_equal(back.left_to_normalized, msg.left_to_normalized)
    np.testing.assert_array_equal(
        back.right_to_normalized.reshape(2, 3), [[1.1, 0.2, -1e-3], [-0.2, 1.1, 2e-3]]
    )
    np.testing.assert_array_equal(
        back.left_params.covariance, parallel_projection("x", "left", 3).covariance
    )
    assert back.right_params.view == "right" and back.right_params.scene_id == "right_scene"
    restored = np.frombuffer(back.left.data, dtype=np.uint16).reshape(back.left.height, -1)
    np.testing.assert_array_equal(
        restored, np.random.default_rng(1).integers(0, 65535, size=(4, 5), dtype=np.uint16)
    )
    assert back.left.header.stamp == back.right.header.stamp == back.header.stamp


def test_method_constants() -> None:
    expected = {
        "METHOD_NAVIGATION": 0,
        "METHOD_NAVIGATION_VIRTUAL_GCP": 1,
        "METHOD_GCP_AFFINE": 2,
        "METHOD_GCP_KNOWN_ROLL": 3,
        "METHOD_GCP_ROLL_ESTIMATED": 4,
        "METHOD_TIE_POINTS": 5,
    }
    for name, value in expected.items():
        assert getattr(ParallelProjection, name) == value
    consts = {k for k in dir(ParallelProjection) if k.startswith("METHOD_")}
    assert consts == set(expected)


@pytest.mark.parametrize(
    ("msg_type", "field", "size"),
    [
        (ParallelProjection, "affine", 8),
        (ParallelProjection, "covariance", 81),
        (StereoPair, "left_to_normalized", 6),
        (StereoPair, "right_to_normalized", 6),
    ],
)
def test_wrong_length_fixed_array_is_rejected(msg_type: type, field: str, size: int) -> None:
    for bad in ([0.0] * (size - 1), [0.0] * (size + 1), np.zeros(size - 1)):
        with pytest.raises(AssertionError):
            msg_type(**{field: bad, "check_fields": True})
        msg = msg_type(check_fields=True)
        with pytest.raises(AssertionError):
            setattr(msg, field, bad)
    msg_type(**{field: [1.0] * size, "check_fields": True})  # right length accepted


CHECK_FIELDS_SCRIPT = """
from parproj_msgs.msg import ParallelProjection, StereoPair
for make in (lambda: ParallelProjection(affine=[0.0] * 7),
             lambda: StereoPair(left_to_normalized=[0.0] * 5)):
    try:
        make()
    except AssertionError:
        continue
    raise SystemExit("wrong-length fixed array accepted")
ParallelProjection().covariance = [0.0] * 81
print("ok")
"""


def test_ros_python_check_fields_env_rejects_wrong_length() -> None:
    # The generated modules read ROS_PYTHON_CHECK_FIELDS at import time, so check in a fresh
    # interpreter (inheriting this environment, as the venv's bootstrap needs).
    env = dict(os.environ, ROS_PYTHON_CHECK_FIELDS="1")
    out = subprocess.run(
        [sys.executable, "-c", CHECK_FIELDS_SCRIPT],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert out.returncode == 0, out.stderr + out.stdout
    assert out.stdout.strip().endswith("ok")


FIELD_RE = re.compile(r"^[A-Za-z][\w/]*(\[\d*\])?\s+\w+")


@pytest.mark.parametrize("msg_type", ALL_TYPES, ids=lambda t: t.__name__)
def test_msg_files_comment_every_field(msg_type: type) -> None:
    lines = (MSG_DIR / f"{msg_type.__name__}.msg").read_text(encoding="ascii").splitlines()
    assert lines[0].startswith("# "), "the file must start with a header comment"
    uncommented = []
    for i, line in enumerate(lines):
        if not FIELD_RE.match(line):
            continue
        # a field (or constant) needs a comment directly above it, possibly shared by a group of
        # consecutive fields that the comment names
        j = i - 1
        while j >= 0 and FIELD_RE.match(lines[j]):
            j -= 1
        if j < 0 or not lines[j].startswith("#"):
            uncommented.append(line)
    assert not uncommented
