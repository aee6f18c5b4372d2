"""From a clean workspace: colcon builds both packages and the node runs from the install tree.

As a ROS user does it (docs/ros.md): the package's sources (``git ls-files``, untracked files
included: the working tree without build products) copied to ``<ws>/src/parproj``, the real
colcon (requirements/dev.txt) builds parproj_msgs (msg_defs/, ament_cmake) and parproj_ros
(ament_python) with the ROS 2 wheels of this venv as the underlay; then a bash that sourced
``install/setup.bash`` finds the node through the ament index (what ``ros2 run`` does, it has
no wheel) and starts it with the installed launch file's parameters and remaps
(tests/testkit/launch_stub.py; ``ros2 launch`` has no wheel either). The default bag is replayed
into it over real DDS, and its pair is compared with ``parproj process`` of the same bag.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from testkit.launch_stub import load_launch, node_ros_args
from testkit.paths import BAGS, ROOT

from parproj_ros.apps.process import process_bag
from parproj_ros.core import contract
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.conversions import image_to_array
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import node_params_yaml, ros_environment, run_through_node

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # a colcon build, then the node over DDS

#: The venv of this run: the ROS 2 wheels, the underlay of the workspace (shared/ROS2_WHEELS.md).
VENV = Path(sys.prefix)
COLCON = Path(sys.executable).parent / "colcon"
BAG = BAGS / "ikonos_agile"  # the default bag (./dev demo)
BASE_PATHS = ["src", "src/parproj/msg_defs"]  # docs/ros.md: colcon stops at a package root


def copy_sources(dest: Path) -> int:
    """Copy the repository's files (tracked and untracked, not ignored) to ``dest``; how many."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        check=True,
        capture_output=True,
    ).stdout.split(b"\0")
    n = 0
    for name in filter(None, (p.decode() for p in listed)):
        src = ROOT / name
        if not src.is_file():  # deleted in the working tree, not yet in the index
            continue
        (dest / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, dest / name)
        n += 1
    return n


