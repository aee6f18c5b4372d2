"""The package as a ROS workspace sees it (docs/ros.md), without ROS.

- launch/parproj.launch.py, executed with a stand-in of the launch API (launch has no wheel
  here): its node is this package's console script, every parameter it sets is a row of the
  parameter table (parproj_ros/core/params.py) with the table's default and type, every remap
  names an input the node subscribes to (parproj_ros/core/contract.py), every launch argument
  is used; and the checker catches each kind of mistake in a doctored copy;
- setup.cfg installs the scripts where ``ros2 run`` looks and the launch and config files
  under share/parproj_ros; colcon_defaults.yaml makes colcon find msg_defs/.

tests/ros/test_colcon_workspace.py builds the workspace with the real colcon and runs the
installed node as the launch file configures it.
"""

from __future__ import annotations

from configparser import ConfigParser
from pathlib import Path
from typing import Any

import pytest
import yaml
from testkit.launch_stub import (
    LaunchConfiguration,
    LaunchDescription,
    ParameterValue,
    load_launch,
    parameter_value,
    resolve,
)
from testkit.paths import ROOT

from parproj_ros.core import contract, params

LAUNCH = ROOT / "launch" / "parproj.launch.py"
CONFIG = ROOT / "config" / "parproj_node.yaml"
SHARE = Path("/install/share")  # a stand-in share root: paths are compared relative to it

PYTHON_TYPE = {"string": str, "bool": bool, "integer": int, "double": float}


def setup_cfg() -> ConfigParser:
    cfg = ConfigParser()
    cfg.optionxform = str  # type: ignore[assignment,method-assign]
    cfg.read(ROOT / "setup.cfg")
    return cfg


def data_files() -> dict[str, list[str]]:
    """setup.cfg's [options.data_files]: install folder -> files."""
    out: dict[str, list[str]] = {}
    for folder, files in setup_cfg()["options.data_files"].items():
        out[folder] = [f.strip() for f in files.replace(",", "\n").splitlines() if f.strip()]
    return out


def param_row(name: str) -> params.Param | None:
    """The table's row of a node parameter (``<view>.<name>`` for a default view), or None."""
    if name in params.BY_NAME:
        return params.BY_NAME[name]
    view, _, bare = name.partition(".")
    if view in params.default("views"):
        return next((p for p in params.VIEW_PARAMS if p.name == bare), None)
    return None


def configurations(value: Any) -> set[str]:
    """The launch arguments a value refers to."""
    if isinstance(value, LaunchConfiguration):
        return {value.variable_name}
    if isinstance(value, ParameterValue):
        return configurations(value.value)
    if isinstance(value, dict):
        return set().union(*(configurations(v) for v in value.values()))
    if isinstance(value, (list, tuple)):
        return set().union(*(configurations(v) for v in value))
    return set()


def subscribed_inputs() -> set[str]:
    """The topics the node subscribes to with its default views."""
    out = set()
    for t in contract.INPUTS:
        if not t.subscribed:
            continue
        if contract.VIEW in t.name:
            out |= {t.for_view(v).name for v in params.default("views")}
        else:
            out.add(t.name)
    return out


def launch_problems(desc: LaunchDescription) -> list[str]:
    """What is wrong with a launch description, one line each (empty: nothing)."""
    problems: list[str] = []
    declared = desc.arguments
    if len(desc.nodes) != 1:
        return [f"{len(desc.nodes)} nodes launched, not 1"]
    (node,) = desc.nodes
    cfg = setup_cfg()
    if node.package != cfg["metadata"]["name"]:
        problems.append(f"package {node.package!r} is not {cfg['metadata']['name']!r}")
    scripts = dict(
        (part.strip() for part in line.split("=", 1))
        for line in cfg["options.entry_points"]["console_scripts"].splitlines()
        if line.strip()
    )
    node_scripts = [n for n, target in scripts.items() if target == "parproj_ros.ros.node:entry"]
    if [node.executable] != node_scripts:
        problems.append(f"executable {node.executable!r} is not the node's script {node_scripts}")
    if node.name not in yaml.safe_load(CONFIG.read_text()):
        problems.append(f"node name {node.name!r} is not the key of {CONFIG.name}")
    used = configurations([node.parameters, node.remappings, node.ros_arguments])
    problems += [
        f"launch argument {a!r} used but not declared" for a in sorted(used - set(declared))
    ]
    problems += [
        f"launch argument {a!r} declared but not used" for a in sorted(set(declared) - used)
    ]
    defaults = {
        name: resolve(arg.default_value, {}, lambda pkg: SHARE / pkg)
        for name, arg in declared.items()
    }
    for entry in node.parameters:
        if not isinstance(entry, dict):  # a parameters file: the installed default one
            path = resolve(entry, defaults, lambda pkg: SHARE / pkg)
            if Path(path) != SHARE / "parproj_ros" / "config" / CONFIG.name:
                problems.append(f"parameters file {path} is not the installed {CONFIG.name}")
            continue
        for name, value in entry.items():
            row = param_row(name)
            if row is None:
                problems.append(f"parameter {name!r} is not in the parameter table")
                continue
            want = PYTHON_TYPE.get(row.type)
            if (
                want is None
                or not isinstance(value, ParameterValue)
                or value.value_type is not want
            ):
                problems.append(f"parameter {name!r}: not a ParameterValue of {row.type}")
                continue
            got = parameter_value(value, defaults)
            if got != row.default:
                problems.append(
                    f"parameter {name!r}: default {got!r}, the table's {row.default!r}"
                )
    remapped = set()
    for src, dst in node.remappings:
        remapped.add(src)
        if src not in subscribed_inputs():
            problems.append(f"remap of {src!r}: not a topic the node subscribes to (contract)")
        if resolve(dst, defaults) != src:
            problems.append(f"remap of {src!r}: its argument's default is not {src!r}")
    missing = subscribed_inputs() - remapped
    if missing:
        problems.append(f"inputs without a remap argument: {sorted(missing)}")
    return problems


