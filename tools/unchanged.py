"""Behaviour unchanged across a redesign: the same runs at a base revision and now, compared.

``python -m tools.unchanged --base REV [--current REV | --working-tree] [--out DIR]``

Each side runs in its own git worktree under /tmp (``/tmp/unchanged_base_<sha>``, and
``/tmp/unchanged_current_<sha>`` for ``--current``, default HEAD; ``--working-tree`` takes this
checkout as it is, uncommitted edits included) with the SAME interpreter and venv: PYTHONPATH
set to the tree makes ``import parproj_ros`` take that tree's code ahead of the venv's editable
install (checked in every run; the node the demo starts inherits the environment). Messages
(parproj_msgs) come from the venv for both sides; a difference of msg_defs/ between the two
revisions is reported. Checks:

1. ``parproj demo`` (what ``./dev demo`` runs: the tree's bags/ikonos_agile through the live
   node): evaluation.json compared field by field (no field excluded: it holds no wall-clock
   time, see :data:`EVALUATION_EXCLUDED`).
2. ``parproj paper --json``: stdout byte for byte.
3. One real pair (Ventoux, ../shared/data): ``parproj import`` at each side (input bags compared
   message for message), then the base's input bag through ``parproj process --heights`` at
   each side (output bags compared message for message).

Bags are compared with the mcap reader: topics, types, message definitions and offered QoS,
count per topic, and per message its log/publish time and CDR bytes. Bytes that differ only in
CDR alignment padding (which rclpy's serializer leaves uninitialized: the padding differs from
one build of the code to the next while every field is equal) count as the same: each such
message is decoded (mcap-ros2-support), re-encoded with zero padding and compared again, and
the fields that differ are named (topic, index, field, values). :data:`WALL_CLOCK` lists the
fields left out because they carry wall-clock time.

Prints a table (check, base, current, same?) and exits 0 when every check is the same, 1 when
one differs or a run failed (its stderr tail is printed), 2 when the trees cannot be built.
Takes about 2 minutes (the demo's two live runs are most of it).
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: The repository (tools/ sits at its top).
ROOT = Path(__file__).resolve().parent.parent

#: evaluation.json fields left out of the comparison (JSON path pattern -> why). None: every
#: field of the demo's evaluation is a count, a geometric figure or a file name (checked on
#: 67a122c); a timing added later shows as a difference until it is listed here with its reason.
EVALUATION_EXCLUDED: dict[str, str] = {}

#: Decoded message fields that carry wall-clock time, by message type: (type, field, pattern of
#: the text, why). Only the live node's 1 Hz summary has any; ``parproj process`` writes none.
WALL_CLOCK: tuple[tuple[str, str, str, str], ...] = (
    (
        "diagnostic_msgs/msg/DiagnosticArray",
        "status[].values[] with a key ending in _s",
        r"_s$",
        "seconds of wall clock (the summary's busy_s: how long the worker has held its input)",
    ),
    (
        "diagnostic_msgs/msg/DiagnosticArray",
        "status[].message: '<n> s ago'",
        r"\d+ s ago",
        "age of the last error in wall-clock seconds (the summary's ERROR hold)",
    ),
)

#: The real pair imported (../shared/data/ventoux), as docs/import.md imports it.
REAL_PAIR = "ventoux"


def real_pair_import_args(data: Path) -> list[str]:
    """``parproj import`` arguments for the Ventoux pair in ``data`` (docs/import.md's)."""
    return [
        str(data / "left_image.tif"),
        str(data / "right_image.tif"),
        "--dem",
        str(data / "dem" / "N44E005.hgt"),
        "--geoid-undulation",
        "50",
    ]


#: ``parproj process`` options of the real-pair check (heights too: the DSM path is covered).
PROCESS_ARGS = ("--heights",)

#: Lines of a failed command's stderr printed.
TAIL_LINES = 25


class SetupError(Exception):
    """A tree cannot be built or a revision not resolved (exit 2)."""


class RunError(Exception):
    """A command failed; the message holds its exit code and stderr tail."""


# ---- trees and runs ------------------------------------------------------------------------


def git(*args: str, cwd: Path = ROOT) -> str:
    """Run git; its stdout (stripped), or SetupError with its stderr."""
    for attempt in range(10):
        proc = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)
        if proc.returncode == 0:
            return proc.stdout.strip()
        if "index.lock" in proc.stderr and attempt < 9:  # another engineer's git is running
            time.sleep(2.0)
            continue
        break
    raise SetupError(f"git {' '.join(args)} failed ({proc.returncode}): {proc.stderr.strip()}")


