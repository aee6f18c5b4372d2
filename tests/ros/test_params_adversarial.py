"""parproj_node's configuration surface tried as a user wiring a ROS 2 graph would (issue 24).

Each case is a node process of its own (``-r __node:=<case>``, so that the cases run side by
side on one DDS domain), started with a parameters file and ``-p`` arguments nobody tried; the
test reads its log, asks its parameter services over DDS what it uses, and stops it:

- ``types``: numbers as people write them (``z_avg: 100`` for a double, ``scene_lines: 1000.0``
  for an integer) are taken as that type (before: ERROR "Trying to set parameter 'z_avg' to
  '100' of type 'INTEGER', expecting type 'DOUBLE'", the default used);
- ``refused``: a value refused (a choice, ``height_range`` 0, which ``parproj process``
  refuses and which gave a pair "no usable stereo base", a fraction for an integer, 1 for a
  bool) is an ERROR naming the parameter, and the parameter services report the default the
  node uses (before: ``gcp_roll`` 'bogus' reported while 'estimate' was used; ``height_range``
  0 taken); a relative ``gcp_file`` that is not there is named with the node's folder
  (before: "no_such_gcp.csv: no such file");
- ``renamed``: a parameters file with no section for the node (renamed with ``-r __node:=``,
  or a misspelt node name) and an empty one (before: both ignored in silence);
- ``qos``: a misspelt QoS override, one of a topic that takes none (before: ignored in
  silence), and a publisher's durability override, which docs/node.md promises (before: not
  declared, ignored);
- ``prefault``: ``prefault_mb`` beyond ``memory_budget_mb`` (before: touched regardless; with
  ``scene_lines`` 1e7, in its range, the default -1 asked two raw pairs of 1.1 TB), and a
  budget beyond the machine's memory;
- ``quicklook``: ``heights_quicklook`` where no pair can stream (before: nothing made, nothing
  said; ``scene_lines`` is 0 by default);
- ``frame_id`` beginning with "/", which tf2 refuses: the node does not start (exit 2).
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import DurabilityPolicy
from sensor_msgs.msg import Image
from testkit.live import GraphNode, wait

from parproj_ros.ros.live import NodeProcess, ros_environment
from parproj_ros.ros.startup import machine_memory_mb

pytestmark = pytest.mark.ros

#: case -> (parameters of the file, its section name, more ROS arguments, parameters to read)
CASES: dict[str, tuple[dict[str, Any], str, list[str], list[str]]] = {
    "types": (
        {"z_avg": 100, "scene_lines": 1000.0, "nodata": -5},
        "adv_types",
        ["-p", "heights_margin_px:=12"],
        ["z_avg", "scene_lines", "nodata", "heights_margin_px"],
    ),
    "refused": (
        {"gcp_roll": "bogus", "height_range": 0.0, "max_gap_lines": 2.5, "heights": 1},
        "adv_refused",
        ["-p", "gcp_file:=no_such_gcp.csv"],
        ["gcp_roll", "height_range", "max_gap_lines", "heights"],
    ),
    "renamed": ({"z_avg": 100.0}, "parproj_node", ["--params-file", "@empty"], ["z_avg"]),
    "qos": (
        {
            "qos_overrides": {
                "navigation": {"subscription": {"reliability": "reliable"}},
                "/gcp": {"subscription": {"depth": 3}},
                "/dsm": {"publisher": {"durability": "volatile"}},
            }
        },
        "adv_qos",
        [],
        ["qos_overrides./dsm.publisher.durability"],
    ),
    "prefault": (
        {"prefault_mb": 1200.0, "memory_budget_mb": 256.0},
        "adv_prefault",
        [],
        ["prefault_mb"],
    ),
    "budget": ({"memory_budget_mb": 1e6}, "adv_budget", [], ["memory_budget_mb"]),
    "launch": ({"anaglyph": True}, "adv_launch", ["@launch"], ["heights", "frame_id"]),
    "quicklook": (
        {"heights": True, "heights_quicklook": 2, "scene_lines": 1000, "streaming": False},
        "adv_quicklook",
        ["-p", "views:=[pan]"],
        ["heights_quicklook"],
    ),
}


def _node(case: str) -> str:
    return f"adv_{case}"


@pytest.fixture(scope="module")
def started(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, dict[str, Any]]]:
    """Every case's node started together; its log, parameters, RSS and endpoints' QoS."""
    tmp = tmp_path_factory.mktemp("params_adversarial")
    env = ros_environment(log_dir=tmp / "ros_log")
    empty = tmp / "empty.yaml"
    empty.write_text("")
    procs: dict[str, NodeProcess] = {}
    files: dict[str, Path] = {}
    test = GraphNode("test_params_adversarial")
    out: dict[str, dict[str, Any]] = {c: {} for c in CASES}
    try:
        for case, (params, section, extra, _) in CASES.items():
            files[case] = tmp / f"{case}.yaml"
            doc = {section: {"ros__parameters": params}}
            files[case].write_text(yaml.safe_dump(doc, sort_keys=False))
            args = [str(empty) if a == "@empty" else a for a in extra]
            if args == ["@launch"]:
                args = _as_launched(tmp)
            program = [sys.executable, "-m", "parproj_ros.ros.node", "--ros-args"]
            program += ["-r", f"__node:={_node(case)}", *args]
            procs[case] = NodeProcess(files[case], env, tmp / f"{case}.log", program=program)
        for proc in procs.values():
            assert wait(lambda p=proc: "starting: views" in p.output(), 30), proc.output()
        for case, (_, _, _, names) in CASES.items():
            node = _node(case)
            out[case]["values"] = _get(test, node, names)
            out[case]["rss_mb"] = _rss_mb(procs[case].proc.pid)
        out["qos"]["dsm"] = {
            i.node_name: i.qos_profile.durability
            for i in test.node.get_publishers_info_by_topic("/dsm")
        }
        # Run-time changes: read-only, an unknown name, a wrong type: refused, values kept.
        req = SetParameters.Request()
        req.parameters = [
            Parameter("heights_quicklook", value=2).to_parameter_msg(),
            Parameter("z_avg", value="high").to_parameter_msg(),
            Parameter("no_such_parameter", value=1.0).to_parameter_msg(),
            Parameter("use_sim_time", value="abc").to_parameter_msg(),
        ]
        out["types"]["set"] = _call(test, SetParameters, "/adv_types/set_parameters", req)
        out["types"]["after"] = _get(test, "adv_types", ["heights_quicklook", "z_avg"])
        for case, proc in procs.items():
            out[case]["alive"] = proc.proc.poll() is None
    finally:
        for case, proc in procs.items():
            out[case]["code"] = proc.stop()
            out[case]["log"] = proc.output()
            out[case]["file"] = files[case]
        out["renamed"]["empty"] = empty
        test.close()
    yield out


#: A user's parameters file for parproj.launch.py's params_file: heights and frame_id set.
MINE = {"heights": True, "frame_id": "enu_wgs84:lat=44.2,lon=5.2,h=500"}


def _as_launched(tmp: Path) -> list[str]:
    """The ROS arguments launch/parproj.launch.py gives the node with ``params_file`` a file
    of :data:`MINE` (testkit.launch_stub: launch has no wheel here), the node named
    adv_launch."""
    from testkit.launch_stub import load_launch, node_ros_args
    from testkit.paths import ROOT

    mine = tmp / "mine.yaml"
    mine.write_text(yaml.safe_dump({"adv_launch": {"ros__parameters": MINE}}))
    desc = load_launch(ROOT / "launch" / "parproj.launch.py")
    (node,) = desc.nodes
    args = node_ros_args(node, desc, {"params_file": str(mine)}, lambda p: ROOT, tmp)
    assert args[0] == "--ros-args" and args[-1] == "--"
    return [a.replace("__node:=parproj_node", "__node:=adv_launch") for a in args[1:-1]]


def _call(test: GraphNode, srv: Any, name: str, request: Any) -> Any:
    client = test.node.create_client(srv, name)
    assert client.wait_for_service(timeout_sec=20), f"{name}: not available"
    # A request sent before the server's reply writer matched this client gets no reply
    # (test_params_live.py): asked again, at most 4 times.
    for _ in range(4):
        future = client.call_async(request)
        if wait(future.done, 5):
            return future.result()
        client.remove_pending_request(future)
    raise AssertionError(f"{name}: no response to 4 requests")


def _get(test: GraphNode, node: str, names: list[str]) -> dict[str, Any]:
    """``names``' values from ``node``'s parameter service (None: not declared)."""
    got = {}
    for name in names:  # one by one: a name not declared gets no value, nor do the others
        req = GetParameters.Request()
        req.names = [name]
        values = _call(test, GetParameters, f"/{node}/get_parameters", req).values
        got[name] = parameter_value_to_python(values[0]) if values else None
    return got


def _rss_mb(pid: int) -> float:
    """Resident memory of process ``pid``, MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError("no VmRSS")


