"""``parproj longrun``: the live node fed one bag over and over, for hours of simulated time.

``parproj_node`` runs in its own process (reliable input QoS, as in the demo). The bag
(default ``bags/ikonos_agile``) is published again and again; repetition ``k`` has every header
stamp and log time moved forward by ``k`` times (bag duration + ``margin_s``), and its scene ids
(the strips' ``header.frame_id``, the scene ids of the GCP observations) and GCP ids prefixed
with ``r<k>_``, so that each repetition is a new acquisition to the node. Messages go out as fast
as the node acknowledges them (rate 0) unless a rate is given; a repetition is sent only when
the pairs of the repetition ``in_flight`` before it have come back, so the replay runs at the
rate the node sustains instead of filling its input queue. A repetition's latched inputs (GCP,
scanner info, truth points) are sent, and acknowledged, before its stream of navigation and
strips, as a ground station latches them ahead of a pass.

While it runs, the node's resident memory (``/proc/<pid>/status`` VmRSS) is sampled every second (a
thread of this process), its 1 Hz ``/diagnostics`` summary (counters, input queue length and peak,
navigation samples and GCP held) is recorded, and every pair that comes back is checked
(:class:`PairChecker`): StereoPair with its left, right and anaglyph images (or its column blocks),
finite transforms, image sizes equal to the StereoPair's width and height, scene ids of one
repetition, and every number of the pair (both scenes' parameters, the normalization, grids,
y-parallax statistics), the images and the y-parallax of the bag's truth points equal to the first
repetition's.

The tolerance of that last comparison is zero (bit for bit), by design: the pipeline sees a
repetition only through differences of integer-nanosecond stamps, which are exact, through the
same pixels and the same GCP, and it is deterministic (tie-point RANSAC seeded, SIFT and the
brute-force matcher deterministic). Any difference is a defect: absolute time leaking into
floating point (a float64 of 1.7e9 s has a 2.4e-7 s step, 1.5e-3 lines at 6500 lines/s), or
state carried over from one acquisition to the next.

The report (``longrun.json``, ``longrun.png`` with RSS and queue against time, a printed table):
wall and simulated duration, repetitions, pairs expected / published / malformed, drops
(``strips_rejected``, ``nav_rejected``, messages sent but not received by the node, warnings
and errors on ``/diagnostics``), RSS start / end / max and its slope (least squares after a
warm-up) in MB per hour and per pair, and that of the per-minute medians over the second half
(robust to spikes and to a late allocator step), and the queue length.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from . import conversions as conv
from .bag import BagReader, get_message_class
from .evaluate import normalized_px
from .live import NodeProcess, _qos, node_params_yaml, ros_environment
from .live import wait_until as _wait_until
from .pipeline import GroundPoint
from .recording import node_parameters, truth_from_bag, views_from_bag

SUMMARY_NAME = "parproj_node: summary"
_REP = re.compile(r"^r(\d+)_(.*)$")

#: ParallelProjection fields that legitimately change from one repetition to the next.
_SCENE_VARIES = {"header", "scene_id", "first_line_time", "last_line_time"}
#: StereoPair fields not compared as numbers (stamps, ids; images are compared by digest).
_PAIR_VARIES = {"header", "pair_id", "left", "right", "left_params", "right_params"}


def repetition_id(scene_id: str, rep: int) -> str:
    """The scene id (or GCP id) ``scene_id`` in repetition ``rep``: ``r<rep>_<scene_id>``."""
    return f"r{rep:04d}_{scene_id}"


def split_repetition(scene_id: str) -> tuple[int, str] | None:
    """(repetition, original id) of an id made by :func:`repetition_id`, or None."""
    m = _REP.match(scene_id)
    return (int(m.group(1)), m.group(2)) if m else None


def shift_message(topic: str, msg: Any, rep: int, offset_ns: int) -> None:
    """Move a bag message to repetition ``rep`` in place.

    The header stamp moves forward by ``offset_ns`` (integer nanoseconds). Strips
    (``*/image_strip``) get the repetition's scene id as ``header.frame_id``. GCP sets (``gcp``,
    ``truth/points``) get repetition ids for their points and for the scene ids of their
    observations.
    """
    header = getattr(msg, "header", None)
    if header is not None:
        conv.ns_to_stamp(conv.stamp_to_ns(header.stamp) + offset_ns, header.stamp)
    if topic.endswith("/image_strip"):
        header.frame_id = repetition_id(header.frame_id, rep)
    points = getattr(msg, "points", None)
    if points is not None:
        for p in points:
            p.id = repetition_id(p.id, rep)
            for o in p.observations:
                o.scene_id = repetition_id(o.scene_id, rep)


@dataclass(frozen=True)
class BagPlan:
    """What one repetition of a bag holds and how repetitions are spaced.

    Attributes:
        bag: the bag folder.
        duration_ns: log time from the first to the last message, nanoseconds.
        shift_ns: stamp offset between consecutive repetitions (duration + margin), ns.
        counts: messages per topic in one repetition.
        scenes: scene ids (strip frame_ids) per view, in order of arrival.
        pairs: pair ids per repetition, without the repetition prefix.
        single_camera: one view whose consecutive scenes pair up.
    """

    bag: Path
    duration_ns: int
    shift_ns: int
    counts: dict[str, int]
    scenes: dict[str, list[str]]
    pairs: list[str]
    single_camera: bool

    @property
    def scene_count(self) -> int:
        """Scenes per repetition."""
        return sum(len(v) for v in self.scenes.values())


def plan_bag(bag: Path, margin_s: float = 1.0) -> BagPlan:
    """Read the bag once: its duration, its scenes and the pairs the node will form."""
    reader = BagReader(bag)
    if reader.start_ns is None or reader.end_ns is None:
        raise ValueError(f"{bag}: empty bag")
    views = [v.name for v in views_from_bag(reader)]
    scenes: dict[str, list[str]] = {v: [] for v in views}
    for item in reader.messages(topics=[f"{v}/image_strip" for v in views]):
        sid = item.msg.header.frame_id
        ids = scenes[item.topic.rsplit("/", 1)[0]]
        if sid not in ids:
            ids.append(sid)
    if len(views) == 1:
        ids = scenes[views[0]]
        pairs = [f"{ids[i]}+{ids[i + 1]}" for i in range(0, len(ids) - 1, 2)]
    else:
        pairs = [f"{a}+{b}" for a, b in zip(scenes[views[0]], scenes[views[1]], strict=False)]
    duration = int(reader.end_ns - reader.start_ns)
    return BagPlan(
        Path(bag),
        duration,
        duration + round(margin_s * 1e9),
        reader.message_counts(),
        scenes,
        pairs,
        len(views) == 1,
    )


def repetition_messages(
    plan: BagPlan, rep: int, topics: list[str] | None = None
) -> Iterator[tuple[str, Any, int]]:
    """(topic, message, log time ns) of repetition ``rep``: the bag read afresh and shifted.

    ``topics``: only these (None: all).
    """
    if topics is not None and not topics:
        return
    offset = rep * plan.shift_ns
    for item in BagReader(plan.bag).messages(topics=topics):
        shift_message(item.topic, item.msg, rep, offset)
        yield item.topic, item.msg, item.log_time_ns + offset


# ---- checking what comes back ----------------------------------------------------------------


def _flatten(msg: Any, skip: set[str], prefix: str = "") -> dict[str, Any]:
    """Field name -> value (numbers, strings, number tuples) of a message, nested ones dotted."""
    out: dict[str, Any] = {}
    for name in msg.get_fields_and_field_types():
        if name in skip:
            continue
        v = getattr(msg, name)
        if hasattr(v, "get_fields_and_field_types"):
            out.update(_flatten(v, set(), f"{prefix}{name}."))
        elif isinstance(v, str | bool | int | float):
            out[prefix + name] = v
        else:
            out[prefix + name] = tuple(float(x) for x in v)
    return out


def pair_numbers(sp: Any) -> dict[str, Any]:
    """Everything of a StereoPair that must not change between repetitions, by field name."""
    out = _flatten(sp, _PAIR_VARIES)
    for side in ("left_params", "right_params"):
        out.update(_flatten(getattr(sp, side), _SCENE_VARIES, f"{side}."))
    return out


def _same(a: Any, b: Any, rtol: float) -> tuple[bool, float]:
    """Whether two field values agree (NaN equals NaN) and their relative difference."""
    if isinstance(a, str) or isinstance(b, str):
        return a == b, 0.0 if a == b else math.inf
    x = np.atleast_1d(np.asarray(a, dtype=float))
    y = np.atleast_1d(np.asarray(b, dtype=float))
    if x.shape != y.shape:
        return False, math.inf
    both_nan = np.isnan(x) & np.isnan(y)
    with np.errstate(invalid="ignore"):
        diff = np.where(both_nan, 0.0, np.abs(x - y))
        scale = np.maximum(np.abs(x), np.abs(y))
        rel = np.where(diff == 0, 0.0, diff / np.where(scale > 0, scale, 1.0))
    worst = float(np.nanmax(rel)) if rel.size else 0.0
    if np.isnan(rel).any():
        worst = math.inf
    return bool(worst <= rtol), worst


def compare_pairs(ref: dict[str, Any], new: dict[str, Any], rtol: float = 0.0) -> dict[str, Any]:
    """Fields of two :func:`pair_numbers` results that differ beyond ``rtol`` (relative).

    Returns the differing field names and the largest relative difference over all fields.
    """
    differ = []
    worst = 0.0
    for key in sorted(set(ref) | set(new)):
        if key not in ref or key not in new:
            differ.append(key)
            worst = math.inf
            continue
        ok, rel = _same(ref[key], new[key], rtol)
        worst = max(worst, rel)
        if not ok:
            differ.append(key)
    return {"differ": differ, "max_rel_diff": worst}


#: Bytes per pixel and channels of the encodings the node publishes.
_ENCODINGS = {"mono8": (1, 1), "8UC1": (1, 1), "mono16": (2, 1), "16UC1": (2, 1)}
_ENCODINGS |= {"32FC1": (4, 1), "rgb8": (3, 3), "bgr8": (3, 3)}


def _image_problems(img: Any, what: str, width: int, height: int, channels: int) -> list[str]:
    """Size, layout and value problems of one sensor_msgs/Image against the pair's size."""
    probs = []
    if (img.width, img.height) != (width, height):
        probs.append(f"{what} is {img.width} x {img.height} px, the pair {width} x {height}")
    enc = _ENCODINGS.get(img.encoding)
    if enc is None:
        return [*probs, f"{what}: unexpected encoding {img.encoding!r}"]
    if enc[1] != channels:
        probs.append(f"{what} is {img.encoding}, expected {channels} channel(s)")
    if img.step < img.width * enc[0] or len(img.data) != img.step * img.height:
        probs.append(
            f"{what}: step {img.step}, {len(img.data)} bytes for {img.width} x {img.height} "
            f"px of {img.encoding}"
        )
    elif img.encoding == "32FC1" and not np.isfinite(conv.image_to_array(img)).all():
        probs.append(f"{what} holds non-finite pixels")
    return probs


