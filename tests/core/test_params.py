"""The one parameter table (parproj_ros/core/params.py), what is generated from it or must agree.

docs/node.md's Parameters table and config/parproj_node.yaml are the rendered ones; each settings
group of PipelineConfig has a field per row of its concern, with the table's default; ``parproj
process`` has an option per offline row with the same default and range; setup.cfg and
package.xml list what the code imports. The live half (the node started with
config/parproj_node.yaml) is in test_params_live.py.
"""

from __future__ import annotations

import ast
import configparser
import math
import re
import sys
import xml.etree.ElementTree as ET
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from testkit.paths import ROOT

from parproj_ros.apps import cli
from parproj_ros.core import config, param_docs, params
from parproj_ros.core.config import PipelineConfig, config_from_values
from parproj_ros.core.params import PARAMS, VIEW_PARAMS

BAG = ROOT / "bags" / "ikonos_agile"


# ---- generated files ----------------------------------------------------------------------------


def test_readme_table_is_the_rendered_one() -> None:
    readme = (ROOT / param_docs.NODE_DOC).read_text()
    begin = readme.index(param_docs.README_BEGIN) + len(param_docs.README_BEGIN) + 1
    end = readme.index(param_docs.README_END)
    assert readme[begin:end] == param_docs.parameters_markdown(), (
        f"{param_docs.NODE_DOC}'s Parameters table differs from parproj_ros/core/params.py: "
        "run `python -m parproj_ros.core.param_docs --write .`"
    )


def test_params_file_is_the_rendered_one() -> None:
    assert (ROOT / param_docs.PARAMS_FILE).read_text() == param_docs.parameters_yaml(), (
        "config/parproj_node.yaml differs from parproj_ros/core/params.py: "
        "run `python -m parproj_ros.core.param_docs --write .`"
    )