def _errors(log: str) -> list[str]:
    return [ln for ln in log.splitlines() if "[ERROR]" in ln or "[WARN]" in ln]


def _ran(r: dict[str, Any]) -> None:
    assert r["alive"] and r["code"] == 0, r["log"]
    assert "Traceback" not in r["log"], r["log"]


def test_numbers_as_people_write_them(started: dict[str, dict[str, Any]]) -> None:
    """z_avg: 100 is 100.0 m, scene_lines: 1000.0 is 1000 lines: no ERROR, the values used."""
    r = started["types"]
    _ran(r)
    assert _errors(r["log"]) == [], r["log"]
    got = r["values"]
    assert got == {"z_avg": 100.0, "scene_lines": 1000, "nodata": -5.0, "heights_margin_px": 12.0}
    assert [type(v) for v in got.values()] == [float, int, float, float]
    (line,) = [ln for ln in r["log"].splitlines() if "starting: views" in ln]
    assert "scene_lines=1000, z_avg=100.0, nodata=-5.0, heights_margin_px=12.0" in line, line


def test_run_time_changes_refused(started: dict[str, dict[str, Any]]) -> None:
    """Mid-run: read-only, a wrong type, an unknown name: each refused with rclpy's reason."""
    reasons = [(x.successful, x.reason) for x in started["types"]["set"].results]
    assert reasons == [
        (False, "Trying to set a read-only parameter: heights_quicklook."),
        (False, "Trying to set a read-only parameter: z_avg."),
        (False, "Invalid access to undeclared parameter(s): []"),
        (False, "Wrong parameter type, expected '1' got '4'"),
    ]
    assert started["types"]["after"] == {"heights_quicklook": 0, "z_avg": 100.0}