def _digest(img: Any) -> str:
    return hashlib.blake2b(bytes(img.data), digest_size=16).hexdigest()


#: StereoPair numbers that must be finite (the transforms and grids a user applies).
_FINITE = (
    "left_to_normalized",
    "right_to_normalized",
    "kappa_n",
    "s_n",
    "normalized_pixel_size",
    "left_x_origin",
    "right_x_origin",
    "y_origin",
    "parallax_per_height",
    "parallax_offset",
    "height_per_disparity_px",
    "height_offset_m",
)
_FINITE_SCENE = ("l", "m", "n", "omega", "phi", "kappa", "s", "dx", "dy", "affine", "roll_psi")


@dataclass
class PairRecord:
    """One pair as received and checked.

    Attributes:
        pair_id: as published.
        rep: repetition (from the scene ids; -1 when they do not carry one).
        original: pair id without the repetition prefix.
        wall_s: receive time of its last part, seconds since the start of the replay.
        problems: what is wrong with it (empty: well formed).
        identical: numbers, images and truth y-parallax equal to the first repetition's.
        max_rel_diff: largest relative difference of its numbers from the first repetition's.
        truth_y_rms_px: RMS y-parallax of the bag's truth points through the published
            transforms, pixels (None without truth points).
        streamed: its images came as column blocks.
    """

    pair_id: str
    rep: int
    original: str
    wall_s: float
    problems: list[str]
    identical: bool
    max_rel_diff: float
    truth_y_rms_px: float | None
    streamed: bool


