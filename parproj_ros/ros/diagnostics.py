"""The node's reporting: issues logged, counted and published on ``/diagnostics``; the summary.

Every problem the node meets is an :class:`~parproj_ros.core.results.Issue` (what was wrong and
what was done): logged at its level, counted, and published as a DiagnosticStatus. Reporting is
called from the worker and from callbacks and never raises: when logging or publishing fails,
the issues go to stderr. The 1 Hz summary's level follows :meth:`Reporter.status`.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from ..core import contract
from ..core.results import Issue, Level, Outputs
from . import conversions as conv
from .startup import to_stderr

#: The name of the summary status.
SUMMARY = "parproj_node: summary"


class Reporter:
    """Logs, counts and publishes the node's issues; makes its 1 Hz summary.

    ``hardware_id()`` names what the statuses are about (the object frame). Thread-safe: the
    counters take a lock; the rest only publishes.
    """

    def __init__(self, node: Node, hardware_id: Callable[[], str], error_hold_s: float) -> None:
        self._node = node
        self._hardware_id = hardware_id
        #: An ERROR status keeps the summary at ERROR this long, s.
        self.error_hold_s = error_hold_s
        row = contract.topic(contract.DIAGNOSTICS)
        self.pub = node.create_publisher(DiagnosticArray, row.name, conv.qos_profile(row.qos))
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
        self._lock = threading.Lock()
        self.last_error: tuple[float, str] | None = None  # (monotonic, "where: message")
        #: Problems found at start (a parameter refused, the gcp_file): ERROR for the node's life.
        self.startup_issues: list[Issue] = []
        #: Set at shutdown: nothing more is published.
        self.closed = False

    def count(self, key: str, n: int = 1) -> None:
        """Add to a summary counter (callbacks and the worker count from two threads)."""
        with self._lock:
            self.counts[key] += n

    def log(self, level: str, text: str) -> None:
        """Log ``text`` at ``level`` ("error", "warn", anything else: info).

        One call site per severity, on purpose: rclpy fixes the severity of a logging call site
        (function, file, line, bytecode offset) at its first call and raises ``ValueError:
        Logger severity cannot be changed between calls`` when the same site later logs at
        another one (``log = logger.error if ... else logger.warning; log(...)`` did).
        """
        logger = self._node.get_logger()
        if level == "error":
            logger.error(text)
        elif level == "warn":
            logger.warning(text)
        else:
            logger.info(text)

    def report(self, issues: Sequence[Issue]) -> None:
        """Log the issues, count them, and publish them on ``/diagnostics``. Never raises.

        If logging or publishing fails, the issues (and why) are printed to stderr instead, so
        that reporting cannot end either.
        """
        if not issues or self.closed:
            return
        try:
            for iss in issues:
                if iss.level == "error":
                    self.count("errors")
                    self.last_error = (time.monotonic(), f"{iss.where}: {iss.message}")
                elif iss.level == "warn":
                    self.count("warnings")
                self.log(iss.level, f"{iss.where}: {iss.message}")
            self.pub.publish(
                conv.issues_to_diagnostics(
                    list(issues),
                    stamp_ns=self._node.get_clock().now().nanoseconds,
                    hardware_id=self._hardware_id(),
                )
            )
        except Exception as err:
            to_stderr(f"parproj_node: reporting failed ({type(err).__name__}: {err}):")
            for iss in issues:
                to_stderr(f"parproj_node: [{iss.level}] {iss.where}: {iss.message}")

    def outputs(self, out: Outputs) -> None:
        """Count and log the scenes and pairs of ``out`` (an INFO line each); report its issues."""
        for res in out.scenes:
            self.count("scenes")
            sc = res.scene
            self.log("info", f"scene {sc.view}/{sc.scene_id}: {sc.lines} lines, {res.method}")
        for pair in out.pairs:
            self.count("pairs")
            mean, rms, mx = pair.y_parallax_stats
            self.log(
                "info",
                f"pair {pair.pair_id}: {pair.left_grid.width}x{pair.left_grid.height} px, "
                f"y-parallax ({pair.y_parallax_source}) mean {mean:.3f} rms {rms:.3f} "
                f"max {mx:.3f} px",
            )
        self.report(out.issues)

    def internal_error(self, what: str, err: BaseException) -> None:
        """Count an exception caught in the node and report it. Never raises.

        An ERROR on ``/diagnostics`` (status ``parproj_node: internal error``) naming the input,
        the exception and where it was raised; ``internal_errors`` in the summary.
        """
        try:
            self.count("internal_errors")
            tb = traceback.extract_tb(err.__traceback__)
            at = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno} in {tb[-1].name}" if tb else ""
            self.report(
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

    def status(self, worker_problem: str | None) -> tuple[int, str]:
        """Level and message of the summary.

        ERROR while any of these holds, OK otherwise: a parameter was refused at start (or the
        gcp_file could not be loaded: an ERROR at start), for the node's life;
        ``worker_problem`` (the worker is not running, or has been on one input longer than
        ``worker_stall_s``); an ERROR status was reported less than :attr:`error_hold_s` ago.
        WARN statuses (at start too) do not change the level
        (they are counted in ``warnings``).
        """
        problems = [worker_problem] if worker_problem else []
        last = self.last_error
        if last is not None and time.monotonic() - last[0] < self.error_hold_s:
            problems.append(
                f"{self.counts['errors']} errors so far, the latest "
                f"{time.monotonic() - last[0]:.0f} s ago: {last[1]}"
            )
        refused = [i for i in self.startup_issues if i.level == "error"]
        if refused:  # a WARN at start (an option ignored, a memory note) is counted, no more
            problems.append("at start: " + "; ".join(f"{i.where}: {i.message}" for i in refused))
        if problems:
            return DiagnosticStatus.ERROR[0], "running; " + "; ".join(problems)
        return DiagnosticStatus.OK[0], "running"

    def summary(self, level: int, message: str, values: Iterable[tuple[str, Any]]) -> None:
        """Publish the summary status: ``level``, ``message``, the counters, then ``values``."""
        if self.closed:
            return
        arr = DiagnosticArray()
        arr.header.stamp = self._node.get_clock().now().to_msg()
        pairs = [*self.counts.items(), *values]
        arr.status.append(
            DiagnosticStatus(
                level=bytes([level]),
                name=SUMMARY,
                message=message,
                hardware_id=self._hardware_id(),
                values=[KeyValue(key=k, value=str(v)) for k, v in pairs],
            )
        )
        self.pub.publish(arr)
