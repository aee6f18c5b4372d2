"""Message <-> array conversions (parproj_ros.ros.conversions); no ROS graph needed."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from parproj_msgs.msg import GroundControlPoints, ParallelProjection
from sensor_msgs.msg import Image
from testkit.paths import BAGS

from parproj_ros.apps.process import process_bag
from parproj_ros.core.results import METHODS, GroundPoint, SceneResult
from parproj_ros.core.trajectory import NavSample
from parproj_ros.geometry import ParallelProjection as GeomParallelProjection
from parproj_ros.geometry import nonlinear_to_affine, rotation_from_angles
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader

pytestmark = pytest.mark.ros  # message classes and bags

STAMP = 1_700_000_123 * 1_000_000_000 + 456_789


def image(encoding: str, h: int, w: int, step: int, data: bytes, bigendian: int = 0) -> Image:
    m = Image()
    m.encoding, m.height, m.width, m.step, m.is_bigendian = encoding, h, w, step, bigendian
    m.data = data
    return m


# ---- images -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("dtype", "encoding", "values"),
    [
        (np.uint8, "mono8", [0, 1, 127, 255]),
        (np.uint16, "mono16", [0, 1, 256, 65535]),
        (np.float32, "32FC1", [-1.5e30, 0.1, 3.0e-38, np.inf]),
    ],
)
def test_image_round_trip(dtype: type, encoding: str, values: list[float]) -> None:
    rng = np.random.default_rng(1)
    arr = rng.permutation(np.resize(np.array(values, dtype=dtype), 7 * 5)).reshape(7, 5)
    arr[3, 2] = values[-1]
    msg = conv.array_to_image(arr, Image(), frame_id="left_scene_0003", stamp_ns=STAMP)
    assert msg.encoding == encoding
    assert (msg.height, msg.width, msg.step) == (7, 5, 5 * np.dtype(dtype).itemsize)
    assert msg.is_bigendian == 0
    assert msg.header.frame_id == "left_scene_0003"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_123, 456_789)
    assert conv.stamp_to_ns(msg.header.stamp) == STAMP
    back = conv.image_to_array(msg)
    assert back.dtype == np.dtype(dtype) and back.shape == (7, 5)
    np.testing.assert_array_equal(back, arr)
    # Little-endian bytes on the wire, whatever the machine.
    assert bytes(msg.data) == arr.astype(np.dtype(dtype).newbyteorder("<")).tobytes()


def test_float32_nan_survives_round_trip() -> None:
    arr = np.array([[np.nan, 1.0], [2.0, -0.0]], np.float32)
    back = conv.image_to_array(conv.array_to_image(arr, Image(), frame_id="f", stamp_ns=0))
    assert np.isnan(back[0, 0]) and back[1, 0] == 2.0 and np.signbit(back[1, 1])


def test_rgb8() -> None:
    arr = np.random.default_rng(2).integers(0, 256, (4, 6, 3), dtype=np.uint8)
    msg = conv.array_to_image(arr, Image(), frame_id="a", stamp_ns=5, encoding="rgb8")
    assert (msg.encoding, msg.height, msg.width, msg.step) == ("rgb8", 4, 6, 18)
    back = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, 3)
    np.testing.assert_array_equal(back, arr)
    with pytest.raises(conv.ConversionError, match="rgb8 needs"):
        conv.array_to_image(arr[..., 0], Image(), frame_id="a", stamp_ns=5, encoding="rgb8")
    with pytest.raises(conv.ConversionError, match="rgb8 needs"):
        conv.array_to_image(
            arr.astype(np.uint16), Image(), frame_id="a", stamp_ns=5, encoding="rgb8"
        )


@pytest.mark.parametrize(
    "arr",
    [np.zeros((2, 2), np.int32), np.zeros((2, 2), np.float64), np.zeros((2, 2, 3), np.uint8)],
)
def test_array_to_image_rejects_other_arrays(arr: np.ndarray) -> None:
    with pytest.raises(conv.ConversionError, match="cannot encode"):
        conv.array_to_image(arr, Image(), frame_id="a", stamp_ns=0)


def test_padded_rows() -> None:
    arr = np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000 + 7
    pad = b"\xee" * 6
    data = b"".join(row.astype("<u2").tobytes() + pad for row in arr)
    msg = image("mono16", 3, 4, 14, data)
    out = conv.image_to_array(msg)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, arr)
    # Odd padding for float32 (step not a multiple of 4) and extra bytes at the end.
    f = np.linspace(-1, 1, 6, dtype=np.float32).reshape(2, 3)
    data = b"".join(row.tobytes() + b"\x01" for row in f) + b"junk"
    np.testing.assert_array_equal(conv.image_to_array(image("32FC1", 2, 3, 13, data)), f)


def test_big_endian_mono16() -> None:
    arr = np.array([[1, 256, 258], [65534, 4096, 0]], dtype=np.uint16)
    msg = image("mono16", 2, 3, 6, arr.astype(">u2").tobytes(), bigendian=1)
    out = conv.image_to_array(msg)
    assert out.dtype == np.dtype(np.uint16)
    np.testing.assert_array_equal(out, arr)
    # The same bytes read as little-endian are byte-swapped values.
    msg.is_bigendian = 0
    np.testing.assert_array_equal(conv.image_to_array(msg), arr.byteswap())


def test_big_endian_float32_with_padding() -> None:
    arr = np.array([[1.5, -2.25], [1e10, 3.0]], dtype=np.float32)
    data = b"".join(row.astype(">f4").tobytes() + b"\0\0" for row in arr)
    np.testing.assert_array_equal(
        conv.image_to_array(image("32FC1", 2, 2, 10, data, bigendian=1)), arr
    )


@pytest.mark.parametrize(
    ("msg", "text"),
    [
        (image("bgr8", 2, 2, 6, bytes(12)), "unsupported encoding 'bgr8'"),
        (image("bayer_rggb8", 2, 2, 2, bytes(4)), "unsupported encoding 'bayer_rggb8'"),
        (image("mono16", 2, 4, 7, bytes(14)), "step 7 < width 4 x 2 bytes"),
        (image("mono8", 3, 4, 4, bytes(11)), "data has 11 bytes, step x height needs 12"),
        (image("32FC1", 2, 2, 8, bytes(15)), "data has 15 bytes"),
        (image("mono8", 0, 4, 4, b""), "empty image"),
        (image("mono8", 3, 0, 0, b""), "empty image"),
    ],
)
def test_image_to_array_errors(msg: Image, text: str) -> None:
    with pytest.raises(conv.ConversionError, match=text):
        conv.image_to_array(msg)


def test_aliases_8uc1_16uc1() -> None:
    arr = np.array([[1, 2]], np.uint16)
    out = conv.image_to_array(image("16UC1", 1, 2, 4, arr.tobytes()))
    np.testing.assert_array_equal(out, arr)
    assert conv.image_to_array(image("8UC1", 1, 2, 2, b"\x05\x06")).tolist() == [[5, 6]]


# ---- odometry -----------------------------------------------------------------------------------


def _nav_sample() -> NavSample:
    rot = rotation_from_angles(np.radians(-5.0), np.radians(17.0), np.radians(30.0))
    return NavSample(
        STAMP, np.array([-299_123.5, 59_491.25, 680_000.0]), rot, np.array([7000.0, 10.0, -3.0])
    )


def test_odometry_round_trip_velocity_in_child_frame() -> None:
    s = _nav_sample()
    msg = conv.sample_to_odometry(s, Odometry(), frame_id="map", child_frame_id="base_link")
    assert (msg.header.frame_id, msg.child_frame_id) == ("map", "base_link")
    assert conv.stamp_to_ns(msg.header.stamp) == STAMP
    p = msg.pose.pose.position
    assert (p.x, p.y, p.z) == (-299_123.5, 59_491.25, 680_000.0)
    lin = msg.twist.twist.linear
    np.testing.assert_allclose([lin.x, lin.y, lin.z], s.rotation.T @ s.velocity, atol=1e-9)
    assert abs(lin.x - 7000.0) > 100.0  # really the body frame, not the object frame
    o = msg.pose.pose.orientation
    assert math.isclose(o.x**2 + o.y**2 + o.z**2 + o.w**2, 1.0, rel_tol=1e-12)
    back = conv.odometry_to_sample(msg)
    assert back.t_ns == STAMP
    np.testing.assert_array_equal(back.position, s.position)
    np.testing.assert_allclose(back.rotation, s.rotation, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.velocity, s.velocity, rtol=0, atol=1e-9)


@pytest.mark.parametrize("field", ["position.y", "orientation.w", "twist"])
def test_odometry_non_finite_rejected(field: str) -> None:
    msg = conv.sample_to_odometry(_nav_sample(), Odometry(), frame_id="map", child_frame_id="b")
    if field == "position.y":
        msg.pose.pose.position.y = float("nan")
    elif field == "orientation.w":
        msg.pose.pose.orientation.w = float("nan")
    else:
        msg.twist.twist.linear.z = float("inf")
    with pytest.raises(conv.ConversionError, match="navigation sample rejected"):
        conv.odometry_to_sample(msg)


def test_odometry_zero_quaternion_rejected() -> None:
    msg = Odometry()
    msg.pose.pose.orientation.w = 0.0
    with pytest.raises(conv.ConversionError, match="zero norm"):
        conv.odometry_to_sample(msg)


# ---- GCP ----------------------------------------------------------------------------------------


def test_gcp_round_trip() -> None:
    pts = [
        GroundPoint(
            "g01",
            np.array([1520.3, -880.0, 412.7]),
            False,
            {"left_0000": (1033.25, 517.5), "right_0000": (998.0, 520.125)},
        ),
        GroundPoint("c01", np.array([-1.0e5, 2.5, -58.4]), True, {"left_0000": (0.0, 767.0)}),
        GroundPoint("lonely", np.array([0.0, 0.0, 0.0]), False, {}),
    ]
    msg = conv.gcp_to_msg(pts, GroundControlPoints(), frame_id="map", stamp_ns=STAMP)
    assert msg.header.frame_id == "map" and conv.stamp_to_ns(msg.header.stamp) == STAMP
    assert [p.id for p in msg.points] == ["g01", "c01", "lonely"]
    assert [len(p.observations) for p in msg.points] == [2, 1, 0]
    assert msg.points[1].check_point is True
    back = conv.gcp_from_msg(msg)
    assert len(back) == 3
    for a, b in zip(pts, back, strict=True):
        assert a.id == b.id and a.check == b.check
        np.testing.assert_array_equal(a.xyz, b.xyz)
        assert a.observations == b.observations


# ---- ParallelProjection from a processed bag ----------------------------------------------------


def _process(name: str, dst: Path) -> tuple[list[SceneResult], list[ParallelProjection]]:
    results: list[SceneResult] = []
    summary = process_bag(
        BAGS / name, dst, progress=False, on_outputs=lambda out: results.extend(out.scenes)
    )
    assert summary.scenes == 2 and summary.pairs == 1
    msgs = [m.msg for m in BagReader(dst).messages(topics=["parallel_projection"])]
    return results, msgs


@pytest.fixture(scope="module")
def airborne(tmp_path_factory: pytest.TempPathFactory):
    return _process("airborne_foreaft", tmp_path_factory.mktemp("conv") / "airborne")


@pytest.fixture(scope="module")
def ikonos(tmp_path_factory: pytest.TempPathFactory):
    return _process("ikonos_agile", tmp_path_factory.mktemp("conv") / "ikonos")


def _check_against_result(msg: ParallelProjection, res: SceneResult) -> None:
    """Every field of the message, from the SceneResult it was made of."""
    sc = res.scene
    assert msg.header.frame_id == "map"
    assert conv.stamp_to_ns(msg.header.stamp) == sc.first_line_ns
    assert (msg.scene_id, msg.view) == (sc.scene_id, sc.view)
    assert conv.stamp_to_ns(msg.first_line_time) == sc.first_line_ns
    assert conv.stamp_to_ns(msg.last_line_time) == sc.first_line_ns + round(
        (sc.lines - 1) * sc.line_period * 1e9
    )
    assert (msg.lines, msg.detectors) == (sc.lines, sc.detectors)
    p = res.params
    assert (msg.l, msg.m, msg.n) == (p.L, p.M, p.N)
    assert (msg.omega, msg.phi, msg.kappa) == (p.omega, p.phi, p.kappa)
    assert (msg.s, msg.dx, msg.dy) == (p.s, p.dx, p.dy)
    assert list(msg.affine) == list(res.affine.A)
    assert msg.roll_psi == res.psi
    assert msg.principal_distance == res.camera.principal_distance
    assert msg.pixel_size == res.frame.pixel_size == res.camera.pixel_size
    assert msg.line_mid == res.frame.line_mid == (sc.lines - 1) / 2
    assert msg.x_per_line == res.frame.x_per_line
    assert msg.principal_point == res.frame.principal_point == res.camera.pp
    assert msg.method == METHODS.index(res.method)
    assert msg.method_note == res.note and msg.method_note
    for name in ("sigma0_px", "residual_rms_px", "residual_max_px", "check_rms_px"):
        a, b = getattr(msg, name), getattr(res, name)
        assert a == b or (math.isnan(a) and math.isnan(b)), name
    assert (msg.gcp_count, msg.check_count) == (res.gcp_count, res.check_count)
    assert list(msg.covariance) == list(np.asarray(res.covariance).ravel())
    assert msg.crab_angle == res.crab_angle


def _check_consistent(msg: ParallelProjection) -> None:
    assert math.isclose(msg.l**2 + msg.m**2 + msg.n**2, 1.0, rel_tol=0, abs_tol=1e-12)
    assert msg.n > 0
    pp = GeomParallelProjection(msg.l, msg.m, msg.omega, msg.phi, msg.kappa, msg.s, msg.dx, msg.dy)
    a = nonlinear_to_affine(pp).array
    np.testing.assert_allclose(np.array(msg.affine), a, rtol=1e-9, atol=1e-9 * np.abs(a).max())
    assert math.isfinite(msg.crab_angle)
    assert len(msg.covariance) == 81
    assert msg.s > 0 and msg.x_per_line > 0
    assert msg.principal_distance > 0 and msg.pixel_size > 0


def test_scene_to_msg_navigation(airborne) -> None:
    results, msgs = airborne
    assert len(msgs) == 2 and len(results) == 2
    for msg, res in zip(msgs, results, strict=True):
        _check_against_result(msg, res)
        _check_consistent(msg)
        assert msg.method == ParallelProjection.METHOD_NAVIGATION
        assert (msg.lines, msg.detectors) == (768, 768)
        assert msg.principal_distance == 0.3 and msg.pixel_size == 6.5e-6
        assert msg.roll_psi == 0.0  # level flight, no roll
        assert math.isnan(msg.sigma0_px)  # not adjusted
        assert (msg.gcp_count, msg.check_count) == (0, 0) and math.isnan(msg.check_rms_px)
        assert not any(msg.covariance)
        assert abs(msg.crab_angle) < 1e-12
    assert [m.view for m in msgs] == ["left", "right"]
    assert [m.scene_id for m in msgs] == ["left_scene_0000", "right_scene_0001"]
    # Fore camera looks forward (l < 0: projection vector towards -X), aft camera backward.
    assert msgs[0].l < -0.2 and msgs[1].l > 0.2
    assert math.isclose(msgs[0].l, -msgs[1].l, rel_tol=1e-9)


@pytest.mark.slow
def test_scene_to_msg_gcp(ikonos) -> None:
    results, msgs = ikonos
    for msg, res in zip(msgs, results, strict=True):
        _check_against_result(msg, res)
        _check_consistent(msg)
        assert msg.method == ParallelProjection.METHOD_GCP_ROLL_ESTIMATED
        assert msg.gcp_count == 20 and msg.check_count == 8
        assert 0 < msg.sigma0_px < 0.2 and 0 < msg.check_rms_px < 0.5
        assert msg.residual_max_px >= msg.residual_rms_px > 0
        cov = np.array(msg.covariance).reshape(9, 9)
        np.testing.assert_allclose(cov, cov.T, rtol=1e-9, atol=0)
        assert np.all(np.diag(cov) > 0)
        assert msg.roll_psi != 0.0


def test_scene_to_msg_nan_crab_becomes_zero(airborne) -> None:
    results, _ = airborne
    res = results[0]
    gcp_only = SceneResult(**{**res.__dict__, "crab_angle": float("nan")})
    msg = conv.scene_to_msg(gcp_only, ParallelProjection(), frame_id="world")
    assert msg.crab_angle == 0.0 and msg.header.frame_id == "world"


def test_whole_images_once_and_no_anaglyph() -> None:
    """Issue 11: stereo_pair_images=false and anaglyph=false leave out the duplicate pixels."""
    from parproj_ros.core.pipeline import Pipeline, PipelineConfig
    from parproj_ros.core.results import Outputs
    from parproj_ros.sim.synthetic import (
        VIEWS,
        StripMessages,
        acquisition,
        make_platform,
        nav_message,
    )

    plat = make_platform(2048, 320)  # a shorter scene has too small a base
    pipe = Pipeline(
        PipelineConfig(
            views=plat.views,
            scene_lines=2048,
            z_avg=0.0,
            height_range=500.0,
            streaming=False,
            tie_points=False,
        )
    )
    strips = StripMessages(plat, 256)
    out = Outputs()
    for ev in acquisition(plat, 1, 256, 50.0):
        if ev.kind == "nav":
            out.extend(pipe.add_navigation(conv.odometry_to_sample(nav_message(plat, ev.t_s))))
        else:
            arr = conv.image_to_array(strips.get(ev))
            out.extend(pipe.add_strip(VIEWS[ev.view], ev.stamp_ns, ev.scene_id, arr))
    out.extend(pipe.flush())
    assert len(out.pairs) == 1 and out.pairs[0].left_image is not None
    full = {t: m for t, m, _ in conv.outputs_to_messages(out, frame_id="map", stamp_ns=0)}
    lean = {
        t: m
        for t, m, _ in conv.outputs_to_messages(
            out, frame_id="map", stamp_ns=0, stereo_pair_images=False, anaglyph=False
        )
    }
    assert "anaglyph" in full and "anaglyph" not in lean
    sp_full, sp_lean = full["stereo_pair"], lean["stereo_pair"]
    assert len(sp_full.left.data) > 0 and len(sp_lean.left.data) == len(sp_lean.right.data) == 0
    assert not sp_lean.streamed and sp_lean.width == sp_full.width > 0
    assert sp_lean.left.header.stamp == lean["left/image_normalized"].header.stamp
    for side in ("left", "right"):
        a = conv.image_to_array(full[f"{side}/image_normalized"])
        b = conv.image_to_array(lean[f"{side}/image_normalized"])
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, conv.image_to_array(getattr(sp_full, side)))
    # The rest of the StereoPair is the same (repr: NaN fields compare unequal).
    for name in sp_full.get_fields_and_field_types():
        if name not in ("left", "right"):
            assert repr(getattr(sp_full, name)) == repr(getattr(sp_lean, name)), name


def test_contract_qos_are_the_node_profiles() -> None:
    """``qos_profile`` of the contract's QoS gives the rclpy profiles the node builds: strips
    and navigation sensor-data reliability with deep queues, GCP and pair selection reliable
    transient-local, outputs and /diagnostics ``QoSProfile(depth=10)``, the latched outputs
    (issue 25) reliable transient-local (their depth then set by ``latched_depth``)."""
    from rclpy.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
        qos_profile_sensor_data,
    )

    from parproj_ros.core import contract
    from parproj_ros.ros.conversions import qos_profile

    sensor = qos_profile_sensor_data.reliability
    node = {
        "navigation": QoSProfile(depth=500, reliability=sensor, history=HistoryPolicy.KEEP_LAST),
        "left/image_strip": QoSProfile(
            depth=200, reliability=sensor, history=HistoryPolicy.KEEP_LAST
        ),
        "gcp": QoSProfile(
            depth=10,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        ),
        **{t: QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE) for t in OUTPUTS},
        **{
            t.name: QoSProfile(
                depth=10,
                reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL,
            )
            for t in contract.OUTPUTS
            if t.qos is contract.LATCHED_OUTPUT_QOS
        },
        "/diagnostics": QoSProfile(depth=10),  # create_publisher(..., 10)
    }
    node["pairs"] = node["gcp"]
    for name, profile in node.items():
        assert qos_profile(contract.topic(name).qos) == profile, name
    # the bags' presets are rclpy's QoSProfile(depth=10), sensor data and a latched depth 1
    assert qos_profile(contract.BAG_QOS["reliable"]) == QoSProfile(depth=10)
    assert qos_profile(contract.BAG_QOS["sensor_data"]) == qos_profile_sensor_data
    latched = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    assert qos_profile(contract.BAG_QOS["transient_local"]) == latched


#: The published topics, as node.py and process.py have always named them.
OUTPUTS = (
    "parallel_projection",
    "stereo_pair",
    "left/image_normalized",
    "right/image_normalized",
    "anaglyph",
    "left/normalized_block",
    "right/normalized_block",
    "disparity",
    "height",
    "dsm",
    "dsm_fused",
)
