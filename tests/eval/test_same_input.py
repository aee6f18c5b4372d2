"""Truth of another acquisition in the same frame is refused by its images (evaluate, dsm).

The simulated bags all use frame ``map``; ``ikonos_agile`` and ``crab_foreaft`` even name their
scenes alike and share their stamps. Before: ``parproj evaluate OUT --truth bags/crab_foreaft``
on the outputs of ``ikonos_agile`` exited 0 with "against the true surface: NMAD 84.387 m", and
with ``bags/airborne_foreaft`` "NMAD 35.480 m"; ``parproj dsm --scenario crab_foreaft`` the same.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from testkit.cli import run
from testkit.paths import BAGS

from parproj_ros.apps import cli
from parproj_ros.core import contract
from parproj_ros.eval.same_input import (
    MIN_CORRELATION,
    check_same_input,
    output_sides,
    scenario_lines,
    truth_bag_lines,
)
from parproj_ros.io.files import InputError
from parproj_ros.ros.bag import BagReader, BagWriter
from parproj_ros.ros.conversions import array_to_image, image_to_array

pytestmark = pytest.mark.ros  # bags written and read


@pytest.fixture(scope="module")
def ikonos(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``bags/ikonos_agile`` processed with heights (about 8 s)."""
    out = tmp_path_factory.mktemp("same") / "ikonos"
    assert (
        cli.main(["process", str(BAGS / "ikonos_agile"), "-o", str(out), "-q", "--heights"]) == 0
    )
    return out


def test_the_acquisition_itself_correlates_fully(ikonos: Path) -> None:
    """Its own bag and its scenario rendered again: both scenes, r >= 0.95 (as the error says).

    The normalized image is the raw image resampled once through the published transforms: the
    same pixels; this is what makes :data:`MIN_CORRELATION` (0.5) a wide margin.
    """
    for lines in (truth_bag_lines(BAGS / "ikonos_agile"), scenario_lines("ikonos_agile")):
        got = check_same_input(ikonos, lines, option="--truth", source="x")
        assert [s for s, _, _ in got] == ["pan_scene_0000", "pan_scene_0001"]
        for _, r, n in got:
            assert r >= 0.95 and n >= 10_000, got


def _streamed_copy(out: Path, path: Path) -> Path:
    """``out`` with its pair as the live node streams one: images in column blocks only."""
    from parproj_msgs.msg import NormalizedBlock
    from sensor_msgs.msg import Image

    reader = BagReader(out)
    with BagWriter(path) as bw:
        for topic, msgtype in reader.topics().items():
            bw.add_topic(topic, msgtype, reader.qos(topic))
        for side in contract.SIDES:
            bw.add_topic(contract.normalized_block_topic(side), "parproj_msgs/msg/NormalizedBlock")
        for m in reader.messages():
            if m.topic == contract.STEREO_PAIR:
                sp = m.msg
                for side in contract.SIDES:
                    img = image_to_array(getattr(sp, side))
                    h, w = img.shape
                    for k, c0 in enumerate(range(0, w, 200)):
                        b = NormalizedBlock(
                            pair_id=sp.pair_id, side=side, col0=c0, full_width=w,
                            full_height=h, index=k, last=c0 + 200 >= w,
                        )  # fmt: skip
                        b.image = array_to_image(
                            img[:, c0 : c0 + 200].copy(), Image(), frame_id="", stamp_ns=0
                        )
                        bw.write(contract.normalized_block_topic(side), b, m.log_time_ns)
                    setattr(sp, side, Image())
                sp.streamed = True
            bw.write(m.topic, m.msg, m.log_time_ns)
    return path


def test_a_streamed_pair_is_compared_through_its_blocks(ikonos: Path, tmp_path: Path) -> None:
    """A streamed pair (its images in normalized column blocks only) is checked too."""
    out = _streamed_copy(ikonos, tmp_path / "streamed")
    got = output_sides(out)
    assert got is not None and got[0].streamed and got[0].left.width == 0
    checked = check_same_input(out, truth_bag_lines(BAGS / "ikonos_agile"), option="-", source="")
    assert len(checked) == 2 and min(r for _, r, _ in checked) >= 0.95, checked
    with pytest.raises(InputError, match="its images of scene 'pan_scene_0000' are not"):
        check_same_input(out, truth_bag_lines(BAGS / "crab_foreaft"), option="-", source="")


def test_evaluate_refuses_the_truth_of_another_scenario(
    ikonos: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Same scene ids and stamps (crab) or other scenes (airborne): exit 2, --truth named."""
    code, out, err = run(["evaluate", str(ikonos), "--truth", str(BAGS / "crab_foreaft")], capsys)
    assert code == 2 and out == "", (out, err)
    (line,) = err.strip().splitlines()
    assert line.startswith(f"parproj evaluate: --truth: {BAGS / 'crab_foreaft'}: its images of ")
    r = float(re.search(r"correlate (-?[\d.]+) with", line).group(1))  # type: ignore[union-attr]
    assert abs(r) < 0.2 < MIN_CORRELATION, line
    assert "the truth of another acquisition" in line
    code, out, err = run(
        ["evaluate", str(ikonos), "--truth", str(BAGS / "airborne_foreaft")], capsys
    )
    assert code == 2, err
    assert "has no image of scene 'pan_scene_0000'" in err
    assert "(its scenes: left_scene_0000, right_scene_0001)" in err
    code, out, err = run(
        ["evaluate", str(ikonos), "--truth", str(BAGS / "ikonos_agile"), "--no-matching"], capsys
    )
    assert code == 0 and "300 truth points" in out, err


def test_dsm_refuses_the_terrain_of_another_scenario(
    ikonos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``dsm --scenario crab_foreaft`` on ikonos outputs: exit 2, nothing written; its own: 0."""
    out = tmp_path / "d"
    code, _, err = run(["dsm", str(ikonos), "-o", str(out), "--scenario", "crab_foreaft"], capsys)
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith("parproj dsm: --scenario: scenario crab_foreaft: its images of ")
    assert not out.exists()
    code, printed, err = run(
        ["dsm", str(ikonos), "-o", str(out), "--scenario", "ikonos_agile"], capsys
    )
    assert code == 0, err
    nmad = float(re.search(r"against truth NMAD ([\d.]+) m", printed).group(1))  # type: ignore[union-attr]
    assert nmad < 0.5, printed  # under half a pixel of x-parallax (1.18 m)