def test_launch_file_matches_parameter_table_and_contract() -> None:
    desc = load_launch(LAUNCH)
    assert launch_problems(desc) == []
    (node,) = desc.nodes
    assert {src for src, _ in node.remappings} == subscribed_inputs()
    assert [n for e in node.parameters if isinstance(e, dict) for n in e] == [
        "frame_id",
        "heights",
    ]


@pytest.mark.parametrize(
    ("wrong", "right", "problem"),
    [
        ('("heights", bool,', '("height", bool,', "parameter 'height' is not in the parameter"),
        ('"heights", bool, "false"', '"heights", bool, "true"', "default True, the table's False"),
        ('"heights", bool,', '"heights", str,', "not a ParameterValue of bool"),
        ('("gcp", "gcp_topic"', '("gcps", "gcp_topic"', "remap of 'gcps': not a topic"),
        ('("pairs", "pairs_topic"', '("truth/points", "pairs_topic"', "remap of 'truth/points'"),
        ('("pairs", "pairs_topic"', '("navigation", "pairs_topic"', "inputs without a remap"),
        ('"log_level", default_value', '"loglevel", default_value', "'log_level' used but not"),
        ('"config", "parproj_node.yaml"', '"config", "node.yaml"', "is not the installed"),
        ('executable="parproj_node"', 'executable="parproj"', "is not the node's script"),
        ('name="parproj_node"', 'name="parproj"', "node name 'parproj' is not the key"),
    ],
)
def test_launch_checker_catches(wrong: str, right: str, problem: str) -> None:
    """Each kind of mistake, made in a copy of the launch file, is reported."""
    source = LAUNCH.read_text()
    assert source.count(wrong) == 1, wrong
    found = launch_problems(load_launch(LAUNCH, source.replace(wrong, right)))
    assert any(problem in p for p in found), found


def test_setup_cfg_installs_as_ament_python() -> None:
    cfg = setup_cfg()
    name = cfg["metadata"]["name"]
    # where `ros2 run` looks; colcon passes it to setuptools (a venv's pip ignores it: .venv/bin)
    assert cfg["install"]["install_scripts"] == f"$base/lib/{name}"
    # setuptools >= 80's develop has no script_dir: `pip install -e .` would fail on it
    assert not cfg.has_section("develop")
    files = data_files()
    launch_files = sorted(f"launch/{p.name}" for p in (ROOT / "launch").iterdir() if p.is_file())
    assert sorted(files[f"share/{name}/launch"]) == launch_files == ["launch/parproj.launch.py"]
    assert files[f"share/{name}/config"] == ["config/parproj_node.yaml"]
    assert files[f"share/{name}"] == ["package.xml"]
    marker = files["share/ament_index/resource_index/packages"]
    assert marker == [f"resource/{name}"] and (ROOT / marker[0]).is_file()


def test_colcon_defaults_find_both_packages() -> None:
    """colcon run from the repository lists parproj_ros (.) and parproj_msgs (msg_defs)."""
    defaults = yaml.safe_load((ROOT / "colcon_defaults.yaml").read_text())
    names = {}
    for verb in ("list", "build"):
        paths = defaults[verb]["base-paths"]
        assert paths == [".", "msg_defs"], verb
        for p in paths:
            text = (ROOT / p / "package.xml").read_text()
            names[p] = text.split("<name>")[1].split("</name>")[0]
    assert names == {".": "parproj_ros", "msg_defs": "parproj_msgs"}