def _flat(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in tree.items():
        if isinstance(v, dict):
            out |= _flat(v, f"{prefix}{k}.")
        else:
            out[f"{prefix}{k}"] = v
    return out


def test_params_file_holds_every_default_with_its_type() -> None:
    doc = yaml.safe_load(param_docs.parameters_yaml())
    values = _flat(doc["parproj_node"]["ros__parameters"])
    want = params.default_values()
    assert values == want
    for name, v in values.items():
        assert type(v) is type(want[name]), name


def test_params_file_comments_give_unit_and_range() -> None:
    text = param_docs.parameters_yaml()
    for p in (*PARAMS, *VIEW_PARAMS):
        block = re.search(rf"((?:\s*#.*\n)+)\s*{p.name}: ", text)
        assert block, p.name
        if p.unit:
            assert f"unit {p.unit}" in block[1], p.name
        if p.range_text:
            assert p.range_text in block[1], p.name


def test_readme_says_how_to_regenerate(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / param_docs.NODE_DOC).write_text(
        f"x\n{param_docs.README_BEGIN}\nold table\n{param_docs.README_END}\ny\n"
    )
    assert param_docs.main(["--write", str(tmp_path)]) == 0
    text = (tmp_path / param_docs.NODE_DOC).read_text()
    table = param_docs.parameters_markdown()
    assert text == f"x\n{param_docs.README_BEGIN}\n{table}{param_docs.README_END}\ny\n"
    assert (tmp_path / param_docs.PARAMS_FILE).read_text() == param_docs.parameters_yaml()


# ---- the table and PipelineConfig ---------------------------------------------------------------


def test_every_setting_has_one_row_with_its_default() -> None:
    """Each field of each settings group is the row that fills it, with its default."""
    rows = {p.target: p for p in PARAMS if p.target is not None}
    assert len(rows) == len([p for p in PARAMS if p.target is not None])
    have = {(c, f.name): f for c, cls in config.GROUPS.items() for f in fields(cls)}
    assert set(rows) == set(have)
    for key, f in have.items():
        assert f.default == rows[key].default, key
    assert {f.name for f in fields(PipelineConfig)} == {"views", *config.GROUPS}


def test_table_rows_are_consistent() -> None:
    names = [p.name for p in PARAMS] + [p.name for p in VIEW_PARAMS]
    assert len(set(names)) == len(names)
    for p in (*PARAMS, *VIEW_PARAMS):
        assert p.description and p.read_only, p.name
        assert not p.description.endswith("."), p.name
        if p.type in ("integer", "double") and not p.strict:
            assert p.low is not None and p.high is not None, f"{p.name}: no range"
            assert p.low <= p.default <= p.high, p.name
        if p.choices:
            assert p.type == "string" and p.default in p.choices, p.name
        if p.offline:
            assert p.field is not None, f"{p.name}: an offline option fills no pipeline setting"


def _other_value(p: params.Param) -> Any:
    """A valid value of ``p`` other than its default."""
    if p.type == "bool":
        return not p.default
    if p.choices:
        return next(c for c in p.choices if c != p.default)
    assert p.low is not None and p.high is not None
    v = p.default + 1 if p.default + 1 <= p.high else p.low
    return int(v) if p.type == "integer" else float(v)


def test_config_from_values_fills_each_field_from_its_parameter() -> None:
    default = config_from_values({})
    assert [v.name for v in default.views] == ["left", "right"]
    rows = [p for p in PARAMS if p.target is not None]
    for p in rows:
        assert _setting(default, p) == p.default, p.name
    values = {p.name: _other_value(p) for p in rows}
    cfg = config_from_values(values)
    for p in rows:
        assert _setting(cfg, p) == values[p.name], p.name
        assert _setting(cfg, p) != p.default, p.name
    # Integers given for doubles (as ROS gives [1, 2, 3]) come out as floats.
    assert isinstance(config_from_values({"z_avg": 3}).orientation.z_avg, float)


def _setting(cfg: PipelineConfig, p: params.Param) -> Any:
    """The value ``cfg`` holds for the row ``p`` (its group's setting)."""
    assert p.target is not None
    return getattr(getattr(cfg, p.target[0]), p.target[1])


def test_config_from_values_builds_the_views() -> None:
    cfg = config_from_values(
        {
            "views": ["fore", "aft"],
            "fore.principal_distance": 2.0,
            "fore.pixel_size": 1e-5,
            "fore.detectors": 100,
            "fore.principal_point": 40.5,
            "fore.line_period": 1e-3,
            "fore.mounting_rpy_deg": (0.0, 0.0, 90.0),
            "fore.encoding": "mono16",
            "aft.principal_point": -1.0,
        }
    )
    fore, aft = cfg.views
    assert (fore.name, aft.name) == ("fore", "aft") and not cfg.single_camera
    c = fore.camera
    assert (c.principal_distance, c.pixel_size, c.detectors, c.line_period) == (
        2.0,
        1e-5,
        100,
        1e-3,
    )
    assert c.principal_point == 40.5 and fore.dtype == "uint16"
    np.testing.assert_allclose(fore.mounting, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    assert aft.camera.principal_point is None and aft.dtype is None  # -1: line centre; '': any
    np.testing.assert_array_equal(aft.mounting, np.eye(3))
    assert aft.camera.principal_distance == 10.0  # the table's default
    assert config_from_values({"views": ["pan"]}).single_camera


def test_view_values_is_the_inverse_of_view_config() -> None:
    given = {
        "principal_distance": 2.0,
        "pixel_size": 1e-5,
        "detectors": 101,
        "principal_point": 40.5,
        "line_period": 1e-3,
        "mounting_rpy_deg": [1.0, -2.0, 30.0],
        "encoding": "mono8",
    }
    vc = config.view_config("fore", given)
    back = config.view_values(vc)
    assert set(back) == {p.name for p in VIEW_PARAMS}
    np.testing.assert_allclose(back.pop("mounting_rpy_deg"), given.pop("mounting_rpy_deg"))
    assert back == given
    plain = config.view_values(config.view_config("pan", {}))
    assert plain["principal_point"] == (13816 - 1) / 2 and plain["encoding"] == ""


@pytest.mark.ros
def test_node_parameters_of_a_bag_are_table_names() -> None:
    from parproj_ros.ros.bag import BagReader
    from parproj_ros.ros.inputs import node_parameters, views_from_bag

    params = node_parameters(views_from_bag(BagReader(BAG)))
    assert set(params) == {"views"} | {f"pan.{p.name}" for p in VIEW_PARAMS}


def test_settings_docstrings_list_the_table() -> None:
    for p in PARAMS:
        if p.target is not None:
            doc = config.GROUPS[p.target[0]].__doc__ or ""
            assert f"        {p.target[1]}: " in doc and f"``{p.name}``" in doc, p.name


@pytest.mark.ros
def test_node_declares_the_table() -> None:
    from parproj_ros.ros import startup

    assert startup.PARAMS is config.PARAMS and startup.VIEW_PARAMS is config.VIEW_PARAMS
    d = startup.descriptor(next(p for p in PARAMS if p.name == "z_avg"))
    assert d.description.endswith("[m]") and d.read_only
    assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (
        -1000.0,
        9000.0,
    )
    d = startup.descriptor(next(p for p in PARAMS if p.name == "scene_lines"))
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (0, 10_000_000)
    d = startup.descriptor(next(p for p in PARAMS if p.name == "gcp_roll"))
    assert "navigation" in d.additional_constraints


# ---- parproj process options --------------------------------------------------------------------


def _process_args(*extra: str) -> Any:
    return cli.build_parser().parse_args(["process", "b", "-o", "o", *extra])


def test_process_has_an_option_per_offline_parameter_with_its_default() -> None:
    args = _process_args()
    offline = [p for p in PARAMS if p.offline]
    assert len(offline) >= 15
    for p in offline:
        assert getattr(args, p.name) == p.default, p.name


def test_the_dem_rows_name_the_process_options_that_set_them() -> None:
    """The node's DEM parameters are parproj process's --dem options (io/dem.py's, shared with
    import and dsm): the table's `process` option column names them, and process has them."""
    rows = [p for p in PARAMS if p.process_options]
    assert [p.name for p in rows] == ["dem", "geoid_undulation", "geoid", "dem_ellipsoidal"]
    assert all(p.strict and not p.offline and p.fills == "node" for p in rows)
    args = _process_args("--dem", "a.tif", "b.tif", "--geoid-undulation", "50")
    assert (args.dem, args.geoid_undulation, args.geoid, args.dem_ellipsoidal) == (
        ["a.tif", "b.tif"],
        50.0,
        None,
        False,
    )
    assert _process_args("--dem", "a.tif", "--dem-ellipsoidal").dem_ellipsoidal is True
    table = param_docs.parameters_markdown().splitlines()
    for p in rows:
        (line,) = [x for x in table if x.startswith(f"| `{p.name}` |")]
        assert f"| `{p.process_options[0]}` |" in line, line


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = cli.main(argv)
    return code, capsys.readouterr().err


@pytest.mark.parametrize("p", [p for p in PARAMS if p.offline and p.low is not None], ids=str)
def test_process_option_takes_the_parameter_range(
    p: params.Param, capsys: pytest.CaptureFixture[str]
) -> None:
    assert p.low is not None and p.high is not None
    fmt = (lambda v: str(int(v))) if p.type == "integer" else repr
    low_ok = p.low + (abs(p.high - p.low) * 1e-3 if p.low_open else 0.0)
    for v in (low_ok, p.high):
        value = int(v) if p.type == "integer" else v
        assert getattr(_process_args(p.option, fmt(v)), p.name) == value
    bad = [p.high + max(1.0, abs(p.high)), "nan", "inf"] + ([p.low] if p.low_open else [])
    bad.append(p.low - max(1.0, abs(p.low)))
    for v in bad:
        with pytest.raises(SystemExit) as ex:
            _process_args(p.option, v if isinstance(v, str) else fmt(v))
        assert ex.value.code == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and p.option in err, err


def test_process_keeps_the_old_option_names() -> None:
    args = _process_args(
        "--scene-lines",
        "500",
        "--no-tie-points",
        "--no-streaming",
        "--no-gcp",
        "--segment-max-error",
        "0.5",
        "--output-extent",
        "union",
        "--z-avg",
        "-1e2",
        "--height-range",
        "20",
        "--gcp-roll",
        "navigation",
        "--interpolation",
        "cubic",
    )
    assert (args.scene_lines, args.tie_points, args.streaming, args.no_gcp) == (
        500,
        False,
        False,
        True,
    )
    assert (args.segment_max_error_px, args.output_extent, args.z_avg) == (0.5, "union", -100.0)
    assert (args.height_range, args.gcp_roll, args.interpolation) == (20.0, "navigation", "cubic")


@pytest.mark.ros
def test_process_passes_every_option_to_the_pipeline(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from parproj_ros.apps import process

    seen: dict[str, Any] = {}

    def fake(src: Path, dst: Path, *, overrides: dict[str, Any], **kw: Any) -> Any:
        seen.update(overrides)
        dst.mkdir(parents=True, exist_ok=True)
        return process.ProcessSummary()

    monkeypatch.setattr(process, "process_bag", fake)
    rows = [p for p in PARAMS if p.offline]
    argv = ["process", str(BAG), "-o", str(tmp_path / "o"), "-q"]
    for p in rows:
        v = _other_value(p)
        if p.type == "bool":
            argv.append(p.option if v else f"--no-{p.option[2:]}")
        else:
            argv += [p.option, str(v)]
    assert cli.main(argv) == 1  # no pairs from the fake
    assert seen == {p.field: _other_value(p) for p in rows}
    cli.main(["process", str(BAG), "-o", str(tmp_path / "o2"), "-q", "--no-gcp"])
    assert seen["min_gcp"] > 10**6


# ---- dependencies -------------------------------------------------------------------------------

#: import name -> PyPI distribution (setup.cfg install_requires)
PYPI = {
    "laspy": "laspy",
    "numpy": "numpy",
    "scipy": "scipy",
    "cv2": "opencv-python-headless",
    "tqdm": "tqdm",
    "matplotlib": "matplotlib",
    "yaml": "pyyaml",
    "tifffile": "tifffile",
    "rasterio": "rasterio",
    "pyproj": "pyproj",
    "mcap": "mcap",
    "zstandard": "zstandard",
    "lz4": "lz4",
    "distributed": "distributed",
    "psutil": "psutil",
}
#: import name -> rosdep key (package.xml); None: none exists (installed with pip)
ROSDEP = {
    "laspy": None,  # no rosdep key: pip
    "numpy": "python3-numpy",
    "scipy": "python3-scipy",
    "cv2": "python3-opencv",
    "tqdm": "python3-tqdm",
    "matplotlib": "python3-matplotlib",
    "yaml": "python3-yaml",
    "tifffile": "python3-tifffile",
    "rasterio": "python3-rasterio",
    "pyproj": "python3-pyproj",
    "zstandard": "python3-zstandard",
    "lz4": "python3-lz4",
    "mcap": None,
    "distributed": None,
    "psutil": "python3-psutil",
}
#: ROS packages imported (package.xml exec_depend under the same name)
ROS = {
    "rclpy",
    "rcl_interfaces",
    "sensor_msgs",
    "nav_msgs",
    "diagnostic_msgs",
    "stereo_msgs",
    "geometry_msgs",
    "parproj_msgs",
}


def _optional(tree: ast.AST) -> set[int]:
    """ids of import nodes inside ``try: ... except ImportError`` (optional imports)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(
            h.type is not None and "ImportError" in ast.unparse(h.type) for h in node.handlers
        ):
            for stmt in node.body:
                out |= {
                    id(n) for n in ast.walk(stmt) if isinstance(n, ast.Import | ast.ImportFrom)
                }
    return out


def third_party_imports() -> set[str]:
    """Top-level names of what parproj_ros imports, the standard library and itself aside."""
    found: set[str] = set()
    for path in sorted((ROOT / "parproj_ros").rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        optional = _optional(tree)
        for node in ast.walk(tree):
            if id(node) in optional:
                continue
            if isinstance(node, ast.Import):
                found |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split(".")[0])
    return {m for m in found if m not in sys.stdlib_module_names and m != "parproj_ros"}


def test_imports_are_known() -> None:
    unknown = third_party_imports() - set(PYPI) - ROS
    assert not unknown, f"add {unknown} to setup.cfg or package.xml, and to this test's maps"


def test_setup_cfg_lists_what_the_code_imports() -> None:
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    listed = {
        re.split(r"[<>=!~ ;\[]", line.strip())[0].lower()
        for line in cfg["options"]["install_requires"].splitlines()
        if line.strip()
    }
    imported = {PYPI[m] for m in third_party_imports() if m in PYPI}
    assert listed == imported, (
        f"setup.cfg lists {listed - imported} unused, misses {imported - listed}"
    )


def test_package_xml_lists_what_the_code_imports() -> None:
    root = ET.parse(ROOT / "package.xml").getroot()
    listed = {e.text for e in root.iter("exec_depend")}
    imports = third_party_imports()
    want = (imports & ROS) | {ROSDEP[m] for m in imports if ROSDEP.get(m)}
    assert listed == want, f"package.xml lists {listed - want} unused, misses {want - listed}"


def test_numbers_in_the_table_are_finite() -> None:
    for p in (*PARAMS, *VIEW_PARAMS):
        for b in (p.low, p.high):
            assert b is None or math.isfinite(b), p.name


def test_encoding_choices_are_the_supported_pixel_types() -> None:
    """``<view>.encoding`` offers exactly the encodings the pipeline writes (and "")."""
    from parproj_ros.core.params import VIEW_PARAMS
    from parproj_ros.imaging.encodings import DTYPE_ENCODINGS

    choices = next(p.choices for p in VIEW_PARAMS if p.name == "encoding")
    assert set(choices) == {"", *DTYPE_ENCODINGS.values()}
