"""The node's process: its command line, rclpy's init, its parameters, the spin and the stop.

What can go wrong before ``parproj_node`` runs becomes one line on stderr and exit code 2
(:class:`StartupError`); :func:`run` spins a node until a signal, then flushes and stops it.
"""

from __future__ import annotations

import array
import contextlib
import math
import os
import re
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    NameValidationException,
    ParameterException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from ..core import contract
from ..core.config import PARAMS, VIEW_PARAMS, Param
from ..core.results import Issue, Level

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


def check_frame_id(value: Any) -> str:
    """The ``frame_id`` parameter: "" (the inputs' frame), any name, or a tangent plane.

    Raises:
        StartupError: ``enu_wgs84:...`` that does not parse, or whose origin cannot be (a
            latitude beyond +-90 deg, a figure not finite): the outputs would carry a frame
            that ``parproj dsm`` cannot place, and no object-frame transform would be published;
            a name beginning with "/", which tf2 (and so RViz) refuses.
    """
    from ..io.geotiff import frame_of
    from ..io.scene_import import TANGENT_PLANE_FORM

    text = str(value)
    if text.startswith("/"):
        raise StartupError(
            f"parameter frame_id: {text!r} begins with '/', which tf2 refuses in a frame id "
            f"(RViz would show none of the outputs): write {text.lstrip('/')!r}"
        )
    try:
        frame_of(text)
    except ValueError as err:
        raise StartupError(f"parameter frame_id: {text!r}: {err}; {TANGENT_PLANE_FORM}") from None
    return text


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