def test_refused_values_name_the_cause_and_the_services_tell_the_truth(
    started: dict[str, dict[str, Any]],
) -> None:
    r = started["refused"]
    _ran(r)
    want = {
        "gcp_roll": "'bogus' is not one of ['estimate', 'navigation', 'none']; the default "
        "'estimate' is used",
        "height_range": "0.0: it must be more than 0 m; the default 500.0 is used",
        "max_gap_lines": "2.5 is a number with a fraction, where an integer is expected; the "
        "default 64 is used",
        "heights": "1 is an integer, where a bool (true or false) is expected; the default "
        "False is used",
    }
    errors = _errors(r["log"])
    for name, says in want.items():
        assert [e for e in errors if "[ERROR]" in e and f"parameter {name}: {says}" in e], errors
    # a relative gcp_file is named as the node looked for it (a launched node's folder)
    gcp = Path.cwd() / "no_such_gcp.csv"
    assert [
        e
        for e in errors
        if e.endswith(f"gcp_file: GcpFileError: {gcp}: no such file; continuing without it")
    ], errors
    assert len(errors) == len(want) + 1, errors
    assert r["values"] == {
        "gcp_roll": "estimate",
        "height_range": 500.0,
        "max_gap_lines": 64,
        "heights": False,
    }


def test_a_parameters_file_for_another_node_is_named(started: dict[str, dict[str, Any]]) -> None:
    r = started["renamed"]
    _ran(r)
    errors = sorted(_errors(r["log"]), key=lambda e: "[WARN]" in e)  # ERROR first
    assert len(errors) == 2, errors
    assert "[ERROR] " in errors[0] and errors[0].endswith(
        f"parameters file: {r['file']}: no section for this node, /adv_renamed (the file's "
        "sections: parproj_node): none of its 1 parameters is used (name the section "
        "adv_renamed or /**)"
    ), errors[0]
    assert "[WARN] " in errors[1] and errors[1].endswith(
        f"parameters file: {r['empty']}: holds no parameters (no section with "
        "ros__parameters): nothing set from it"
    ), errors[1]
    assert r["values"] == {"z_avg": 0.0}


