"""Shared test set-up: the ROS environment defaults, and the ROS-free run.

Markers (registered in setup.cfg): ``ros`` for tests that need rclpy, DDS or ROS message
packages (live node, replay, recording, bags read or written: the bag reader deserializes with
rclpy), ``slow`` for tests that take more than about 5 s. ``./dev test`` runs everything;
``./dev fast`` (``pytest -m "not ros and not slow"``) is the fast ROS-free part.

A run whose ``-m`` expression leaves out every ``ros`` test is a ROS-free run: any import of
rclpy, a message package or the rest of the ROS 2 Python packages is refused (ModuleNotFoundError)
and fails the test that tried it, with a message asking for the ``ros`` marker; test modules
marked ``ros`` as a whole (``pytestmark``) are not even imported. So a ROS-free run needs no
ROS 2 installation. ``PARPROJ_NO_ROS=1`` forces this mode (and deselects the ros tests) whatever
``-m`` says. Not covered: child processes (a test that runs our code in a subprocess needing ROS
is marked by hand).

Helpers shared by several test modules are in ``testkit/`` (``scenes``, ``diagnostics``,
``rasters``: ROS-free; ``live``: rclpy nodes of the tests).

This module itself must not import ROS (it is loaded before any test module).
"""

from __future__ import annotations

import ast
import importlib.abc
import os
import sys
from collections.abc import Generator, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

# ---- the ROS environment ------------------------------------------------------------------------

# ./dev sets these for every run; a bare `pytest` gets the same safe defaults: DDS stays on this
# machine, and the domain is not the default 0 shared with every other ROS user of the machine.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(os.getpid() % 100 + 100))


# ---- the ROS-free run ---------------------------------------------------------------------------

ROS_NAMES = frozenset({"rclpy", "rpyutils", "ament_index_python", "tracetools"})
ROS_PREFIXES = ("rosidl_", "rcl", "rmw", "ament_")
ROS_SUFFIXES = ("_msgs", "_interfaces")


def is_ros_module(name: str) -> bool:
    """Whether ``name`` belongs to ROS 2: rclpy, rcl*, rmw*, rosidl_*, message packages.

    Not ROS: ``mcap``, ``mcap_ros2`` and ``rosbags`` (pure-Python MCAP and CDR libraries).
    """
    top = name.partition(".")[0]
    return top in ROS_NAMES or top.startswith(ROS_PREFIXES) or top.endswith(ROS_SUFFIXES)


class RosImportBlocker(importlib.abc.MetaPathFinder):
    """Refuses ROS imports and remembers which test tried them."""

    def __init__(self, why: str) -> None:
        self.why = why
        self.current = "(collection)"
        self.hits: dict[str, list[str]] = {}

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> None:
        if not is_ros_module(fullname):
            return None
        self.hits.setdefault(self.current, []).append(fullname)
        raise ModuleNotFoundError(
            f"import of {fullname!r} refused: this is a ROS-free run ({self.why}); "
            "a test that needs ROS must be marked ros",
            name=fullname,
        )


_blocker: RosImportBlocker | None = None


def _excludes_ros(markexpr: str) -> bool:
    """Whether ``-m markexpr`` deselects every test marked ``ros`` (with or without ``slow``)."""
    if not markexpr:
        return False
    from _pytest.mark.expression import Expression

    expr = Expression.compile(markexpr)
    return not any(
        expr.evaluate(lambda name, /, marks=marks, **kw: not kw and name in marks)
        for marks in ({"ros"}, {"ros", "slow"})
    )


def _module_marked_ros(path: Path) -> bool:
    """Whether a test module says ``pytestmark = ... pytest.mark.ros ...`` (read, not imported)."""
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"))
    except (OSError, SyntaxError):
        return False
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets
        ):
            for sub in ast.walk(node.value):
                if (
                    isinstance(sub, ast.Attribute)
                    and sub.attr == "ros"
                    and isinstance(sub.value, ast.Attribute)
                    and sub.value.attr == "mark"
                ):
                    return True
    return False


def pytest_configure(config: pytest.Config) -> None:
    global _blocker
    markexpr = config.getoption("markexpr", "") or ""
    if os.environ.get("PARPROJ_NO_ROS") == "1":
        why = "PARPROJ_NO_ROS=1"
    elif _excludes_ros(markexpr):
        why = f"-m {markexpr!r}"
    else:
        return
    loaded = sorted(m for m in sys.modules if is_ros_module(m))
    if loaded:
        raise pytest.UsageError(f"ROS-free run, but ROS modules are already imported: {loaded}")
    _blocker = RosImportBlocker(why)
    sys.meta_path.insert(0, _blocker)


def pytest_unconfigure(config: pytest.Config) -> None:
    global _blocker
    if _blocker is not None:
        sys.meta_path.remove(_blocker)
        _blocker = None


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """In a ROS-free run, test modules marked ros as a whole are not imported."""
    if _blocker is not None and collection_path.suffix == ".py":
        if collection_path.name.startswith("test_") and _module_marked_ros(collection_path):
            return True
    return None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """In a ROS-free run (PARPROJ_NO_ROS=1 without -m too), tests marked ros are deselected."""
    if _blocker is None:
        return
    ros = [item for item in items if item.get_closest_marker("ros") is not None]
    if ros:
        config.hook.pytest_deselected(items=ros)
        items[:] = [item for item in items if item.get_closest_marker("ros") is None]


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Generator:
    if _blocker is not None:
        _blocker.current = item.nodeid
    try:
        return (yield)
    finally:
        if _blocker is not None:
            _blocker.current = "(between tests)"


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[Any]) -> Generator:
    """A test that tried a ROS import in a ROS-free run fails, even if it caught the error."""
    report = yield
    tried = _blocker.hits.pop(item.nodeid, None) if _blocker is not None else None
    if tried and _blocker is not None:
        report.outcome = "failed"
        report.longrepr = (
            f"{item.nodeid} is not marked ros but imported {sorted(set(tried))} "
            f"({_blocker.why}); mark it with @pytest.mark.ros (or the module with "
            "pytestmark = pytest.mark.ros)"
        )
    return report
