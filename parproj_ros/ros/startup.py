"""The node's start: its parameters' descriptors and checks, its command line, rclpy's init.

What can go wrong before ``parproj_node`` runs becomes one line on stderr and exit code 2
(:class:`StartupError`); nothing here needs a node.
"""

from __future__ import annotations

import array
import math
import os
import re
import sys
from collections.abc import Sequence
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from ..core.config import Param

#: Exit codes of parproj_node (README, "Exit codes").
EXIT_OK, EXIT_NOT_FLUSHED, EXIT_BAD_START = 0, 1, 2


class StartupError(Exception):
    """The node cannot start.

    A parameter without a safe default, the parameters file, a QoS override: ``main`` prints it
    as one line and exits with :data:`EXIT_BAD_START`.
    """


def descriptor(p: Param) -> ParameterDescriptor:
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


def shown(value: Any) -> str:
    """A parameter value as the user wrote it (arrays and tuples as lists)."""
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
            f"parameter views: {shown(value)} is not a list of view names "
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
            f"parameter {name}: {shown(value)} is not 3 numbers [roll, pitch, yaw] in degrees"
        )
    rpy = (float(value[0]), float(value[1]), float(value[2]))
    if not all(math.isfinite(a) and abs(a) <= 360.0 for a in rpy):
        raise StartupError(
            f"parameter {name}: {list(rpy)!r}: each angle must be finite and within +-360 deg"
        )
    return rpy


def to_stderr(text: str) -> None:
    """Print to stderr when logging itself failed; never raises."""
    try:
        print(text, file=sys.stderr, flush=True)
    except Exception:
        pass


def one_line(text: str) -> str:
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


def init_rclpy(argv: list[str]) -> None:
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
            raise StartupError(f"cannot parse the {where}: {one_line(str(err))}") from err
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        held.seek(0)
        text = held.read().decode(errors="replace")
    if text:
        to_stderr(text.rstrip("\n"))
