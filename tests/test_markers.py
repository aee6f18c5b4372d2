"""The markers and the ROS-free run of tests/conftest.py.

A run whose ``-m`` leaves out the ``ros`` tests refuses ROS imports: these tests run pytest in
a subprocess to check that the ROS-free part of this suite collects without ROS, and that the
refusal catches a test that needs ROS but is not marked.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent


def pytest_run(args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args],
        cwd=cwd,
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.slow
def test_ros_free_part_collects_without_ros() -> None:
    """Every module of the suite either is marked ros as a whole or imports no ROS at the top."""
    r = pytest_run(["-m", "not ros", "--collect-only", "-q"], ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "error" not in r.stdout.splitlines()[-1], r.stdout[-3000:]


BAD_SUITE = {
    "test_unmarked.py": """
import pytest


def test_plain():
    import numpy  # noqa: F401


def test_needs_ros_unmarked():
    import rclpy  # noqa: F401


def test_needs_ros_swallowed():
    try:
        import sensor_msgs.msg  # noqa: F401
    except ImportError:
        pass


@pytest.mark.ros
def test_needs_ros_marked():
    import rclpy  # noqa: F401
""",
    "test_ros_module.py": """
import pytest
import rclpy  # noqa: F401

pytestmark = pytest.mark.ros


def test_live():
    pass
""",
    "pytest.ini": "[pytest]\nmarkers =\n    ros: r\n    slow: s\naddopts = --strict-markers\n",
}


def test_ros_free_run_fails_an_unmarked_test_that_imports_ros(tmp_path: Path) -> None:
    for name, text in BAD_SUITE.items():
        (tmp_path / name).write_text(text)
    args = ["-p", "conftest", "-q", "-rf", "-m", "not ros and not slow"]
    r = pytest_run(args, tmp_path, PYTHONPATH=str(TESTS))
    out = r.stdout + r.stderr
    assert r.returncode == 1, out
    assert "2 failed, 1 passed, 1 deselected" in out, out
    assert "test_needs_ros_unmarked is not marked ros but imported ['rclpy']" in out, out
    assert "test_needs_ros_swallowed is not marked ros but imported ['sensor_msgs']" in out, out
    assert "test_ros_module" not in out, out  # marked ros as a whole: not even imported