@dataclass
class Tree:
    """One side of the comparison: its code, where it was taken from, whether we made it."""

    label: str
    path: Path
    rev: str  # full sha, or "working tree"
    made: bool = False  # a worktree this run added (removed at the end unless --keep)


def worktree(label: str, rev: str) -> Tree:
    """A detached worktree of ``rev`` under /tmp: reused when present and clean, else added."""
    sha = git("rev-parse", "--verify", f"{rev}^{{commit}}")
    path = Path("/tmp") / f"unchanged_{label}_{sha[:7]}"
    if path.exists():
        try:
            at = git("rev-parse", "HEAD", cwd=path)
            dirty = git("status", "--porcelain", "--untracked-files=no", cwd=path)
        except SetupError as err:
            raise SetupError(f"{path} exists but is not a worktree ({err}); remove it") from err
        if at != sha or dirty:
            raise SetupError(
                f"{path} exists at {at[:7]}{' with edits' if dirty else ''}, not at {sha[:7]}; "
                f"remove it: git worktree remove --force {path}"
            )
        print(f"unchanged: reusing {path} ({rev} = {sha[:7]})")
        return Tree(label, path, sha)
    git("worktree", "prune")
    git("worktree", "add", "--detach", str(path), sha)
    print(f"unchanged: worktree {path} ({rev} = {sha[:7]})")
    return Tree(label, path, sha, made=True)


def remove(tree: Tree) -> None:
    """Remove a worktree this run added."""
    if tree.made:
        try:
            git("worktree", "remove", "--force", str(tree.path))
        except SetupError as err:
            print(f"unchanged: warning: {err}", file=sys.stderr)


@dataclass
class Runner:
    """Runs ``python -m parproj_ros.apps.cli`` with one tree's code, logs kept in ``logs``."""

    tree: Tree
    env: dict[str, str]
    logs: Path

    @classmethod
    def make(cls, tree: Tree, base_env: dict[str, str], logs: Path) -> Runner:
        """The runner of ``tree``: PYTHONPATH first the tree, the rest of the environment kept."""
        env = dict(base_env)
        env["PYTHONPATH"] = os.pathsep.join(
            [str(tree.path), *filter(None, [base_env.get("PYTHONPATH")])]
        )
        logs.mkdir(parents=True, exist_ok=True)
        return cls(tree, env, logs)

    def check_import(self) -> str:
        """Where ``parproj_ros`` comes from in this runner; SetupError if not the tree."""
        code = (
            "import parproj_ros, parproj_ros.apps.cli as c; "
            "print(parproj_ros.__file__, c.__file__)"
        )
        out = self.run("import_check", ["-c", code], module=False).strip()
        files = [Path(p).resolve() for p in out.split()]
        want = self.tree.path.resolve()
        if len(files) != 2 or not all(f.is_relative_to(want) for f in files):
            raise SetupError(f"{self.tree.label}: parproj_ros imported from {out}, not {want}")
        return str(files[0])

    def run(self, name: str, args: Sequence[str], *, module: bool = True) -> str:
        """Run the CLI (or python with ``args``) in the tree; its stdout, or RunError."""
        return self.run_bytes(name, args, module=module).decode(errors="replace")

    def run_bytes(self, name: str, args: Sequence[str], *, module: bool = True) -> bytes:
        """Like :meth:`run`, the stdout as bytes (for a byte-for-byte comparison)."""
        cmd = [sys.executable, *(["-m", "parproj_ros.apps.cli"] if module else []), *args]
        t0 = time.monotonic()
        proc = subprocess.run(cmd, cwd=self.tree.path, env=self.env, capture_output=True)
        out = proc.stdout.decode(errors="replace")
        err = proc.stderr.decode(errors="replace")
        log = self.logs / f"{self.tree.label}_{name}.log"
        log.write_text(f"$ {' '.join(cmd)}\n(cwd {self.tree.path})\n{out}\n--- stderr\n{err}")
        print(f"unchanged: {self.tree.label}: {name} ({time.monotonic() - t0:.0f} s, exit "
              f"{proc.returncode})")  # fmt: skip
        if proc.returncode != 0:
            tail = "\n".join(err.splitlines()[-TAIL_LINES:] or out.splitlines()[-TAIL_LINES:])
            raise RunError(
                f"{self.tree.label}: `{' '.join(cmd[1:])}` exited {proc.returncode} "
                f"(log {log}); stderr tail:\n{tail}"
            )
        return proc.stdout