def test_qos_overrides_that_apply_to_nothing_are_named(started: dict[str, dict[str, Any]]) -> None:
    r = started["qos"]
    _ran(r)
    errors = _errors(r["log"])
    assert len(errors) == 2, errors
    for name, value in (
        ("qos_overrides./gcp.subscription.depth", "3"),
        ("qos_overrides.navigation.subscription.reliability", "'reliable'"),
    ):
        assert [
            e
            for e in errors
            if f"parameter {name}: {value} given, but parproj_node has no such QoS override "
            "(they are qos_overrides./<topic>.subscription.<history|depth|reliability> for "
            "the inputs navigation and <view>/image_strip"
            in e
            and e.endswith("): ignored")
        ], errors
    # the durability override of an output, as docs/node.md says, applies
    assert r["values"] == {"qos_overrides./dsm.publisher.durability": "volatile"}
    assert r["dsm"]["adv_qos"] == DurabilityPolicy.VOLATILE
    assert r["dsm"]["adv_types"] == DurabilityPolicy.TRANSIENT_LOCAL  # the contract's


def test_a_prefault_beyond_the_budget_is_not_done(started: dict[str, dict[str, Any]]) -> None:
    """prefault_mb 1200 with memory_budget_mb 256: an ERROR, nothing touched (RSS ~100 MB;
    before: 1200 MB touched, RSS ~1.3 GB, over the node's own budget)."""
    r = started["prefault"]
    _ran(r)
    (error,) = _errors(r["log"])
    assert error.endswith(
        "parameter prefault_mb: 1200 asks 1200 MB of heap and 0 MB of line buffers touched at "
        "start, more than the 243 MB that memory_budget_mb 256 MB leaves (less 5% headroom): "
        "nothing touched (as prefault_mb 0)"
    ), error
    assert r["rss_mb"] < 600, r["rss_mb"]
    assert "MB of heap and" not in r["log"].replace(error, ""), r["log"]


def test_a_budget_beyond_the_machine_is_a_warning(started: dict[str, dict[str, Any]]) -> None:
    r = started["budget"]
    _ran(r)
    total, _ = machine_memory_mb()
    assert total is not None and total < 1e6
    (warn,) = _errors(r["log"])
    assert "[WARN]" in warn and warn.endswith(
        f"parameter memory_budget_mb: 1e+06 MB is more than this machine's memory, "
        f"{total:.0f} MB: the kernel may end the node (out of memory) before the admission "
        "sheds a pair; set it below that"
    ), warn
    assert r["values"] == {"memory_budget_mb": 1e6}


def test_quicklook_that_cannot_be_made_is_a_warning(started: dict[str, dict[str, Any]]) -> None:
    r = started["quicklook"]
    _ran(r)
    (warn,) = _errors(r["log"])
    assert "[WARN]" in warn and warn.endswith(
        "parameter heights_quicklook: 2: no quick-look tiles will be made: one view "
        "(single-camera mode), streaming is off (they are made while a pair streams: heights "
        "on, two views, scene_lines > 0, streaming on)"
    ), warn
    assert r["values"] == {"heights_quicklook": 2}


