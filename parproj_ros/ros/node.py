"""parproj_node: the rclpy adapter around :class:`parproj_ros.core.pipeline.Pipeline`.

It declares the parameters from the one table (:mod:`parproj_ros.core.config`, which also builds
the pipeline's settings from their values), converts messages to arrays (conversions.py), queues
them to one worker thread that runs the pipeline (so a long resampling never blocks message
reception), and publishes what the pipeline returns. Topic names are relative, to be remapped.
See README for the topic and parameter tables.
"""

from __future__ import annotations

import array
import contextlib
import math
import os
import queue
import re
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
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
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
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

from ..core.config import PARAMS, VIEW_PARAMS, Param, config_from_values
from ..core.frames import ObjectFrame
from ..core.memory import (
    held_bytes,
    malloc_trim,
    prefault_heap,
    raw_pair_bytes,
    rss_bytes,
    tune_malloc,
)
from ..core.pipeline import Pipeline
from ..core.render_process import RenderProcess
from ..core.results import BlockResult, Issue, Level, Outputs
from ..io.gcp_file import load_gcp_file
from . import conversions as conv
from .cdr import CdrError, ImageView, parse_image


def auto_prefault_mb(config: Any) -> float:
    """``prefault_mb`` -1: two raw pairs of the configured scenes, MB (0 without scene_lines).

    scene_lines x detectors x 2 bytes (uint16; an upper bound for 8-bit strips) summed over
    the views, twice: 1476 MB for two IKONOS-size views (14000 x 13816), the reserve with
    which the node keeps up at the full rate (bench/BENCHMARKS.md).
    """
    return float(2.0 * raw_pair_bytes(config) / 2**20)


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


class InputKind(StrEnum):
    """What an item of the worker's queue holds (callbacks and timers queue, the worker runs)."""

    NAV = "nav"  # a NavSample
    STRIP = "strip"  # (view, stamp_ns, frame_id, array)
    GCP = "gcp"  # a list of GroundPoint
    PAIRS = "pairs"  # a pair selection: [(left scene id, right scene id)]
    CLOSE = "close"  # the scene timeout: close the idle scenes
    CLOSE_VIEW = "close_view"  # a view's next scene was shed: close its open (whole) scene
    FLUSH = "flush"  # the flush at stop (a _FlushRequest)


#: Exit codes of parproj_node (README, "Exit codes").
EXIT_OK, EXIT_NOT_FLUSHED, EXIT_BAD_START = 0, 1, 2


class StartupError(Exception):
    """The node cannot start.

    A parameter without a safe default, the parameters file, a QoS override: ``main`` prints it
    as one line and exits with :data:`EXIT_BAD_START`.
    """


def _descriptor(p: Param) -> ParameterDescriptor:
    """The descriptor of ``p``: description with the unit, read-only, range, choices."""
    # Strict parameters take any type, so that the node's own check (check_views,
    # check_mounting) gives the message, and [1, 2, 3] (integers) is a valid mounting.
    d = ParameterDescriptor(
        description=p.ros_description, read_only=p.read_only, dynamic_typing=p.strict
    )
    if p.choices:
        d.additional_constraints = f"one of {p.range_text}"
    if p.low is not None and p.high is not None:
        if p.type == "integer":
            d.integer_range = [IntegerRange(from_value=int(p.low), to_value=int(p.high), step=0)]
        else:
            d.floating_point_range = [
                FloatingPointRange(from_value=float(p.low), to_value=float(p.high), step=0.0)
            ]
    return d


#: A view name: a ROS name token (it prefixes topic and parameter names), not hidden ("_...").
VIEW_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


def _shown(value: Any) -> str:
    return repr(list(value) if isinstance(value, array.array | tuple) else value)


