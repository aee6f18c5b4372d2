"""parproj_node's output frame (core/frames.py): with ``frame_id`` left at its default ("") the
node publishes in the frame of its inputs, here the imported Marseille pair's tangent plane
(the GCP message's ``enu_wgs84:...``); given a frame, it publishes in that one and WARNs that
the GCP are in another, naming both. The node runs in its own process over DDS on localhost;
its outputs are recorded and read back.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from parproj_ros.apps.importer import import_pair
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import node_parameters, views_from_bag
from parproj_ros.ros.live import run_through_node

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # live node over DDS

MARSEILLE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "marseille_triplet"


@pytest.fixture(scope="module")
def imported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    bag = tmp_path_factory.mktemp("marseille") / "b12"
    import_pair(MARSEILLE / "img_01.tif", MARSEILLE / "img_02.tif", bag, log=lambda s: None)
    (gcp,) = [m.msg for m in BagReader(bag).messages(topics=["gcp"])]
    return bag, str(gcp.header.frame_id)


@pytest.mark.parametrize("given", ["", "map"])
def test_outputs_in_the_frame_of_the_inputs(
    imported: tuple[Path, str], tmp_path: Path, given: str
) -> None:
    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    bag, gcp_frame = imported
    assert gcp_frame.startswith("enu_wgs84:lat=43.26")
    params = node_parameters(views_from_bag(BagReader(bag)), frame_id=given, tie_points=False)
    run = run_through_node(bag, tmp_path / "out", params=params, log=lambda s: None)
    assert run.discovered and run.code == 0, run.log
    out = BagReader(run.output)
    frames = {
        m.topic: m.msg.header.frame_id
        for m in out.messages(topics=["stereo_pair", "parallel_projection"])
    }
    want = given or gcp_frame
    assert frames == {"stereo_pair": want, "parallel_projection": want}, frames
    warned = f"input in frame {gcp_frame!r}, the outputs are in 'map'"
    assert (warned in run.log) == (given == "map"), run.log[-2000:]