#: case -> (ROS arguments, the one line on stderr); @config: config/parproj_node.yaml
BAD_START = {
    # before: started, every output labelled '/map', which tf2 (and so RViz) refuses
    "frame_id /map": (
        ["-p", "frame_id:=/map"],
        "parproj_node: cannot start: parameter frame_id: '/map' begins with '/', which tf2 "
        "refuses in a frame id (RViz would show none of the outputs): write 'map'",
    ),
    # before: "cannot parse the parameters file .../parproj_node.yaml: ... '-p gcp_roll:='.
    # Error: error not set", the good file blamed for the rule
    "rule without value": (
        ["--params-file", "@config", "-p", "gcp_roll:="],
        "parproj_node: cannot start: cannot parse the ROS arguments: failed to initialize rcl: "
        "Couldn't parse parameter override rule: '-p gcp_roll:='. Error: no value after ':='",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_START))
def test_invalid_start_names_the_cause(case: str, tmp_path: Path) -> None:
    """Exit 2 with one line on stderr naming the real cause."""
    from testkit.paths import ROOT

    args, says = BAD_START[case]
    args = [str(ROOT / "config" / "parproj_node.yaml") if a == "@config" else a for a in args]
    env = ros_environment(log_dir=tmp_path / "ros_log")
    cmd = [sys.executable, "-m", "parproj_ros.ros.node", "--ros-args", *args]
    cmd += ["-r", "__node:=adv_bad_start"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=30)
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stdout == "" and r.stderr.splitlines() == [says], r.stderr


#: (memory_budget_mb, machine (total, available) MB, prefault_mb) -> (level, message) or None
PREFAULTS: dict[str, tuple[float, tuple[float, float], float, str | None]] = {
    "fits": (6144.0, (24000.0, 20000.0), -1.0, None),
    "over the budget": (
        2048.0,
        (24000.0, 20000.0),
        -1.0,
        "-1 (two raw pairs of scene_lines 14000) asks 1476 MB of heap and 1476 MB of line "
        "buffers touched at start, more than the 1946 MB that memory_budget_mb 2048 MB leaves "
        "(less 5% headroom): nothing touched (as prefault_mb 0)",
    ),
    "over what is available": (
        6144.0,
        (24000.0, 1000.0),
        500.0,
        "500 asks 500 MB of heap and 1476 MB of line buffers touched at start, more than the "
        "1000 MB this machine has available: nothing touched (as prefault_mb 0)",
    ),
}