def check_views(value: Any) -> list[str]:
    """The ``views`` parameter as 1 or 2 distinct view names.

    Raises:
        StartupError: not a list of names, not 1 or 2 of them, a name that is not a ROS name
            token (a letter, then letters, digits, underscores), or a name given twice.
    """
    if value is None:
        raise StartupError("parameter views: no view names given (an empty list?)")
    if not isinstance(value, list | tuple) or not all(isinstance(n, str) for n in value):
        raise StartupError(
            f"parameter views: {_shown(value)} is not a list of view names "
            "(e.g. [left, right], or [pan] for one camera)"
        )
    names = list(value)
    if not 1 <= len(names) <= 2:
        raise StartupError(
            f"parameter views: {names!r} has {len(names)} names; 1 (single-camera mode) or "
            "2 (fore/aft cameras) are needed"
        )
    for n in names:
        if not VIEW_NAME.fullmatch(n):
            raise StartupError(
                f"parameter views: {n!r} is not a valid view name (a letter, then letters, "
                "digits or underscores: it prefixes topic and parameter names)"
            )
    if len(set(names)) != len(names):
        raise StartupError(f"parameter views: {names!r} names the same view twice")
    return names


def check_mounting(name: str, value: Any) -> tuple[float, float, float]:
    """A ``<view>.mounting_rpy_deg`` parameter as (roll, pitch, yaw) in degrees.

    Raises:
        StartupError: not exactly 3 numbers, or one not finite or beyond +-360 degrees.
    """
    ok = isinstance(value, list | tuple | array.array) and len(value) == 3
    if not ok or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in value):
        raise StartupError(
            f"parameter {name}: {_shown(value)} is not 3 numbers [roll, pitch, yaw] in degrees"
        )
    rpy = (float(value[0]), float(value[1]), float(value[2]))
    if not all(math.isfinite(a) and abs(a) <= 360.0 for a in rpy):
        raise StartupError(
            f"parameter {name}: {list(rpy)!r}: each angle must be finite and within +-360 deg"
        )
    return rpy


#: Navigation samples the navigation callback takes besides its own (those already waiting).
NAV_DRAIN_MAX = 100
#: Raw pairs' worth of memory the node is first assumed to need besides the pairs in flight
#: (the normalized images of the pair being finished, the messages being serialized); the
#: admission then learns the working set from the resident memory (the benchmark, streaming:
#: peak RSS 3.6 raw pairs above the start-up memory with 2-3 pairs in flight; whole images at
#: 2048 x 2048: about 13).
WORKING_SET_PAIRS = 2
#: The same when pairs are normalized as whole images (not streamed: ``streaming`` false, or
#: ``scene_lines`` 0, or one view), as raw pairs plus a fixed amount: both normalized images,
#: their messages and what DDS copies of them. At 2048 x 2048 (16 MB pairs) the memory held
#: beyond start-up and raw data was 52-89 MB and the resident memory 100-145 MB
#: (tests/ros/test_overload_live.py, 2026-11-24); 64 MB + 4 pairs (128 MB there) kept the
#: resident memory under the budget in that test, and at IKONOS size (738 MB pairs) it is
#: 3 GB, so that the default budget still holds 3 pairs.
WHOLE_IMAGE_WORKING_SET_PAIRS = 4
WHOLE_IMAGE_WORKING_SET_MB = 64.0
#: Least time between two returns of the free heap to the system by :meth:`PairAdmission.sample`
#: (each costs milliseconds, and the pages given back cost 2.2 ms per MB to touch again), s.
TRIM_INTERVAL_S = 1.0
#: Resident memory samples (two per pair: at its decision and at its publication) over which
#: the working set is the largest.
WORKING_SET_SAMPLES = 4
#: Share of ``memory_budget_mb`` the admission leaves free: what it cannot foresee, the strips
#: DDS holds before the executor takes them and heap fragmentation (the overload test went
#: 1-4 % over its budget without it, 2026-11-24).
HEADROOM = 0.05


def working_set_floor(config: Any) -> tuple[float, float]:
    """(raw pairs, MB): the least working set the admission assumes for this configuration.

    Streamed pairs (``streaming``, a ``scene_lines``, two views: what :class:`Streamer` needs)
    hold column blocks; the others are normalized as whole images.
    """
    if config.streaming and config.scene_lines > 0 and not config.single_camera:
        return float(WORKING_SET_PAIRS), 0.0
    return float(WHOLE_IMAGE_WORKING_SET_PAIRS), WHOLE_IMAGE_WORKING_SET_MB


