"""A stand-in of the ROS 2 launch API, to load launch/parproj.launch.py where launch has no wheel.

:func:`load_launch` executes a launch file with this module's classes in place of ``launch`` and
``launch_ros`` (only for the duration of the call) and returns what its
``generate_launch_description()`` built: the declared arguments and the nodes, with their
parameters and remaps as written. :func:`node_ros_args` turns a node into the ``--ros-args``
that launch_ros gives the process, for given launch arguments: so a test can start the node
exactly as the launch file configures it.

ROS-free: imports neither launch nor rclpy.
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import yaml


class Substitution:
    """A value known only when launching (the launch API's Substitution)."""


@dataclass(frozen=True)
class LaunchConfiguration(Substitution):
    """The value of a launch argument."""

    variable_name: str


@dataclass(frozen=True)
class FindPackageShare(Substitution):
    """A package's share directory, from the ament index."""

    package: str


@dataclass(frozen=True)
class PathJoinSubstitution(Substitution):
    """Path parts joined with ``/``."""

    substitutions: Sequence[Any]


@dataclass(frozen=True)
class ParameterValue:
    """A parameter value with the type it is converted to (launch_ros.parameter_descriptions)."""

    value: Any
    value_type: type | None = None


@dataclass(frozen=True)
class DeclareLaunchArgument:
    """A launch argument, its default (text or a substitution) and its description."""

    name: str
    default_value: Any = None
    description: str = ""


@dataclass
class Node:
    """launch_ros.actions.Node: the keyword arguments as given."""

    package: str
    executable: str
    name: str = ""
    namespace: str = ""
    parameters: Sequence[Any] = ()
    remappings: Sequence[tuple[Any, Any]] = ()
    ros_arguments: Sequence[Any] = ()
    arguments: Sequence[Any] = ()
    output: str = "log"


@dataclass
class LaunchDescription:
    """The entities a launch file returns."""

    entities: Sequence[Any] = ()

    @property
    def arguments(self) -> dict[str, DeclareLaunchArgument]:
        """The declared launch arguments by name."""
        return {e.name: e for e in self.entities if isinstance(e, DeclareLaunchArgument)}

    @property
    def nodes(self) -> list[Node]:
        """The nodes launched."""
        return [e for e in self.entities if isinstance(e, Node)]


def _module(name: str, **attrs: Any) -> ModuleType:
    mod = ModuleType(name)
    mod.__dict__.update(attrs)
    return mod


@contextmanager
def _stubbed_launch_api() -> Iterator[None]:
    """``launch`` and ``launch_ros`` in sys.modules as this module's classes, then restored."""
    stubs = {
        "launch": _module("launch", LaunchDescription=LaunchDescription),
        "launch.actions": _module("launch.actions", DeclareLaunchArgument=DeclareLaunchArgument),
        "launch.substitutions": _module(
            "launch.substitutions",
            LaunchConfiguration=LaunchConfiguration,
            PathJoinSubstitution=PathJoinSubstitution,
        ),
        "launch_ros": _module("launch_ros"),
        "launch_ros.actions": _module("launch_ros.actions", Node=Node),
        "launch_ros.parameter_descriptions": _module(
            "launch_ros.parameter_descriptions", ParameterValue=ParameterValue
        ),
        "launch_ros.substitutions": _module(
            "launch_ros.substitutions", FindPackageShare=FindPackageShare
        ),
    }
    saved = {name: sys.modules.get(name) for name in stubs}
    sys.modules.update(stubs)
    try:
        yield
    finally:
        for name, mod in saved.items():
            if mod is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = mod


def load_launch(path: Path, source: str | None = None) -> LaunchDescription:
    """Execute the launch file ``path`` (or ``source`` in its place) against the stand-in API.

    Returns:
        what its ``generate_launch_description()`` returned.
    """
    with _stubbed_launch_api():
        spec = importlib.util.spec_from_loader("parproj_launch_under_test", loader=None)
        assert spec is not None
        mod = importlib.util.module_from_spec(spec)
        mod.__file__ = str(path)
        code = compile(source if source is not None else path.read_text(), str(path), "exec")
        exec(code, mod.__dict__)
        desc = mod.generate_launch_description()
    assert isinstance(desc, LaunchDescription), f"{path}: not a LaunchDescription: {desc!r}"
    return desc


def resolve(
    value: Any, args: Mapping[str, str], share: Callable[[str], Path] = lambda p: Path(p)
) -> str:
    """The text of ``value`` at launch: launch arguments from ``args``, shares from ``share``.

    Raises:
        KeyError: a launch argument with no value in ``args``.
    """
    if isinstance(value, str):
        return value
    if isinstance(value, LaunchConfiguration):
        return args[value.variable_name]
    if isinstance(value, FindPackageShare):
        return str(share(value.package))
    if isinstance(value, PathJoinSubstitution):
        return "/".join(resolve(v, args, share) for v in value.substitutions)
    if isinstance(value, (list, tuple)):
        return "".join(resolve(v, args, share) for v in value)
    raise TypeError(f"not a substitution: {value!r}")


def parameter_value(value: Any, args: Mapping[str, str]) -> Any:
    """A parameter's value as launch_ros gives it to the node.

    A :class:`ParameterValue` of ``str`` keeps the text; another type parses it as YAML and must
    give that type; a bare substitution is parsed as YAML (launch_ros' rule).
    """
    if isinstance(value, ParameterValue):
        text = resolve(value.value, args)
        if value.value_type is str:
            return text
        parsed = yaml.safe_load(text)
        if value.value_type is not None and not isinstance(parsed, value.value_type):
            raise TypeError(f"{text!r} is not a {value.value_type.__name__}")
        return parsed
    if isinstance(value, Substitution):
        return yaml.safe_load(resolve(value, args))
    return value


def launch_arguments(desc: LaunchDescription, given: Mapping[str, str]) -> dict[str, str]:
    """Every declared argument's value: ``given`` (``name:=value`` on the command line) or its
    default (a substitution default stays a substitution, see :func:`resolve`).

    Raises:
        KeyError: an argument given that the file does not declare, or one without a value.
    """
    declared = desc.arguments
    unknown = sorted(set(given) - set(declared))
    if unknown:
        raise KeyError(f"launch arguments not declared: {unknown}")
    out: dict[str, Any] = {}
    for name, arg in declared.items():
        if name in given:
            out[name] = given[name]
        elif arg.default_value is None:
            raise KeyError(f"launch argument {name!r} has no default and was not given")
        else:
            out[name] = arg.default_value
    return out


def node_ros_args(
    node: Node,
    desc: LaunchDescription,
    given: Mapping[str, str],
    share: Callable[[str], Path],
    workdir: Path,
) -> list[str]:
    """The ``--ros-args ... --`` block launch_ros gives ``node``'s process.

    Parameter files are passed in order; a dict of parameters is written to a file of its own
    in ``workdir`` (as launch_ros does, under ``/**``); remaps as ``-r from:=to``.
    """
    # a default may itself be a substitution (params_file's FindPackageShare path)
    values = {k: resolve(v, {}, share) for k, v in launch_arguments(desc, given).items()}
    out = ["--ros-args", *(resolve(a, values, share) for a in node.ros_arguments)]
    if node.name:
        out += ["-r", f"__node:={node.name}"]
    if node.namespace:
        out += ["-r", f"__ns:={node.namespace}"]
    for k, entry in enumerate(node.parameters):
        if isinstance(entry, dict):
            params = {name: parameter_value(v, values) for name, v in entry.items()}
            path = workdir / f"launch_params_{k}.yaml"
            path.write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
            out += ["--params-file", str(path)]
        else:
            out += ["--params-file", resolve(entry, values, share)]
    for src, dst in node.remappings:
        out += ["-r", f"{resolve(src, values, share)}:={resolve(dst, values, share)}"]
    return [*out, "--"]
