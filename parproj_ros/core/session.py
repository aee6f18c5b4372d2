"""One session of the pipeline, shared by both front ends: ``feed(kind, payload)`` and a worker.

The node (:mod:`parproj_ros.ros.node`) and ``parproj process`` (:mod:`parproj_ros.apps.process`)
turn their messages into the same inputs (:class:`InputKind` and its payload) and hand them to
:meth:`Session.feed`, the one dispatch onto the :class:`~parproj_ros.core.pipeline.Pipeline`.
The node runs the session in a :class:`Worker` (one thread, one input at a time, so a long
resampling never blocks message reception); ``parproj process`` feeds it from its read-ahead
thread's queue in its own thread. Nothing here imports ROS.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from .config import PipelineConfig
from .pipeline import Pipeline
from .render_process import RenderProcess
from .results import Issue, Level, Outputs


class InputKind(StrEnum):
    """What an input is (its payload's type in brackets)."""

    NAV = "nav"  # a navigation sample (trajectory.NavSample)
    STRIP = "strip"  # a strip of scan lines (Strip)
    GCP = "gcp"  # ground control and check points (a list of results.GroundPoint)
    PAIRS = "pairs"  # a pair selection ([(left scene id, right scene id)])
    CLOSE = "close"  # the scene timeout: close the idle scenes (None)
    CLOSE_VIEW = "close_view"  # a view's next scene was shed: close its open scene (view name)
    FLUSH = "flush"  # end of data (the node: a FlushRequest; process: None)


class Strip(NamedTuple):
    """One strip of scan lines of a view.

    ``pixels`` (lines, detectors) of ``view``, its first line exposed at ``stamp_ns`` (ns), in
    the scene ``scene_id`` (the strip's frame_id).
    """

    view: str
    stamp_ns: int
    scene_id: str
    pixels: NDArray[np.generic]


@dataclass
class FlushRequest:
    """The flush at stop, queued to the worker: ``done`` set when handled, ``ok`` if it worked."""

    done: threading.Event = field(default_factory=threading.Event)
    ok: bool = False


def describe(kind: InputKind, payload: Any) -> str:
    """The input in words (for errors and the watchdog)."""
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


class Session:
    """A pipeline and the one dispatch of inputs onto it."""

    def __init__(self, config: PipelineConfig) -> None:
        self.pipeline = Pipeline(config)
        #: The process rendering streamed blocks (:meth:`start_renderer`), or None.
        self.renderer: RenderProcess | None = None

    def feed(self, kind: InputKind, payload: Any) -> Outputs:
        """Run one input through the pipeline; what it produced.

        Raises what the pipeline raises (the node's worker reports it and goes on).
        """
        p = self.pipeline
        if kind == InputKind.NAV:
            return p.add_navigation(payload)
        if kind == InputKind.STRIP:
            return p.add_strip(*payload)
        if kind == InputKind.GCP:
            return p.add_gcp(payload)
        if kind == InputKind.PAIRS:
            return p.set_pairs(payload)
        if kind == InputKind.CLOSE:
            return p.close_idle_scenes()
        if kind == InputKind.CLOSE_VIEW:
            return p.close_view(payload)
        return p.flush()

    def start_renderer(self) -> list[Issue]:
        """Render streamed blocks in a child process (two views, ``scene_lines`` set).

        Call before the first strip. A WARN when the process cannot start (no /dev/shm, no
        process): the blocks are then rendered in the calling thread.
        """
        config = self.pipeline.config
        if self.renderer is not None or config.scenes.lines <= 0 or len(config.views) != 2:
            return []
        try:
            self.renderer = RenderProcess()
            self.pipeline.use_render_process(self.renderer)
        except Exception as err:  # no /dev/shm, no process: render in the worker
            return [
                Issue(
                    Level.WARN,
                    "render_process",
                    f"cannot start the render process ({type(err).__name__}: {err}): "
                    "streamed blocks are rendered in the worker thread",
                )
            ]
        return []

    def close(self) -> None:
        """Stop the render process and the tile thread, if any (no input may be fed after)."""
        self.pipeline.close()
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

    def open_at_stop(self) -> list[Issue]:
        """A WARN per scene still open when a node stops: the flush publishes it as it is."""
        issues = []
        for view, opened in self.pipeline.open_scenes().items():
            issues.append(
                Issue(
                    Level.WARN,
                    f"{view}/{opened.scene_id}",
                    f"node stopping with this scene open ({opened.lines} lines received): it "
                    "is closed and processed as it is; lines still to come are not in it",
                )
            )
        return issues


class Worker:
    """One thread taking inputs from a queue in order and handing each to ``handle``.

    ``handle(kind, payload)`` runs the input (the node: feed, publish); an exception it raises
    goes to ``on_error(what, err)`` and the worker carries on with the next input. The worker
    keeps what it is busy with (:attr:`busy`) for the watchdog (:meth:`problem`), the queue's
    peak length, and the bytes of the strips queued (raw data the admission counts).
    """

    def __init__(
        self,
        handle: Callable[[InputKind, Any], None],
        on_error: Callable[[str, BaseException], None],
        *,
        name: str = "parproj_pipeline",
    ) -> None:
        self._handle = handle
        self._on_error = on_error
        self._queue: queue.Queue[tuple[InputKind, Any] | None] = queue.Queue()
        self._lock = threading.Lock()
        #: The input being handled, in words, and since when (monotonic s); None when idle.
        self.busy: tuple[str, float] | None = None
        #: Longest queue since :meth:`take_peak`, inputs.
        self.peak = 0
        #: Pixels of the strips queued, bytes.
        self.queued_bytes = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        """Start taking inputs (those put before are taken first)."""
        self._thread.start()

    @property
    def alive(self) -> bool:
        """Whether the worker thread runs."""
        return self._thread.is_alive()

    def qsize(self) -> int:
        """Inputs queued."""
        return self._queue.qsize()

    def take_peak(self) -> int:
        """The longest queue since the last call (at least the queue now), inputs."""
        peak, self.peak = max(self.peak, self._queue.qsize()), 0
        return peak

    def put(self, kind: InputKind, payload: Any) -> None:
        """Queue one input."""
        if kind == InputKind.STRIP:
            with self._lock:
                self.queued_bytes += payload[3].nbytes
        self._queue.put((kind, payload))
        self.peak = max(self.peak, self._queue.qsize())

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                kind, payload = item
                if kind == InputKind.STRIP:
                    with self._lock:
                        self.queued_bytes -= payload[3].nbytes
                self._one(kind, payload)
            except BaseException as err:  # _one catches Exception; this is the last guard
                self._on_error(f"an input ({item[0] if item else item})", err)
            finally:
                self.busy = None
                self._queue.task_done()

    def _one(self, kind: InputKind, payload: Any) -> None:
        try:
            what = describe(kind, payload)
        except Exception:
            what = f"an input of kind {kind!r}"
        self.busy = (what, time.monotonic())
        request = payload if isinstance(payload, FlushRequest) else None
        try:
            self._handle(kind, payload)
            if request is not None:
                request.ok = True
        except Exception as err:
            self._on_error(what, err)
        finally:
            if request is not None:
                request.done.set()

    def problem(self, stall_s: float) -> str | None:
        """Why the worker is not working (dead, or on one input over ``stall_s``), or None."""
        if not self.alive:
            return (
                "the worker thread is not running: inputs are no longer processed "
                f"({self.qsize()} queued)"
            )
        busy = self.busy
        if busy is not None:
            held = time.monotonic() - busy[1]
            if held > stall_s:
                return (
                    f"the worker has been processing {busy[0]} for {held:.0f} s "
                    f"(more than worker_stall_s, {stall_s:g} s); "
                    f"{self.qsize()} inputs queued behind it"
                )
        return None

    def flush(self, timeout_s: float, abort: Callable[[], bool] = bool) -> tuple[bool, str]:
        """Queue the flush and wait until handled: (whether it worked, why not when known).

        Waits at most ``timeout_s`` or until ``abort()`` turns true (a second signal); a worker
        not running is not waited for. A flush that raised is (False, ""): ``on_error`` has
        reported it.
        """
        if not self.alive:
            return False, "the worker thread is not running: open scenes lost"
        req = FlushRequest()
        self._queue.put((InputKind.FLUSH, req))
        deadline = time.monotonic() + timeout_s
        while not req.done.wait(0.05):
            why = ""
            if not self.alive:
                why = "the worker thread stopped"
            elif abort():
                why = "a second signal"
            elif time.monotonic() > deadline:
                busy = self.busy
                why = f"stop_timeout_s ({timeout_s:g} s) passed" + (
                    f" with the worker on {busy[0]} for {time.monotonic() - busy[1]:.0f} s"
                    if busy
                    else ""
                )
            if why:
                return False, (
                    f"not flushed: {why}; {max(0, self.qsize() - 1)} inputs still queued and "
                    "the open scenes are lost"
                )
        return req.ok, ""

    def stop(self, timeout_s: float) -> None:
        """Stop after the queue drains (``timeout_s`` at most)."""
        self._queue.put(None)
        if self.alive:
            self._thread.join(timeout=timeout_s)
