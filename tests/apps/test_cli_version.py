"""``parproj --version`` (issue 25, item 6): the installed package's version, exit 0."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import parproj_ros
from parproj_ros.apps import cli

#: The console script installed next to the interpreter (.venv/bin/parproj).
PARPROJ = Path(sys.executable).with_name("parproj")


def test_version_prints_the_package_metadata_version_and_exits_0() -> None:
    """The console script prints ``parproj <version>`` of the metadata, nothing else, exit 0."""
    p = subprocess.run([str(PARPROJ), "--version"], capture_output=True, text=True, timeout=60)
    assert (p.returncode, p.stdout, p.stderr) == (0, f"parproj {version('parproj_ros')}\n", "")


def test_version_is_the_source_version_and_wins_over_a_command() -> None:
    """The metadata (setup.cfg) and ``parproj_ros.__version__`` agree; ``--version`` before a
    command prints it without running the command (no command is required with it)."""
    assert cli.package_version() == version("parproj_ros") == parproj_ros.__version__
    p = subprocess.run(
        [sys.executable, "-m", "parproj_ros.apps.cli", "--version", "process"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (p.returncode, p.stdout, p.stderr) == (0, f"parproj {parproj_ros.__version__}\n", "")
