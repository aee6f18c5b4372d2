"""Issue 9: inputs nobody tried, through every ``parproj`` command (RELIABILITY.md).

- Every command fed damaged files (random bytes, cut-off bags, garbage, nested and non-UTF-8
  metadata.yaml, wrong message types, missing topics, FIFOs, folders for files): exit 2 and one
  line ``parproj <command>: <file>: <problem>`` naming the file, never a traceback. Most cases run
  in this process through ``cli.main``; a few run as real processes to show that nothing else
  reaches stderr.
- Outputs: never the input, inside it or around it; an existing one only with --force; an
  interrupted run (exception, SIGINT, SIGTERM, SIGKILL) leaves nothing at the output's name.
- Options: NaN, Inf, out of range, a height range of zero width: exit 2 before any work.
- ``parproj replay``: paced from the bag's first message (tiny and huge first log times), a
  decades-long wait refused, SIGINT and SIGTERM obeyed within a second.
- GCP files (node parameter ``gcp_file``) and damaged MCAP bytes at the reader level.
"""

from __future__ import annotations

import hashlib
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mcap.writer import Writer as McapWriter
from nav_msgs.msg import Odometry
from parproj_msgs.msg import StereoPair
from sensor_msgs.msg import Image
from testkit.cli import run
from testkit.paths import DATA, ROOT

from parproj_ros.apps import cli
from parproj_ros.io.files import MARKER
from parproj_ros.io.gcp_file import GcpFileError, load_gcp_file
from parproj_ros.ros.bag import BagError, BagReader, BagWriter

pytestmark = pytest.mark.ros  # message classes, bags written and read

BAG = ROOT / "bags" / "ventoux"  # 19 messages, one pair: processed in about a second
BIG_BAG = ROOT / "bags" / "ikonos_agile"  # several seconds to process

PARPROJ = [sys.executable, "-m", "parproj_ros.apps.cli"]
FAST = ["-q", "--no-tie-points"]


def assert_bad_input(code: int, err: str, command: str, names: str) -> None:
    """Exit 2, one line ``parproj <command>: ...`` naming ``names``, no traceback."""
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"parproj {command}: "), err
    assert names in lines[0], (names, err)


