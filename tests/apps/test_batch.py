"""``parproj batch`` on a Dask LocalCluster: bags, an image pair, a bad input, a lost worker.

One batch of two worker processes runs: three bundled bags, the Ventoux crops as an image-pair
list (imported on the worker), a bag that cannot be read, and while ``airborne_foreaft`` runs
its worker process is killed (SIGKILL). Every good input must come out complete with the same
figures as ``process_bag`` called directly; the bad one is reported with its traceback and
leaves no output; the killed task is run again elsewhere and leaves no partial output.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from testkit.paths import BAGS, DATA

from parproj_ros.apps.batch import (
    FAILED_DIR,
    SUMMARY,
    BatchInput,
    find_inputs,
    format_summary,
    read_pair_list,
    run_batch,
)
from parproj_ros.io.files import InputError

pytestmark = [pytest.mark.ros, pytest.mark.slow]  # bags (rclpy serialization), ~1 min

VICTIM = "airborne_foreaft"


def _kill_when_running(client: Any, name: str, out: dict[str, Any]) -> None:
    """SIGKILL the worker process that runs ``name``'s task, about 1 s into it."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        for addr, keys in client.processing().items():
            if any(name in str(k) for k in keys):
                time.sleep(1.0)
                pid = client.run(os.getpid, workers=[addr])[addr]
                os.kill(pid, signal.SIGKILL)
                out["pid"] = pid
                return
        time.sleep(0.05)


@pytest.fixture(scope="module")
def batch(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    from distributed import Client, LocalCluster

    root = tmp_path_factory.mktemp("batch")
    broken = root / "inputs" / "broken"
    broken.mkdir(parents=True)
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 5}\n")
    (broken / "broken_0.mcap").write_bytes(b"\x89MCAP0\r\n" + os.urandom(2000))
    pairs = root / "inputs" / "pairs.csv"
    pairs.write_text(
        "name,left,right,height_min,height_max\n"
        f"ventoux_crops,{DATA / 'left_image.tif'},{DATA / 'right_image.tif'},300,1950\n"
    )
    inputs = find_inputs([BAGS / "ventoux", BAGS / "crab_foreaft", BAGS / VICTIM, pairs, broken])
    killed: dict[str, Any] = {}
    with (
        LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            memory_limit="4GiB",
        ) as cluster,
        Client(cluster) as client,
    ):
        killer = threading.Thread(target=_kill_when_running, args=(client, VICTIM, killed))
        killer.start()
        result = run_batch(inputs, root / "out", client=client, progress=False, log=print)
        killer.join()
    print(format_summary(result))
    return {"root": root, "out": root / "out", "result": result, "killed": killed}


def _rows(batch: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {r["name"]: r for r in batch["result"].rows}


def test_every_good_input_is_done_with_the_direct_figures(batch: dict[str, Any]) -> None:
    from parproj_ros.apps.process import process_bag
    from parproj_ros.eval.evaluate import evaluate_bag

    rows = _rows(batch)
    assert [r["status"] for r in batch["result"].rows] == ["done"] * 4 + ["failed"]
    for name in ("ventoux", "crab_foreaft", VICTIM, "ventoux_crops"):
        out = batch["out"] / name
        assert (out / "output" / "metadata.yaml").is_file(), name
        assert json.loads((out / "summary.json").read_text())["status"] == "done"
        assert rows[name]["pairs"] == 1, rows[name]
    # the batch path gives what process_bag gives, number for number
    for name in ("ventoux", VICTIM):
        direct = batch["root"] / f"direct_{name}"
        process_bag(BAGS / name, direct, progress=False)
        ev = evaluate_bag(direct, BAGS / name, matching=False)
        got = json.loads((batch["out"] / name / "evaluation.json").read_text())
        want = json.loads(json.dumps(ev, default=float))
        assert (
            got["pairs"][0]["published_y_parallax_px"]
            == want["pairs"][0]["published_y_parallax_px"]
        )
        assert got["pairs"][0]["geometric"] == want["pairs"][0]["geometric"]
    # the imported pair: its own bag, normalized to the tolerance of a GCP-only RPC pair
    assert (batch["out"] / "ventoux_crops" / "input" / "metadata.yaml").is_file()
    assert rows["ventoux_crops"]["y_parallax_rms_px"] < 0.5


def test_a_killed_worker_is_replaced_and_its_task_run_again(batch: dict[str, Any]) -> None:
    assert "pid" in batch["killed"], "the victim's task was never seen running"
    row = _rows(batch)[VICTIM]
    assert row["status"] == "done"
    assert row["worker_pid"] != batch["killed"]["pid"]
    # nothing half-written is left: no hidden .partial folder, no stray folder
    leftovers = sorted(p.name for p in batch["out"].iterdir())
    assert leftovers == sorted(
        [FAILED_DIR, SUMMARY, "ventoux", "crab_foreaft", VICTIM, "ventoux_crops"]
    ), leftovers


def test_a_bad_input_is_reported_and_stops_nothing(batch: dict[str, Any]) -> None:
    row = _rows(batch)["broken"]
    assert row["status"] == "failed" and row["error"], row
    log = (batch["out"] / FAILED_DIR / "broken.log").read_text()
    assert "Traceback" in log
    assert not (batch["out"] / "broken").exists()
    summary = json.loads((batch["out"] / SUMMARY).read_text())
    assert (summary["done"], summary["failed"], summary["inputs"]) == (4, 1, 5)
    assert [r["name"] for r in summary["rows"]] == [r["name"] for r in batch["result"].rows]


def test_a_rerun_skips_what_is_up_to_date(batch: dict[str, Any], tmp_path: Path) -> None:
    from distributed import Client, LocalCluster

    with (
        LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        again = run_batch(
            find_inputs([BAGS / "ventoux"]), batch["out"], client=client, progress=False
        )
    assert again.rows[0]["status"] == "skipped"
    assert again.rows[0]["pairs"] == 1


def test_inputs_are_named_and_checked(tmp_path: Path) -> None:
    both = find_inputs([BAGS / "ventoux", BAGS / "ventoux"])
    assert [i.name for i in both] == ["ventoux", "ventoux-2"]
    folder = find_inputs([BAGS])
    assert {i.name for i in folder} >= {"ventoux", "ikonos_agile"}
    with pytest.raises(InputError, match="no such file"):
        find_inputs([tmp_path / "nothing"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="neither a bag nor a folder of bags"):
        find_inputs([tmp_path / "empty"])
    bad = tmp_path / "pairs.yaml"
    bad.write_text("- {name: a, left: l.tif}\n")
    with pytest.raises(InputError, match="missing"):
        read_pair_list(bad)
    bad.write_text("- {name: a, left: l.tif, right: r.tif, height_min: 1}\n")
    with pytest.raises(InputError, match="go together"):
        read_pair_list(bad)
    good = tmp_path / "ok.yaml"
    good.write_text("pairs:\n  - {name: a, left: l.tif, right: r.tif, dem: d.hgt}\n")
    (pair,) = read_pair_list(good)
    assert pair == BatchInput(
        "a", "pair", (tmp_path / "l.tif", tmp_path / "r.tif"), {"dem": tmp_path / "d.hgt"}
    )