@dataclass
class _Pending:
    sp: Any = None
    images: dict[str, Any] = field(default_factory=dict)


class PairChecker:
    """Receives the node's outputs and checks each pair as soon as all its parts are in.

    Pairs are matched to their images by stamp (StereoPair, left, right and anaglyph images of a
    pair carry the same stamp) and to their blocks by pair id. Nothing but the verdict, the
    digests of the first repetition and the numbers of the first repetition is kept.
    """

    IMAGE_TOPICS = ("left/image_normalized", "right/image_normalized", "anaglyph")

    def __init__(
        self, plan: BagPlan, truth: list[GroundPoint], t0: float, rtol: float = 0.0
    ) -> None:
        self.plan = plan
        self.rtol = rtol
        self.t0 = t0
        self.truth = truth
        self.records: list[PairRecord] = []
        self.reference: dict[str, dict[str, Any]] = {}
        self.scenes: dict[int, int] = {}
        self.scene_problems: list[str] = []
        self.summaries: list[tuple[float, dict[str, str]]] = []
        self.issues: dict[str, int] = {}
        self.issue_levels: dict[str, int] = {"ok": 0, "warn": 0, "error": 0, "stale": 0}
        self._pending: dict[int, _Pending] = {}
        self._blocks: dict[tuple[str, str], list[Any]] = {}
        self._lock = threading.Lock()
        self._done_reps: dict[int, int] = {}

    # -- subscriptions --
    def subscribe(self, node: Any) -> list[Any]:
        """Create the subscriptions on ``node`` (reliable, like the node's publishers)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        subs = []
        for topic, msgtype in conv.OUTPUT_TOPICS.items():
            cls = get_message_class(msgtype)
            subs.append(
                node.create_subscription(cls, topic, lambda m, t=topic: self.on_message(t, m), qos)
            )
        return subs

    def on_message(self, topic: str, msg: Any) -> None:
        """Dispatch one received message."""
        with self._lock:
            if topic == "/diagnostics":
                self._on_diagnostics(msg)
            elif topic == "parallel_projection":
                self._on_scene(msg)
            elif topic.endswith("/normalized_block"):
                self._blocks.setdefault((msg.pair_id, msg.side), []).append(msg)
            else:
                stamp = conv.stamp_to_ns(msg.header.stamp)
                pend = self._pending.setdefault(stamp, _Pending())
                if topic == "stereo_pair":
                    pend.sp = msg
                else:
                    pend.images[topic] = msg
                self._try_complete(stamp)

    def _on_diagnostics(self, msg: Any) -> None:
        now = time.monotonic() - self.t0
        for st in msg.status:
            if st.name == SUMMARY_NAME:
                self.summaries.append((now, {kv.key: kv.value for kv in st.values}))
                continue
            raw = st.level
            num = int.from_bytes(raw, "little") if isinstance(raw, bytes) else int(raw)
            level = {0: "ok", 1: "warn", 2: "error", 3: "stale"}.get(num, str(num))
            self.issue_levels[level] = self.issue_levels.get(level, 0) + 1
            if level != "ok":
                key = re.sub(r"r\d{4,}_", "r*_", f"[{level}] {st.name}: {st.message}")
                self.issues[key] = self.issues.get(key, 0) + 1

    def _on_scene(self, msg: Any) -> None:
        rep = split_repetition(msg.scene_id)
        if rep is None:
            self.scene_problems.append(f"scene {msg.scene_id}: no repetition in its id")
            return
        self.scenes[rep[0]] = self.scenes.get(rep[0], 0) + 1

    def _try_complete(self, stamp: int) -> None:
        pend = self._pending[stamp]
        sp = pend.sp
        if sp is None:
            return
        if sp.streamed:
            sides = [self._blocks.get((sp.pair_id, s), []) for s in ("left", "right")]
            if not all(b and any(x.last for x in b) for b in sides):
                return  # blocks come before the StereoPair; wait for a straggler
        elif not all(t in pend.images for t in self.IMAGE_TOPICS):
            return
        del self._pending[stamp]
        blocks = {s: self._blocks.pop((sp.pair_id, s), []) for s in ("left", "right")}
        self.records.append(self._check(sp, pend.images, blocks))
        rec = self.records[-1]
        self._done_reps[rec.rep] = self._done_reps.get(rec.rep, 0) + 1

    # -- the checks --
    def _check(self, sp: Any, images: dict[str, Any], blocks: dict[str, list[Any]]) -> PairRecord:
        probs: list[str] = []
        lp, rp = sp.left_params, sp.right_params
        ls, rs = split_repetition(lp.scene_id), split_repetition(rp.scene_id)
        rep, original = -1, sp.pair_id
        if ls is None or rs is None or ls[0] != rs[0]:
            probs.append(f"scene ids {lp.scene_id}, {rp.scene_id} are not of one repetition")
        else:
            rep, original = ls[0], f"{ls[1]}+{rs[1]}"
            if original not in self.plan.pairs:
                probs.append(f"pair {original} is not one of the bag's {self.plan.pairs}")
        if sp.pair_id != f"{lp.scene_id}+{rp.scene_id}":
            probs.append(f"pair_id {sp.pair_id} is not '<left scene>+<right scene>'")
        for name in _FINITE:
            if not np.all(np.isfinite(np.asarray(getattr(sp, name), dtype=float))):
                probs.append(f"{name} not finite")
        for side, prm in (("left", lp), ("right", rp)):
            for name in _FINITE_SCENE:
                if not np.all(np.isfinite(np.asarray(getattr(prm, name), dtype=float))):
                    probs.append(f"{side}_params.{name} not finite")
        if not (sp.s_n > 0 and sp.normalized_pixel_size > 0):
            probs.append("s_n or normalized_pixel_size not positive")
        w, h = int(sp.width), int(sp.height)
        if w <= 0 or h <= 0:
            probs.append(f"empty pair ({w} x {h} px)")
        digests: dict[str, str] = {}
        if sp.streamed:
            probs += self._check_blocks(sp, blocks, digests)
        else:
            embedded = {"left": sp.left, "right": sp.right}
            for side in ("left", "right"):
                topic = images[f"{side}/image_normalized"]
                probs += _image_problems(embedded[side], f"StereoPair.{side}", w, h, 1)
                probs += _image_problems(topic, f"{side}/image_normalized", w, h, 1)
                digests[side] = _digest(topic)
                if _digest(embedded[side]) != digests[side]:
                    probs.append(f"StereoPair.{side} differs from {side}/image_normalized")
            if sp.left.encoding != sp.right.encoding:
                probs.append(f"encodings differ: {sp.left.encoding} / {sp.right.encoding}")
            probs += _image_problems(images["anaglyph"], "anaglyph", w, h, 3)
            digests["anaglyph"] = _digest(images["anaglyph"])
        ytruth = self._truth_y_rms(sp, ls, rs) if ls and rs else None
        numbers = pair_numbers(sp)
        numbers["images"] = json.dumps(digests, sort_keys=True)
        numbers["truth_y_rms_px"] = math.nan if ytruth is None else ytruth
        identical, worst = True, 0.0
        ref = self.reference.get(original)
        if ref is None and not probs:
            self.reference[original] = numbers
        elif ref is not None:
            cmp = compare_pairs(ref, numbers, self.rtol)
            worst = cmp["max_rel_diff"]
            if cmp["differ"]:
                identical = False
                shown = ", ".join(cmp["differ"][:6]) + (" ..." if len(cmp["differ"]) > 6 else "")
                probs.append(f"differs from the first repetition in {shown}")
        return PairRecord(
            sp.pair_id,
            rep,
            original,
            time.monotonic() - self.t0,
            probs,
            identical,
            worst,
            ytruth,
            bool(sp.streamed),
        )

    @staticmethod
    def _check_blocks(sp: Any, blocks: dict[str, list[Any]], digests: dict[str, str]) -> list[str]:
        probs = []
        for side in ("left", "right"):
            if getattr(sp, side).width or getattr(sp, side).height:
                probs.append(f"streamed pair carries a {side} image")
            bl = sorted(blocks[side], key=lambda b: b.index)
            if [b.index for b in bl] != list(range(len(bl))) or not bl[-1].last:
                probs.append(f"{side} blocks {[b.index for b in bl]} incomplete")
            col = 0
            h = hashlib.blake2b(digest_size=16)
            for b in bl:
                if (b.full_width, b.full_height) != (sp.width, sp.height):
                    probs.append(
                        f"{side} block {b.index} of a {b.full_width} x {b.full_height} pair"
                    )
                if b.col0 != col or b.image.height != sp.height:
                    probs.append(f"{side} block {b.index} at column {b.col0}, expected {col}")
                probs += _image_problems(
                    b.image, f"{side} block {b.index}", b.image.width, int(sp.height), 1
                )
                col = b.col0 + b.image.width
                h.update(bytes(b.image.data))
            if col != sp.width:
                probs.append(f"{side} blocks cover {col} of {sp.width} columns")
            digests[side] = h.hexdigest()
        return probs

    def _truth_y_rms(self, sp: Any, ls: tuple[int, str], rs: tuple[int, str]) -> float | None:
        """RMS y-parallax of the truth points through the published transforms, pixels."""
        pts = [p for p in self.truth if ls[1] in p.observations and rs[1] in p.observations]
        if not pts:
            return None
        ol = np.array([p.observations[ls[1]] for p in pts])
        orr = np.array([p.observations[rs[1]] for p in pts])
        pix = sp.normalized_pixel_size
        _, rl = normalized_px(
            sp.left_params, sp.left_to_normalized, sp.left_x_origin, sp.y_origin, pix, *ol.T
        )
        _, rr = normalized_px(
            sp.right_params, sp.right_to_normalized, sp.right_x_origin, sp.y_origin, pix, *orr.T
        )
        return float(np.sqrt(np.mean((rl - rr) ** 2)))

    # -- queries --
    def pairs_done(self, rep: int) -> int:
        """Pairs of repetition ``rep`` received complete (checked)."""
        with self._lock:
            return self._done_reps.get(rep, 0)

    def latest_summary(self) -> dict[str, str]:
        """The node's latest 1 Hz summary (empty before the first)."""
        with self._lock:
            return dict(self.summaries[-1][1]) if self.summaries else {}

    def summaries_since(self, t: float) -> int:
        """Summaries received after ``t`` (seconds since the start)."""
        with self._lock:
            return sum(1 for s, _ in self.summaries if s > t)

    def incomplete(self) -> list[str]:
        """Pairs received in part only (a StereoPair without all its images, or images alone)."""
        with self._lock:
            out = [
                (p.sp.pair_id if p.sp is not None else f"stamp {s}") + f" ({sorted(p.images)})"
                for s, p in self._pending.items()
            ]
            out += [f"blocks of {pid} ({side})" for pid, side in self._blocks]
            return out