def digest(path: Path) -> str:
    """A hash of a file or of every file of a folder (names and bytes)."""
    h = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for f in files:
        h.update(str(f.relative_to(path.parent)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def write_bag(path: Path, messages: list[tuple[str, Any, int]]) -> Path:
    with BagWriter(path) as bw:
        for topic, msg, t in messages:
            bw.write(topic, msg, t)
    return path


# ---- a corpus of damaged inputs -----------------------------------------------------------------


@pytest.fixture(scope="module")
def bad(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Damaged files and bags, each under a name that says what is wrong with it."""
    d = tmp_path_factory.mktemp("bad")
    rng = random.Random(9)
    mcap = next(BAG.glob("*.mcap"))
    out: dict[str, Path] = {}

    def bag_with_metadata(name: str, text: bytes) -> None:
        b = d / name
        b.mkdir()
        shutil.copy(mcap, b / mcap.name)
        (b / "metadata.yaml").write_bytes(text)
        out[name] = b

    (d / "random.bin").write_bytes(rng.randbytes(4000))
    out["random_file"] = d / "random.bin"
    (d / "random_bag").mkdir()
    (d / "random_bag" / "random_bag_0.mcap").write_bytes(rng.randbytes(4000))
    out["random_bag"] = d / "random_bag"
    (d / "cut_bag").mkdir()
    (d / "cut_bag" / "cut_bag_0.mcap").write_bytes(mcap.read_bytes()[:3000])
    out["cut_bag"] = d / "cut_bag"
    bag_with_metadata("garbage_yaml", b"rosbag2_bagfile_information: [{{ :::\n")
    bag_with_metadata(
        "nested_yaml",
        b"rosbag2_bagfile_information:\n  relative_file_paths: {a: {b: {c: 1}}}\n",
    )
    bag_with_metadata("list_yaml", b"- 1\n- 2\n")
    bag_with_metadata("scalar_info", b"rosbag2_bagfile_information: 12\n")
    bag_with_metadata("count_text", b"rosbag2_bagfile_information:\n  message_count: many\n")
    bag_with_metadata("latin1_yaml", "rosbag2_bagfile_information: {a: 'é'}\n".encode("latin-1"))
    bag_with_metadata("deep_yaml", b"a: " + b"[" * 5000 + b"]" * 5000 + b"\n")
    fifo_meta = d / "fifo_meta"
    fifo_meta.mkdir()
    shutil.copy(mcap, fifo_meta / mcap.name)
    os.mkfifo(fifo_meta / "metadata.yaml")
    out["fifo_meta"] = fifo_meta
    os.mkfifo(d / "fifo.mcap")
    out["fifo"] = d / "fifo.mcap"
    (d / "folder.tif").mkdir()
    out["folder"] = d / "folder.tif"
    # wrong message types, missing topics
    out["nav_is_image"] = write_bag(d / "nav_is_image", [("navigation", Image(), 10**18)])
    out["only_nav"] = write_bag(d / "only_nav", [("navigation", Odometry(), 10**18)])
    out["camera_is_odometry"] = write_bag(
        d / "camera_is_odometry", [("left/scanner_info", Odometry(), 10**18)]
    )
    out["pair_is_image"] = write_bag(d / "pair_is_image", [("stereo_pair", Image(), 10**18)])
    nan_pair = StereoPair()
    nan_pair.left_params.x_per_line = float("nan")
    out["empty_pair"] = write_bag(d / "empty_pair", [("stereo_pair", StereoPair(), 10**18)])
    out["nan_pair"] = write_bag(d / "nan_pair", [("stereo_pair", nan_pair, 10**18)])
    json_bag = d / "json_bag"  # a foreign (non-ROS) MCAP: JSON messages
    json_bag.mkdir()
    with (json_bag / "json_bag_0.mcap").open("wb") as fh:
        w = McapWriter(fh)
        w.start(profile="", library="test")
        sid = w.register_schema("nav_msgs/msg/Odometry", "jsonschema", b"{}")
        cid = w.register_channel("navigation", "json", sid)
        w.add_message(cid, log_time=10**18, data=b'{"x": 1}', publish_time=10**18)
        w.finish()
    out["json_bag"] = json_bag
    # import / segments inputs
    tif = DATA / "left_image.tif"
    (d / "cut.tif").write_bytes(tif.read_bytes()[:20000])
    out["cut_tif"] = d / "cut.tif"
    (d / "random.tif").write_bytes(rng.randbytes(3000))
    out["random_tif"] = d / "random.tif"
    geom = (DATA / "left_image.geom").read_bytes()
    (d / "cut.geom").write_bytes(geom[:700])
    out["cut_rpc"] = d / "cut.geom"
    (d / "latin1.geom").write_bytes(geom.decode().replace("line_off", "líne_off").encode("cp1252"))
    out["latin1_rpc"] = d / "latin1.geom"
    (d / "nan.geom").write_bytes(geom.replace(b"line_scale:", b"line_scale: nan #", 1))
    out["nan_rpc"] = d / "nan.geom"
    (d / "garbage.json").write_text("{not json")
    out["garbage_json"] = d / "garbage.json"
    return out


# (command line, the name the message must hold). {x} is a path of the corpus above.
BAD_CASES = [
    ("process {random_file} -o {tmp}/o", "{random_file}"),
    ("process {random_bag} -o {tmp}/o", "random_bag_0.mcap"),
    ("process {cut_bag} -o {tmp}/o", "{cut_bag}"),
    ("process {garbage_yaml} -o {tmp}/o", "garbage_yaml/metadata.yaml"),
    ("process {nested_yaml} -o {tmp}/o", "nested_yaml/metadata.yaml"),
    ("process {list_yaml} -o {tmp}/o", "list_yaml/metadata.yaml"),
    ("process {scalar_info} -o {tmp}/o", "scalar_info/metadata.yaml"),
    ("process {count_text} -o {tmp}/o", "count_text/metadata.yaml"),
    ("process {latin1_yaml} -o {tmp}/o", "latin1_yaml/metadata.yaml"),
    ("process {deep_yaml} -o {tmp}/o", "deep_yaml/metadata.yaml"),
    ("process {fifo_meta} -o {tmp}/o", "fifo_meta/metadata.yaml"),
    ("process {fifo} -o {tmp}/o", "{fifo}"),
    ("process {nav_is_image} -o {tmp}/o", "{nav_is_image}"),
    ("process {only_nav} -o {tmp}/o", "{only_nav}"),
    ("process {camera_is_odometry} -o {tmp}/o", "{camera_is_odometry}"),
    ("process {json_bag} -o {tmp}/o", "{json_bag}: topic navigation has message encoding 'json'"),
    ("process {tmp}/nothing -o {tmp}/o", "{tmp}/nothing"),
    ("process " + str(BAG) + " -o {random_file}/o", "{random_file}/o"),
    ("evaluate {random_bag}", "random_bag_0.mcap"),
    ("evaluate {only_nav}", "{only_nav}"),
    ("evaluate {pair_is_image}", "{pair_is_image}"),
    ("evaluate {latin1_yaml}", "latin1_yaml/metadata.yaml"),
    ("evaluate {empty_pair}", "{empty_pair}: stereo_pair message 0"),
    ("evaluate {nan_pair}", "left_params.x_per_line is not finite"),
    ("evaluate " + str(BAG), str(BAG)),  # an input bag, not an output
    ("evaluate {pair_is_image} --truth {only_nav}", "{pair_is_image}"),
    ("replay {random_bag}", "random_bag_0.mcap"),
    ("replay {fifo}", "{fifo}"),
    ("replay {nested_yaml}", "nested_yaml/metadata.yaml"),
    ("replay " + str(BAG) + " --wait-for nope", "--wait-for"),
    ("demo --bag {garbage_yaml} -o {tmp}/d", "garbage_yaml/metadata.yaml"),
    ("demo --bag {only_nav} -o {tmp}/d", "{only_nav}"),
    ("simulate nosuchscenario -o {tmp}/s", "nosuchscenario"),
    ("simulate ikonos_agile -o {random_file}", "{random_file}"),
    ("segments {random_file} {random_file}", "{random_file}"),
    ("segments {cut_rpc} " + str(DATA / "right_image.geom"), "{cut_rpc}"),
    ("segments {latin1_rpc} " + str(DATA / "right_image.geom"), "{latin1_rpc}"),
    ("segments {nan_rpc} " + str(DATA / "right_image.geom"), "{nan_rpc}"),
    ("segments {folder} " + str(DATA / "right_image.geom"), "{folder}"),
    ("segments {fifo} " + str(DATA / "right_image.geom"), "{fifo}"),
    ("import {random_tif} " + str(DATA / "right_image.tif") + " -o {tmp}/i", "{random_tif}"),
    ("import {cut_tif} " + str(DATA / "right_image.tif") + " -o {tmp}/i", "{cut_tif}"),
    ("import {folder} " + str(DATA / "right_image.tif") + " -o {tmp}/i", "{folder}"),
    ("import {fifo} " + str(DATA / "right_image.tif") + " -o {tmp}/i", "{fifo}"),
    (
        f"import {DATA / 'left_image.tif'} {DATA / 'right_image.tif'} --rpc-left {{cut_rpc}} "
        "-o {tmp}/i",
        "{cut_rpc}",
    ),
    (
        f"import {DATA / 'left_image.tif'} {DATA / 'right_image.tif'} --rpc-left {{latin1_rpc}} "
        "-o {tmp}/i",
        "{latin1_rpc}",
    ),
    (
        f"import {DATA / 'left_image.tif'} {DATA / 'right_image.tif'} --rpc-right {{fifo}} "
        "-o {tmp}/i",
        "{fifo}",
    ),
    (
        f"import {DATA / 'left_image.tif'} {DATA / 'right_image.tif'} --dem {{random_file}} "
        "-o {tmp}/i",
        "{random_file}",
    ),
    (
        f"ventoux-eval {{only_nav}} --left {DATA / 'left_image.tif'} --right "
        f"{DATA / 'right_image.tif'} --grids {DATA / 'reference_grids'}",
        "{only_nav}",
    ),
    (
        f"ventoux-eval {{pair_is_image}} --left {DATA / 'left_image.tif'} --right "
        f"{{cut_tif}} --grids {DATA / 'reference_grids'}",
        "{pair_is_image}",
    ),
]


def _fill(text: str, bad: dict[str, Path], tmp: Path) -> str:
    return text.format(tmp=tmp, **{k: str(v) for k, v in bad.items()})


@pytest.mark.parametrize(("line", "names"), BAD_CASES, ids=[c[0][:60] for c in BAD_CASES])
def test_bad_input_is_one_line_exit_2(
    line: str,
    names: str,
    bad: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = _fill(line, bad, tmp_path).split()
    code, _, err = run(argv, capsys)
    assert_bad_input(code, err, argv[0], _fill(names, bad, tmp_path))
    assert not list(tmp_path.iterdir()), "nothing written"


def test_debug_shows_the_traceback(bad: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"metadata\.yaml"):
        cli.main(["--debug", "process", str(bad["garbage_yaml"]), "-o", str(tmp_path / "o")])


def test_internal_error_is_exit_3(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bug (here a TypeError inside the pipeline) is not reported as bad input."""
    from parproj_ros.core.pipeline import Pipeline

    def broken(self: Any, *a: Any, **k: Any) -> Any:
        raise TypeError("simulated bug")

    monkeypatch.setattr(Pipeline, "flush", broken)
    out = tmp_path / "out"
    code, _, err = run(["process", str(BAG), "-o", str(out), *FAST], capsys)
    assert code == 3 and "internal error" in err and "TypeError: simulated bug" in err, err
    assert "--debug" in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.iterdir())  # nothing left, not even .partial


def test_process_past_the_page_cache_or_through_it(tmp_path: Path, capsys: Any) -> None:
    """``parproj process`` writes its output past the page cache by default (O_DIRECT) and
    through it with ``--no-direct``: the same messages either way."""
    got = []
    for opt in ([], ["--no-direct"]):
        out = tmp_path / ("cached" if opt else "direct")
        code, _, err = run(["process", str(BAG), "-o", str(out), *FAST, *opt], capsys)
        assert code == 0, err
        got.append([(m.topic, m.log_time_ns, len(m.data)) for m in BagReader(out).raw_messages()])
    assert got[0] == got[1] and len(got[0]) >= 5


# ---- options ------------------------------------------------------------------------------------

OPTION_CASES = [
    ("process {bag} -o {tmp}/o --z-avg nan", "--z-avg"),
    ("process {bag} -o {tmp}/o --z-avg -1e5", "--z-avg"),  # the node's range: -1000..9000
    ("process {bag} -o {tmp}/o --height-range inf", "--height-range"),
    ("process {bag} -o {tmp}/o --height-range 0", "--height-range"),
    ("process {bag} -o {tmp}/o --segment-max-error -1", "--segment-max-error"),
    ("process {bag} -o {tmp}/o --scene-lines -5", "--scene-lines"),
    ("replay {bag} --rate nan", "--rate"),
    ("replay {bag} --max-gap 0", "--max-gap"),
    ("simulate ikonos_agile -o {tmp}/s --noise-px nan", "--noise-px"),
    ("demo -o {tmp}/d --rate -inf", "--rate"),
    ("paper --sets -1", "--sets"),
    ("segments {geom} {geom} --heights 1000 1000", "--heights"),
    ("segments {geom} {geom} --heights 1000 1005", "--heights"),
    ("segments {geom} {geom} --heights 1100 900", "--heights"),
    ("segments {geom} {geom} --heights nan 900", "--heights"),
    ("segments {geom} {geom} --bound nan", "--bound"),
    ("segments {geom} {geom} --bound 0", "--bound"),
    ("segments {geom} {geom} --width 0", "--width"),
    ("import {tif} {tif2} -o {tmp}/i --heights 500 500", "--heights"),
    ("import {tif} {tif2} -o {tmp}/i --pixel-size 0", "--pixel-size"),
    ("import {tif} {tif2} -o {tmp}/i --ids a a", "--ids"),
    ("import {tif} {tif} -o {tmp}/i", "is the same image as"),
    ("ventoux-eval {bag} --left {tif} --right {tif} --grids {tmp} --pair -1", "--pair"),
]


@pytest.mark.parametrize(("line", "option"), OPTION_CASES, ids=[c[0] for c in OPTION_CASES])
def test_bad_option_is_one_line_exit_2(
    line: str, option: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = line.format(
        bag=BAG,
        tmp=tmp_path,
        geom=DATA / "left_image.geom",
        tif=DATA / "left_image.tif",
        tif2=DATA / "right_image.tif",
    ).split()
    code, _, err = run(argv, capsys)
    assert_bad_input(code, err, argv[0], option)
    assert not list(tmp_path.iterdir())


def test_zero_width_heights_say_why(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    geom = str(DATA / "left_image.geom")
    code, _, err = run(["segments", geom, geom, "--heights", "1000", "1000"], capsys)
    assert code == 2 and "must be above" in err
    code, _, err = run(["segments", geom, geom, "--heights", "1000", "1001"], capsys)
    assert code == 2 and "narrower than 10 m" in err and "height terms" in err


# ---- outputs ------------------------------------------------------------------------------------


@pytest.fixture
def bag_copy(tmp_path: Path) -> Path:
    dst = tmp_path / "in"
    shutil.copytree(BAG, dst)
    return dst


@pytest.mark.parametrize("where", ["same", "same_spelled_otherwise", "inside", "around"])
def test_output_is_never_the_input(
    where: str, bag_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = digest(bag_copy)
    out = {
        "same": bag_copy,
        "same_spelled_otherwise": Path(f"{bag_copy}/../{bag_copy.name}/"),
        "inside": bag_copy / "out",
        "around": tmp_path,
    }[where]
    code, _, err = run(["process", str(bag_copy), "-o", str(out), "--force", *FAST], capsys)
    assert_bad_input(code, err, "process", "input")
    assert digest(bag_copy) == before


def test_existing_output_needs_force(
    bag_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other = tmp_path / "other"
    shutil.copytree(BAG, other)  # another bag, in the way
    before = digest(other)
    code, _, err = run(["process", str(bag_copy), "-o", str(other), *FAST], capsys)
    assert_bad_input(code, err, "process", f"{other}: exists (add --force to replace it)")
    assert digest(other) == before
    code, _, err = run(["process", str(bag_copy), "-o", str(other), "--force", *FAST], capsys)
    assert code == 0, err
    assert set(BagReader(other).topics()) >= {"stereo_pair", "parallel_projection"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "other"]  # no .partial left
    # --force never replaces what is not a bag
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "thesis.txt").write_text("years of work")
    code, _, err = run(["process", str(bag_copy), "-o", str(notes), "--force", *FAST], capsys)
    assert_bad_input(code, err, "process", "not a bag")
    assert (notes / "thesis.txt").read_text() == "years of work"


def test_evaluate_plots_folder_is_safe(
    bag_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert run(["process", str(bag_copy), "-o", str(out), *FAST], capsys)[0] == 0
    code, _, err = run(["evaluate", str(out), "--plots", str(out), "--no-matching"], capsys)
    assert_bad_input(code, err, "evaluate", "is the input")
    plots = tmp_path / "plots"
    argv = ["evaluate", str(out), "--truth", str(bag_copy), "--plots", str(plots)]
    assert run([*argv, "--no-matching"], capsys)[0] == 0
    assert (plots / MARKER).is_file() and list(plots.glob("*_geometry.png"))
    assert run([*argv, "--no-matching"], capsys)[0] == 2  # exists
    assert run([*argv, "--no-matching", "--force"], capsys)[0] == 0  # written by parproj


@pytest.mark.parametrize("how", ["exception", "SIGINT"])
def test_interrupted_process_leaves_no_output(
    how: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """An error or SIGINT after the output bag was begun: nothing at the output's name."""
    from parproj_ros.apps import process

    real = process.process_bag

    def dies_half_way(src: Path, dst: Path, **kw: Any) -> Any:
        def on_outputs(out: Any) -> None:
            if out.scenes:  # the output bag holds messages by now
                assert any(dst.glob("*.mcap"))
                raise KeyboardInterrupt if how == "SIGINT" else OSError(28, "No space left")

        return real(src, dst, on_outputs=on_outputs, **kw)

    monkeypatch.setattr(process, "process_bag", dies_half_way)
    out = tmp_path / "out"
    code, _, err = run(["process", str(BAG), "-o", str(out), *FAST], capsys)
    assert code == (130 if how == "SIGINT" else 2), err
    assert "Traceback" not in err
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_killed_process_leaves_no_output(sig: signal.Signals, tmp_path: Path) -> None:
    """A real ``parproj process`` stopped while it writes (SIGTERM: 143, cleaned up; SIGKILL:
    only a hidden ``.out.*.partial`` folder is left, never ``out``)."""
    out = tmp_path / "out"
    proc = subprocess.Popen(
        # tie points and heights: about 6 s after the file appears at 0.5 s (with FAST the
        # whole run is under 1 s, and a loaded machine signalled it after the rename)
        [*PARPROJ, "process", str(BIG_BAG), "-o", str(out), "-q", "--heights"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".out.*.partial/out/*.mcap")) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=30)
    assert not out.exists(), (proc.returncode, err)
    if sig == signal.SIGTERM:
        assert proc.returncode == 143 and "stopped by SIGTERM" in err and "Traceback" not in err
        assert not list(tmp_path.iterdir())
    else:
        assert [p.name.startswith(".out.") for p in tmp_path.iterdir()] == [True]


# ---- real processes: nothing but the one line reaches stderr ------------------------------------


def test_real_processes_print_one_line(bad: dict[str, Path], tmp_path: Path) -> None:
    cases = [
        (["process", str(bad["garbage_yaml"]), "-o", str(tmp_path / "o")], "metadata.yaml"),
        (["import", str(bad["random_tif"]), str(DATA / "right_image.tif"), "-o", "x"], "random"),
        (["segments", str(bad["folder"]), str(bad["folder"])], str(bad["folder"])),
        (["process", str(BAG), "-o", str(tmp_path / "o"), "--z-avg", "nan"], "--z-avg"),
    ]
    procs = [
        (subprocess.Popen([*PARPROJ, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True), argv, names)
        for argv, names in cases
    ]  # fmt: skip
    for proc, argv, names in procs:
        out, err = proc.communicate(timeout=120)
        assert_bad_input(proc.returncode, err, argv[0], names)
        assert out == ""


# ---- replay -------------------------------------------------------------------------------------


def nav_bag(path: Path, times_ns: list[int]) -> Path:
    return write_bag(path, [("navigation", Odometry(), t) for t in times_ns])


@pytest.fixture(scope="module")
def replay_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("replay")
    now = 1_764_000_000 * 10**9
    step = 300_000_000  # 0.3 s
    return {
        "tiny": nav_bag(d / "tiny", [1 + k * step for k in range(4)]),
        "huge": nav_bag(d / "huge", [2**63 - 10**10 + k * step for k in range(4)]),
        "unset_first": nav_bag(d / "unset_first", [1] + [now + k * step for k in range(3)]),
        "slow": nav_bag(d / "slow", [now, now + 60 * 10**9]),
    }


def replay(bag: Path, *args: str) -> tuple[int, str, str, float]:
    t0 = time.monotonic()
    p = subprocess.run(
        [*PARPROJ, "replay", "-q", str(bag), *args], capture_output=True, text=True, timeout=60
    )
    return p.returncode, p.stdout, p.stderr, time.monotonic() - t0


def test_replay_paces_from_the_first_message(replay_bags: dict[str, Path]) -> None:
    """Tiny and huge first log times: 4 messages 0.3 s apart take 0.9 s, paced from the first."""
    results = {}
    threads = [
        threading.Thread(target=lambda k=k: results.__setitem__(k, replay(replay_bags[k])))
        for k in ("tiny", "huge")
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for name in ("tiny", "huge"):
        code, out, err, _ = results[name]
        assert code == 0, err
        assert "published 4 messages in" in out, out
        seconds = float(out.split("published 4 messages in ")[1].split()[0])
        assert 0.85 <= seconds < 3.0, (name, out)


def test_replay_refuses_a_decades_long_wait(replay_bags: dict[str, Path]) -> None:
    code, _, err, _ = replay(replay_bags["unset_first"])
    assert_bad_input(code, err, "replay", str(replay_bags["unset_first"]))
    assert "--max-gap" in err and "jumps ahead by" in err
    code, out, err, _ = replay(replay_bags["unset_first"], "--max-gap", "0.3")
    assert code == 0 and "published 4 messages" in out, err


@pytest.mark.parametrize(
    ("sig", "code", "ignored"),
    [(signal.SIGINT, 130, False), (signal.SIGTERM, 143, False), (signal.SIGINT, 130, True)],
    ids=["SIGINT", "SIGTERM", "SIGINT-ignored-at-start"],
)
def test_replay_stops_at_once_on_a_signal(
    sig: signal.Signals, code: int, ignored: bool, replay_bags: dict[str, Path]
) -> None:
    """SIGINT and SIGTERM stop a replay at once; SIGINT too when the command was started with
    it ignored, as a shell starts a background job (``parproj replay bag &``; before, it
    waited out its 60 s)."""
    # sh ignores SIGINT, then execs the command with it ignored (a background job's state)
    start = ["sh", "-c", "trap '' INT; exec \"$@\"", "sh"] if ignored else []
    proc = subprocess.Popen(
        [*start, *PARPROJ, "replay", "-q", str(replay_bags["slow"])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().startswith("replay ")  # about to publish, then 60 s to wait
    time.sleep(1.0)
    t0 = time.monotonic()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=30)
    stopped = time.monotonic() - t0
    assert proc.returncode == code, err
    assert stopped < 1.0, stopped
    assert "stopped by" in err and "Traceback" not in err


# ---- GCP files (the node's gcp_file) ------------------------------------------------------------


@pytest.fixture
def gcp_files(tmp_path: Path) -> Iterator[dict[str, Path]]:
    f = {
        "fifo": tmp_path / "fifo.csv",
        "folder": tmp_path / "folder.yaml",
        "latin1": tmp_path / "latin1.csv",
        "garbage_yaml": tmp_path / "garbage.yaml",
        "deep_yaml": tmp_path / "deep.yaml",
        "points_not_mappings": tmp_path / "flat.yaml",
        "observations_list": tmp_path / "obs.yaml",
        "short_row": tmp_path / "short.csv",
        "nul_bytes": tmp_path / "nul.csv",
        "random": tmp_path / "random.csv",
    }
    os.mkfifo(f["fifo"])
    f["folder"].mkdir()
    f["latin1"].write_bytes(
        "id,X,Y,Z,check,scene_id,line,sample\né,1,2,3,0,s,1,2\n".encode("cp1252")
    )
    f["garbage_yaml"].write_text("points: [{{{ ::\n")
    f["deep_yaml"].write_text("points: " + "[" * 5000 + "]" * 5000 + "\n")
    f["points_not_mappings"].write_text("points: [1, 2, 3]\n")
    f["observations_list"].write_text("points:\n  - {id: a, xyz: [1, 2, 3], observations: [1]}\n")
    f["short_row"].write_text("id,X,Y,Z,check,scene_id,line,sample\ng1,1,2\n")
    f["nul_bytes"].write_bytes(b"id,X,Y,Z,check,scene_id,line,sample\ng1,\x00,2,3,0,s,1,2\n")
    f["random"].write_bytes(random.Random(3).randbytes(3000))
    yield f


def _load_into(path: Path, done: list[BaseException | None]) -> None:
    try:
        load_gcp_file(path)
        done.append(None)
    except Exception as err:
        done.append(err)


def test_gcp_file_errors_name_the_file(gcp_files: dict[str, Path]) -> None:
    for name, path in gcp_files.items():
        done: list[BaseException | None] = []
        t = threading.Thread(target=_load_into, args=(path, done), daemon=True)
        t.start()
        t.join(5.0)
        assert done, f"{name}: load_gcp_file blocked"
        err = done[0]
        assert isinstance(err, GcpFileError), (name, repr(err))
        assert str(err).startswith(str(path)), (name, str(err))


def test_gcp_file_size_limit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from parproj_ros.io import gcp_file

    p = tmp_path / "big.csv"
    p.write_text("id,X,Y,Z,check,scene_id,line,sample\n" + "g1,1,2,3,0,s,1,2\n" * 100)
    assert len(gcp_file.load_gcp_file(p)) == 1
    monkeypatch.setattr(gcp_file, "MAX_GCP_FILE_BYTES", 1000)
    with pytest.raises(GcpFileError, match="more than the 1000 bytes"):
        gcp_file.load_gcp_file(p)


# ---- damaged MCAP bytes at the reader -----------------------------------------------------------


def test_damaged_mcap_bytes_give_bag_error_or_recovery(tmp_path: Path) -> None:
    """300 mutations of a real bag's MCAP file: a BagError naming it, or messages recovered."""
    data = next(BAG.glob("*.mcap")).read_bytes()
    rng = random.Random(2026)
    f = tmp_path / "x.mcap"
    outcomes = {"recovered": 0, "BagError": 0}
    for k in range(300):
        b = bytearray(data)
        how = "header" if k % 50 == 0 else rng.choice(["flip", "cut", "zero", "splice"])
        at = rng.randrange(len(b))
        if how == "flip":
            for _ in range(rng.randint(1, 20)):
                b[rng.randrange(len(b))] = rng.randrange(256)
        elif how == "cut":
            b = b[:at]
        elif how == "header":
            b = b[: k % 7]
        elif how == "zero":
            b[at : at + 500] = bytes(len(b[at : at + 500]))
        else:
            b = b[:at] + b[rng.randrange(len(b)) :]
        f.write_bytes(bytes(b))
        try:
            reader = BagReader(f)
            reader.topics()
            for _ in reader.messages():
                pass
            outcomes["recovered"] += 1
        except BagError as err:
            assert str(f) in str(err)
            outcomes["BagError"] += 1
    assert outcomes["recovered"] > 0 and outcomes["BagError"] > 0, outcomes


# ---- evaluate --truth in another object frame (issue 24 item 6) ---------------------------------


def _truth_in_frame(path: Path, frame_id: str) -> Path:
    """The Ventoux bag's truth points, relabelled ``frame_id`` (same numbers)."""
    items = list(BagReader(BAG).messages(topics=["truth/points"]))
    for item in items:
        item.msg.header.frame_id = frame_id
    return write_bag(path, [("truth/points", i.msg, i.log_time_ns) for i in items])


def test_evaluate_refuses_truth_from_another_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Truth in ``map`` or in another tangent plane against outputs in the imported pair's
    frame: exit 2, one line naming both frames (and how far apart two tangent planes are)."""
    from parproj_ros.eval.evaluate import first_frame_id
    from parproj_ros.io.scene_import import frame_from_id, frame_id_of
    from parproj_ros.rpc import LocalTangentPlane

    out = tmp_path / "out"
    assert run(["process", str(BAG), "-o", str(out), *FAST], capsys)[0] == 0
    frame = first_frame_id(BagReader(BAG), "truth/points")
    assert frame is not None and frame.startswith("enu_wgs84:")
    assert first_frame_id(BagReader(out), "stereo_pair") == frame  # as recorded by process
    ok = ["evaluate", str(out), "--truth", str(BAG), "--no-matching", "--json"]
    assert run(ok, capsys)[0] == 0
    f0 = frame_from_id(frame)
    moved = frame_id_of(LocalTangentPlane(f0.lat0 + 0.009, f0.lon0, f0.h0 + 12.0))
    x, y, _ = LocalTangentPlane(f0.lat0 + 0.009, f0.lon0, f0.h0 + 12.0).to_local(
        f0.lon0, f0.lat0, f0.h0
    )
    apart = f"(origins {float(math.hypot(float(x), float(y))):.0f} m apart"
    for other, extra in (("map", ""), (moved, apart)):
        truth = _truth_in_frame(tmp_path / f"truth_{len(extra)}", other)
        argv = ["evaluate", str(out), "--truth", str(truth), "--no-matching"]
        code, _, err = run(argv, capsys)
        assert_bad_input(code, err, "evaluate", f"in object frame {other!r}")
        assert f"in {frame!r}" in err and "--truth" in err and extra in err, err