@pytest.mark.parametrize("case", sorted(PREFAULTS))
def test_prefault_of_ikonos_size_scenes(case: str) -> None:
    """Two IKONOS-size views (13816 detectors) of 14000 lines: a raw pair is 738 MB; -1 asks
    two of heap, and the pools' two line buffers per view are as much again (2952 MB)."""
    from parproj_ros.core.config import config_from_values
    from parproj_ros.core.results import Level
    from parproj_ros.ros.startup import memory_issues

    budget, machine, asked, says = PREFAULTS[case]
    cfg = config_from_values({"scene_lines": 14000})
    assert [v.camera.detectors for v in cfg.views] == [13816, 13816]
    used, issues = memory_issues(cfg, asked, budget, machine)
    if says is None:
        assert (used, issues) == (asked, [])
        return
    (iss,) = issues
    assert used == 0.0 and iss.where == "parameter prefault_mb" and iss.message == says
    assert iss.level == (Level.WARN if asked < 0 else Level.ERROR)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """bags/ikonos_agile through a node with output_pixel 1 and nav_jump_s 0.01: statuses."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from testkit.paths import BAGS

    from parproj_ros.ros.bag import BagReader
    from parproj_ros.ros.inputs import node_parameters, views_from_bag
    from parproj_ros.ros.live import node_params_yaml, replay

    tmp = tmp_path_factory.mktemp("params_adversarial_replay")
    bag = BAGS / "ikonos_agile"
    params = node_parameters(
        views_from_bag(BagReader(bag)), tie_points=False, output_pixel=1.0, nav_jump_s=0.01
    )
    pfile = node_params_yaml(
        params, tmp / "p.yaml", reliable_inputs=["/navigation", "/pan/image_strip"]
    )
    test = GraphNode("test_params_adversarial_replay", start=False)
    statuses: list[Any] = []
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    sub = test.node.create_subscription(
        DiagnosticArray, "/diagnostics", lambda m: statuses.extend(m.status), qos
    )
    test.start()
    env = ros_environment(log_dir=tmp / "ros_log")
    proc = NodeProcess(pfile, env, tmp / "n.log")
    # a second node on the same replay: start_margin_s 3600 (an hour of navigation before a
    # view's first scene), nav_position_tolerance_m 0
    margin = dict(
        params,
        start_margin_s=3600.0,
        output_pixel=0.0,
        nav_jump_s=10.0,
        nav_position_tolerance_m=0.0,
    )
    mfile = tmp / "margin.yaml"
    node_params_yaml(margin, mfile, reliable_inputs=["/navigation", "/pan/image_strip"])
    mfile.write_text(mfile.read_text().replace("parproj_node:", "adv_margin:", 1))
    program = [sys.executable, "-m", "parproj_ros.ros.node", "--ros-args"]
    other = NodeProcess(mfile, env, tmp / "m.log", program=[*program, "-r", "__node:=adv_margin"])
    pair = "parproj_node: pair pan_scene_0000+pan_scene_0001"
    try:
        # /diagnostics is volatile: what the node publishes before its writer has matched this
        # reader is lost (discovery is not symmetric: settle 1 s once the reader sees it)
        assert wait(lambda: sub.get_publisher_count() > 1, 20), proc.output()
        time.sleep(1.0)
        strips = test.node.create_publisher(Image, "/pan/image_strip", 10)
        assert wait(lambda: strips.get_subscription_count() > 1, 20), other.output()
        test.node.destroy_publisher(strips)
        replay(test.node, bag, rate=0.0, max_gap_s=0.2, wait_for=["/pan/image_strip"], log=print)
        skipped = "parproj_node: pan/pan_scene_0000"
        wait(
            lambda: {pair, skipped} <= {s.name for s in list(statuses)},
            20,
            lambda: proc.proc.poll() is None and other.proc.poll() is None,
        )
        alive = proc.proc.poll() is None and other.proc.poll() is None
    finally:
        code = proc.stop()
        code_other = other.stop()
        test.close()
    return {
        "alive": alive,
        "code": (code, code_other),
        "log": proc.output() + other.output(),
        "statuses": list(statuses),
    }


def test_output_pixel_too_coarse_is_named_not_the_overlap(replayed: dict[str, Any]) -> None:
    """output_pixel 1 (m of the normalized image plane: 85000 times bags/ikonos_agile's own
    pixel) through the live node: ERROR naming output_pixel and the 1 x 1 px it gives (before:
    "its normalized images share only 0.0 % of their pixels with data in both (< 5 %): the
    scenes see different ground at the heights used ... Check that the scenes overlap")."""
    from testkit.diagnostics import level

    r = replayed
    assert r["alive"] and r["code"] == (0, 0) and "Traceback" not in r["log"], r["log"]
    pair = "parproj_node: pair pan_scene_0000+pan_scene_0001"
    (s,) = [s for s in r["statuses"] if s.name == pair]
    assert level(s) == 2 and s.message == (
        "normalized images would be 1 x 1 px at output_pixel 1 (< 16 px a side: nothing to "
        "match): pair skipped; give a smaller output_pixel, or 0 for the scenes' own resolution"
    ), s.message


def test_navigation_dropped_by_nav_jump_s_names_it(replayed: dict[str, Any]) -> None:
    """nav_jump_s 0.01 s, under the bag's 0.05 s navigation period (within its range 0.01 ..
    86400): every other sample is held and dropped, each with a WARN that now names nav_jump_s
    (before: "a sample stamped +0.050 s from the newest one was not followed by others:
    dropped", which does not say what made +0.050 s suspicious)."""
    from testkit.diagnostics import level

    nav = [s for s in replayed["statuses"] if s.name == "parproj_node: navigation"]
    assert len(nav) > 100, len(nav)  # 20 Hz navigation for the two scenes, half dropped
    assert {(level(s), s.message) for s in nav} == {
        (
            1,
            "a sample stamped +0.050 s from the newest one (more than nav_jump_s, 0.01 s) was "
            "not followed by others: dropped",
        )
    }


def test_a_first_scene_skipped_by_start_margin_s_names_it(replayed: dict[str, Any]) -> None:
    """start_margin_s 3600 (in its range): the view's first scene is skipped, and the ERROR
    names the parameter (before: "(less than 3600.0 s before)", no name to look for)."""
    from testkit.diagnostics import level

    (s,) = [s for s in replayed["statuses"] if s.name == "parproj_node: pan/pan_scene_0000"]
    assert level(s) == 2 and s.message == (
        "first scene received on view pan (768 lines), and navigation starts only 1.000 s "
        "before its first line (less than start_margin_s, 3600 s, before): the node may have "
        "started, or restarted, while this scene was under way, so its beginning, its line "
        "numbers (GCP observations) and its pair are unknown: scene skipped"
    ), s.message


def test_navigation_scatter_names_nav_position_tolerance_m(replayed: dict[str, Any]) -> None:
    """nav_position_tolerance_m 0 (in its range): the second scene's WARN names it (before:
    "navigation positions scatter by 0.000 m rms about the constant-velocity line (> 0.0 m)",
    a scatter shown as 0.000 over a tolerance of 0.0 and no parameter named)."""
    from testkit.diagnostics import level

    (s,) = [
        s
        for s in replayed["statuses"]
        if s.name == "parproj_node: pan/pan_scene_0001" and "scatter" in s.message
    ]
    rms = s.message.split("scatter by ")[1].split(" m rms")[0]
    assert level(s) == 1 and 0.0 < float(rms) < 1e-3, s.message  # simulated: no noise
    assert s.message == (
        f"navigation positions scatter by {rms} m rms about the constant-velocity line "
        "(> nav_position_tolerance_m, 0 m): an outlier or a manoeuvre; the parameters carry "
        "that error"
    ), s.message


def test_a_value_the_launch_file_resets_is_named(started: dict[str, dict[str, Any]]) -> None:
    """parproj.launch.py passes frame_id and heights after params_file, their defaults too:
    heights true and a frame_id in the user's params_file are lost. Each is now a WARN naming
    both files and the value used (before: nothing; the start line said "every parameter at
    its default")."""
    r = started["launch"]
    _ran(r)
    warns = _errors(r["log"])
    assert len(warns) == 2 and all("[WARN]" in w for w in warns), warns
    launch_file = str(r["file"].parent / "launch_params_1.yaml")
    mine = str(r["file"].parent / "mine.yaml")
    for name, value, default in (("heights", True, False), ("frame_id", MINE["frame_id"], "")):
        assert [
            w
            for w in warns
            if w.endswith(
                f"parameter {name}: given {value!r} in {mine}, but a later file, {launch_file}, "
                f"sets the default {default!r}: {default!r} used (with parproj.launch.py, give "
                "frame_id and heights as its arguments: it passes them after params_file, "
                "defaults too)"
            )
        ], warns
    assert r["values"] == {"heights": False, "frame_id": ""}


def test_launch_arguments_over_the_installed_file_are_not_reported(tmp_path: Path) -> None:
    """The documented use, heights:=true over the installed config/parproj_node.yaml (every
    parameter at its default): no WARN; the trap only (a value reset to the default)."""
    from testkit.paths import ROOT

    from parproj_ros.ros.startup import params_file_issues

    later = tmp_path / "launch_params_1.yaml"
    later.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"heights": True}}}))
    files = [str(ROOT / "config" / "parproj_node.yaml"), str(later)]
    used = {"heights": True, "views": ["left", "right"]}
    assert params_file_issues("/parproj_node", files, used) == []
    # files layered on purpose (a later value other than the default) are not reported either
    base = tmp_path / "base.yaml"
    base.write_text(yaml.safe_dump({"parproj_node": {"ros__parameters": {"z_avg": 100.0}}}))
    site = tmp_path / "site.yaml"
    site.write_text(yaml.safe_dump({"parproj_node": {"ros__parameters": {"z_avg": 250.0}}}))
    assert params_file_issues("/parproj_node", [str(base), str(site)], {"z_avg": 250.0}) == []