# ---- comparisons -------------------------------------------------------------------------


@dataclass
class Row:
    """One line of the table and the differences under it."""

    check: str
    base: str = ""
    current: str = ""
    same: bool | None = None  # None: not run (a command failed)
    notes: list[str] = field(default_factory=list)


def flatten(doc: Any, path: str = "") -> dict[str, Any]:
    """A JSON document as {path: leaf value}; list items as path[i]."""
    if isinstance(doc, dict):
        out: dict[str, Any] = {}
        for k, v in doc.items():
            out.update(flatten(v, f"{path}/{k}"))
        return out or {path: {}}
    if isinstance(doc, list):
        out = {}
        for i, v in enumerate(doc):
            out.update(flatten(v, f"{path}[{i}]"))
        return out or {path: []}
    return {path: doc}


def excluded(path: str) -> str | None:
    """Why an evaluation.json field is left out, or None."""
    for pattern, why in EVALUATION_EXCLUDED.items():
        if re.fullmatch(pattern, path):
            return why
    return None


def compare_json(a: Any, b: Any) -> list[str]:
    """Each field that differs between two JSON documents, one line each (exact values)."""
    fa, fb = flatten(a), flatten(b)
    lines = []
    for path in sorted(set(fa) | set(fb), key=lambda p: (p not in fa, p)):
        if excluded(path):
            continue
        if path not in fa:
            lines.append(f"{path}: only current ({fb[path]!r})")
        elif path not in fb:
            lines.append(f"{path}: only base ({fa[path]!r})")
        elif json.dumps(fa[path]) != json.dumps(fb[path]):
            lines.append(f"{path}: base {fa[path]!r}, current {fb[path]!r}")
    return lines


def sha(data: bytes) -> str:
    """Short sha256 of ``data``."""
    return hashlib.sha256(data).hexdigest()[:12]


@dataclass
class Msg:
    """One message of a bag, as stored."""

    topic: str
    schema: str
    log_time: int
    publish_time: int
    data: bytes
    canonical: bytes = b""  # decoded, wall-clock fields blanked, re-encoded with zero padding
    wall_clock: int = 0  # wall-clock fields blanked


@dataclass
class Bag:
    """A bag's channels and messages (per topic, in order)."""

    path: Path
    channels: dict[str, tuple[str, str, str]]  # topic -> (type, definition sha, offered QoS)
    definitions: dict[str, str]  # type -> definition text
    messages: dict[str, list[Msg]]

    @property
    def count(self) -> int:
        """Messages in the bag."""
        return sum(len(m) for m in self.messages.values())

    def summary(self) -> str:
        """'N msgs, T topics, sha of the canonical CDR' (the same when the bags compare equal)."""
        h = hashlib.sha256()
        for topic in sorted(self.messages):
            for m in self.messages[topic]:
                h.update(m.canonical)
        return f"{self.count} msgs, {len(self.messages)} topics, cdr {h.hexdigest()[:12]}"


