"""A bag repeated as new acquisitions, and the checks of every pair that comes back."""

from __future__ import annotations

import hashlib
import json
import math
import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from parproj_ros.core import contract
from parproj_ros.core.results import GroundPoint
from parproj_ros.eval.published import normalized_px
from parproj_ros.imaging.encodings import ENCODING_DTYPES
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader, get_message_class
from parproj_ros.ros.inputs import views_from_bag

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
    if header is not None and contract.view_of(topic) is not None:
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
    for item in reader.messages(topics=[contract.strip_topic(v) for v in views]):
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
_ENCODINGS = {enc: (dtype.itemsize, 1) for enc, dtype in ENCODING_DTYPES.items()}
_ENCODINGS |= {"rgb8": (3, 3), "bgr8": (3, 3)}


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

    IMAGE_TOPICS = contract.PAIR_IMAGE_TOPICS
    BLOCK_TOPICS = frozenset(map(contract.normalized_block_topic, contract.SIDES))

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
        for topic, msgtype in contract.OUTPUT_TOPICS.items():
            cls = get_message_class(msgtype)
            subs.append(
                node.create_subscription(cls, topic, lambda m, t=topic: self.on_message(t, m), qos)
            )
        return subs

    def on_message(self, topic: str, msg: Any) -> None:
        """Dispatch one received message."""
        with self._lock:
            if topic == contract.DIAGNOSTICS:
                self._on_diagnostics(msg)
            elif topic == contract.PARALLEL_PROJECTION:
                self._on_scene(msg)
            elif topic in self.BLOCK_TOPICS:
                self._blocks.setdefault((msg.pair_id, msg.side), []).append(msg)
            else:
                stamp = conv.stamp_to_ns(msg.header.stamp)
                pend = self._pending.setdefault(stamp, _Pending())
                if topic == contract.STEREO_PAIR:
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
            for side in contract.SIDES:
                name = contract.normalized_image_topic(side)
                topic = images[name]
                probs += _image_problems(embedded[side], f"StereoPair.{side}", w, h, 1)
                probs += _image_problems(topic, name, w, h, 1)
                digests[side] = _digest(topic)
                if _digest(embedded[side]) != digests[side]:
                    probs.append(f"StereoPair.{side} differs from {name}")
            if sp.left.encoding != sp.right.encoding:
                probs.append(f"encodings differ: {sp.left.encoding} / {sp.right.encoding}")
            anaglyph = images[contract.ANAGLYPH]
            probs += _image_problems(anaglyph, "anaglyph", w, h, 3)
            digests["anaglyph"] = _digest(anaglyph)
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
