"""No silent empty result from ``parproj process`` (issue 24 item 5).

The real Ventoux pair imported with virtual points at heights given far from its ground
(``--heights 750 950``; the ground is at about 540 m): at those heights the two normalized
images hold different ground; asked to keep them (``--terrain prior``) the pair is unusable
and has no DSM, and the run says so and exits 1. Measured from the pair (the default) the same
bag gives a DSM and exit 0.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from testkit.paths import DATA

from parproj_ros.apps import cli
from parproj_ros.apps.commands.process import verdict
from parproj_ros.apps.process import ProcessSummary

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ventoux") / "in"
    imgs = [str(DATA / "left_image.tif"), str(DATA / "right_image.tif")]
    assert cli.main(["import", *imgs, "-o", str(out), "--heights", "750", "950"]) == 0
    return out


@pytest.mark.slow
def test_unusable_pair_exits_1(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "prior"
    code = cli.main(["process", str(bag), "-o", str(out), "-q", "--heights", "--terrain", "prior"])
    err = capsys.readouterr().err
    assert code == 1, err
    assert "[error] pair left+right: its normalized images share only 0.0 % of their" in err
    assert "parproj process: pair left+right: the normalized images share almost no" in err
    assert "parproj process: --heights: no DSM for left+right" in err
    code = cli.main(["process", str(bag), "-o", str(tmp_path / "m"), "-q", "--heights"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "[error]" not in err and "heights: terrain" in err


def test_verdict() -> None:
    """Every shortfall is a line and exit 1; a complete result exit 0."""
    ok = ProcessSummary(pairs=2, heights=[("a+b", True), ("c+d", True)])
    assert verdict(ok, heights=True) == 0
    assert verdict(ProcessSummary(pairs=2), heights=False) == 0
    assert verdict(ProcessSummary(pairs=0), heights=False) == 1
    assert verdict(ProcessSummary(pairs=1, unusable=["a+b"]), heights=False) == 1
    half = ProcessSummary(pairs=2, heights=[("a+b", True), ("c+d", False)])
    assert verdict(half, heights=True) == 1
    assert verdict(ProcessSummary(pairs=1), heights=True) == 1  # heights asked, none made
