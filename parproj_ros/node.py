"""parproj_node: the rclpy adapter around :class:`parproj_ros.pipeline.Pipeline`.

It declares the parameters, converts messages to arrays (conversions.py), queues them to one worker
thread that runs the pipeline (so a long resampling never blocks message reception), and publishes
what the pipeline returns. Topic names are relative, to be remapped. See README for the topic and
parameter tables.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from parproj_msgs.msg import (
    GroundControlPoints,
    NormalizedBlock,
    ParallelProjection,
    StereoPair,
)
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import Image

from . import conversions as conv
from .gcp_file import load_gcp_file
from .geometry import LineCamera, rotation_from_angles
from .pipeline import Issue, Outputs, Pipeline, PipelineConfig, ViewConfig


@dataclass(frozen=True)
class Param:
    """One declared parameter: name, default, description with unit, range, read-only."""

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    read_only: bool = True
    choices: tuple[str, ...] = ()


#: Node-wide parameters (per-view camera parameters are in VIEW_PARAMS).
PARAMS: tuple[Param, ...] = (
    Param(
        "views",
        ["left", "right"],
        "view names: two (left, right) for fore/aft cameras, or "
        "one for single-camera mode (consecutive scenes pair up)",
    ),
    Param("frame_id", "map", "object frame (local Cartesian, Z up, metres) of navigation and GCP"),
    Param(
        "scene_lines",
        0,
        "lines per scene; 0 = scenes end only on a gap or a frame_id change",
        0,
        10_000_000,
    ),
    Param(
        "max_gap_lines",
        64,
        "a larger jump between strips ends the scene; a smaller one is "
        "filled with nodata and reported",
        0,
        1_000_000,
    ),
    Param(
        "z_avg", 0.0, "average terrain height, m (Eq 12; zero-disparity height)", -1000.0, 9000.0
    ),
    Param(
        "height_range",
        500.0,
        "half range of terrain heights, m (virtual check points)",
        0.0,
        9000.0,
    ),
    Param(
        "crab_tolerance_px",
        0.05,
        "largest predicted crab-angle error accepted from Eqs 10-13, "
        "px; above it A1..A8 are fitted to the rigorous model",
        0.0,
        1000.0,
    ),
    Param(
        "scene_timeout",
        2.0,
        "close the open scenes when no strip arrived for this long, s (wall clock), once the "
        "navigation has moved past them (or without navigation); 0 = never",
        0.0,
        3600.0,
    ),
    Param(
        "gcp_roll",
        "estimate",
        "with GCP: 'estimate' the roll (Eq 8), use the 'navigation' roll, or 'none' (no PTP)",
        choices=("estimate", "navigation", "none"),
    ),
    Param("min_gcp", 5, "non-check GCP observed in a scene needed to use them", 4, 100000),
    Param("gcp_file", "", "CSV/YAML file of GCP loaded at start ('' = none); see README"),
    Param("nodata", 0.0, "output value outside a scene and for missing lines", -1e30, 1e30),
    Param(
        "interpolation", "linear", "'linear' or 'cubic' resampling", choices=("linear", "cubic")
    ),
    Param(
        "output_pixel", 0.0, "normalized metres per output pixel; 0 = native resolution", 0.0, 1.0
    ),
    Param(
        "max_output_pixels", 200_000_000, "larger normalized images are refused", 1, 2_000_000_000
    ),
    Param(
        "tie_points",
        True,
        "refine whole-scene pairs with tie points matched between the normalized images "
        "(RANSAC on G1..G4), removing y-parallax left by biased navigation, GCP or RPC",
    ),
    Param(
        "tie_threshold_px", 1.0, "RANSAC inlier threshold on the epipolar residual, px", 0.05, 50.0
    ),
    Param(
        "segment_max_error_px",
        1.0,
        "model error bound of a long GCP/RPC scene, px: a pair whose parallel model misses its "
        "points by more is cut along track into segment pairs (0 = never cut)",
        0.0,
        1000.0,
    ),
    Param(
        "segment_overlap",
        0.1,
        "fraction of a segment's length by which it extends into its neighbours",
        0.0,
        0.5,
    ),
    Param(
        "streaming",
        True,
        "publish normalized column blocks while the scenes arrive (two views, scene_lines > 0, "
        "navigation-derived parameters); otherwise whole images after both scenes",
    ),
)

#: Per-view parameters, declared as "<view>.<name>".
VIEW_PARAMS: tuple[Param, ...] = (
    Param("principal_distance", 10.0, "principal distance c, m", 1e-4, 100.0),
    Param("pixel_size", 12e-6, "detector pitch, m", 1e-7, 1e-3),
    Param("detectors", 13816, "detectors in the line", 1, 1_000_000),
    Param(
        "principal_point",
        -1.0,
        "sample coordinate of the principal point, px; -1 = centre",
        -1.0,
        1e6,
    ),
    Param("line_period", 1.0 / 6500.0, "time between scan lines, s", 1e-7, 10.0),
    Param(
        "mounting_rpy_deg",
        [0.0, 0.0, 0.0],
        "sensor frame in the body frame: roll, pitch, "
        "yaw in degrees, R = Rx(roll) Ry(pitch) Rz(yaw)",
    ),
    Param(
        "encoding",
        "",
        "pixel encoding the camera delivers (mono8, mono16, 32FC1); strips of another encoding "
        "are dropped; '' = whatever a scene's first strip has",
        choices=("", "mono8", "mono16", "32FC1"),
    ),
)

ENCODING_DTYPES = {"mono8": "uint8", "mono16": "uint16", "32FC1": "float32"}


def _descriptor(p: Param, name: str) -> ParameterDescriptor:
    d = ParameterDescriptor(description=p.description, read_only=p.read_only)
    if p.low is not None and p.high is not None:
        if isinstance(p.default, int) and not isinstance(p.default, bool):
            d.integer_range = [IntegerRange(from_value=int(p.low), to_value=int(p.high), step=0)]
        else:
            d.floating_point_range = [
                FloatingPointRange(from_value=float(p.low), to_value=float(p.high), step=0.0)
            ]
    return d


class ParprojNode(Node):
    """ROS 2 node: strips + navigation (+ GCP) -> ParallelProjection, StereoPair, images."""

    def _declare(self, name: str, p: Param) -> Any:
        """Declare one parameter; a bad value is replaced by the default and reported.

        Out of range or not among the choices: the node keeps running with the default, logs an
        error, and its 1 Hz summary stays at ERROR naming the parameter.
        """
        desc = _descriptor(p, name)
        try:
            value = self.declare_parameter(name, p.default, desc).value
        except (InvalidParameterValueException, InvalidParameterTypeException) as err:
            self._startup_issues.append(
                Issue("error", f"parameter {name}", f"{err}; the default {p.default!r} is used")
            )
            return self.declare_parameter(name, p.default, desc, ignore_override=True).value
        if p.choices and value not in p.choices:
            self._startup_issues.append(
                Issue(
                    "error",
                    f"parameter {name}",
                    f"{value!r} is not one of {list(p.choices)}; "
                    f"the default {p.default!r} is used",
                )
            )
            return p.default
        return value

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("parproj_node", **kwargs)
        self._startup_issues: list[Issue] = []
        vals = {p.name: self._declare(p.name, p) for p in PARAMS}
        views = []
        for name in vals["views"]:
            v = {p.name: self._declare(f"{name}.{p.name}", p) for p in VIEW_PARAMS}
            pp = None if v["principal_point"] < 0 else float(v["principal_point"])
            cam = LineCamera(
                float(v["principal_distance"]),
                float(v["pixel_size"]),
                int(v["detectors"]),
                float(v["line_period"]),
                pp,
            )
            rpy = np.radians(np.asarray(v["mounting_rpy_deg"], dtype=float))
            views.append(
                ViewConfig(
                    name, cam, rotation_from_angles(*rpy), ENCODING_DTYPES.get(v["encoding"])
                )
            )
        self.frame_id = str(vals["frame_id"])
        config = PipelineConfig(
            views=tuple(views),
            scene_lines=int(vals["scene_lines"]),
            max_gap_lines=int(vals["max_gap_lines"]),
            z_avg=float(vals["z_avg"]),
            height_range=float(vals["height_range"]),
            crab_tolerance_px=float(vals["crab_tolerance_px"]),
            gcp_roll=vals["gcp_roll"],
            min_gcp=int(vals["min_gcp"]),
            nodata=float(vals["nodata"]),
            interpolation=vals["interpolation"],
            output_pixel=float(vals["output_pixel"]),
            max_output_pixels=int(vals["max_output_pixels"]),
            streaming=bool(vals["streaming"]),
            tie_points=bool(vals["tie_points"]),
            tie_threshold_px=float(vals["tie_threshold_px"]),
            segment_max_error_px=float(vals["segment_max_error_px"]),
            segment_overlap=float(vals["segment_overlap"]),
        )
        self.pipeline = Pipeline(config)
        self.counts = {
            "strips": 0,
            "strips_rejected": 0,
            "nav": 0,
            "nav_rejected": 0,
            "scenes": 0,
            "pairs": 0,
        }
        self._queue: queue.Queue[tuple[str, Any] | None] = queue.Queue()
        self._queue_peak = 0  # longest input queue since the last 1 Hz summary, items
        # Inputs: sensor-data QoS (REP 2003: best effort, volatile) with a deep queue, since a
        # strip lost is a gap in a scene; reliability can be overridden per topic
        # (qos_overrides.<topic>.subscription.reliability) for lossless replay.
        strip_qos = QoSProfile(
            depth=200,
            reliability=qos_profile_sensor_data.reliability,
            history=HistoryPolicy.KEEP_LAST,
        )
        nav_qos = QoSProfile(
            depth=500,
            reliability=qos_profile_sensor_data.reliability,
            history=HistoryPolicy.KEEP_LAST,
        )
        overrides = QoSOverridingOptions.with_default_policies()
        self.create_subscription(
            Odometry, "navigation", self._on_nav, nav_qos, qos_overriding_options=overrides
        )
        for v in views:
            self.create_subscription(
                Image,
                f"{v.name}/image_strip",
                lambda msg, view=v.name: self._on_strip(view, msg),
                strip_qos,
                qos_overriding_options=overrides,
            )
        # GCP: reliable and transient-local, so a GCP set published before the node started
        # (a ground station's latched set) still arrives.
        gcp_qos = QoSProfile(
            depth=10,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self.create_subscription(GroundControlPoints, "gcp", self._on_gcp, gcp_qos)
        # Outputs: reliable, so that every scene's parameters and every pair reach recorders.
        out_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        # The topics are conv.OUTPUT_TOPICS (the offline process writes the same), /diagnostics
        # apart (below).
        classes = {
            "parproj_msgs/msg/ParallelProjection": ParallelProjection,
            "parproj_msgs/msg/StereoPair": StereoPair,
            "sensor_msgs/msg/Image": Image,
            "parproj_msgs/msg/NormalizedBlock": NormalizedBlock,
        }
        types = {t: classes[m] for t, m in conv.OUTPUT_TOPICS.items() if t != "/diagnostics"}
        self.pubs = {t: self.create_publisher(cls, t, out_qos) for t, cls in types.items()}
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._summary)
        self.scene_timeout = float(vals["scene_timeout"])
        self._last_strip = time.monotonic()
        self.create_timer(0.25, self._check_idle)
        if vals["gcp_file"]:
            try:
                self._queue.put(("gcp", load_gcp_file(vals["gcp_file"])))
            except (OSError, ValueError) as err:
                self._report(
                    [
                        Issue(
                            "error",
                            "gcp_file",
                            f"{vals['gcp_file']}: {err}; continuing without it",
                        )
                    ]
                )
        self._report(self._startup_issues)
        self._worker = threading.Thread(target=self._work, name="parproj_pipeline", daemon=True)
        self._worker.start()

    # ---- callbacks: convert and queue ----------------------------------------------------
    def _on_nav(self, msg: Odometry) -> None:
        try:
            self._enqueue(("nav", conv.odometry_to_sample(msg)))
            self.counts["nav"] += 1
        except conv.ConversionError as err:
            self.counts["nav_rejected"] += 1
            self._report([Issue("warn", "navigation", f"{err}: sample dropped")])

    def _on_strip(self, view: str, msg: Image) -> None:
        try:
            arr = conv.image_to_array(msg)
        except conv.ConversionError as err:
            self.counts["strips_rejected"] += 1
            self._report(
                [Issue("warn", f"{view}/{msg.header.frame_id}", f"strip rejected: {err}: dropped")]
            )
            return
        self.counts["strips"] += 1
        self._last_strip = time.monotonic()
        self._enqueue(
            ("strip", (view, conv.stamp_to_ns(msg.header.stamp), msg.header.frame_id, arr))
        )

    def _on_gcp(self, msg: GroundControlPoints) -> None:
        self._enqueue(("gcp", conv.gcp_from_msg(msg)))

    def _enqueue(self, item: tuple[str, Any]) -> None:
        """Queue an input for the worker and keep the queue's peak length for the summary."""
        self._queue.put(item)
        self._queue_peak = max(self._queue_peak, self._queue.qsize())

    # ---- worker: run the pipeline, publish ------------------------------------------------
    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            kind, payload = item
            try:
                if kind == "nav":
                    out = self.pipeline.add_navigation(payload)
                elif kind == "strip":
                    out = self.pipeline.add_strip(*payload)
                elif kind == "gcp":
                    out = self.pipeline.add_gcp(payload)
                elif kind == "close":
                    out = self.pipeline.close_idle_scenes()
                else:
                    out = Outputs(issues=self._open_at_stop())
                    out.extend(self.pipeline.flush())
                self._publish(out)
            except Exception as err:
                self._report(
                    [
                        Issue(
                            "error",
                            kind,
                            f"internal error {type(err).__name__}: {err}; input dropped",
                        )
                    ]
                )
            finally:
                self._queue.task_done()

    def _open_at_stop(self) -> list[Issue]:
        """A WARN per scene still open when the node stops: the flush publishes it as it is."""
        issues = []
        for view, asm in self.pipeline.assemblers.items():
            opened = asm.open_scene()
            if opened is not None:
                issues.append(
                    Issue(
                        "warn",
                        f"{view}/{opened[0]}",
                        f"node stopping with this scene open ({opened[3]} lines received): it "
                        "is closed and processed as it is; lines still to come are not in it",
                    )
                )
        return issues

    def _check_idle(self) -> None:
        idle = time.monotonic() - self._last_strip
        if self.scene_timeout > 0 and idle > self.scene_timeout and self.pipeline.has_open_scene:
            self._last_strip = time.monotonic()
            self._queue.put(("close", None))

    def flush(self) -> None:
        """Close open scenes (end of a pass) and wait until the worker has published them."""
        self._queue.put(("flush", None))
        self._queue.join()

    def _publish(self, out: Outputs) -> None:
        now = self.get_clock().now().nanoseconds
        for topic, msg, _ in conv.outputs_to_messages(out, frame_id=self.frame_id, stamp_ns=now):
            if topic in self.pubs:
                self.pubs[topic].publish(msg)
        for res in out.scenes:
            self.counts["scenes"] += 1
            self.get_logger().info(
                f"scene {res.scene.view}/{res.scene.scene_id}: "
                f"{res.scene.lines} lines, {res.method}"
            )
        for pair in out.pairs:
            self.counts["pairs"] += 1
            mean, rms, mx = pair.y_parallax_stats
            self.get_logger().info(
                f"pair {pair.pair_id}: {pair.left_grid.width}x{pair.left_grid.height} px, "
                f"y-parallax ({pair.y_parallax_source}) mean {mean:.3f} rms {rms:.3f} "
                f"max {mx:.3f} px"
            )
        self._report(out.issues)

    def _report(self, issues: Sequence[Issue]) -> None:
        if not issues:
            return
        for iss in issues:
            log = self.get_logger().error if iss.level == "error" else self.get_logger().warning
            log(f"{iss.where}: {iss.message}")
        self.pub_diag.publish(
            conv.issues_to_diagnostics(
                list(issues),
                stamp_ns=self.get_clock().now().nanoseconds,
                hardware_id=self.frame_id,
            )
        )

    def _summary(self) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status.append(
            DiagnosticStatus(
                level=DiagnosticStatus.ERROR if self._startup_issues else DiagnosticStatus.OK,
                name="parproj_node: summary",
                message="running"
                + (
                    "; bad parameters replaced by defaults: "
                    + "; ".join(f"{i.where}: {i.message}" for i in self._startup_issues)
                    if self._startup_issues
                    else ""
                ),
                values=[KeyValue(key=k, value=str(v)) for k, v in self.counts.items()]
                + [
                    KeyValue(key=k, value=str(v))
                    for k, v in (
                        ("queue", self._queue.qsize()),
                        ("queue_max", max(self._queue_peak, self._queue.qsize())),
                        ("nav_samples", len(self.pipeline.nav)),
                        ("gcp_points", len(self.pipeline.gcp)),
                    )
                ],
            )
        )
        self._queue_peak = 0
        self.pub_diag.publish(arr)

    def wait_delivered(self, timeout_s: float) -> bool:
        """Wait until every subscriber has acknowledged what was published (``timeout_s`` in all).

        So that the outputs of the flush at shutdown are not lost when the process exits; says
        which topic was not acknowledged.
        """
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout_s
        done = True
        for pub in [*self.pubs.values(), self.pub_diag]:
            left = max(0.0, deadline - time.monotonic())
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                done = False
                self.get_logger().warning(
                    f"{pub.topic_name}: not acknowledged by every subscriber within "
                    f"{timeout_s} s of stopping"
                )
        return done

    def stop(self) -> None:
        """Stop the worker thread (after the queue drains)."""
        self._queue.put(None)
        self._worker.join(timeout=30)


def main(args: list[str] | None = None) -> int:
    """Entry point of ``parproj_node``: spin until SIGINT/SIGTERM, then flush and exit."""
    import signal

    rclpy.init(args=args, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = ParprojNode()
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    executor = rclpy.executors.SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
        node.get_logger().info("stopping: flushing open scenes")
        node.flush()
        node.wait_delivered(5.0)
    finally:
        node.stop()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