# ---- the run ---------------------------------------------------------------------------------


def _slope(t: np.ndarray, y: np.ndarray) -> float | None:
    """Least-squares slope of y against t (None for fewer than 3 samples or no spread)."""
    if len(t) < 3 or np.ptp(t) == 0:
        return None
    return float(np.polyfit(t, y, 1)[0])


def _second_half_slope(t: np.ndarray, mb: np.ndarray, wall: float) -> float | None:
    """Slope of the per-minute median RSS over the second half of the run, MB per hour.

    Insensitive to the short spikes of a pair being processed and to a late step of the
    allocator during warm-up, which weigh on the least-squares slope of a 20-minute run.
    """
    minutes = np.floor(t / 60.0)
    sel = t >= wall / 2
    keys = np.unique(minutes[sel])
    if keys.size < 3:
        return None
    med = np.array([np.median(mb[sel & (minutes == k)]) for k in keys])
    return float(np.polyfit(keys * 60.0, med, 1)[0] * 3600)


def _cpu_busy_s() -> float:
    """CPU seconds the whole machine has been busy since boot (all cores, /proc/stat)."""
    vals = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
    return (sum(vals[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def _jsonable(x: Any) -> Any:
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python, tuples -> lists."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def run_longrun(
    bag: Path,
    out: Path,
    *,
    minutes: float = 20.0,
    repetitions: int | None = None,
    rate: float = 0.0,
    margin_s: float = 1.0,
    in_flight: int = 2,
    warmup_s: float = 120.0,
    rtol: float = 0.0,
    stall_timeout_s: float = 180.0,
    node_params: dict[str, Any] | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Replay ``bag`` into a live ``parproj_node`` repeatedly; return (and write) the report.

    Args:
        bag: the bag replayed.
        out: folder for ``longrun.json``, ``longrun.png``, the node's log and parameters.
        minutes: no repetition is started after this many minutes of wall time.
        repetitions: stop after this many repetitions (None: only ``minutes`` limits).
        rate: speed factor against the bag's log times within a repetition; 0 = as fast as
            the node acknowledges.
        margin_s: simulated seconds between the end of one repetition and the next, s.
        in_flight: repetition k is sent once every pair of repetition k - ``in_flight`` is back
            (a pair is completed by the next repetition's first strip; so 2 keeps the node busy
            without queueing more than about one repetition).
        warmup_s: RSS samples of the first ``warmup_s`` seconds (at most half the run) are left
            out of the slope, s.
        rtol: relative tolerance of the comparison with the first repetition (0: bit for bit,
            see the module docstring).
        stall_timeout_s: give up waiting for a repetition's pairs after this long, s.
        node_params: extra parproj_node parameters.
        progress: tqdm bar over the repetitions.
        log: where progress messages go.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy
    from tqdm import tqdm

    from .bench import RssMonitor, machine_info

    out.mkdir(parents=True, exist_ok=True)
    plan = plan_bag(bag, margin_s)
    reader = BagReader(bag)
    views = views_from_bag(reader)
    truth = truth_from_bag(reader)
    env = ros_environment()
    for key in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "ROS_LOG_DIR"):
        os.environ[key] = env[key]  # this process joins the node's domain
    params = node_parameters(views, scene_timeout=2.0, **(node_params or {}))
    inputs = ["/navigation"] + [f"/{v.name}/image_strip" for v in views]
    pfile = _params_file(params, out / "node_params.yaml", inputs)
    machine = machine_info()
    log(
        f"longrun: {bag} ({plan.duration_ns / 1e9:.1f} s, {sum(plan.counts.values())} messages, "
        f"{len(plan.pairs)} pair(s) per repetition), ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}, "
        f"node log {out / 'node.log'}"
    )
    node_proc = NodeProcess(pfile, env, out / "node.log")
    rss = RssMonitor(node_proc.proc.pid, period_s=1.0)
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("parproj_longrun", context=ctx)
    t_start = time.monotonic()
    checker = PairChecker(plan, truth, t_start, rtol)
    checker.subscribe(node)
    pubs: dict[str, Any] = {}
    for topic, msgtype in reader.topics().items():
        cls = get_message_class(msgtype)
        if cls is not None:
            qos = _qos(reader.qos(topic))
            if f"/{topic}" in inputs:
                qos.history = HistoryPolicy.KEEP_ALL  # flow control: see _params_file
            pubs[topic] = node.create_publisher(cls, topic, qos)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    sent: dict[str, int] = {t: 0 for t in pubs}
    reps_sent = 0
    ack_s = 0.0
    stalls: list[str] = []
    aborted: str | None = None
    t_replay = t_end_send = t_done = t_start
    cpu0 = (_cpu_busy_s(), time.monotonic())
    own0 = _own_cpu()
    node_cpu = 0.0
    alive = lambda: node_proc.proc.poll() is None  # noqa: E731

    def wait_until(ok: Callable[[], bool], timeout_s: float) -> bool:
        return _wait_until(ok, timeout_s, alive, poll_s=0.02)

    try:
        outputs = [t for t in conv.OUTPUT_TOPICS if t != "/diagnostics"]
        discovered = wait_until(
            lambda: (
                all(node.count_publishers(t) > 0 for t in outputs)
                and all(pubs[t[1:]].get_subscription_count() > 0 for t in inputs)
            ),
            60.0,
        )
        if not discovered:
            raise RuntimeError("the node and this process did not discover each other in 60 s")
        time.sleep(1.0)  # the writers' side of discovery (see live.Recorder.wait_for_publishers)
        t_replay = time.monotonic()
        checker.t0 = t_replay
        bar = tqdm(
            total=repetitions,
            desc=f"longrun {bag.name}",
            unit="rep",
            disable=not progress,
            dynamic_ncols=True,
        )
        try:
            # The latched inputs of a repetition (GCP, scanner info, truth: transient local) go
            # out before its stream, with the previous repetition's acknowledgement wait, as a
            # ground station latches them ahead of a pass. Sent together with the stream, a GCP
            # set delayed by a DDS repair (heartbeat, about 3 s here) can reach the node after
            # its first scene: that scene then has no GCP (seen once in 281 repetitions).
            latched = {t for t in pubs if reader.qos(t) == "transient_local"}

            def more(k: int) -> bool:
                if repetitions is not None and k >= repetitions:
                    return False
                return time.monotonic() - t_replay < minutes * 60.0 and alive()

            def publish(topic: str, msg: Any) -> None:
                pubs[topic].publish(msg)
                sent[topic] += 1

            def wait_acked(k: int) -> float:
                # In slices of 50 ms: rclpy holds the GIL during the wait, which stopped the
                # RSS sampling and the subscriptions of this process for up to 3.7 s.
                t_ack = time.monotonic()
                for topic, p in pubs.items():
                    deadline = time.monotonic() + 10.0
                    while not p.wait_for_all_acked(Duration(nanoseconds=50_000_000)):
                        if time.monotonic() > deadline:
                            log(f"longrun: {topic}: not acknowledged in 10 s (repetition {k})")
                            break
                        time.sleep(0.001)
                return time.monotonic() - t_ack

            rep = 0
            planned = more(0)
            if planned:
                for topic, msg, _ in repetition_messages(plan, 0, sorted(latched)):
                    publish(topic, msg)
                ack_s += wait_acked(0)
            while planned:
                back = rep - in_flight
                if back >= 0 and not wait_until(
                    lambda b=back: checker.pairs_done(b) >= len(plan.pairs), stall_timeout_s
                ):
                    if not alive():
                        break
                    stalls.append(
                        f"repetition {back}: {checker.pairs_done(back)} of {len(plan.pairs)} "
                        f"pairs after {stall_timeout_s:.0f} s"
                    )
                t_rep = time.monotonic()
                first_log: int | None = None
                stream = [t for t in pubs if t not in latched]
                for topic, msg, log_ns in repetition_messages(plan, rep, stream):
                    if rate > 0:
                        first_log = log_ns if first_log is None else first_log
                        wait = t_rep + (log_ns - first_log) / 1e9 / rate - time.monotonic()
                        if wait > 0:
                            time.sleep(wait)
                    publish(topic, msg)
                planned = more(rep + 1)
                if planned:
                    for topic, msg, _ in repetition_messages(plan, rep + 1, sorted(latched)):
                        publish(topic, msg)
                ack_s += wait_acked(rep)
                rep += 1
                reps_sent = rep
                s = checker.latest_summary()
                bar.set_postfix(
                    pairs=len(checker.records),
                    rss=f"{rss.rss_mb:.0f}MB",
                    queue=s.get("queue", "?"),
                    refresh=False,
                )
                bar.update(1)
            if not alive():
                aborted = f"node exited with {node_proc.proc.returncode}"
        except KeyboardInterrupt:
            aborted = "interrupted (Ctrl-C)"
        finally:
            bar.close()
        t_end_send = time.monotonic()
        # Drain: the last repetition's last scene closes after the node's scene_timeout.
        expected_total = reps_sent * len(plan.pairs)
        wait_until(lambda: len(checker.records) >= expected_total, stall_timeout_s)
        t_done = time.monotonic()
        # Two more summaries: the final counters and the queue once idle.
        wait_until(lambda: checker.summaries_since(t_done - t_replay) >= 2, 10.0)
        log(f"longrun: {ack_s:.1f} s waiting for acknowledgements")
        cpu = rss.cpu[-1][1] if rss.cpu else 0.0
        node_cpu = cpu
    finally:
        cpu1 = (_cpu_busy_s(), time.monotonic())
        own = _own_cpu() - own0
        code = node_proc.stop()
        rss.stop()
        executor.shutdown()
        spin.join(timeout=5)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)

    report = _report(
        plan,
        checker,
        rss,
        sent=sent,
        reps_sent=reps_sent,
        times=(t_start, t_replay, t_end_send, t_done),
        settings={
            "bag": str(bag),
            "minutes": minutes,
            "repetitions_limit": repetitions,
            "rate": rate,
            "margin_s": margin_s,
            "in_flight": in_flight,
            "warmup_s": warmup_s,
            "rtol": rtol,
            "node_params": params,
        },
        node={
            "exit_code": code,
            "cpu_s": node_cpu,
            "traceback_in_log": "Traceback" in node_proc.output(),
            "log": str(out / "node.log"),
        },
        stalls=stalls,
        aborted=aborted,
        machine=machine,
        cpu=(cpu0, cpu1, own + node_cpu),
    )
    (out / "longrun.json").write_text(json.dumps(_jsonable(report), indent=1))
    plot_report(report, out / "longrun.png")
    return report


def _params_file(params: dict[str, Any], path: Path, inputs: list[str]) -> Path:
    """The node's --params-file: reliable, keep-all input subscriptions.

    Keep-all rather than the demo's keep-last 1000: while the node's worker runs a pair (tie
    points), its executor thread gets the GIL only now and then and takes a few tens of messages
    a second; a repetition sent at once (1447 navigation messages) then overran a keep-last
    history and 564 navigation samples were lost in a 6-repetition trial. With keep-all on both
    sides the reliable protocol holds the writer back instead: nothing is lost, and the
    replay runs at the rate the node takes messages.
    """
    import yaml

    node_params_yaml(params, path, reliable_inputs=inputs)
    doc = yaml.safe_load(path.read_text())
    for topic in inputs:
        sub = doc["parproj_node"]["ros__parameters"]["qos_overrides"][topic]["subscription"]
        sub["history"] = "keep_all"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _own_cpu() -> float:
    """CPU seconds of this process so far."""
    import resource

    me = resource.getrusage(resource.RUSAGE_SELF)
    return me.ru_utime + me.ru_stime


def _report(
    plan: BagPlan,
    checker: PairChecker,
    rss: Any,
    *,
    sent: dict[str, int],
    reps_sent: int,
    times: tuple[float, float, float, float],
    settings: dict[str, Any],
    node: dict[str, Any],
    stalls: list[str],
    aborted: str | None,
    machine: dict[str, Any],
    cpu: tuple[tuple[float, float], tuple[float, float], float],
) -> dict[str, Any]:
    """The figures of a run (see the module docstring); series for the plot included."""
    t_start, t_replay, t_end_send, t_done = times
    wall = t_done - t_replay
    wall0 = time.time() - (time.monotonic() - t_replay)  # epoch time of t_replay
    records = checker.records
    expected = reps_sent * len(plan.pairs)
    malformed = [r for r in records if r.problems]
    published_ids = {(r.rep, r.original) for r in records}
    missing = [
        repetition_id(p.split("+")[0], k)
        for k in range(reps_sent)
        for p in plan.pairs
        if (k, p) not in published_ids
    ]
    final = checker.summaries[-1][1] if checker.summaries else {}

    def count(key: str) -> int | None:
        return int(final[key]) if key in final else None

    strips_sent = sum(n for t, n in sent.items() if t.endswith("/image_strip"))
    nav_sent = sent.get("navigation", 0)
    drops = {
        "strips_rejected": count("strips_rejected"),
        "nav_rejected": count("nav_rejected"),
        "strips_not_received": None if count("strips") is None else strips_sent - count("strips"),
        "nav_not_received": None if count("nav") is None else nav_sent - count("nav"),
        "diagnostics_warn": checker.issue_levels.get("warn", 0),
        "diagnostics_error": checker.issue_levels.get("error", 0),
        "diagnostics_messages": dict(sorted(checker.issues.items(), key=lambda kv: -kv[1])[:20]),
    }
    # RSS: samples relative to the start of the replay.
    samples = np.array(rss.samples, dtype=float).reshape(-1, 2)
    ts = samples[:, 0] - wall0
    mb = samples[:, 1]
    in_run = (ts >= 0) & (ts <= wall)
    warm = min(settings["warmup_s"], 0.5 * wall)
    fit = in_run & (ts >= warm)
    pair_times = np.array(sorted(r.wall_s for r in records))
    pairs_at = np.searchsorted(pair_times, ts, side="right").astype(float)
    slope_s = _slope(ts[fit], mb[fit])
    slope_p = _slope(pairs_at[fit], mb[fit])
    half = _second_half_slope(ts[in_run], mb[in_run], wall)
    run_mb = mb[in_run] if in_run.any() else mb
    queue = [
        (t, int(s.get("queue", 0)), int(s.get("queue_max", s.get("queue", 0))))
        for t, s in checker.summaries
    ]
    q_run = [q for q in queue if q[0] <= wall + 5]
    nav_held = [(t, int(s["nav_samples"])) for t, s in checker.summaries if "nav_samples" in s]
    gcp_held = [(t, int(s["gcp_points"])) for t, s in checker.summaries if "gcp_points" in s]
    ytruth = [r.truth_y_rms_px for r in records if r.truth_y_rms_px is not None]
    (busy0, w0), (busy1, w1), ours = cpu
    machine_cpu = (busy1 - busy0) / max(w1 - w0, 1e-9)
    ok = (
        aborted is None
        and not stalls
        and len(records) == expected
        and not malformed
        and not missing
        and all(
            v == 0
            for k, v in drops.items()
            if k in ("strips_rejected", "nav_rejected", "strips_not_received", "nav_not_received")
        )
        and drops["diagnostics_warn"] == 0
        and drops["diagnostics_error"] == 0
        and node["exit_code"] == 0
        and not node["traceback_in_log"]
    )
    return {
        "ok": ok,
        "date": datetime.fromtimestamp(wall0, UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "settings": settings,
        "machine": machine,
        "bag": {
            "duration_s": plan.duration_ns / 1e9,
            "shift_s": plan.shift_ns / 1e9,
            "messages": plan.counts,
            "pairs": plan.pairs,
        },
        "wall_s": wall,
        "send_s": t_end_send - t_replay,
        "startup_s": t_replay - t_start,
        "simulated_s": reps_sent * plan.shift_ns / 1e9,
        "simulated_per_wall": reps_sent * plan.shift_ns / 1e9 / wall if wall > 0 else None,
        "repetitions": reps_sent,
        "messages_sent": sent,
        "pairs": {
            "expected": expected,
            "published": len(records),
            "well_formed": len(records) - len(malformed),
            "malformed": len(malformed),
            "missing": missing[:20],
            "missing_count": len(missing),
            "identical_to_first": sum(1 for r in records if r.identical and r.rep > 0),
            "compared": sum(1 for r in records if r.rep > 0),
            "max_rel_diff": max((r.max_rel_diff for r in records), default=0.0),
            "streamed": sum(1 for r in records if r.streamed),
            "incomplete": checker.incomplete()[:20],
            "malformed_examples": [
                {"pair_id": r.pair_id, "problems": r.problems} for r in malformed[:10]
            ],
            "per_hour": len(records) / wall * 3600 if wall > 0 else None,
        },
        "scenes": {
            "expected": reps_sent * plan.scene_count,
            "published": sum(checker.scenes.values()),
            "problems": checker.scene_problems[:10],
        },
        "truth_y_parallax_rms_px": {
            "first": ytruth[0] if ytruth else None,
            "min": min(ytruth) if ytruth else None,
            "max": max(ytruth) if ytruth else None,
        },
        "drops": drops,
        "rss_mb": {
            "start": float(run_mb[0]) if run_mb.size else None,
            "end": float(run_mb[-1]) if run_mb.size else None,
            "max": float(run_mb.max()) if run_mb.size else None,
            "hwm": rss.hwm_mb,
            "slope_mb_per_hour": None if slope_s is None else slope_s * 3600,
            "slope_mb_per_pair": slope_p,
            "at_warmup_end": float(mb[fit][0]) if fit.any() else None,
            "slope_second_half_mb_per_hour": half,
            "fit_from_s": warm,
            "fit_samples": int(fit.sum()),
        },
        "queue": {
            "max": max((q[2] for q in q_run), default=None),
            "max_sampled": max((q[1] for q in q_run), default=None),
            "last": q_run[-1][1] if q_run else None,
            "nav_samples_held": {
                "max": max((v for _, v in nav_held), default=None),
                "last": nav_held[-1][1] if nav_held else None,
            },
            "gcp_points_held": {
                "max": max((v for _, v in gcp_held), default=None),
                "last": gcp_held[-1][1] if gcp_held else None,
            },
        },
        "node": {**node, "final_summary": final},
        "cpu": {
            "machine_busy_cores": machine_cpu,
            "ours_cores": ours / max(w1 - w0, 1e-9),
            "others_cores": machine_cpu - ours / max(w1 - w0, 1e-9),
            "load_average_end": [round(x, 2) for x in os.getloadavg()],
        },
        "stalls": stalls,
        "aborted": aborted,
        "series": {
            "rss": [[round(float(t), 2), round(float(m), 2)] for t, m in zip(ts, mb, strict=True)],
            "queue": [[round(t, 2), q, qm] for t, q, qm in queue],
            "nav_samples": [[round(t, 2), v] for t, v in nav_held],
            "gcp_points": [[round(t, 2), v] for t, v in gcp_held],
            "pairs": [round(float(t), 2) for t in pair_times],
        },
    }


def plot_report(report: dict[str, Any], path: Path) -> None:
    """RSS (with the fitted slope), queue length and pairs against wall time, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ser = report["series"]
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    rss = np.array(ser["rss"], dtype=float).reshape(-1, 2)
    if rss.size:
        ax[0].plot(rss[:, 0] / 60, rss[:, 1], lw=1, label="node VmRSS")
        r = report["rss_mb"]
        if r["slope_mb_per_hour"] is not None:
            t = rss[:, 0]
            sel = (t >= r["fit_from_s"]) & (t <= report["wall_s"])
            if sel.sum() >= 2:
                c = np.polyfit(t[sel], rss[sel, 1], 1)
                ax[0].plot(
                    t[sel] / 60,
                    np.polyval(c, t[sel]),
                    "--",
                    lw=1,
                    label=f"fit {r['slope_mb_per_hour']:+.2f} MB/h",
                )
        ax[0].legend(loc="lower right")
    ax[0].set(ylabel="RSS (MB)", title=f"parproj longrun: {Path(report['settings']['bag']).name}")
    q = np.array(ser["queue"], dtype=float).reshape(-1, 3)
    if q.size:
        ax[1].plot(q[:, 0] / 60, q[:, 2], lw=0.8, label="peak in the last second")
        ax[1].plot(q[:, 0] / 60, q[:, 1], lw=0.8, label="at the 1 Hz summary")
        ax[1].legend(loc="upper right")
    ax[1].set(ylabel="input queue (items)")
    pt = np.array(ser["pairs"], dtype=float)
    ax[2].step(pt / 60, np.arange(1, pt.size + 1), where="post", lw=1, label="pairs")
    nav = np.array(ser["nav_samples"], dtype=float).reshape(-1, 2)
    if nav.size:
        ax2 = ax[2].twinx()
        ax2.plot(nav[:, 0] / 60, nav[:, 1], color="tab:orange", lw=0.8)
        ax2.set_ylabel("navigation samples held", color="tab:orange")
    ax[2].set(xlabel="wall time since the first message (min)", ylabel="pairs published")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def format_report(r: dict[str, Any]) -> str:
    """A short table of the figures."""

    def f(v: Any, fmt: str = ".1f") -> str:
        return "-" if v is None else format(v, fmt)

    p, m, q, d = r["pairs"], r["rss_mb"], r["queue"], r["drops"]
    rows = [
        ("result", "ok" if r["ok"] else "NOT OK" + (f" ({r['aborted']})" if r["aborted"] else "")),
        ("wall duration", f"{f(r['wall_s'] / 60)} min"),
        (
            "simulated duration",
            f"{f(r['simulated_s'] / 3600, '.2f')} h ({f(r['simulated_per_wall'])} x wall)",
        ),
        ("repetitions", str(r["repetitions"])),
        (
            "pairs expected / published / malformed",
            f"{p['expected']} / {p['published']} / {p['malformed']}",
        ),
        (
            "identical to the first repetition",
            f"{p['identical_to_first']} of {p['compared']} (max rel diff {p['max_rel_diff']:.1e})",
        ),
        (
            "drops: strips/nav rejected, not received",
            f"{d['strips_rejected']} / {d['nav_rejected']}, "
            f"{d['strips_not_received']} / {d['nav_not_received']}",
        ),
        (
            "diagnostics warn / error",
            f"{d['diagnostics_warn']} / {d['diagnostics_error']}",
        ),
        (
            "RSS start / after warm-up / end / max",
            f"{f(m['start'])} / {f(m['at_warmup_end'])} / {f(m['end'])} / {f(m['max'])} MB",
        ),
        (
            "RSS slope",
            f"{f(m['slope_mb_per_hour'], '+.2f')} MB/h, "
            f"{f(m['slope_mb_per_pair'], '+.4f')} MB/pair (after {m['fit_from_s']:.0f} s); "
            f"second half, per-minute medians: {f(m['slope_second_half_mb_per_hour'], '+.2f')} "
            "MB/h",
        ),
        ("queue max / last", f"{q['max']} / {q['last']}"),
        (
            "navigation samples / GCP held (last)",
            f"{q['nav_samples_held']['last']} / {q['gcp_points_held']['last']}",
        ),
        (
            "CPU: machine busy / ours / others",
            f"{r['cpu']['machine_busy_cores']:.2f} / {r['cpu']['ours_cores']:.2f} / "
            f"{r['cpu']['others_cores']:.2f} cores",
        ),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    for s in r["stalls"]:
        lines.append(f"stall: {s}")
    for e in p["malformed_examples"][:3]:
        lines.append(f"malformed: {e['pair_id']}: {'; '.join(e['problems'][:3])}")
    for k, n in list(d["diagnostics_messages"].items())[:5]:
        lines.append(f"diagnostics x{n}: {k}")
    return "\n".join(lines)
