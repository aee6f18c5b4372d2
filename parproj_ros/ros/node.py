"""parproj_node: the rclpy adapter around a :class:`~parproj_ros.core.session.Session`.

It subscribes, converts, feeds and publishes, nothing more: the parameters come from the one
table (:mod:`parproj_ros.core.params`, declared by :mod:`.startup`), the topics and their QoS
from the interface contract (:mod:`parproj_ros.core.contract`); each callback converts its
message (:mod:`.conversions`) and queues it to the session's worker thread (so a long
resampling never blocks message reception), which runs it through the pipeline; what comes out
is published, and every problem is reported on ``/diagnostics`` (:mod:`.diagnostics`). The
overload policy is :mod:`parproj_ros.core.admission`. Topics and parameters: docs/node.md.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from functools import partial
from typing import Any

from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Image

from ..core import contract
from ..core.admission import PairAdmission, prefault, working_set_floor
from ..core.config import config_from_values
from ..core.dem_terrain import DemTerrain
from ..core.frames import ObjectFrame
from ..core.results import BlockResult, Issue, Level, Outputs
from ..core.session import InputKind, Session, Worker
from ..io.earth import earth_transform
from ..io.gcp_file import load_gcp_file
from . import conversions as conv
from .cdr import CdrError, read_image
from .diagnostics import Reporter
from .endpoints import advertise, subscribe
from .startup import (
    GIVEN_PARAMS_FILES,
    declare_all,
    exit_with,
    load_dem_parameters,
    machine_memory_mb,
    memory_issues,
    params_file_issues,
    quicklook_issues,
    run,
    start_line,
    unknown_parameters,
    wait_acked,
)

#: Navigation samples the navigation callback takes besides its own (those already waiting).
NAV_DRAIN_MAX = 100


class ParprojNode(Node):
    """ROS 2 node: strips + navigation (+ GCP) -> ParallelProjection, StereoPair, images."""

    def __init__(self, **kwargs: Any) -> None:
        """Declare and check the parameters, create the endpoints, start the worker.

        Raises:
            StartupError: a parameter without a safe default is invalid (``views``,
                ``<view>.mounting_rpy_deg``) or a QoS override cannot be applied; ``main``
                turns it into a one-line error and exit code 2.
        """
        super().__init__("parproj_node", **kwargs)
        # A node that cannot start is not destroyed: parproj_node then prints its one line and
        # leaves by os._exit (startup.exit_with). Destroying a DDS participant that has just
        # been created, or rclpy's teardown after it, was seen to die of SIGSEGV (-11) in 3 of
        # about 1,800 invalid starts (CI 2026-11-25 and 2026-11-27, once before the line).
        self._set_up()

    def _set_up(self) -> None:
        """The body of :meth:`__init__` after the rclpy node exists."""
        issues: list[Issue] = []
        vals = declare_all(self, issues)
        dem = load_dem_parameters(vals, issues)  # read now: a DEM that cannot serve does not start
        # outputs in the frame_id parameter, or ("") in the frame of the inputs (core/frames.py)
        self._frame = ObjectFrame(str(vals["frame_id"]))
        self.reporter = Reporter(self, lambda: self.frame_id, float(vals["error_hold_s"]))
        self.reporter.startup_issues = issues
        self.counts, self.pub_diag = self.reporter.counts, self.reporter.pub
        self._report, self.internal_error = self.reporter.report, self.reporter.internal_error
        self.log, self._count = self.reporter.log, self.reporter.count
        config = config_from_values(vals)
        self.session = Session(config)
        self.pipeline = self.session.pipeline
        if dem is not None:  # placed in the outputs' object frame as it is at each pair
            self.pipeline.use_dem(DemTerrain(dem, lambda: self.frame_id))
            self.log("info", f"dem {dem.name} ({dem.reference}): the pairs' terrain from it")
        if bool(vals["render_process"]):
            issues += self.session.start_renderer()
        if bool(vals["tile_thread"]):
            self.pipeline.use_tile_thread()
        # Streamed blocks are published as each is rendered (the render process renders the
        # next one meanwhile), not gathered until the input's other outputs are made.
        self.pipeline.set_block_sink(self._publish_block, self._blocks_wanted)
        self.blocks_unsubscribed = 0  # streamed blocks not sent: no subscriber (volatile)
        prefault_mb, said_memory = memory_issues(
            config,
            float(vals["prefault_mb"]),
            float(vals["memory_budget_mb"]),
            machine_memory_mb(),
        )
        issues += said_memory + quicklook_issues(config)
        if said := prefault(config, prefault_mb, self.pipeline.assemblers):
            self.log("info", said)
        self.worker_stall_s = float(vals["worker_stall_s"])
        self.stop_timeout_s = float(vals["stop_timeout_s"])
        self.stereo_pair_images = bool(vals["stereo_pair_images"])
        self.anaglyph = bool(vals["anaglyph"])
        self.dsm_cloud_step = config.dense.cloud_step
        self.admission = PairAdmission(
            vals["views"],
            float(vals["memory_budget_mb"]),
            config.scenes.lines,
            self._raw_held,
            *working_set_floor(config),
            book=self.pipeline.ledger.admission,
            tiles_held=self._tiles_held,
            quicklook=self.pipeline.tiles is not None and self.pipeline.tiles.quicklook,
        )
        self.worker = Worker(self._handle, self.internal_error)
        inputs: dict[str, Callable[[Any], None]] = {contract.NAVIGATION: self._on_nav}
        for v in config.views:
            inputs[contract.strip_topic(v.name)] = partial(self._on_strip, v.name)
        inputs |= {contract.GCP: self._on_gcp, contract.PAIRS: self._on_pairs}
        self._nav_sub = subscribe(self, inputs)[contract.NAVIGATION]
        # Outputs: every topic of the contract's table (the offline process writes the same).
        self.pubs = advertise(self, int(vals["latched_depth"]))
        self.create_timer(1.0, self._summary)
        self.scene_timeout = float(vals["scene_timeout"])
        self._last_strip = time.monotonic()
        self.create_timer(0.25, self._check_idle)
        if vals["gcp_file"]:
            self._load_gcp_file(str(vals["gcp_file"]), issues)
        issues += unknown_parameters(self)
        used = {k: v.value for k, v in self._parameter_overrides.items()}
        issues += params_file_issues(self.get_fully_qualified_name(), GIVEN_PARAMS_FILES, used)
        self.log("info", start_line(vals))
        self._announced = ""
        self._announce_frame()  # a frame_id parameter given: its place on Earth now
        self._report(issues)
        self.worker.start()

    def _load_gcp_file(self, path: str, issues: list[Issue]) -> None:
        """Queue the points of the ``gcp_file`` parameter; an ERROR in ``issues`` if unreadable.

        A relative path is taken from the node's working folder, and named so: a node started
        by a launch file may not run where its user thinks.
        """
        path = os.path.abspath(os.path.expanduser(path))
        self.log("info", f"gcp_file {path}: loading")
        try:
            self.worker.put(InputKind.GCP, load_gcp_file(path))
        except Exception as err:  # whatever the loader raises: a clear error, not a crash
            why = f"{type(err).__name__}: {err}"
            where = why if path in str(err) else f"{path}: {why}"
            issues.append(Issue(Level.ERROR, "gcp_file", f"{where}; continuing without it"))

    def _observe(self, where: str, frame_id: str) -> None:
        """Note an input's frame (a WARN if not the outputs'); then :meth:`_announce_frame`."""
        self._report(self._frame.observe(where, frame_id))
        self._announce_frame()

    def _announce_frame(self) -> None:
        """Once the outputs' frame is known, say where it is on Earth (once per frame)."""
        frame = self.frame_id
        if frame == self._announced or not (self._frame.given or self._frame.seen):
            return
        self._announced = frame
        if (t := earth_transform(frame)) is not None:
            now = self.get_clock().now().nanoseconds
            self.pubs[contract.OBJECT_FRAME].publish(conv.earth_transform_to_msg(t, stamp_ns=now))
            self._report([Issue(Level.OK, "object frame", f"{frame}: {t.definition}")])

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
            self._report([Issue(Level.WARN, contract.NAVIGATION, f"{err}: sample dropped")])
            return
        except Exception as err:
            self.internal_error("a navigation message (callback)", err)
            return
        self._observe(contract.NAVIGATION, msg.header.frame_id)
        self._enqueue((InputKind.NAV, sample))
        self._count("nav")

    def _on_strip(self, view: str, raw: bytes | Image) -> None:
        """A strip, as its CDR bytes (``raw=True`` subscription) or an Image."""
        try:
            msg = read_image(raw)
        except CdrError as err:
            self._count("strips_rejected")
            why = f"strip rejected: unreadable CDR ({err}): dropped"
            self._report([Issue(Level.WARN, view, why)])
            return
        except Exception as err:
            self.internal_error(f"a strip of {view} (CDR)", err)
            return
        if not self._admit(view, msg):
            self._count("strips")
            return
        try:
            item = conv.strip_from_msg(view, msg)
        except conv.ConversionError as err:
            self._count("strips_rejected")
            where = f"{view}/{msg.header.frame_id}"
            self._report([Issue(Level.WARN, where, f"strip rejected: {err}: dropped")])
            return
        except Exception as err:
            self.internal_error(f"a strip of {view} (callback)", err)
            return
        self._count("strips")
        self._last_strip = time.monotonic()
        self._enqueue((InputKind.STRIP, item))

    def _admit(self, view: str, msg: Any) -> bool:
        """Whether the admission takes this strip (its pair is shed when not: a WARN)."""
        try:
            fields = (str(msg.header.frame_id), int(msg.height), len(msg.data))
        except Exception:  # not an Image at all: the conversion reports it
            return True
        try:
            ok, shed, close = self.admission.admit(view, *fields)
        except Exception as err:
            self.internal_error(f"a strip of {view} (admission)", err)
            return True
        self._report(shed)
        if close:
            self._enqueue((InputKind.CLOSE_VIEW, view))
        return ok

    def _on_gcp(self, msg: Any) -> None:
        try:
            self._observe(contract.GCP, msg.header.frame_id)
            points = conv.gcp_from_msg(msg)
        except Exception as err:
            self.internal_error("a GCP message (callback)", err)
            return
        self._enqueue((InputKind.GCP, points))

    def _on_pairs(self, msg: Any) -> None:
        try:
            self._enqueue((InputKind.PAIRS, conv.pairs_from_msg(msg)))
        except conv.ConversionError as err:
            self._report([Issue(Level.ERROR, contract.PAIRS, f"{err}: pair selection dropped")])
        except Exception as err:
            self.internal_error("a pair selection (callback)", err)

    def _enqueue(self, item: tuple[InputKind, Any]) -> None:
        """Queue an input for the worker."""
        self.worker.put(*item)

    def _raw_held(self) -> int:
        """Raw scene data the node holds: line buffers (kept or in use), queued strips, bytes."""
        lines = sum(a.pool.live_bytes for a in list(self.pipeline.assemblers.values()))
        return lines + self.worker.queued_bytes

    def _tiles_held(self) -> int:
        """Bytes the streamed DSM tiles hold (columns kept for tiles still to come)."""
        tiles = self.pipeline.tiles
        return 0 if tiles is None else tiles.held_bytes()

    def _check_idle(self) -> None:
        idle = time.monotonic() - self._last_strip
        if self.scene_timeout > 0 and idle > self.scene_timeout and self.pipeline.has_open_scene:
            self._last_strip = time.monotonic()
            self.worker.put(InputKind.CLOSE, None)

    # ---- worker: run the session, publish --------------------------------------------------
    def _handle(self, kind: InputKind, payload: Any) -> None:
        """Run one input through the session and publish the outputs (the worker's thread)."""
        early = self.session.open_at_stop() if kind == InputKind.FLUSH else []
        out = self.session.feed(kind, payload)
        out.issues[:0] = early
        if kind == InputKind.FLUSH:
            self.admission.release_all()
        self._publish(out)
        self.admission.sample()

    def _publish(self, out: Outputs) -> None:
        if self.reporter.closed:
            return
        now = self.get_clock().now().nanoseconds
        for topic, msg, _ in conv.outputs_to_messages(
            out,
            frame_id=self.frame_id,
            stamp_ns=now,
            stereo_pair_images=self.stereo_pair_images,
            anaglyph=self.anaglyph,
            dsm_cloud_step=self.dsm_cloud_step,
            raw_blocks=True,  # blocks published as CDR bytes: one copy instead of three
        ):
            if topic in self.pubs:
                self.pubs[topic].publish(msg)
        for pair in out.pairs:
            self.admission.published(pair.left.scene.view, pair.left.scene.scene_id)
        self.reporter.outputs(out)

    def _publish_block(self, blk: BlockResult) -> None:
        """Publish one streamed block as it is rendered (its pixels borrowed). Never raises.

        A block topic nobody subscribes to gets nothing: it is volatile, so no subscriber,
        present or later, could receive the block (image_transport's lazy publishing); its
        CDR copy and DDS write (7 MB a block at the IKONOS width) are saved, and the
        summary's ``blocks_unsubscribed`` counts the blocks not sent. A draft block (quick-look
        only, rendered so because nobody subscribed, :attr:`BlockResult.draft`) is never sent.
        """
        if self.reporter.closed:
            return
        topic = contract.normalized_block_topic(blk.side)
        if blk.draft or self.pubs[topic].get_subscription_count() == 0:
            self.blocks_unsubscribed += 1
            return
        try:
            self.pubs[topic].publish(conv.block_to_cdr(blk, frame_id=self.frame_id))
        except Exception as err:
            self.internal_error(
                f"block {blk.index} of pair {blk.pair_id} ({topic}; only that block is lost)", err
            )

    def _blocks_wanted(self, side: str) -> bool:
        """Whether anybody subscribes to ``side``'s blocks (else they may be drafts)."""
        return int(self.pubs[contract.normalized_block_topic(side)].get_subscription_count()) > 0

    # ---- health, stop ----------------------------------------------------------------------
    def worker_problem(self) -> str | None:
        """Why the worker is not doing its job (dead, or stalled on one input), or None."""
        return self.worker.problem(self.worker_stall_s)

    def summary_status(self) -> tuple[int, str]:
        """Level and message of the 1 Hz summary (:meth:`.diagnostics.Reporter.status`)."""
        return self.reporter.status(self.worker_problem())

    def _summary(self) -> None:
        busy = self.worker.busy
        self.reporter.summary(
            *self.summary_status(),
            [
                *self.admission.counts.items(),
                *self.pipeline.ledger.counts().items(),
                ("blocks_unsubscribed", self.blocks_unsubscribed),
                *self._render_values(),
                ("queue", self.worker.qsize()),
                ("queue_max", self.worker.take_peak()),
                ("nav_samples", len(self.pipeline.nav)),
                ("gcp_points", len(self.pipeline.gcp)),
                *self.admission.memory_values(),
                ("worker", "alive" if self.worker.alive else "dead"),
                ("busy_s", f"{time.monotonic() - busy[1]:.1f}" if busy else "0"),
                ("busy_with", busy[0] if busy else ""),
            ],
        )

    def _render_values(self) -> list[tuple[str, object]]:
        """The render process's counts for the summary.

        Blocks rendered there, draft blocks rendered and reduced there, blocks rendered in the
        worker instead (the process failed, or a line buffer it cannot see).
        """
        r = self.session.renderer
        if r is None:
            return [("render_blocks", 0), ("render_drafts", 0), ("render_fallbacks", 0)]
        return [
            ("render_blocks", r.rendered),
            ("render_drafts", r.drafts),
            ("render_fallbacks", r.fallbacks),
        ]

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

    def wait_delivered(self, timeout_s: float) -> bool:
        """Wait until every subscriber acknowledged the outputs (:func:`.startup.wait_acked`)."""
        return wait_acked([*self.pubs.values(), self.pub_diag], timeout_s, self.log)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the worker thread (after the queue drains, ``timeout_s`` at most).

        Nothing is published after it.
        """
        self.worker.stop(timeout_s)
        self.reporter.closed = True
        if not self.worker.alive:
            self.session.close()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``parproj_node``: run the node until SIGINT/SIGTERM (:func:`.startup.run`).

    Exit codes: 0 after a clean stop; 1 when the open scenes could not be flushed at the stop;
    2 when the node could not start (one line on stderr, no traceback).
    """
    return run(ParprojNode, args)


def entry() -> None:
    """The ``parproj_node`` command: :func:`main`, then exit with its code."""
    exit_with(main())


if __name__ == "__main__":
    entry()
