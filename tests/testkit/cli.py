"""``parproj`` commands run in the test's own process (for the CLI tests)."""

from __future__ import annotations

import pytest

from parproj_ros.apps import cli


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``cli.main(argv)`` in this process: exit code, stdout, stderr."""
    capsys.readouterr()
    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err