def rcl_init_error(text: str, files: Sequence[str]) -> str:
    """The command line rcl refused, as one line naming what it refused.

    The parameters file only when rcl could not parse a file (a ``-p`` or ``-r`` rule beside a
    good file was blamed on the file); rcl's "Error: error not set" after a rule with nothing
    after ``:=`` says so.
    """
    said = one_line(text)
    rule = re.search(r"'(-[pr] [^']*:=)'", said)
    if rule is not None:
        said = said.replace("Error: error not set", "Error: no value after ':='")
    in_file = files and "params file" in said
    where = f"parameters file {', '.join(files)}" if in_file else "ROS arguments"
    return f"cannot parse the {where}: {said}"


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
    GIVEN_PARAMS_FILES[:] = _params_files(argv)
    with tempfile.TemporaryFile() as held:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(held.fileno(), 2)
        try:
            rclpy.init(args=argv, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        except Exception as err:
            raise StartupError(rcl_init_error(str(err), _params_files(argv))) from err
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        held.seek(0)
        text = held.read().decode(errors="replace")
    if text:
        to_stderr(text.rstrip("\n"))


def declare(node: Node, name: str, p: Param, issues: list[Issue]) -> Any:
    """Declare one parameter of ``node``; a bad value is replaced by the default and reported.

    The value given (``--params-file``, ``-p``) is checked first (:meth:`Param.check`): a whole
    number for a double and a double with no fraction for an integer are taken as that type;
    a wrong type, a value out of range (``low`` itself for a ``low_open`` row) or not among the
    choices: the node keeps running with the default, which its parameter services then report
    too, an ERROR is added to ``issues`` and the 1 Hz summary stays at ERROR naming the
    parameter. A parameter with no safe default (``p.strict``: ``views``,
    ``<view>.mounting_rpy_deg``) is checked by its caller instead; rclpy refusing it raises
    :class:`StartupError`.
    """
    desc = descriptor(p)
    overrides = node._parameter_overrides  # rclpy: the values given for this node
    given = overrides.get(name)
    if given is not None and given.value is None and p.default == []:
        # A parameters file's "dem: []" (config/parproj_node.yaml) reaches rclpy as no value:
        # it is the default, an empty list, not a parameter without a value.
        return node.declare_parameter(name, p.default, desc, ignore_override=True).value
    if given is not None and p.strict and p.type not in ("string_array", "double_array"):
        # No safe default (the DEM's vertical reference): a bad value does not start the node.
        value, problem = p.check(given.value)
        if problem:
            raise StartupError(f"parameter {name}: {problem}")
        if type(value) is not type(given.value):  # 50 for a double
            overrides[name] = Parameter(name, value=value)
    if given is not None and not p.strict:
        value, problem = p.check(given.value)
        if problem:
            issues.append(
                Issue(
                    Level.ERROR,
                    f"parameter {name}",
                    f"{problem}; the default {p.default!r} is used",
                )
            )
            return node.declare_parameter(name, p.default, desc, ignore_override=True).value
        if type(value) is not type(given.value):  # 100 for a double, 1000.0 for an integer
            overrides[name] = Parameter(name, value=value)
    try:
        return node.declare_parameter(name, p.default, desc).value
    except (InvalidParameterValueException, InvalidParameterTypeException) as err:
        if p.strict:
            raise StartupError(f"parameter {name}: {err}") from err
        issues.append(
            Issue(Level.ERROR, f"parameter {name}", f"{err}; the default {p.default!r} is used")
        )
        return node.declare_parameter(name, p.default, desc, ignore_override=True).value


def check_dem_files(value: Any) -> list[str]:
    """The ``dem`` parameter as a list of files ([]: no DEM).

    A parameters file's ``dem: []`` reaches the node as no value at all (rcl), and one file
    given as a string (``-p dem:=N44E005.hgt``) is taken as that file.

    Raises:
        StartupError: not a list of file names, or an empty name in it.
    """
    if value is None or (isinstance(value, array.array | list | tuple) and len(value) == 0):
        return []
    files = [value] if isinstance(value, str) else value
    if not isinstance(files, list | tuple) or not all(isinstance(f, str) for f in files):
        raise StartupError(
            f"parameter dem: {shown(value)} is not a list of DEM files (e.g. [N44E005.hgt], "
            "or [] for none)"
        )
    if not all(f.strip() for f in files):
        raise StartupError(f"parameter dem: {shown(value)} holds an empty file name")
    return [os.path.expanduser(f) for f in files]


#: How messages name the DEM's parameters (parproj_ros/io/dem.py ``dem_from_options``).
DEM_PARAMETERS = {
    "dem": "parameter dem",
    "geoid": "parameter geoid",
    "geoid_undulation": "parameter geoid_undulation",
    "dem_ellipsoidal": "parameter dem_ellipsoidal",
}


def load_dem_parameters(vals: Mapping[str, Any], issues: list[Issue] | None = None) -> Any:
    """The DEM of the parameters ``dem`` .. ``dem_ellipsoidal`` (None without ``dem``).

    Read at start, so that a DEM that cannot serve does not start the node. A WARN in
    ``issues`` for a ``geoid_undulation`` without ``dem`` (ignored: it applies to no DEM).

    Returns:
        A ``parproj_ros.io.dem.DemHeights``, or None.

    Raises:
        StartupError: a DEM file missing, unreadable (GDAL) or without a CRS, a geoid grid
            likewise or an unknown geoid model, two vertical references at once, a geoid
            option without ``dem``: one line naming the parameter and the file.
    """
    from ..io.dem import dem_from_options
    from ..io.files import InputError

    try:
        return dem_from_options(
            vals["dem"],
            geoid_undulation=float(vals["geoid_undulation"]),
            geoid=str(vals["geoid"]),
            ellipsoidal=bool(vals["dem_ellipsoidal"]),
            names=DEM_PARAMETERS,
            warn=None
            if issues is None
            else lambda text: issues.append(Issue(Level.WARN, "parameter geoid_undulation", text)),
        )
    except InputError as err:  # DemError too: the file at fault, and what is wrong
        if err.path.startswith("parameter "):  # named so by dem_from_options
            raise StartupError(str(err)) from None
        which = "dem" if err.path in {*vals["dem"], ", ".join(vals["dem"])} else "geoid"
        path = str(vals["geoid"]) if err.path == "--geoid" else err.path
        missing = err.problem.startswith("no such file") and not os.path.isabs(path)
        folder = f" (from the node's working folder, {os.getcwd()})" if missing else ""
        raise StartupError(f"parameter {which}: {path}{folder}: {err.problem}") from None


def declare_all(node: Node, issues: list[Issue]) -> dict[str, Any]:
    """Declare every parameter of the table (and of each view): name -> value.

    Raises:
        StartupError: ``views``, ``frame_id``, ``dem`` or a ``<view>.mounting_rpy_deg`` is
            invalid (the DEM's files themselves: :func:`load_dem_parameters`).
    """
    vals = {p.name: declare(node, p.name, p, issues) for p in PARAMS}
    vals["views"] = check_views(vals["views"])
    vals["frame_id"] = check_frame_id(vals["frame_id"])
    vals["dem"] = check_dem_files(vals["dem"])
    for view in vals["views"]:
        for p in VIEW_PARAMS:
            vals[f"{view}.{p.name}"] = declare(node, f"{view}.{p.name}", p, issues)
        key = f"{view}.mounting_rpy_deg"
        vals[key] = check_mounting(key, vals[key])
    return vals


#: The ``--params-file`` arguments of the process's :func:`init_rclpy` (checked by
#: :func:`params_file_issues` once the node knows its name).
GIVEN_PARAMS_FILES: list[str] = []

#: How a QoS override is named (rclpy's QoS overriding; the topic resolved, with its "/").
QOS_OVERRIDE_FORM = (
    "qos_overrides./<topic>.subscription.<history|depth|reliability> for the inputs "
    "navigation and <view>/image_strip, qos_overrides./<topic>.publisher."
    "<history|depth|reliability|durability> for the outputs"
)


def unknown_parameters(node: Node) -> list[Issue]:
    """An ERROR per parameter given (``--params-file``, ``-p``) that the node does not have.

    A misspelt name, a view not in ``views``, or a QoS override of a topic or policy that takes
    none (``qos_overrides.navigation...`` without the topic's "/", ``...subscriber...``, the
    ``gcp`` input): its value would be ignored silently. Called once the endpoints exist (rclpy
    declares the QoS overrides they take).
    """
    given = node._parameter_overrides  # rclpy: every override for this node
    issues = []
    for name in sorted(given):
        if node.has_parameter(name):
            continue
        hint = (
            f"no such QoS override (they are {QOS_OVERRIDE_FORM})"
            if name.startswith("qos_overrides.")
            else "no such parameter (misspelt, or a view not in views?)"
        )
        issues.append(
            Issue(
                Level.ERROR,
                f"parameter {name}",
                f"{shown(given[name].value)} given, but parproj_node has {hint}: ignored",
            )
        )
    return issues


def _sections(tree: Any, path: str = "") -> list[tuple[str, Any]]:
    """The node sections of a parameters file's YAML: (node name as written, its parameters)."""
    out: list[tuple[str, Any]] = []
    if not isinstance(tree, dict):
        return out
    for key, sub in tree.items():
        if key == "ros__parameters":
            out.append((path or "/", sub))
        else:
            out += _sections(sub, f"{path}/{str(key).strip('/')}")
    return out


def _flat(tree: Any, prefix: str = "") -> dict[str, Any]:
    """The parameters under a ``ros__parameters`` key (nested keys make dotted names)."""
    if not isinstance(tree, dict):
        return {prefix: tree}
    out: dict[str, Any] = {}
    for key, sub in tree.items():
        out.update(_flat(sub, f"{prefix}.{key}" if prefix else str(key)))
    return out


def section_applies(section: str, fqn: str) -> bool:
    """Whether a parameters file's section ``section`` applies to the node named ``fqn``.

    As rcl matches them: the name is fully qualified (a leading "/" added), ``**`` stands for
    any number of name tokens and ``*`` for one (or part of one).
    """
    parts = []
    for token in section.strip("/").split("/"):
        if token == "**":
            parts.append("(/[^/]+)*")
        else:
            parts.append("/" + re.escape(token).replace(r"\*", "[^/]*"))
    return re.fullmatch("".join(parts), fqn) is not None


def params_file_issues(
    fqn: str, files: Sequence[str], used: Mapping[str, Any] | None = None
) -> list[Issue]:
    """What a user would not see of the parameters files given to the node named ``fqn``.

    An ERROR per file with no section for the node (a misspelt node name, or the node renamed
    with ``-r __node:=``; a WARN when it has no section at all): none of its values is used,
    although the node would otherwise start as if it had read them. A WARN per parameter that
    a file sets to a value other than the table's default and a later file back to the
    default (the later file wins, in silence: parproj.launch.py passes ``frame_id`` and
    ``heights`` after ``params_file``, so a value of either there is overridden even by those
    arguments' defaults), naming the value used (``used``: the node's overrides). Files
    layered on purpose (a later one changing a value to another than the default) are not
    reported. A file that does not parse here (rcl read it) is left alone.
    """
    import yaml

    issues = []
    given: dict[str, list[tuple[str, Any]]] = {}
    for f in files:
        try:
            with open(f, encoding="utf-8") as fh:
                tree = yaml.safe_load(fh)
        except Exception:
            continue
        sections = _sections(tree)
        mine = [sub for name, sub in sections if section_applies(name, fqn)]
        for sub in mine:
            for name, value in _flat(sub).items():
                given.setdefault(name, []).append((f, value))
        if mine:
            continue
        if not sections:
            why = "holds no parameters (no section with ros__parameters): nothing set from it"
            issues.append(Issue(Level.WARN, "parameters file", f"{f}: {why}"))
            continue
        n = sum(len(_flat(sub)) for _, sub in sections)
        names = ", ".join(name.lstrip("/") for name, _ in sections)
        issues.append(
            Issue(
                Level.ERROR,
                "parameters file",
                f"{f}: no section for this node, {fqn} (the file's sections: {names}): none of "
                f"its {n} parameters is used (name the section {fqn.lstrip('/')} or /**)",
            )
        )
    defaults = {p.name: p.default for p in PARAMS}
    defaults |= {
        f"{v}.{p.name}": p.default for v in (used or {}).get("views", []) for p in VIEW_PARAMS
    }
    for name, values in given.items():
        if used is None or name not in used or name not in defaults:
            continue
        *earlier, (last_file, last) = values
        lost = [(f, v) for f, v in earlier if v != defaults[name]]
        if last != defaults[name] or not lost:
            continue
        where = ", ".join(f"{v!r} in {f}" for f, v in lost)
        issues.append(
            Issue(
                Level.WARN,
                f"parameter {name}",
                f"given {where}, but a later file, {last_file}, sets the default {last!r}: "
                f"{shown(used[name])} used (with parproj.launch.py, give frame_id and heights "
                "as its arguments: it passes them after params_file, defaults too)",
            )
        )
    return issues


#: Line buffers of a scene each that the prefault touches per view (``BufferPool.keep``,
#: parproj_ros/imaging/assembly.py; docs/node.md, ``prefault_mb``: "two line buffers").
LINE_BUFFERS = 2


def machine_memory_mb() -> tuple[float | None, float | None]:
    """(memory of this machine or of the process's cgroup, whichever is less; available), MB.

    From ``/proc/meminfo`` (MemTotal, MemAvailable) and cgroup v2's ``memory.max``; None
    where unknown (not Linux).
    """
    info: dict[str, float] = {}
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                key, _, rest = line.partition(":")
                info[key] = float(rest.split()[0]) / 1024.0  # kB -> MB
    total = info.get("MemTotal")
    with contextlib.suppress(OSError, ValueError):
        with open("/sys/fs/cgroup/memory.max", encoding="ascii") as fh:
            limit = fh.read().strip()
        if limit.isdigit():
            total = min(total or math.inf, int(limit) / 2**20)
    return total, info.get("MemAvailable")


def memory_issues(
    config: Any, prefault_mb: float, budget_mb: float, machine: tuple[float | None, float | None]
) -> tuple[float, list[Issue]]:
    """``prefault_mb`` to use, and what is wrong with it and ``memory_budget_mb``.

    The prefault touches ``prefault_mb`` MB of heap (-1: two raw pairs of the configured
    scenes) and, when it is > 0 and ``scene_lines`` is set, the line buffers each view's pool
    keeps (:data:`LINE_BUFFERS`, a scene each)
    (:func:`parproj_ros.core.admission.prefault`). More than the memory budget leaves (less its
    headroom), or than the machine has available (``machine``: :func:`machine_memory_mb`), and
    it is not done (0: an ERROR when ``prefault_mb`` was given, a WARN for -1): the node would
    start over its own budget, or be killed by the kernel before it has read a strip
    (``scene_lines`` 1e7, in its range, asks two raw pairs of 1.1 TB). A ``memory_budget_mb``
    above the machine's memory is a WARN: the kernel, not the admission, would then end an
    overload.
    """
    from ..core.admission import HEADROOM, auto_prefault_mb
    from ..core.memory import raw_pair_bytes

    issues: list[Issue] = []
    total, available = machine
    if total is not None and budget_mb > total:
        issues.append(
            Issue(
                Level.WARN,
                "parameter memory_budget_mb",
                f"{budget_mb:g} MB is more than this machine's memory, {total:.0f} MB: the "
                "kernel may end the node (out of memory) before the admission sheds a pair; "
                "set it below that",
            )
        )
    heap = auto_prefault_mb(config) if prefault_mb < 0 else prefault_mb
    lines = LINE_BUFFERS * raw_pair_bytes(config) / 2**20 if heap > 0 else 0.0
    usable = budget_mb * (1.0 - HEADROOM)
    room = (
        f"the {usable:.0f} MB that memory_budget_mb {budget_mb:g} MB leaves (less "
        f"{HEADROOM:.0%} headroom)"
    )
    if available is not None and available < usable:
        room = f"the {available:.0f} MB this machine has available"
        usable = available
    if heap + lines <= usable:
        return prefault_mb, issues
    what = (
        f"{prefault_mb:g}"
        if prefault_mb >= 0
        else f"-1 (two raw pairs of scene_lines {config.scenes.lines})"
    )
    issues.append(
        Issue(
            Level.ERROR if prefault_mb >= 0 else Level.WARN,
            "parameter prefault_mb",
            f"{what} asks {heap:.0f} MB of heap and {lines:.0f} MB of line buffers touched at "
            f"start, more than {room}: nothing touched (as prefault_mb 0)",
        )
    )
    return 0.0, issues


def quicklook_issues(config: Any) -> list[Issue]:
    """A WARN when ``heights_quicklook`` is set but no pair can get quick-look tiles.

    They are made while a pair streams (:meth:`parproj_ros.core.tiles.TileStage.applies`):
    heights on, two views, ``scene_lines`` > 0, streaming on. Otherwise the setting does
    nothing, and nothing would say so (``scene_lines`` is 0 by default).
    """
    from ..core.tiles import TileStage

    level = config.dense.quicklook
    if not level or TileStage.applies(config):
        return []
    why = [
        text
        for off, text in (
            (not config.dense.enabled, "heights is off"),
            (config.single_camera, "one view (single-camera mode)"),
            (config.scenes.lines <= 0, "scene_lines is 0"),
            (not config.stream.enabled, "streaming is off"),
        )
        if off
    ]
    return [
        Issue(
            Level.WARN,
            "parameter heights_quicklook",
            f"{level}: no quick-look tiles will be made: {', '.join(why)} (they are made while "
            "a pair streams: heights on, two views, scene_lines > 0, streaming on)",
        )
    ]


def wants_help(argv: Sequence[str]) -> bool:
    """Whether the command line asks for the usage (``-h``/``--help`` before ``--ros-args``)."""
    own = list(argv[1:])
    if "--ros-args" in own:
        own = own[: own.index("--ros-args")]
    return any(a in ("-h", "--help") for a in own)


def usage() -> str:
    """``parproj_node --help``: how to run it, its topics, its parameters (from the tables)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        __version__ = version("parproj_ros")
    except PackageNotFoundError:  # a source tree not installed
        __version__ = "(not installed)"

    lines = [
        f"parproj_node {__version__}: parallel-projection parameters and epipolar-normalized "
        "stereo pairs of pushbroom scanners",
        "",
        "usage: parproj_node [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] "
        "[-r FROM:=TO ...]]",
        "       (or: ros2 run parproj_ros parproj_node --ros-args ...)",
        "",
        "subscribes: " + ", ".join(t.name for t in contract.INPUTS if t.subscribed),
        "publishes:  " + ", ".join(t.name for t in contract.OUTPUTS),
        "",
        "parameters (name, type, default; every one in docs/node.md and "
        "config/parproj_node.yaml):",
    ]
    for p in PARAMS:
        lines.append(f"  {p.name} ({p.type}, default {p.default!r})")
    lines.append("per view (<view>.NAME, for each name in views):")
    for p in VIEW_PARAMS:
        lines.append(f"  <view>.{p.name} ({p.type}, default {p.default!r})")
    lines.append("")
    lines.append("exit codes: 0 clean stop, 1 open scenes not flushed at the stop, 2 cannot start")
    return "\n".join(lines)


def start_line(vals: dict[str, Any]) -> str:
    """The INFO line at start: views, topics, and the parameters that differ from defaults."""
    views = list(vals["views"])
    changed = [
        f"{p.name}={vals[p.name]!r}"
        for p in PARAMS
        if p.name != "views" and p.name in vals and vals[p.name] != p.default
    ]
    for v in views:
        for p in VIEW_PARAMS:
            key = f"{v}.{p.name}"
            value = vals.get(key, p.default)
            if _differs(value, p.default):
                changed.append(f"{key}={shown(value)}")
    subs = [contract.NAVIGATION, *(contract.strip_topic(v) for v in views)]
    subs += [contract.GCP, contract.PAIRS]
    return (
        f"starting: views {', '.join(views)}; subscribed {', '.join(subs)}; publishing "
        f"{len(contract.OUTPUTS)} topics ({', '.join(t.name for t in contract.OUTPUTS)}); "
        + (
            "parameters not at their default: " + ", ".join(changed)
            if changed
            else "every parameter at its default"
        )
    )


def _differs(value: Any, default: Any) -> bool:
    if isinstance(value, list | tuple | array.array):
        return list(value) != list(default)
    return bool(value != default)


def run(make_node: Callable[[], Any], args: list[str] | None = None) -> int:
    """Start a node (``make_node()``), spin until SIGINT/SIGTERM, then flush and stop it.

    The node has ``internal_error``, ``log``, ``flush``, ``wait_delivered``, ``stop`` and
    ``stop_timeout_s`` (:class:`~parproj_ros.ros.node.ParprojNode`).

    Exit codes: 0 after a clean stop; 1 when the open scenes could not be flushed at the stop
    (the worker was dead, or did not finish within ``stop_timeout_s``, or a second signal came);
    2 when the node could not start: the ROS arguments or a parameters file do not parse, or a
    parameter without a safe default is invalid (one line on stderr, no traceback).
    """
    import signal

    argv = list(sys.argv if args is None else args)
    if wants_help(argv):
        print(usage())
        return EXIT_OK
    try:
        init_rclpy(argv)
        node = make_node()
    except (StartupError, ParameterException, NameValidationException) as err:
        # No rclpy shutdown: the caller leaves by os._exit (exit_with); tearing down a node
        # that has just joined DDS was seen to crash (ParprojNode.__init__).
        to_stderr(f"parproj_node: cannot start: {one_line(str(err))}")
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
        node.log("info", f"stopping: flushing open scenes ({node.stop_timeout_s:g} s at most)")
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


def exit_with(code: int) -> None:
    """Leave the process with ``code``.

    A node that could not start leaves at once (``os._exit`` once stdout and stderr are
    flushed): nothing is in flight, and the interpreter's teardown of rclpy and Fast DDS after a
    node was created and destroyed was seen to die of SIGSEGV (-11) after the one-line error,
    instead of exiting 2, in 2 of about 1,800 invalid starts (CI 2026-11-25 and 2026-11-27,
    ``test_invalid_start_exits_2_with_one_line``).
    """
    if code == EXIT_BAD_START:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)
    sys.exit(code)


def wait_acked(pubs: Sequence[Any], timeout_s: float, log: Callable[[str, str], None]) -> bool:
    """Wait until every subscriber has acknowledged what ``pubs`` published (``timeout_s``).

    So that the outputs of the flush at shutdown are not lost when the process exits; a WARN
    (``log``) names each topic not acknowledged in time.
    """
    from rclpy.duration import Duration

    deadline = time.monotonic() + timeout_s
    done = True
    for pub in pubs:
        left = max(0.0, deadline - time.monotonic())
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
            done = False
            log(
                "warn",
                f"{pub.topic_name}: not acknowledged by every subscriber within {timeout_s} s "
                "of stopping",
            )
    return done