def read_bag(folder: Path) -> Bag:
    """Every message of the MCAP bag in ``folder`` (one .mcap file)."""
    from mcap.reader import make_reader

    files = sorted(glob.glob(str(folder / "*.mcap")))
    if len(files) != 1:
        raise RunError(f"{folder}: {len(files)} .mcap files, expected one")
    channels: dict[str, tuple[str, str, str]] = {}
    definitions: dict[str, str] = {}
    messages: dict[str, list[Msg]] = {}
    with open(files[0], "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        if summary is not None:  # topics declared but never written count too
            for ch in summary.channels.values():
                s = summary.schemas[ch.schema_id]
                channels[ch.topic] = (
                    s.name,
                    sha(s.data),
                    ch.metadata.get("offered_qos_profiles", ""),
                )
                definitions[s.name] = s.data.decode()
                messages.setdefault(ch.topic, [])
        for schema, ch, rec in reader.iter_messages(log_time_order=False):
            name = schema.name if schema is not None else ""
            messages.setdefault(ch.topic, []).append(
                Msg(ch.topic, name, rec.log_time, rec.publish_time, bytes(rec.data))
            )
    codec = Codec(definitions)
    for msgs in messages.values():
        for msg in msgs:
            decoded = codec.decode(msg.schema, msg.data)
            msg.wall_clock = blank_wall_clock(msg.schema, decoded)
            msg.canonical = codec.encode(msg.schema, decoded)
    return Bag(Path(files[0]), channels, definitions, messages)


class Codec:
    """Decoding and zero-padded re-encoding of CDR messages by type (mcap-ros2-support)."""

    def __init__(self, definitions: dict[str, str]) -> None:
        self.definitions = definitions
        self._dec: dict[str, Callable[[bytes], Any]] = {}
        self._enc: dict[str, Callable[[Any], bytes]] = {}

    def decode(self, schema: str, data: bytes) -> Any:
        """The decoded message."""
        from mcap_ros2._dynamic import generate_dynamic

        if schema not in self._dec:
            self._dec[schema] = generate_dynamic(schema, self.definitions[schema])[schema]
        return self._dec[schema](data)

    def encode(self, schema: str, msg: Any) -> bytes:
        """``msg`` serialized again, padding zeroed."""
        from mcap_ros2._dynamic import serialize_dynamic

        if schema not in self._enc:
            self._enc[schema] = serialize_dynamic(schema, self.definitions[schema])[schema]
        return bytes(self._enc[schema](msg))


def blank_wall_clock(schema: str, msg: Any) -> int:
    """Replace the :data:`WALL_CLOCK` fields of ``msg`` by a constant; how many were."""
    n = 0
    rules = [r for r in WALL_CLOCK if r[0] == schema]
    if not rules or schema != "diagnostic_msgs/msg/DiagnosticArray":
        return 0
    key_re, text_re = re.compile(rules[0][2]), re.compile(rules[1][2])
    for status in msg.status:
        for kv in status.values:
            if key_re.search(kv.key):
                kv.value = "<wall clock>"
                n += 1
        new = text_re.sub("<n> s ago", status.message)
        n += new != status.message
        status.message = new
    return n


def _fields(msg: Any) -> list[str]:
    return list(getattr(msg, "__slots__", ()))


def _image_diff(a: Any, b: Any) -> str:
    """Where two images' pixels differ (count, first pixel, largest difference)."""
    import numpy as np

    dtypes = {"32FC1": "f4", "64FC1": "f8", "16UC1": "u2", "mono16": "u2", "16SC1": "i2"}
    dtypes |= {"32SC1": "i4"}
    dt = np.dtype(("<", ">")[bool(a.is_bigendian)] + dtypes.get(a.encoding, "u1"))
    if len(a.data) != len(b.data) or len(a.data) % dt.itemsize:
        return f"{len(a.data)} vs {len(b.data)} bytes"
    va, vb = np.frombuffer(a.data, dt), np.frombuffer(b.data, dt)
    bad = np.flatnonzero(va.view(f"u{dt.itemsize}") != vb.view(f"u{dt.itemsize}"))
    if not bad.size:
        return "equal"
    cols = max(1, a.step // dt.itemsize) if a.step else max(1, a.width)
    fa, fb = va[bad].astype(float), vb[bad].astype(float)
    na, nb = np.isnan(fa), np.isnan(fb)
    both_nan = int(np.sum(na & nb))  # NaN either side, other bits (sign, payload)
    one_nan = int(np.sum(na != nb))
    valued = bad[~na & ~nb]
    text = f"{bad.size} of {va.size} pixels ({a.encoding}) differ"
    if valued.size:
        first = int(valued[0])
        big = float(np.max(np.abs(va[valued].astype(float) - vb[valued].astype(float))))
        text += (
            f"; {valued.size} in value, first at row {first // cols} col {first % cols} "
            f"(base {va[first].item()!r}, current {vb[first].item()!r}), largest |difference| "
            f"{big:.6g}"
        )
    if one_nan:
        first = int(bad[na != nb][0])
        text += (
            f"; {one_nan} NaN on one side only, first at row {first // cols} col {first % cols} "
            f"(base {va[first].item()!r}, current {vb[first].item()!r})"
        )
    if both_nan:
        ia = int(va.view(f"u{dt.itemsize}")[bad[na & nb][0]])
        ib = int(vb.view(f"u{dt.itemsize}")[bad[na & nb][0]])
        text += f"; {both_nan} NaN on both sides with other bits (e.g. {ia:#x} vs {ib:#x})"
    return text


def diff_fields(a: Any, b: Any, path: str = "") -> Iterator[str]:
    """The fields of two decoded messages that differ (floats bit for bit)."""
    if _fields(a):
        if {"encoding", "step", "data"} <= set(_fields(a)) and a.data != b.data:
            yield f"{path}.data: {_image_diff(a, b)}"
            for k in _fields(a):
                if k != "data":
                    yield from diff_fields(getattr(a, k), getattr(b, k), f"{path}.{k}")
            return
        for k in _fields(a):
            yield from diff_fields(getattr(a, k), getattr(b, k), f"{path}.{k}")
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            yield f"{path}: {len(a)} vs {len(b)} items"
            return
        found = [
            d
            for i, (x, y) in enumerate(zip(a, b, strict=True))
            for d in diff_fields(x, y, f"{path}[{i}]")
        ]
        yield from found[:5]
        if len(found) > 5:
            yield f"{path}: ... {len(found)} differing items in all"
    elif isinstance(a, float) and isinstance(b, float):
        if struct.pack("<d", a) != struct.pack("<d", b):
            yield f"{path}: base {a!r}, current {b!r} (difference {b - a:.3g})"
    elif isinstance(a, (bytes, bytearray)) and isinstance(b, (bytes, bytearray)):
        if a != b:
            n = sum(x != y for x, y in zip(a, b, strict=False)) + abs(len(a) - len(b))
            yield f"{path}: {n} of {max(len(a), len(b))} bytes differ"
    elif type(a) is not type(b) or a != b:
        yield f"{path}: base {a!r:.120}, current {b!r:.120}"


def compare_bags(base: Bag, cur: Bag) -> tuple[list[str], list[str]]:
    """(differences, notes) of two bags, message for message."""
    diffs: list[str] = []
    notes: list[str] = []
    for topic in sorted(set(base.channels) | set(cur.channels)):
        cb, cc = base.channels.get(topic), cur.channels.get(topic)
        if cb is None or cc is None:
            diffs.append(f"topic {topic}: only in {'current' if cb is None else 'base'}")
            continue
        for what, i in (("type", 0), ("message definition (sha)", 1), ("offered QoS", 2)):
            if cb[i] != cc[i]:
                diffs.append(f"topic {topic}: {what} base {cb[i]!r:.200}, current {cc[i]!r:.200}")
    codec_b, codec_c = Codec(base.definitions), Codec(cur.definitions)
    padding = blanked = 0
    for topic in sorted(set(base.messages) & set(cur.messages)):
        mb, mc = base.messages[topic], cur.messages[topic]
        if len(mb) != len(mc):
            diffs.append(f"{topic}: {len(mb)} messages at base, {len(mc)} now")
        for i, (x, y) in enumerate(zip(mb, mc, strict=False)):
            where = f"{topic}[{i}]"
            for what in ("log_time", "publish_time"):
                if getattr(x, what) != getattr(y, what):
                    diffs.append(f"{where}: {what} {getattr(x, what)} vs {getattr(y, what)}")
            if x.data == y.data:
                continue
            if x.schema != y.schema:
                diffs.append(f"{where}: type {x.schema} vs {y.schema}")
                continue
            if x.canonical == y.canonical:
                if x.wall_clock or y.wall_clock:
                    blanked += 1
                else:
                    padding += 1
                continue
            da, db = codec_b.decode(x.schema, x.data), codec_c.decode(y.schema, y.data)
            blank_wall_clock(x.schema, da)
            blank_wall_clock(y.schema, db)
            fields = list(diff_fields(da, db, where)) or [f"{where}: CDR differs (no field found)"]
            diffs.extend(fields)
    if padding:
        notes.append(
            f"{padding} message(s) differ only in CDR alignment padding (every field equal; "
            "re-encoded with zero padding they are byte-identical)"
        )
    if blanked:
        notes.append(f"{blanked} message(s) equal once their wall-clock fields are left out")
    return diffs, notes


# ---- the checks --------------------------------------------------------------------------


@dataclass
class Check:
    """One comparison: what each side produces (a file or folder) and how two are compared."""

    key: str  # --only name
    name: str  # the table's check column
    produce: Callable[[Runner, Path, Path], Path]  # (runner, its folder, base folder) -> result
    compare: Callable[[Path, Path], Row]  # (base result, current result) -> row


def produce_demo(r: Runner, folder: Path, base_folder: Path) -> Path:
    """``parproj demo`` on the tree's own bags/ikonos_agile (what ``./dev demo`` runs)."""
    bag = r.tree.path / "bags" / "ikonos_agile"
    r.run("demo", ["demo", "--bag", str(bag), "-o", str(folder / "demo"), "--force", "-q"])
    return folder / "demo" / "evaluation.json"


def compare_demo(a: Path, b: Path) -> Row:
    """evaluation.json field by field."""
    ta, tb = a.read_bytes(), b.read_bytes()
    da, db = json.loads(ta), json.loads(tb)
    row = Row("demo evaluation.json")
    row.base = f"{len(flatten(da))} fields, sha {sha(ta)}"
    row.current = f"{len(flatten(db))} fields, sha {sha(tb)}"
    row.notes = compare_json(da, db)
    row.same = not row.notes
    if EVALUATION_EXCLUDED:
        row.notes.append(
            "excluded: " + "; ".join(f"{p} ({w})" for p, w in EVALUATION_EXCLUDED.items())
        )
    return row


def produce_paper(r: Runner, folder: Path, base_folder: Path) -> Path:
    """``parproj paper --json``'s stdout in ``folder``/paper.json."""
    data = r.run_bytes("paper", ["paper", "--json"])
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "paper.json").write_bytes(data)
    return folder / "paper.json"


def compare_paper(a: Path, b: Path) -> Row:
    """Byte for byte; when not, the first differing line and the JSON fields that differ."""
    da, db = a.read_bytes(), b.read_bytes()
    row = Row("paper --json", f"{len(da)} B, sha {sha(da)}", f"{len(db)} B, sha {sha(db)}")
    row.same = da == db
    if not row.same:
        la, lb = da.splitlines(), db.splitlines()
        first = next(
            (i for i, (x, y) in enumerate(zip(la, lb, strict=False)) if x != y),
            min(len(la), len(lb)),
        )
        row.notes.append(f"first differing line {first + 1}")
        try:
            row.notes.extend(compare_json(json.loads(da), json.loads(db)))
        except ValueError as err:
            row.notes.append(f"not JSON: {err}")
    return row


def import_producer(data: Path) -> Callable[[Runner, Path, Path], Path]:
    """``parproj import`` of the real pair in ``data``."""

    def produce(r: Runner, folder: Path, base_folder: Path) -> Path:
        args = real_pair_import_args(data)
        r.run("import", ["import", *args, "-o", str(folder / "real_input"), "--force"])
        return folder / "real_input"

    return produce


def produce_process(r: Runner, folder: Path, base_folder: Path) -> Path:
    """``parproj process`` of the base's imported bag (the same input for every side)."""
    src = base_folder / "real_input"
    if not src.exists():
        raise RunError(f"{src}: the base's import is missing (run the import check first)")
    out = folder / "real_output"
    r.run("process", ["process", str(src), "-o", str(out), "--force", "-q", *PROCESS_ARGS])
    return out


def bag_compare(name: str) -> Callable[[Path, Path], Row]:
    """A comparer of the bags in two folders, message for message."""

    def compare(a: Path, b: Path) -> Row:
        ba, bb = read_bag(a), read_bag(b)
        diffs, notes = compare_bags(ba, bb)
        return Row(name, ba.summary(), bb.summary(), not diffs, diffs + notes)

    return compare


def checks(data: Path) -> list[Check]:
    """Every check, in the order run (the process check needs the base's import)."""
    return [
        Check("demo", "demo evaluation.json", produce_demo, compare_demo),
        Check("paper", "paper --json", produce_paper, compare_paper),
        Check(
            "real",
            f"import {REAL_PAIR} (input bag)",
            import_producer(data),
            bag_compare(f"import {REAL_PAIR} (input bag)"),
        ),
        Check(
            "real",
            f"process {' '.join(PROCESS_ARGS)} (output bag)",
            produce_process,
            bag_compare(f"process {' '.join(PROCESS_ARGS)} (output bag)"),
        ),
    ]


def run_check(check: Check, base: Runner, cur: Runner, out: Path) -> Row:
    """Both sides of one check; a failed command gives a FAILED row with its stderr tail."""
    try:
        a = check.produce(base, out / base.tree.label, out / base.tree.label)
        b = check.produce(cur, out / cur.tree.label, out / base.tree.label)
        return check.compare(a, b)
    except RunError as err:
        return Row(check.name, "", "", None, str(err).splitlines())


def first_differing(
    check: Check, env: dict[str, str], out: Path, base_rev: str, cur_rev: str
) -> str:
    """The first commit (first-parent history base..current) at which ``check`` differs.

    Binary search, assuming that once the check differs it stays different; each probe
    is a worktree of the commit with this check's side run (the base's results reused).
    """
    revs = git("rev-list", "--first-parent", "--reverse", f"{base_rev}..{cur_rev}").split()
    if not revs:
        return "none (current is the base)"
    lo, hi = 0, len(revs) - 1  # revs[hi] differs (the current side)
    while lo < hi:
        mid = (lo + hi) // 2
        tree = worktree("probe", revs[mid])
        try:
            r = Runner.make(tree, env, out / "logs")
            r.check_import()
            folder = out / f"probe_{revs[mid][:7]}"
            result = check.produce(r, folder, out / "base")
            a = out / "base" / result.relative_to(folder)
            same = check.compare(a, result).same
        except RunError as err:
            return f"not found: the probe at {revs[mid][:7]} failed: {str(err).splitlines()[0]}"
        finally:
            remove(tree)
        print(f"unchanged: bisect {check.name}: {revs[mid][:7]} {'same' if same else 'differs'}")
        if same:
            lo = mid + 1
        else:
            hi = mid
    subject = git("log", "-1", "--format=%h %s", revs[lo])
    return subject[:160]


#: Paths whose changes can change what the checks run (the code, its data, its messages).
BEHAVIOUR_PATHS = ("parproj_ros", "bags", "msg_defs", "config", "setup.cfg", "setup.py")


def walk(
    todo: Sequence[Check], env: dict[str, str], out: Path, base_rev: str, cur_rev: str
) -> list[str]:
    """Each commit of base..current touching :data:`BEHAVIOUR_PATHS` against the one before.

    Returns one line per (commit, check) that changes the result, with its first differences;
    a commit that changes nothing is not listed. Commits touching other paths are skipped.
    """
    revs = git(
        "rev-list", "--first-parent", "--reverse", f"{base_rev}..{cur_rev}", "--", *BEHAVIOUR_PATHS
    ).split()
    print(f"unchanged: walking {len(revs)} commits of {base_rev[:7]}..{cur_rev[:7]}")
    prev: dict[str, Path] = {}  # check -> the last result it gave (the base's at first)
    lines: list[str] = []
    for rev in revs:
        subject = git("log", "-1", "--format=%h %s", rev)[:100]
        tree = worktree("walk", rev)
        folder = out / f"walk_{rev[:7]}"
        changed = []
        try:
            r = Runner.make(tree, env, out / "logs")
            try:
                r.check_import()
            except RunError as err:  # a commit that does not run: compared past it
                lines.append(f"{subject}:\n  does not import: {err.args[0].splitlines()[-1]}")
                print(f"unchanged: walk {subject[:60]}: does not import")
                continue
            for check in todo:
                try:
                    result = check.produce(r, folder, out / "base")
                    before = prev.get(check.name, out / "base" / result.relative_to(folder))
                    row = check.compare(before, result)
                except (RunError, OSError) as err:
                    msg = str(err).splitlines()
                    changed.append(f"  {check.name}: FAILED: {msg[0]}")
                    changed.extend(f"    {line[:160]}" for line in msg[1:][-3:])
                    continue
                prev[check.name] = result
                if not row.same:
                    diffs = [n for n in row.notes if "only in CDR alignment padding" not in n]
                    changed.append(f"  {check.name}: {len(diffs)} differences, e.g.")
                    changed.extend(f"    {d[:160]}" for d in diffs[:4])
        finally:
            remove(tree)
        for old in out.glob("walk_*"):  # results no check compares with any more
            if not any(p.is_relative_to(old) for p in prev.values()):
                shutil.rmtree(old, ignore_errors=True)
        print(f"unchanged: walk {subject[:60]}: {'changes' if changed else 'same'}")
        if changed:
            lines += [f"{subject}:", *changed]
    return lines or [f"no commit of the {len(revs)} walked changes a result"]


def print_table(rows: Sequence[Row]) -> None:
    """The table, then each row's differences and notes."""
    heads = ("check", "base", "current", "same?")
    cells = [
        (r.check, r.base, r.current, "FAILED" if r.same is None else "yes" if r.same else "NO")
        for r in rows
    ]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(heads)]
    line = " | ".join(h.ljust(w) for h, w in zip(heads, widths, strict=True))
    print("\n" + line + "\n" + "-+-".join("-" * w for w in widths))
    for c in cells:
        print(" | ".join(v.ljust(w) for v, w in zip(c, widths, strict=True)))
    for r in rows:
        if r.notes:
            print(f"\n{r.check}:")
            shown = r.notes[:40]
            for n in shown:
                print(f"  {n}")
            if len(r.notes) > len(shown):
                print(f"  ... {len(r.notes) - len(shown)} more")


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    p = argparse.ArgumentParser(
        prog="python -m tools.unchanged", description=(__doc__ or "").split("\n")[0]
    )
    p.add_argument("--base", required=True, help="the revision before the redesign")
    side = p.add_mutually_exclusive_group()
    side.add_argument("--current", default="HEAD", help="revision compared (default HEAD)")
    side.add_argument(
        "--working-tree", action="store_true", help="compare this checkout, edits included"
    )
    p.add_argument("--out", type=Path, help="results folder (default /tmp/unchanged_<base>_<cur>)")
    p.add_argument(
        "--data",
        type=Path,
        default=ROOT.parent / "shared" / "data" / REAL_PAIR,
        help="the Ventoux pair's folder (default ../shared/data/ventoux)",
    )
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: the environment's)")
    p.add_argument("--keep", action="store_true", help="keep the worktrees this run adds")
    p.add_argument(
        "--only",
        nargs="+",
        choices=("demo", "paper", "real"),
        default=("demo", "paper", "real"),
        help="run only these checks",
    )
    p.add_argument(
        "--bisect",
        action="store_true",
        help="for each check that differs, find the first commit base..current where it does",
    )
    p.add_argument(
        "--walk",
        action="store_true",
        help="run the checks at every commit of base..current that touches the code, bags, "
        "messages or config, each against the one before: which commits change what",
    )
    return p.parse_args(argv)