def colcon(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """Run the venv's colcon."""
    return subprocess.run(
        [str(COLCON), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def listed(out: str) -> set[tuple[str, ...]]:
    """``colcon list`` lines as (name, path, type) tuples."""
    return {tuple(line.split("\t")) for line in out.splitlines() if line.strip()}


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A workspace with this repository under src/, built by colcon; its environment."""
    ws = tmp_path_factory.mktemp("ws")
    pkg = ws / "src" / "parproj"  # any folder name: colcon reads package.xml
    assert copy_sources(pkg) > 100
    env = ros_environment(log_dir=ws / "ros_log")
    # The underlay: the venv's ROS 2 wheels (no setup script of their own; rosidl needs
    # AMENT_PREFIX_PATH at configure time). COLCON_HOME: no user defaults or metadata.
    env.update(
        AMENT_PREFIX_PATH=str(VENV), CMAKE_PREFIX_PATH=str(VENV), COLCON_HOME=str(ws / "home")
    )
    lists = {
        "repository": colcon(["list"], pkg, env),  # colcon_defaults.yaml there
        "workspace": colcon(["list", "--base-paths", *BASE_PATHS], ws, env),
        "plain": colcon(["list"], ws, env),
    }
    t0 = time.monotonic()
    build = colcon(
        [
            "build",
            "--base-paths",
            *BASE_PATHS,
            "--cmake-args",
            f"-DPython3_EXECUTABLE={sys.executable}",
            "-DBUILD_TESTING=OFF",
        ],
        ws,
        env,
    )
    seconds = time.monotonic() - t0
    print(f"colcon build: {seconds:.1f} s")
    assert build.returncode == 0, build.stdout[-4000:] + build.stderr[-4000:]
    return {"ws": ws, "env": env, "lists": lists, "build_s": seconds, "build": build}


def in_install_env(ws: Path, env: dict[str, str], command: str) -> str:
    """Run ``command`` in bash after ``source <ws>/install/setup.bash``; its stdout.

    In the workspace folder: ``python -c`` puts the working directory first on sys.path, and
    the repository's would shadow the install tree.
    """
    setup = shlex.quote(str(ws / "install" / "setup.bash"))
    r = subprocess.run(
        ["bash", "-c", f"source {setup} && {command}"],
        cwd=ws,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


def test_colcon_lists_both_packages(workspace: dict) -> None:
    lists = {k: r.stdout for k, r in workspace["lists"].items()}
    assert all(r.returncode == 0 for r in workspace["lists"].values()), lists
    assert listed(lists["repository"]) == {
        ("parproj_msgs", "msg_defs", "(ros.ament_cmake)"),
        ("parproj_ros", ".", "(ros.ament_python)"),
    }
    assert listed(lists["workspace"]) == {
        ("parproj_msgs", "src/parproj/msg_defs", "(ros.ament_cmake)"),
        ("parproj_ros", "src/parproj", "(ros.ament_python)"),
    }
    # Why the base paths: colcon does not descend into a package (msg_defs/ is inside one).
    assert listed(lists["plain"]) == {("parproj_ros", "src/parproj", "(ros.ament_python)")}


def test_install_tree_layout(workspace: dict) -> None:
    inst = workspace["ws"] / "install"
    src = workspace["ws"] / "src" / "parproj"
    ros = inst / "parproj_ros"
    for script in ("parproj_node", "parproj"):
        path = ros / "lib" / "parproj_ros" / script  # where ros2 run looks
        assert path.is_file() and os.access(path, os.X_OK), path
        assert path.read_text().startswith(f"#!{sys.executable}"), path.read_text()[:200]
    assert not (ros / "bin").exists()
    share = ros / "share" / "parproj_ros"
    for name in ("package.xml", "config/parproj_node.yaml", "launch/parproj.launch.py"):
        assert (share / name).read_bytes() == (src / name).read_bytes(), name
    assert (ros / "share/ament_index/resource_index/packages/parproj_ros").is_file()
    msgs = inst / "parproj_msgs"
    assert (msgs / "share/ament_index/resource_index/packages/parproj_msgs").is_file()
    assert (msgs / "share/parproj_msgs/msg/StereoPair.msg").is_file()
    assert list((msgs / "lib").glob("libparproj_msgs__rosidl_typesupport_fastrtps_c.so"))


def test_install_environment(workspace: dict) -> None:
    """After sourcing install/setup.bash both packages come from the install tree."""
    ws = workspace["ws"]
    code = (
        "import json, parproj_ros, parproj_msgs.msg as m\n"
        "from rclpy.serialization import serialize_message\n"
        "from ament_index_python.packages import get_package_prefix as prefix\n"
        "serialize_message(m.StereoPair(pair_id='x'))\n"
        "maps = sorted({l.split()[-1] for l in open('/proc/self/maps') if 'parproj_msgs' in l})\n"
        "print(json.dumps({'parproj_ros': parproj_ros.__file__, 'msgs': m.__file__,\n"
        "  'prefix': prefix('parproj_ros'), 'msgs_prefix': prefix('parproj_msgs'),\n"
        "  'maps': maps}))\n"
    )
    out = json.loads(
        in_install_env(
            ws, workspace["env"], f"{shlex.quote(sys.executable)} -c {shlex.quote(code)}"
        )
    )
    inst = ws / "install"
    assert out["prefix"] == str(inst / "parproj_ros")
    assert out["msgs_prefix"] == str(inst / "parproj_msgs")
    assert out["parproj_ros"].startswith(str(inst / "parproj_ros" / "lib")), out
    assert out["msgs"].startswith(str(inst / "parproj_msgs" / "lib")), out
    # The message package's Python extension is the install tree's; its C libraries are found
    # through LD_LIBRARY_PATH, which the venv's bootstrap reorders (a set): the venv's own copy
    # (./dev setup builds one there) may serve them, the same messages built from the same files.
    ext = [p for p in out["maps"] if "/site-packages/parproj_msgs/" in p]
    assert ext and all(p.startswith(str(inst)) for p in ext), out["maps"]


def test_node_from_install_tree_publishes_the_pair(workspace: dict, tmp_path: Path) -> None:
    """The installed node, started as the installed launch file says, over real DDS."""
    ws, env = workspace["ws"], workspace["env"]
    share = ws / "install" / "parproj_ros" / "share"
    desc = load_launch(share / "parproj_ros" / "launch" / "parproj.launch.py")
    (node,) = desc.nodes
    # The default bag is single-camera (view pan): a params_file of its own, as a user gives
    # one (the installed default names the cameras left and right).
    views = views_from_bag(BagReader(BAG))
    params = node_parameters(views)
    mine = node_params_yaml(params, tmp_path / "my_params.yaml", reliable_inputs=[])
    given = {"params_file": str(mine)}
    ros_args = node_ros_args(node, desc, given, lambda pkg: share / pkg, tmp_path)
    setup = shlex.quote(str(ws / "install" / "setup.bash"))
    find = (
        "from ament_index_python.packages import get_package_prefix; "
        f"print(get_package_prefix({node.package!r}))"
    )
    # ros2 run <package> <executable>: <prefix from the ament index>/lib/<package>/<executable>
    script = (
        f"source {setup} && prefix=$({shlex.quote(sys.executable)} -c {shlex.quote(find)}) && "
        f'echo "ros2 run: $prefix/lib/{node.package}/{node.executable}" && '
        f'exec "$prefix/lib/{node.package}/{node.executable}" "$@"'
    )
    t0 = time.monotonic()
    run = run_through_node(
        BAG,
        tmp_path / "live",
        params=params,  # again, with reliable QoS on the inputs (a lossless replay)
        env=env,
        log=lambda s: None,
        program=["bash", "-c", script, "parproj_node", *ros_args],
    )
    print(f"live run from the install tree: {time.monotonic() - t0:.1f} s")
    assert f"ros2 run: {ws / 'install' / 'parproj_ros'}/lib/parproj_ros/parproj_node" in run.log
    assert "no such parameter" not in run.log, run.log
    assert run.discovered and run.complete, run.log
    assert run.code == 0, run.log
    assert run.counts[contract.STEREO_PAIR] == 1, run.counts
    assert run.counts[contract.PARALLEL_PROJECTION] == 2, run.counts

    # The same pair as `parproj process` of the same bag (this checkout's code, in-process).
    summary = process_bag(BAG, tmp_path / "offline", progress=False)
    assert summary.pairs == 1

    def first(path: Path, topic: str) -> object:
        (msg,) = [m.msg for m in BagReader(path).messages(topics=[topic])]
        return msg

    on = first(run.output, contract.STEREO_PAIR)
    off = first(tmp_path / "offline", contract.STEREO_PAIR)
    assert on.pair_id == off.pair_id != ""
    assert (on.width, on.height) == (off.width, off.height)
    np.testing.assert_allclose(on.left_to_normalized, off.left_to_normalized, rtol=1e-12, atol=0)
    np.testing.assert_allclose(on.right_to_normalized, off.right_to_normalized, rtol=1e-12, atol=0)
    # y-parallax of the published pair: the simulated IKONOS pair is normalized to 0.1 px
    # (tests/ros/test_node_live.py), and the installed node gives the offline figures.
    assert on.y_parallax_points == off.y_parallax_points >= 100
    assert on.y_parallax_rms_px == pytest.approx(off.y_parallax_rms_px, abs=1e-9)
    assert on.y_parallax_max_px == pytest.approx(off.y_parallax_max_px, abs=1e-9)
    assert on.y_parallax_rms_px <= 0.1
    for side in contract.SIDES:
        topic = contract.normalized_image_topic(side)
        a = image_to_array(first(run.output, topic))
        b = image_to_array(first(tmp_path / "offline", topic))
        assert np.array_equal(a, b), topic
