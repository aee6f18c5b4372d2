"""parproj_node: the rclpy adapter around :class:`parproj_ros.core.pipeline.Pipeline`.

It declares the parameters from the one table (:mod:`parproj_ros.core.config`, which also builds
the pipeline's settings from their values), converts messages to arrays (conversions.py), queues
them to one worker thread that runs the pipeline (so a long resampling never blocks message
reception), and publishes what the pipeline returns. Topic names are relative, to be remapped.
See README for the topic and parameter tables.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from parproj_msgs.msg import (
    ElevationGrid,
    GroundControlPoints,
    NormalizedBlock,
    ParallelProjection,
    StereoPair,
)
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    NameValidationException,
    ParameterException,
)
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
from stereo_msgs.msg import DisparityImage

from ..core.admission import PairAdmission, auto_prefault_mb, working_set_floor
from ..core.config import PARAMS, VIEW_PARAMS, Param, config_from_values
from ..core.frames import ObjectFrame
from ..core.memory import (
    held_bytes,
    prefault_heap,
    rss_bytes,
    tune_malloc,
)
from ..core.render_process import RenderProcess
from ..core.results import BlockResult, Issue, Level, Outputs
from ..core.session import InputKind, Session, Strip, Worker
from ..io.gcp_file import load_gcp_file
from . import conversions as conv
from .cdr import CdrError, ImageView, parse_image
from .startup import (
    EXIT_BAD_START,
    EXIT_NOT_FLUSHED,
    EXIT_OK,
    StartupError,
    check_mounting,
    check_views,
    descriptor,
    init_rclpy,
    one_line,
    shown,
    to_stderr,
)


def _read_strip(raw: bytes | Image) -> ImageView | Image:
    """A received strip, read from its CDR bytes (:func:`.cdr.parse_image`).

    Bytes that are not plain CDR are deserialized by rclpy; an Image already deserialized is
    returned as it is.

    Raises:
        CdrError: the bytes are not a well-formed Image.
    """
    if not isinstance(raw, bytes | bytearray | memoryview):
        return raw
    view = parse_image(raw)
    if view is not None:
        return view
    from rclpy.serialization import deserialize_message

    try:
        return deserialize_message(bytes(raw), Image)
    except Exception as err:  # rclpy raises assorted exception types for bad CDR
        raise CdrError(f"rclpy could not deserialize it: {type(err).__name__}: {err}") from None


#: Navigation samples the navigation callback takes besides its own (those already waiting).
NAV_DRAIN_MAX = 100


class ParprojNode(Node):
    """ROS 2 node: strips + navigation (+ GCP) -> ParallelProjection, StereoPair, images."""

    def _declare(self, name: str, p: Param) -> Any:
        """Declare one parameter; a bad value is replaced by the default and reported.

        Out of range or not among the choices: the node keeps running with the default, logs an
        error, and its 1 Hz summary stays at ERROR naming the parameter. A parameter with no
        safe default (``p.strict``: ``views``, ``<view>.mounting_rpy_deg``) is checked by its
        caller instead; rclpy refusing it raises :class:`StartupError`.
        """
        desc = descriptor(p)
        try:
            value = self.declare_parameter(name, p.default, desc).value
        except (InvalidParameterValueException, InvalidParameterTypeException) as err:
            if p.strict:
                raise StartupError(f"parameter {name}: {err}") from err
            self._startup_issues.append(
                Issue(
                    Level.ERROR, f"parameter {name}", f"{err}; the default {p.default!r} is used"
                )
            )
            return self.declare_parameter(name, p.default, desc, ignore_override=True).value
        if p.choices and value not in p.choices:
            self._startup_issues.append(
                Issue(
                    Level.ERROR,
                    f"parameter {name}",
                    f"{value!r} is not one of {list(p.choices)}; "
                    f"the default {p.default!r} is used",
                )
            )
            return p.default
        return value

    def __init__(self, **kwargs: Any) -> None:
        """Declare and check the parameters, create the endpoints, start the worker.

        Raises:
            StartupError: a parameter without a safe default is invalid (``views``,
                ``<view>.mounting_rpy_deg``) or a QoS override cannot be applied; ``main``
                turns it into a one-line error and exit code 2.
        """
        super().__init__("parproj_node", **kwargs)
        # A node that cannot start is destroyed here, before main shuts rclpy down. The process
        # once died of SIGSEGV (-11) after printing its one-line error instead of exiting 2 (CI,
        # 2026-11-25). Not reproduced in 90 runs; the node's handles left to the interpreter's
        # exit, after rclpy's shutdown, are a guess at the cause; destroying it first is due.
        try:
            self._set_up()
        except BaseException:
            with contextlib.suppress(Exception):
                self.destroy_node()
            raise

    def _set_up(self) -> None:
        """The body of :meth:`__init__` after the rclpy node exists."""
        self._startup_issues: list[Issue] = []
        vals = {p.name: self._declare(p.name, p) for p in PARAMS}
        vals["views"] = check_views(vals["views"])
        for view in vals["views"]:
            vals |= {f"{view}.{p.name}": self._declare(f"{view}.{p.name}", p) for p in VIEW_PARAMS}
            key = f"{view}.mounting_rpy_deg"
            vals[key] = check_mounting(key, vals[key])
        # outputs in the frame_id parameter, or ("") in the frame of the inputs (core/frames.py)
        self._frame = ObjectFrame(str(vals["frame_id"]))
        config = config_from_values(vals)
        self.session = Session(config)
        self.pipeline = self.session.pipeline
        self.renderer: RenderProcess | None = None
        if bool(vals["render_process"]) and config.scene_lines > 0 and len(config.views) == 2:
            try:
                self.renderer = RenderProcess()
                self.pipeline.use_render_process(self.renderer)
            except Exception as err:  # no /dev/shm, no process: render in the worker
                self._startup_issues.append(
                    Issue(
                        Level.WARN,
                        "render_process",
                        f"cannot start the render process ({type(err).__name__}: {err}): "
                        "streamed blocks are rendered in the worker thread",
                    )
                )
        # Streamed blocks are published as each is rendered (the render process renders the
        # next one meanwhile), not gathered until the input's other outputs are made.
        self.pipeline.set_block_sink(self._publish_block)
        self._prefault(config, float(vals["prefault_mb"]))
        self.worker_stall_s = float(vals["worker_stall_s"])
        self.error_hold_s = float(vals["error_hold_s"])
        self.stop_timeout_s = float(vals["stop_timeout_s"])
        self.stereo_pair_images = bool(vals["stereo_pair_images"])
        self.anaglyph = bool(vals["anaglyph"])
        self.admission = PairAdmission(
            vals["views"],
            float(vals["memory_budget_mb"]),
            config.scene_lines,
            self._raw_held,
            *working_set_floor(config),
        )
        self.counts = {
            "strips": 0,
            "strips_rejected": 0,
            "nav": 0,
            "nav_rejected": 0,
            "scenes": 0,
            "pairs": 0,
            "warnings": 0,  # WARN statuses reported (the summary excluded)
            "errors": 0,  # ERROR statuses reported (the summary excluded)
            "internal_errors": 0,  # exceptions caught in the worker or a callback
        }
        self._counts_lock = threading.Lock()
        self._last_error: tuple[float, str] | None = None  # (monotonic, "where: message")
        self._closed = False  # set at shutdown: nothing more is published
        self.worker = Worker(self._handle, self.internal_error)
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
        inputs: list[tuple[str, Any, QoSProfile]] = [("navigation", self._on_nav, nav_qos)]
        for vc in config.views:
            inputs.append(
                (
                    f"{vc.name}/image_strip",
                    lambda msg, view=vc.name: self._on_strip(view, msg),
                    strip_qos,
                )
            )
        for topic, callback, qos in inputs:
            cls = Odometry if topic == "navigation" else Image
            try:
                # strips taken as CDR bytes and read by cdr.parse_image (the pixels a view on
                # them): rclpy's deserialization costs 8.7 ms per full-size strip, GIL held
                sub = self.create_subscription(
                    cls,
                    topic,
                    callback,
                    qos,
                    qos_overriding_options=overrides,
                    raw=cls is Image,
                )
                if topic == "navigation":
                    self._nav_sub = sub
            except Exception as err:  # rclpy: RuntimeError or a parameter exception
                raise StartupError(
                    f"QoS override of {topic}: {type(err).__name__}: {err}"
                ) from err
        # GCP: reliable and transient-local, so a GCP set published before the node started
        # (a ground station's latched set) still arrives.
        gcp_qos = QoSProfile(
            depth=10,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self.create_subscription(GroundControlPoints, "gcp", self._on_gcp, gcp_qos)
        self._subscribe_pairs(gcp_qos)
        # Outputs: reliable, so that every scene's parameters and every pair reach recorders.
        out_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        # The topics are conv.OUTPUT_TOPICS (the offline process writes the same), /diagnostics
        # apart (below).
        classes = {
            "parproj_msgs/msg/ParallelProjection": ParallelProjection,
            "parproj_msgs/msg/StereoPair": StereoPair,
            "sensor_msgs/msg/Image": Image,
            "parproj_msgs/msg/NormalizedBlock": NormalizedBlock,
            "stereo_msgs/msg/DisparityImage": DisparityImage,
            "parproj_msgs/msg/ElevationGrid": ElevationGrid,
        }
        types = {t: classes[m] for t, m in conv.OUTPUT_TOPICS.items() if t != "/diagnostics"}
        self.pubs = {t: self.create_publisher(cls, t, out_qos) for t, cls in types.items()}
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._summary)
        self.scene_timeout = float(vals["scene_timeout"])
        self._last_strip = time.monotonic()
        self.create_timer(0.25, self._check_idle)
        if vals["gcp_file"]:
            path = str(vals["gcp_file"])
            self._log("info", f"gcp_file {path}: loading")
            try:
                self.worker.put(InputKind.GCP, load_gcp_file(path))
            except Exception as err:  # whatever the loader raises: a clear error, not a crash
                why = f"{type(err).__name__}: {err}"
                self._startup_issues.append(
                    Issue(
                        Level.ERROR,
                        "gcp_file",
                        f"{why if path in str(err) else f'{path}: {why}'}; continuing without it",
                    )
                )
        self._startup_issues += self._unknown_parameters()
        self._report(self._startup_issues)
        self.worker.start()

    def _unknown_parameters(self) -> list[Issue]:
        """An ERROR per parameter given (``--params-file``, ``-p``) that the node does not have.

        A misspelt name, or a view not in ``views``: its value would be ignored silently.

        ``qos_overrides.*`` are left to rclpy (those of topics the node does not have are
        ignored).
        """
        given = self._parameter_overrides  # rclpy: every override for this node
        return [
            Issue(
                Level.ERROR,
                f"parameter {name}",
                f"{shown(given[name].value)} given, but parproj_node has no such parameter "
                "(misspelt, or a view not in views?): ignored",
            )
            for name in sorted(given)
            if not name.startswith("qos_overrides.") and not self.has_parameter(name)
        ]

    def _prefault(self, config: Any, prefault_mb: float) -> None:
        """Keep freed memory for reuse (process-wide), and touch the ``prefault_mb`` reserve.

        ``prefault_mb`` -1: :func:`auto_prefault_mb`.
        """
        if prefault_mb < 0:
            prefault_mb = auto_prefault_mb(config)
        tune_malloc(int(prefault_mb * 2**20))
        if prefault_mb <= 0:
            return
        t0 = time.monotonic()
        heap = prefault_heap(int(prefault_mb * 2**20))
        lines = 0
        if config.scene_lines > 0:
            for vc in config.views:
                asm = self.pipeline.assemblers[vc.name]
                asm.pool.prefault(config.scene_lines * vc.camera.detectors * 2)
                lines += asm.pool.held_bytes
        self._log(
            "info",
            f"prefault_mb: {heap / 2**20:.0f} MB of heap and {lines / 2**20:.0f} MB of line "
            f"buffers touched in {time.monotonic() - t0:.1f} s",
        )

    @property
    def frame_id(self) -> str:
        """The outputs' object frame: the parameter, else the inputs' (core/frames.py)."""
        return self._frame.frame_id

    # ---- callbacks: convert and queue ----------------------------------------------------
    def _on_nav(self, msg: Odometry) -> None:
        self._nav_one(msg)
        # Take the navigation samples already waiting too. The executor takes one message per
        # subscription and wait; a strip takes tens of ms to take at the full rate, so one
        # navigation sample per wait fell behind a 50 Hz stream and held the streaming decision
        # of every pair until the scene was complete (``python -m tools.bench``).
        sub = getattr(self, "_nav_sub", None)
        if sub is None:
            return
        for _ in range(NAV_DRAIN_MAX):
            try:
                with sub.handle:
                    taken = sub.handle.take_message(Odometry, False)
            except Exception:  # destroyed at shutdown, or an rclpy without this handle API
                return
            if taken is None:
                return
            self._nav_one(taken[0])

    def _nav_one(self, msg: Odometry) -> None:
        try:
            sample = conv.odometry_to_sample(msg)
        except conv.ConversionError as err:
            self._count("nav_rejected")
            self._report([Issue(Level.WARN, "navigation", f"{err}: sample dropped")])
            return
        except Exception as err:
            self.internal_error("a navigation message (callback)", err)
            return
        self._report(self._frame.observe("navigation", msg.header.frame_id))
        self._enqueue((InputKind.NAV, sample))
        self._count("nav")

    def _on_strip(self, view: str, raw: bytes | Image) -> None:
        """A strip, as its CDR bytes (``raw=True`` subscription) or an Image."""
        try:
            msg = _read_strip(raw)
        except CdrError as err:
            self._count("strips_rejected")
            self._report(
                [Issue(Level.WARN, view, f"strip rejected: unreadable CDR ({err}): dropped")]
            )
            return
        except Exception as err:
            self.internal_error(f"a strip of {view} (CDR)", err)
            return
        ok, close = True, False
        shed: list[Issue] = []
        try:
            fields = (str(msg.header.frame_id), int(msg.height), len(msg.data))
        except Exception:  # not an Image at all: the conversion below reports it
            fields = None
        if fields is not None:
            try:
                ok, shed, close = self.admission.admit(view, *fields)
            except Exception as err:
                self.internal_error(f"a strip of {view} (admission)", err)
        if shed:
            self._report(shed)
        if close:
            self._enqueue((InputKind.CLOSE_VIEW, view))
        if not ok:
            self._count("strips")
            return
        try:
            arr = conv.image_to_array(msg)
            item = Strip(view, conv.stamp_to_ns(msg.header.stamp), msg.header.frame_id, arr)
        except conv.ConversionError as err:
            self._count("strips_rejected")
            self._report(
                [
                    Issue(
                        Level.WARN,
                        f"{view}/{msg.header.frame_id}",
                        f"strip rejected: {err}: dropped",
                    )
                ]
            )
            return
        except Exception as err:
            self.internal_error(f"a strip of {view} (callback)", err)
            return
        self._count("strips")
        self._last_strip = time.monotonic()
        self._enqueue((InputKind.STRIP, item))

    def _on_gcp(self, msg: GroundControlPoints) -> None:
        try:
            self._report(self._frame.observe("gcp", msg.header.frame_id))
            points = conv.gcp_from_msg(msg)
        except Exception as err:
            self.internal_error("a GCP message (callback)", err)
            return
        self._enqueue((InputKind.GCP, points))

    def _subscribe_pairs(self, qos: QoSProfile) -> None:
        """The ``pairs`` topic (parproj_msgs/PairSelection; latched like ``gcp``)."""
        from parproj_msgs.msg import PairSelection

        self.create_subscription(PairSelection, "pairs", self._on_pairs, qos)

    def _on_pairs(self, msg: Any) -> None:
        try:
            self._enqueue((InputKind.PAIRS, conv.pairs_from_msg(msg)))
        except conv.ConversionError as err:
            self._report([Issue(Level.ERROR, "pairs", f"{err}: pair selection dropped")])
        except Exception as err:
            self.internal_error("a pair selection (callback)", err)

    def _enqueue(self, item: tuple[InputKind, Any]) -> None:
        """Queue an input for the worker."""
        self.worker.put(*item)

    def _raw_held(self) -> int:
        """Raw scene data the node holds: line buffers (kept or in use), queued strips, bytes."""
        lines = sum(a.pool.live_bytes for a in list(self.pipeline.assemblers.values()))
        return lines + self.worker.queued_bytes

    def _count(self, key: str, n: int = 1) -> None:
        """Add to a summary counter (callbacks and the worker count from two threads)."""
        with self._counts_lock:
            self.counts[key] += n

    # ---- worker: run the pipeline, publish ------------------------------------------------
    def _handle(self, kind: InputKind, payload: Any) -> None:
        """Run one input through the session and publish the outputs (the worker's thread)."""
        early = self.session.open_at_stop() if kind == InputKind.FLUSH else []
        out = self.session.feed(kind, payload)
        out.issues[:0] = early
        if kind == InputKind.FLUSH:
            self.admission.release_all()
        self._publish(out)
        self.admission.sample()

    def internal_error(self, what: str, err: BaseException) -> None:
        """Count an exception caught in the node and report it. Never raises.

        An ERROR on ``/diagnostics`` (status ``parproj_node: internal error``) naming the input,
        the exception and where it was raised; ``internal_errors`` in the summary.
        """
        try:
            self._count("internal_errors")
            tb = traceback.extract_tb(err.__traceback__)
            at = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno} in {tb[-1].name}" if tb else ""
            self._report(
                [
                    Issue(
                        Level.ERROR,
                        "internal error",
                        f"{type(err).__name__}: {err}{at}, while processing {what}: that input "
                        f"is dropped and the node carries on "
                        f"({self.counts['internal_errors']} internal errors so far)",
                    )
                ]
            )
        except BaseException as again:
            to_stderr(f"parproj_node: internal error {err!r} on {what}; reporting it: {again!r}")

    def _check_idle(self) -> None:
        idle = time.monotonic() - self._last_strip
        if self.scene_timeout > 0 and idle > self.scene_timeout and self.pipeline.has_open_scene:
            self._last_strip = time.monotonic()
            self.worker.put(InputKind.CLOSE, None)

    def worker_problem(self) -> str | None:
        """Why the worker is not doing its job (dead, or stalled on one input), or None."""
        return self.worker.problem(self.worker_stall_s)

    def flush(self, timeout_s: float | None = None, abort: Callable[[], bool] = bool) -> bool:
        """Close the open scenes (end of a pass) and wait until the worker has published them.

        Waits at most ``timeout_s`` (default ``stop_timeout_s``), or until ``abort()`` turns
        true (a second signal); with no worker running it does not wait at all. Returns whether
        the flush was done; if not, says why in an ERROR.
        """
        ok, why = self.worker.flush(self.stop_timeout_s if timeout_s is None else timeout_s, abort)
        if why:
            self._report([Issue(Level.ERROR, "stop", why)])
        return ok

    def _publish(self, out: Outputs) -> None:
        if self._closed:
            return
        now = self.get_clock().now().nanoseconds
        for topic, msg, _ in conv.outputs_to_messages(
            out,
            frame_id=self.frame_id,
            stamp_ns=now,
            stereo_pair_images=self.stereo_pair_images,
            anaglyph=self.anaglyph,
            raw_blocks=True,  # blocks published as CDR bytes: one copy instead of three
        ):
            if topic in self.pubs:
                self.pubs[topic].publish(msg)
        for pair in out.pairs:
            self.admission.published(pair.left.scene.view, pair.left.scene.scene_id)
        for res in out.scenes:
            self._count("scenes")
            self._log(
                "info",
                f"scene {res.scene.view}/{res.scene.scene_id}: "
                f"{res.scene.lines} lines, {res.method}",
            )
        for pair in out.pairs:
            self._count("pairs")
            mean, rms, mx = pair.y_parallax_stats
            self._log(
                "info",
                f"pair {pair.pair_id}: {pair.left_grid.width}x{pair.left_grid.height} px, "
                f"y-parallax ({pair.y_parallax_source}) mean {mean:.3f} rms {rms:.3f} "
                f"max {mx:.3f} px",
            )
        self._report(out.issues)

    def _publish_block(self, blk: BlockResult) -> None:
        """Publish one streamed block as it is rendered (its pixels borrowed). Never raises."""
        if self._closed:
            return
        topic = f"{blk.side}/normalized_block"
        try:
            self.pubs[topic].publish(conv.block_to_cdr(blk, frame_id=self.frame_id))
        except Exception as err:
            self.internal_error(
                f"block {blk.index} of pair {blk.pair_id} ({topic}; only that block is lost)", err
            )

    def _log(self, level: str, text: str) -> None:
        """Log ``text`` at ``level`` ("error", "warn", anything else: info).

        One call site per severity, on purpose: rclpy fixes the severity of a logging call site
        (function, file, line, bytecode offset) at its first call and raises ``ValueError:
        Logger severity cannot be changed between calls`` when the same site later logs at
        another one (``log = logger.error if ... else logger.warning; log(...)`` did).
        """
        logger = self.get_logger()
        if level == "error":
            logger.error(text)
        elif level == "warn":
            logger.warning(text)
        else:
            logger.info(text)

    def _report(self, issues: Sequence[Issue]) -> None:
        """Log the issues, count them, and publish them on ``/diagnostics``. Never raises.

        Called from the worker and from callbacks; if logging or publishing fails, the issues
        (and why) are printed to stderr instead, so that reporting cannot end either.
        """
        if not issues or self._closed:
            return
        try:
            for iss in issues:
                if iss.level == "error":
                    self._count("errors")
                    self._last_error = (time.monotonic(), f"{iss.where}: {iss.message}")
                elif iss.level == "warn":
                    self._count("warnings")
                self._log(iss.level, f"{iss.where}: {iss.message}")
            self.pub_diag.publish(
                conv.issues_to_diagnostics(
                    list(issues),
                    stamp_ns=self.get_clock().now().nanoseconds,
                    hardware_id=self.frame_id,
                )
            )
        except Exception as err:
            to_stderr(f"parproj_node: reporting failed ({type(err).__name__}: {err}):")
            for iss in issues:
                to_stderr(f"parproj_node: [{iss.level}] {iss.where}: {iss.message}")

    def summary_status(self) -> tuple[int, str]:
        """Level and message of the 1 Hz summary.

        ERROR while any of these holds, OK otherwise: a parameter was refused at start (or the
        gcp_file could not be loaded), for the node's life; the worker thread is not running,
        or has been on one input longer than ``worker_stall_s``; an ERROR status was reported
        less than ``error_hold_s`` ago. WARN statuses do not change the level (they are counted
        in ``warnings``).
        """
        problems = []
        worker = self.worker_problem()
        if worker:
            problems.append(worker)
        last = self._last_error
        if last is not None and time.monotonic() - last[0] < self.error_hold_s:
            problems.append(
                f"{self.counts['errors']} errors so far, the latest "
                f"{time.monotonic() - last[0]:.0f} s ago: {last[1]}"
            )
        if self._startup_issues:
            problems.append(
                "at start: " + "; ".join(f"{i.where}: {i.message}" for i in self._startup_issues)
            )
        if problems:
            return DiagnosticStatus.ERROR[0], "running; " + "; ".join(problems)
        return DiagnosticStatus.OK[0], "running"

    def _summary(self) -> None:
        if self._closed:
            return
        level, message = self.summary_status()
        busy = self.worker.busy
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status.append(
            DiagnosticStatus(
                level=bytes([level]),
                name="parproj_node: summary",
                message=message,
                values=[KeyValue(key=k, value=str(v)) for k, v in self.counts.items()]
                + [KeyValue(key=k, value=str(v)) for k, v in self.admission.counts.items()]
                + [KeyValue(key=k, value=str(v)) for k, v in self.pipeline.ledger.counts().items()]
                + [
                    KeyValue(key=k, value=str(v))
                    for k, v in (
                        ("queue", self.worker.qsize()),
                        ("queue_max", self.worker.take_peak()),
                        ("nav_samples", len(self.pipeline.nav)),
                        ("gcp_points", len(self.pipeline.gcp)),
                        ("pairs_in_flight", self.admission.in_flight),
                        ("working_set_mb", f"{self.admission.working_set / 2**20:.0f}"),
                        ("raw_mb", f"{self._raw_held() / 2**20:.0f}"),
                        ("startup_mb", f"{self.admission.base / 2**20:.0f}"),
                        ("held_mb", f"{held_bytes() / 2**20:.0f}"),
                        ("rss_mb", f"{rss_bytes() / 2**20:.0f}"),
                        ("memory_budget_mb", f"{self.admission.budget / 2**20:.0f}"),
                        ("worker", "alive" if self.worker.alive else "dead"),
                        ("busy_s", f"{time.monotonic() - busy[1]:.1f}" if busy else "0"),
                        ("busy_with", busy[0] if busy else ""),
                    )
                ],
            )
        )
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
                self._log(
                    "warn",
                    f"{pub.topic_name}: not acknowledged by every subscriber within "
                    f"{timeout_s} s of stopping",
                )
        return done

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the worker thread (after the queue drains, ``timeout_s`` at most).

        Nothing is published after it.
        """
        self.worker.stop(timeout_s)
        self._closed = True
        if self.renderer is not None and not self.worker.alive:
            self.renderer.close()
            self.renderer = None


def main(args: list[str] | None = None) -> int:
    """Entry point of ``parproj_node``: spin until SIGINT/SIGTERM, then flush and exit.

    Exit codes: 0 after a clean stop; 1 when the open scenes could not be flushed at the stop
    (the worker was dead, or did not finish within ``stop_timeout_s``, or a second signal came);
    2 when the node could not start: the ROS arguments or a parameters file do not parse, or a
    parameter without a safe default is invalid (one line on stderr, no traceback).
    """
    import signal

    argv = list(sys.argv if args is None else args)
    try:
        init_rclpy(argv)
        node = ParprojNode()
    except (StartupError, ParameterException, NameValidationException) as err:
        to_stderr(f"parproj_node: cannot start: {one_line(str(err))}")
        rclpy.try_shutdown()
        return EXIT_BAD_START
    except KeyboardInterrupt:
        to_stderr("parproj_node: interrupted while starting")
        rclpy.try_shutdown()
        return 130
    signals: list[int] = []

    def on_signal(signum: int, frame: Any) -> None:
        signals.append(signum)

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    executor = rclpy.executors.SingleThreadedExecutor()
    executor.add_node(node)
    code = EXIT_OK
    try:
        while not signals and rclpy.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception as err:  # a callback or timer raised: report, keep spinning
                node.internal_error("a callback", err)
        node._log("info", f"stopping: flushing open scenes ({node.stop_timeout_s:g} s at most)")
        if not node.flush(abort=lambda: len(signals) > 1):
            code = EXIT_NOT_FLUSHED
        node.wait_delivered(5.0)
    finally:
        # A worker that did not flush is stuck or gone: do not wait for it.
        node.stop(5.0 if code == EXIT_OK else 0.5)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return code


def entry() -> None:
    """The ``parproj_node`` command: :func:`main`, then exit with its code.

    A node that could not start leaves the process at once (``os._exit`` once stdout and
    stderr are flushed): nothing is in flight, and the interpreter's teardown of rclpy and Fast
    DDS after a node was created and destroyed was seen to die of SIGSEGV (-11) after the
    one-line error, instead of exiting 2, in 2 of about 1,800 invalid starts (CI 2026-11-25 and
    2026-11-27, ``test_invalid_start_exits_2_with_one_line``).
    """
    code = main()
    if code == EXIT_BAD_START:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry()