def environment(args: argparse.Namespace, out: Path) -> dict[str, str]:
    """The environment of the runs: ours, with the ROS rules of every run here."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_PYTHON_CHECK_FIELDS"] = "1"
    if args.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(args.domain_id)
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    env.setdefault("ROS_LOG_DIR", str(out / "ros_log"))
    Path(env["ROS_LOG_DIR"]).mkdir(parents=True, exist_ok=True)
    return env


def main(argv: Sequence[str] | None = None) -> int:
    """Run the checks; 0 when everything is the same, 1 when not, 2 when trees cannot be built."""
    args = parse_args(argv)
    if "real" in args.only and not (args.data / "left_image.tif").exists():
        print(f"unchanged: {args.data}/left_image.tif not found (--data)", file=sys.stderr)
        return 2
    if (args.bisect or args.walk) and args.working_tree:
        print("unchanged: --bisect/--walk need commits, not --working-tree", file=sys.stderr)
        return 2
    trees: list[Tree] = []
    rows: list[Row] = []
    walked: list[str] = []
    try:
        trees.append(worktree("base", args.base))
        if args.working_tree:
            trees.append(Tree("current", ROOT, "working tree"))
        else:
            trees.append(worktree("current", args.current))
        base_t, cur_t = trees
        if base_t.rev == cur_t.rev:
            print(f"unchanged: warning: base and current are both {base_t.rev[:7]}")
        out = args.out or Path("/tmp") / f"unchanged_{base_t.rev[:7]}_{cur_t.rev[:7]}"
        if out.resolve().is_relative_to(ROOT):
            raise SetupError(f"--out {out} is inside the checkout; choose a folder outside it")
        for old in [out / "base", out / "current", *out.glob("probe_*"), *out.glob("walk_*")]:
            shutil.rmtree(old, ignore_errors=True)  # no result of an earlier run is compared
        env = environment(args, out)
        base, cur = (Runner.make(t, env, out / "logs") for t in trees)
        for r in (base, cur):
            print(f"unchanged: {r.tree.label} ({r.tree.rev[:12]}) imports {r.check_import()}")
        if not args.working_tree and git(
            "diff", "--stat", base_t.rev, cur_t.rev, "--", "msg_defs"
        ):
            print("unchanged: warning: msg_defs/ differs; both sides use the venv's parproj_msgs")
        todo = [c for c in checks(args.data) if c.key in args.only]
        for check in todo:
            rows.append(run_check(check, base, cur, out))
        if args.bisect:
            for check, row in zip(todo, rows, strict=True):
                if row.same is False:
                    found = first_differing(check, env, out, base_t.rev, cur_t.rev)
                    row.notes.append(f"first commit where it differs: {found}")
        walked = walk(todo, env, out, base_t.rev, cur_t.rev) if args.walk else []
    except SetupError as err:
        print(f"unchanged: error: {err}", file=sys.stderr)
        return 2
    finally:
        if not args.keep:
            for t in trees:
                remove(t)
    cur_name = "working tree" if args.working_tree else f"{args.current} = {cur_t.rev[:7]}"
    print(f"\nbase {args.base} = {base_t.rev[:7]}, current {cur_name}; results in {out}")
    print_table(rows)
    if walked:
        print("\ncommits that change a result (each against the commit before):")
        print("\n".join(walked))
    return 0 if rows and all(r.same for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
