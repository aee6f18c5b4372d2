"""Inputs an adversarial user gives ``parproj process``, ``dsm``, ``fuse`` and ``evaluate``.

The cases not in RELIABILITY.md's tables that an adversarial review (2026-11-27) found handled
badly: each failed before its fix. The review's list of inputs found handled well is in its
report. ``bags/ventoux`` (19 messages, one real Pleiades pair with GCP) is processed with
heights in about 1.5 s.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from testkit.paths import BAGS

from parproj_ros.apps import cli
from parproj_ros.core import contract
from parproj_ros.core.heights import MAX_CELLS_PER_GSD
from parproj_ros.ros.bag import BagReader

pytestmark = pytest.mark.ros  # bags written and read

BAG = BAGS / "ventoux"


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``cli.main(argv)`` in this process: exit code, stdout, stderr."""
    capsys.readouterr()
    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``bags/ventoux`` processed with heights (its DSM's cell: the pair's GSD)."""
    out = tmp_path_factory.mktemp("vx") / "out"
    assert cli.main(["process", str(BAG), "-o", str(out), "-q", "--heights"]) == 0
    return out


def dsm_cell(bag: Path) -> float:
    """The cell side of the (one) DSM of an output bag, metres."""
    msgs = [m.msg for m in BagReader(bag).messages(topics=[contract.DSM])]
    assert len(msgs) == 1
    return float(msgs[0].cell_size)


def test_dsm_cell_far_below_the_gsd_is_named(
    processed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--heights-cell-m 0.0001`` on a 0.5 m pair: the option named, exit 1, heights kept.

    Before: ``parproj process: out of memory (Unable to allocate 36.6 TiB ...)``, exit 3 and
    no output, the option not named (the DSM grid of 5e12 cells allocated).
    """
    gsd = dsm_cell(processed)  # the default cell is the pair's GSD
    out = tmp_path / "fine"
    code, _, err = run(
        ["process", str(BAG), "-o", str(out), "-q", "--heights", "--heights-cell-m", "0.0001"],
        capsys,
    )
    assert code == 1, err
    assert "Traceback" not in err and "out of memory" not in err
    assert f"no DSM: heights_cell_m 0.0001 m is {gsd / 1e-4:.3g} times finer" in err, err
    assert f"at least {gsd / MAX_CELLS_PER_GSD:.3g} m" in err
    assert "parproj process: --heights: no DSM for left+right" in err
    reader = BagReader(out)
    counts = {t: sum(1 for _ in reader.messages(topics=[t])) for t in reader.topics()}
    assert counts[contract.DISPARITY] == 1 and counts[contract.HEIGHT] == 1  # kept
    assert counts.get(contract.DSM, 0) == 0
    # the least cell accepted gives a DSM
    edge = gsd / MAX_CELLS_PER_GSD * 1.01
    code, _, err = run(
        ["process", str(BAG), "-o", str(tmp_path / "edge"), "-q", "--heights",
         "--heights-cell-m", f"{edge:.6f}"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    assert abs(dsm_cell(tmp_path / "edge") - edge) < 1e-6