@dataclass
class _ViewStream:
    """Where a view's strip stream is: its current scene (frame_id), lines in it, ordinal."""

    frame_id: str | None = None
    lines: int = 0
    ordinal: int = -1
    max_lines: int = 0  # longest scene seen, lines (the size of a pair when scene_lines = 0)
    row_bytes: int = 0


class PairAdmission:
    """Admission of whole pairs under ``memory_budget_mb`` (README, "Overload").

    The decision is taken for a pair at the first strip of either of its scenes (scene k of each
    view; scenes 2k and 2k+1 in single-camera mode) and holds for every strip of both: a pair is
    processed whole or not at all, and shedding both scenes of it keeps the pipeline's pairing
    by scene order intact. A scene starts at a new frame_id, or after ``scene_lines`` lines.

    The memory the node holds (resident, less the free heap glibc keeps for reuse:
    :func:`held_bytes`) is read in two parts: the raw scene data (``raw_held``: the
    assemblers' line buffers, kept or in use, and the strips queued for the worker), and the
    rest. The start-up memory is the rest at the first strip; the working set (normalized
    images, messages being sent, DDS buffers, a strip backlog in DDS) is the largest excess of
    the rest over the start-up memory in the last :data:`WORKING_SET_SAMPLES` samples, taken at
    each decision and each pair published, each holding the peak the worker read (:meth:`sample`,
    after every input) since the one before; a burst's transient is forgotten once the load
    drops. It is at least ``floor_mb`` + ``floor_pairs`` raw pairs (:data:`WORKING_SET_PAIRS`;
    :data:`WHOLE_IMAGE_WORKING_SET_MB` + :data:`WHOLE_IMAGE_WORKING_SET_PAIRS` when pairs are
    normalized as whole images). A pair
    is admitted when

        start-up + max(raw data held, (pairs in flight + 1) x raw pair) + working set

    is within the budget less :data:`HEADROOM` (when the resident memory is over the budget,
    the free heap is first given back). Otherwise every strip of the pair is shed (dropped in
    the subscription callback, before conversion or queueing) and one WARN says so. A pair is
    in flight from its admission until its StereoPair is published (with every earlier one),
    or the flush. With nothing in flight a pair is always admitted (the node can hold no
    less); when the budget cannot hold two pairs in flight (consecutive pairs overlap in time:
    the fore view's next scene begins before the aft view's scene ends), the WARN says so and
    names the budget that would.

    Thread-safe: callbacks call :meth:`admit`, the worker :meth:`published`.
    """

    def __init__(
        self,
        views: Sequence[str],
        budget_mb: float,
        scene_lines: int,
        raw_held: Callable[[], int] = lambda: 0,
        floor_pairs: float = WORKING_SET_PAIRS,
        floor_mb: float = 0.0,
    ) -> None:
        self.views = list(views)
        #: The working set is at least ``floor_mb`` MB + this many raw pairs.
        self.floor_pairs = float(floor_pairs)
        self.floor = int(floor_mb * 2**20)
        self._trimmed = 0.0  # monotonic time of sample()'s last malloc_trim
        #: Bytes of raw scene data held (line buffers, queued strips), read apart from the rest.
        self.raw_held = raw_held
        self.single = len(self.views) == 1
        self.budget = int(budget_mb * 2**20)
        self.scene_lines = int(scene_lines)
        self.base = 0  # memory held at the first strip less its raw data, bytes
        self.working_set = 0  # largest excess of the non-raw memory over base, recent, bytes
        self._samples: deque[int] = deque(maxlen=WORKING_SET_SAMPLES)
        self._peak_rest = 0  # the largest non-raw memory read by sample() since the last sample
        self._streams = {v: _ViewStream() for v in self.views}
        self._decided: dict[int, bool] = {}
        self._in_flight: set[int] = set()
        self._scene_group: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()
        self.counts = {"pairs_shed": 0, "scenes_shed": 0, "strips_shed": 0}

    def pair_bytes(self) -> int:
        """One raw pair (both scenes), bytes, as far as known (0 before any strip)."""
        lines = self.scene_lines or max(s.max_lines for s in self._streams.values())
        # A view with no strip yet: taken as wide as the widest seen (its scene is coming).
        widest = max(s.row_bytes for s in self._streams.values())
        per_view = [lines * (s.row_bytes or widest) for s in self._streams.values()]
        return 2 * per_view[0] if self.single else sum(per_view)

    def admit(
        self, view: str, frame_id: str, rows: int, nbytes: int
    ) -> tuple[bool, list[Issue], bool]:
        """Whether to take this strip; the WARN when it sheds a pair; whether to close the view.

        The last: this strip begins a shed scene right after an admitted one, which the pipeline
        would otherwise close only at the view's next admitted strip.
        """
        issues: list[Issue] = []
        close = False
        with self._lock:
            st = self._streams.get(view)
            if st is None:  # not a configured view: the pipeline reports it
                return True, issues, close
            if not self.base:
                self.base = max(1, self._memory()[2])
            if rows > 0:
                st.row_bytes = max(st.row_bytes, nbytes // rows)
            new_scene = st.frame_id != frame_id or (
                self.scene_lines > 0 and st.lines >= self.scene_lines
            )
            previous = self._group_of(st.ordinal) if st.ordinal >= 0 else None
            if new_scene:
                st.frame_id, st.lines, st.ordinal = frame_id, 0, st.ordinal + 1
            st.lines += rows
            st.max_lines = max(st.max_lines, st.lines)
            group = self._group_of(st.ordinal)
            if new_scene:
                self._scene_group[(view, frame_id)] = group
            if group not in self._decided:
                ok, why = self._decide()
                self._decided[group] = ok
                if ok:
                    self._in_flight.add(group)
                else:
                    self.counts["pairs_shed"] += 1
                    issues.append(
                        Issue(
                            Level.WARN,
                            f"{view}/{frame_id}",
                            f"overload: pair {group} (this scene and the other scene of its "
                            f"pair) shed whole: {why}; {self.counts['pairs_shed']} pairs shed "
                            "so far",
                        )
                    )
                self._prune()
            ok = self._decided[group]
            if not ok:
                self.counts["strips_shed"] += 1
                if new_scene:
                    self.counts["scenes_shed"] += 1
                    close = previous is not None and self._decided.get(previous, False)
            return ok, issues, close

    def _memory(self) -> tuple[int, int, int]:
        """(resident memory, raw data held, the rest of what is held), bytes.

        Held: resident less the free heap glibc keeps for reuse (:func:`held_bytes`), which the
        next allocations take before the resident memory grows again.
        """
        rss = rss_bytes()
        held = held_bytes(rss)
        raw = min(held, max(0, int(self.raw_held())))
        return rss, raw, held - raw

    def _group_of(self, ordinal: int) -> int:
        return ordinal // 2 if self.single else ordinal

    def _learn(self, rest: int) -> None:
        """Update the working set from a sample of the non-raw memory (lock held).

        The sample is the largest of ``rest`` and what :meth:`sample` saw since the last one.
        """
        if self.base:
            self._samples.append(max(0, max(rest, self._peak_rest) - self.base))
            self.working_set = max(self._samples)
        self._peak_rest = 0

    def sample(self) -> None:
        """Read the memory now (the worker, after each input): keeps the peak between samples.

        The reading is of memory still in use after the input (the free heap left out), so a
        transient the input freed is not seen: the floor of the working set and
        :data:`HEADROOM` are for those. When the resident memory is over the budget less the
        headroom, the free heap is given back (``malloc_trim``, at most every
        :data:`TRIM_INTERVAL_S`): a fragmented heap otherwise grew the resident memory pair by
        pair after a burst.
        """
        rss, _, rest = self._memory()
        now = time.monotonic()
        if rss > self.usable and now - self._trimmed >= TRIM_INTERVAL_S:
            self._trimmed = now  # the free heap kept beyond what the budget leaves: given back
            malloc_trim()
        with self._lock:
            self._peak_rest = max(self._peak_rest, rest)

    @property
    def usable(self) -> int:
        """The budget less :data:`HEADROOM`, bytes: what admitted pairs may need."""
        return int(self.budget * (1 - HEADROOM))

    def _work(self, pair: int) -> int:
        """The working set counted for a pair of ``pair`` bytes: learnt, or the floor, bytes."""
        return max(self.working_set, self.floor + int(self.floor_pairs * pair))

    def need(self, in_flight: int, raw: int = 0) -> int:
        """Memory to admit a pair with ``in_flight`` pairs already in flight, bytes."""
        pair = self.pair_bytes()
        return self.base + max(raw, (in_flight + 1) * pair) + self._work(pair)

    def _decide(self) -> tuple[bool, str]:
        if rss_bytes() > self.budget:
            malloc_trim()
        _rss, raw, rest = self._memory()
        self._learn(rest)
        if not self._in_flight:
            return True, ""
        n = len(self._in_flight)
        pair = self.pair_bytes()
        need = self.need(n, raw)
        mb = 2**20
        usable = self.usable
        # Consecutive pairs overlap in time: a budget below this sheds at any rate.
        least = self.need(1)
        short = (
            f" (the budget cannot hold two pairs in flight, which consecutive pairs need at "
            f"any rate: memory_budget_mb >= {math.ceil(least / (1 - HEADROOM) / mb)} would)"
            if least > usable
            else ""
        )
        if need > usable:
            work = self._work(pair)
            return False, (
                f"{n} pairs in flight; with this one it would need {need / mb:.0f} MB "
                f"(start-up {self.base / mb:.0f} MB + raw data "
                f"{max(raw, (n + 1) * pair) / mb:.0f} MB, {n + 1} x {pair / mb:.0f} MB or what is "
                f"held + working set {work / mb:.0f} MB), over {usable / mb:.0f} MB "
                f"(memory_budget_mb {self.budget / mb:.0f} MB less {HEADROOM:.0%} headroom)"
                f"{short}"
            )
        return True, ""

    def _prune(self) -> None:
        if len(self._decided) > 64:
            for g in sorted(self._decided)[: len(self._decided) - 64]:
                if g not in self._in_flight:
                    del self._decided[g]
        if len(self._scene_group) > 256:
            for key in list(self._scene_group)[: len(self._scene_group) - 256]:
                del self._scene_group[key]

    def published(self, view: str, scene_id: str) -> None:
        """A pair with this scene (of ``view``) was published: it and earlier pairs leave."""
        rest = self._memory()[2]  # the pair's working set is still held
        with self._lock:
            self._learn(rest)
            group = self._scene_group.get((view, scene_id))
            if group is None and self._in_flight:  # a scene id of the pipeline's own: pairs
                group = min(self._in_flight)  # come out in order, so it is the oldest one
            if group is not None:
                self._in_flight = {g for g in self._in_flight if g > group}

    def release_all(self) -> None:
        """Nothing is in flight any more (the flush at stop, or a scene timeout)."""
        with self._lock:
            self._in_flight.clear()
        malloc_trim()

    @property
    def in_flight(self) -> int:
        """Pairs admitted and not yet published."""
        return len(self._in_flight)


class ParprojNode(Node):
    """ROS 2 node: strips + navigation (+ GCP) -> ParallelProjection, StereoPair, images."""

    def _declare(self, name: str, p: Param) -> Any:
        """Declare one parameter; a bad value is replaced by the default and reported.

        Out of range or not among the choices: the node keeps running with the default, logs an
        error, and its 1 Hz summary stays at ERROR naming the parameter. A parameter with no
        safe default (``p.strict``: ``views``, ``<view>.mounting_rpy_deg``) is checked by its
        caller instead; rclpy refusing it raises :class:`StartupError`.
        """
        desc = _descriptor(p)
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
        self.pipeline = Pipeline(config)
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
        self._busy: tuple[str, float] | None = None  # the worker's input and since when
        self._closed = False  # set at shutdown: nothing more is published
        self._queue: queue.Queue[tuple[InputKind, Any] | None] = queue.Queue()
        self._queue_peak = 0  # longest input queue since the last 1 Hz summary, items
        self._queued_bytes = 0  # pixels of the strips in the queue, bytes
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
                self._queue.put((InputKind.GCP, load_gcp_file(path)))
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
        self._worker = threading.Thread(target=self._work, name="parproj_pipeline", daemon=True)
        self._worker.start()

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
                f"{_shown(given[name].value)} given, but parproj_node has no such parameter "
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
            item = (view, conv.stamp_to_ns(msg.header.stamp), msg.header.frame_id, arr)
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
        """Queue an input for the worker and keep the queue's peak length for the summary."""
        if item[0] == InputKind.STRIP:
            with self._counts_lock:
                self._queued_bytes += item[1][3].nbytes
        self._queue.put(item)
        self._queue_peak = max(self._queue_peak, self._queue.qsize())

    def _raw_held(self) -> int:
        """Raw scene data the node holds: line buffers (kept or in use), queued strips, bytes."""
        lines = sum(a.pool.live_bytes for a in list(self.pipeline.assemblers.values()))
        return lines + self._queued_bytes

    def _count(self, key: str, n: int = 1) -> None:
        """Add to a summary counter (callbacks and the worker count from two threads)."""
        with self._counts_lock:
            self.counts[key] += n

    # ---- worker: run the pipeline, publish ------------------------------------------------
    def _work(self) -> None:
        """The worker loop: one input at a time; no exception ends it (see :meth:`_handle`)."""
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                if item[0] == InputKind.STRIP:
                    with self._counts_lock:
                        self._queued_bytes -= item[1][3].nbytes
                self._handle(*item)
                self.admission.sample()
            except BaseException as err:  # _handle catches Exception; this is the last guard
                self.internal_error(f"an input ({item[0] if item else item})", err)
            finally:
                self._busy = None
                self._queue.task_done()

    def _handle(self, kind: InputKind, payload: Any) -> None:
        """Run one input through the pipeline and publish the outputs.

        Any exception is caught, counted (``internal_errors``) and reported as an ERROR naming
        the input and the exception; the input is dropped and the worker goes on.
        """
        try:
            what = _describe(kind, payload)
        except Exception:
            what = f"an input of kind {kind!r}"
        self._busy = (what, time.monotonic())
        flush_req = payload if kind == InputKind.FLUSH else None
        try:
            if kind == InputKind.NAV:
                out = self.pipeline.add_navigation(payload)
            elif kind == InputKind.STRIP:
                out = self.pipeline.add_strip(*payload)
            elif kind == InputKind.GCP:
                out = self.pipeline.add_gcp(payload)
            elif kind == InputKind.PAIRS:
                out = self.pipeline.set_pairs(payload)
            elif kind == InputKind.CLOSE:
                out = self.pipeline.close_idle_scenes()
            elif kind == InputKind.CLOSE_VIEW:
                out = self._close_view(payload)
            else:
                out = Outputs(issues=self._open_at_stop())
                out.extend(self.pipeline.flush())
                self.admission.release_all()
            self._publish(out)
            if flush_req is not None:
                flush_req.ok = True
        except Exception as err:
            self.internal_error(what, err)
        finally:
            if flush_req is not None:
                flush_req.done.set()

    def _close_view(self, view: str) -> Outputs:
        """Close and process the open scene of ``view`` (its next scene was shed whole).

        What ``Pipeline.close_scenes`` does, for one view: the scene is whole (its next one has
        begun), and the other view's open scene is left as it is.
        """
        out = Outputs()
        for scene in self.pipeline.assemblers[view].flush():
            out.extend(self.pipeline._scene_closed(scene))
        return out

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
            _stderr(f"parproj_node: internal error {err!r} on {what}; reporting it: {again!r}")

    def _open_at_stop(self) -> list[Issue]:
        """A WARN per scene still open when the node stops: the flush publishes it as it is."""
        issues = []
        for view, asm in self.pipeline.assemblers.items():
            opened = asm.open_scene()
            if opened is not None:
                issues.append(
                    Issue(
                        Level.WARN,
                        f"{view}/{opened.scene_id}",
                        f"node stopping with this scene open ({opened.lines} lines received): it "
                        "is closed and processed as it is; lines still to come are not in it",
                    )
                )
        return issues

    def _check_idle(self) -> None:
        idle = time.monotonic() - self._last_strip
        if self.scene_timeout > 0 and idle > self.scene_timeout and self.pipeline.has_open_scene:
            self._last_strip = time.monotonic()
            self._queue.put((InputKind.CLOSE, None))

    def worker_problem(self) -> str | None:
        """Why the worker is not doing its job (dead, or stalled on one input), or None."""
        if not self._worker.is_alive():
            return (
                "the worker thread is not running: inputs are no longer processed "
                f"({self._queue.qsize()} queued)"
            )
        busy = self._busy
        if busy is not None:
            held = time.monotonic() - busy[1]
            if held > self.worker_stall_s:
                return (
                    f"the worker has been processing {busy[0]} for {held:.0f} s "
                    f"(more than worker_stall_s, {self.worker_stall_s:g} s); "
                    f"{self._queue.qsize()} inputs queued behind it"
                )
        return None

    def flush(self, timeout_s: float | None = None, abort: Callable[[], bool] = bool) -> bool:
        """Close the open scenes (end of a pass) and wait until the worker has published them.

        Waits at most ``timeout_s`` (default ``stop_timeout_s``), or until ``abort()`` turns
        true (a second signal); with no worker running it does not wait at all. Returns whether
        the flush was done; if not, says why in an ERROR.
        """
        timeout_s = self.stop_timeout_s if timeout_s is None else timeout_s
        if not self._worker.is_alive():
            self._report(
                [Issue(Level.ERROR, "stop", "the worker thread is not running: open scenes lost")]
            )
            return False
        req = _FlushRequest()
        self._queue.put((InputKind.FLUSH, req))
        deadline = time.monotonic() + timeout_s
        why = ""
        while not req.done.wait(0.05):
            if not self._worker.is_alive():
                why = "the worker thread stopped"
            elif abort():
                why = "a second signal"
            elif time.monotonic() > deadline:
                busy = self._busy
                why = f"stop_timeout_s ({timeout_s:g} s) passed" + (
                    f" with the worker on {busy[0]} for {time.monotonic() - busy[1]:.0f} s"
                    if busy
                    else ""
                )
            if why:
                self._report(
                    [
                        Issue(
                            Level.ERROR,
                            "stop",
                            f"not flushed: {why}; {max(0, self._queue.qsize() - 1)} inputs "
                            "still queued and the open scenes are lost",
                        )
                    ]
                )
                return False
        return req.ok

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
            _stderr(f"parproj_node: reporting failed ({type(err).__name__}: {err}):")
            for iss in issues:
                _stderr(f"parproj_node: [{iss.level}] {iss.where}: {iss.message}")

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
        busy = self._busy
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status.append(
            DiagnosticStatus(
                level=bytes([level]),
                name="parproj_node: summary",
                message=message,
                values=[KeyValue(key=k, value=str(v)) for k, v in self.counts.items()]
                + [KeyValue(key=k, value=str(v)) for k, v in self.admission.counts.items()]
                + [
                    KeyValue(key=k, value=str(v))
                    for k, v in (
                        ("queue", self._queue.qsize()),
                        ("queue_max", max(self._queue_peak, self._queue.qsize())),
                        ("nav_samples", len(self.pipeline.nav)),
                        ("gcp_points", len(self.pipeline.gcp)),
                        ("pairs_in_flight", self.admission.in_flight),
                        ("working_set_mb", f"{self.admission.working_set / 2**20:.0f}"),
                        ("raw_mb", f"{self._raw_held() / 2**20:.0f}"),
                        ("startup_mb", f"{self.admission.base / 2**20:.0f}"),
                        ("held_mb", f"{held_bytes() / 2**20:.0f}"),
                        ("rss_mb", f"{rss_bytes() / 2**20:.0f}"),
                        ("memory_budget_mb", f"{self.admission.budget / 2**20:.0f}"),
                        ("worker", "dead" if not self._worker.is_alive() else "alive"),
                        ("busy_s", f"{time.monotonic() - busy[1]:.1f}" if busy else "0"),
                        ("busy_with", busy[0] if busy else ""),
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
        self._queue.put(None)
        if self._worker.is_alive():
            self._worker.join(timeout=timeout_s)
        self._closed = True
        if self.renderer is not None and not self._worker.is_alive():
            self.renderer.close()
            self.renderer = None


@dataclass
class _FlushRequest:
    """The flush at stop, queued to the worker: set ``done`` when handled, ``ok`` if it worked."""

    done: threading.Event = field(default_factory=threading.Event)
    ok: bool = False


def _describe(kind: InputKind, payload: Any) -> str:
    """The input a worker item stands for, in words (for errors and the watchdog)."""
    if kind == InputKind.STRIP:
        return f"a strip of {payload[0]}/{payload[2]}"
    if kind == InputKind.NAV:
        return "a navigation sample"
    if kind == InputKind.GCP:
        return f"a GCP set ({len(payload)} points)"
    if kind == InputKind.PAIRS:
        return "a pair selection"
    if kind == InputKind.CLOSE:
        return "the scene timeout"
    if kind == InputKind.CLOSE_VIEW:
        return f"the close of {payload}'s scene (its next scene shed)"
    return "the flush at stop"


def _stderr(text: str) -> None:
    """Print to stderr when logging itself failed; never raises."""
    try:
        print(text, file=sys.stderr, flush=True)
    except Exception:
        pass


def _one_line(text: str) -> str:
    """``text`` on one line (rcl messages end with ``, at /project/src/...`` locations)."""
    text = re.sub(r",? at /\S+:\d+", "", text)
    return " ".join(text.split())


def _params_files(argv: Sequence[str]) -> list[str]:
    """The ``--params-file`` arguments in ``argv``."""
    return [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--params-file"]


#: Largest parameters file the node reads, bytes (a real one is a few kB).
MAX_PARAMS_FILE_BYTES = 16 * 1024 * 1024


def _check_params_files(argv: Sequence[str]) -> None:
    """Each ``--params-file`` a regular file of at most :data:`MAX_PARAMS_FILE_BYTES`.

    Checked before rcl opens them: rcl would wait forever on a FIFO and read any size.

    Raises:
        StartupError: a parameters file that is missing, not a regular file, or too large.
    """
    import stat

    for f in _params_files(argv):
        try:
            st = os.stat(f)
        except OSError as err:
            raise StartupError(f"parameters file {f}: {err.strerror or err}") from None
        if not stat.S_ISREG(st.st_mode):
            raise StartupError(
                f"parameters file {f}: not a regular file (a folder, FIFO, socket or device): "
                "not read"
            )
        if st.st_size > MAX_PARAMS_FILE_BYTES:
            raise StartupError(
                f"parameters file {f}: {st.st_size} bytes, more than the "
                f"{MAX_PARAMS_FILE_BYTES} bytes a parameters file may have"
            )


def _init_rclpy(argv: list[str]) -> None:
    """``rclpy.init`` with rcl's own console output held back, shown again if init works.

    On a bad parameters file rcl prints "Failed to parse global arguments" before it raises;
    the node's one-line error says it all.

    Raises:
        StartupError: the ROS arguments or a parameters file cannot be parsed (or are not a
            regular file of a sensible size: :func:`_check_params_files`).
    """
    import tempfile

    _check_params_files(argv)
    with tempfile.TemporaryFile() as held:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(held.fileno(), 2)
        try:
            rclpy.init(args=argv, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        except Exception as err:
            files = _params_files(argv)
            where = f"parameters file {', '.join(files)}" if files else "ROS arguments"
            raise StartupError(f"cannot parse the {where}: {_one_line(str(err))}") from err
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        held.seek(0)
        text = held.read().decode(errors="replace")
    if text:
        _stderr(text.rstrip("\n"))


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
        _init_rclpy(argv)
        node = ParprojNode()
    except (StartupError, ParameterException, NameValidationException) as err:
        _stderr(f"parproj_node: cannot start: {_one_line(str(err))}")
        rclpy.try_shutdown()
        return EXIT_BAD_START
    except KeyboardInterrupt:
        _stderr("parproj_node: interrupted while starting")
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
