"""Whether a truth source is the acquisition an output bag was computed from (by its images).

``parproj evaluate --truth BAG`` and ``parproj dsm --scenario NAME`` compare outputs with a
truth that names its scenes like every other simulated bag (``pan_scene_0000`` in both the
``ikonos_agile`` and the ``crab_foreaft`` bags, all in frame ``map``, at the same stamps): the
frame check (``parproj_ros.eval.evaluate.check_truth_frame``) passes, and the figures of
another acquisition's truth print as results (NMAD 35-84 m, exit 0).

The images decide. Raw pixels of each output scene, taken from the truth source (the truth
bag's image strips, or the scenario rendered), are mapped through the *published* transforms
(scene frame, PTP roll, normalization affine, output grid; as the evaluation maps truth points)
into the published normalized image and sampled there. For the acquisition the outputs were
made from, raw and normalized values agree (Pearson correlation 0.95-1.0: the same pixels,
resampled once); for another one they are unrelated textures (|r| < 0.1). Below
:data:`MIN_CORRELATION`, the truth is refused naming the option.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..core import contract
from ..io.files import InputError
from ..ros.bag import BagReader
from ..ros.conversions import ConversionError, assemble_blocks, image_to_array
from .published import normalized_px

#: Below this correlation of raw and normalized values the images are another acquisition's.
MIN_CORRELATION = 0.5

#: Fewest raw pixels landing on valid normalized pixels for a verdict (else none is given).
MIN_PIXELS = 400

#: Raw lines compared per scene (around its middle line), and the pixel stride used.
LINES = 128
STRIDE = 2


@dataclass(frozen=True)
class SceneSide:
    """One side of the output bag's first pair: what to compare the raw pixels with.

    Attributes:
        scene: the scene id the raw lines are counted in (``segment_of`` for a segment).
        first_line: the raw line of the side's line 0 (a segment's ``segment_first_line``).
        lines: first and last + 1 raw line to compare.
        params: the side's ParallelProjection message.
        to_normalized: the side's 2x3 normalization affine (6 numbers).
        x_origin: the side's normalized x origin, metres.
        image: the side's normalized image.
    """

    scene: str
    first_line: int
    lines: tuple[int, int]
    params: Any
    to_normalized: Any
    x_origin: float
    image: NDArray[np.generic]


def output_sides(out_bag: Path) -> tuple[Any, list[SceneSide]] | None:
    """The first stereo pair of ``out_bag`` whose images are in it, as two :class:`SceneSide`.

    None when the bag holds no pair with its images (nothing to compare: no verdict).
    """
    reader = BagReader(out_bag)
    if contract.STEREO_PAIR not in reader.topics():
        return None
    for item in reader.messages(topics=[contract.STEREO_PAIR]):
        sp = item.msg
        try:
            if sp.streamed:
                images = _streamed_images(reader, sp.pair_id)
                if images is None:
                    continue
            else:
                images = (image_to_array(sp.left), image_to_array(sp.right))
        except ConversionError:
            continue
        sides = []
        for side, image in zip(contract.SIDES, images, strict=True):
            prm = getattr(sp, f"{side}_params")
            first = int(prm.segment_first_line) if prm.segment_of else 0
            mid = first + int(prm.lines) // 2
            lo = max(first, mid - LINES // 2)
            hi = min(first + int(prm.lines), lo + LINES)
            sides.append(
                SceneSide(
                    scene=str(prm.segment_of or prm.scene_id),
                    first_line=first,
                    lines=(lo, hi),
                    params=prm,
                    to_normalized=getattr(sp, f"{side}_to_normalized"),
                    x_origin=float(getattr(sp, f"{side}_x_origin")),
                    image=np.asarray(image),
                )
            )
        return sp, sides
    return None


def _streamed_images(reader: BagReader, pair_id: str) -> tuple[Any, Any] | None:
    have = reader.topics()
    topics = [t for t in map(contract.normalized_block_topic, contract.SIDES) if t in have]
    if len(topics) < 2:
        return None
    parts: dict[str, list[Any]] = {side: [] for side in contract.SIDES}
    for item in reader.messages(topics=topics):
        if item.msg.pair_id == pair_id:
            parts[item.msg.side].append(item.msg)
    if not all(parts.values()):
        return None
    return assemble_blocks(parts["left"]), assemble_blocks(parts["right"])


#: Raw lines of scenes, ``{scene: (first line, image)}``, and the names of every scene the source
#: has images of.
Lines = tuple[dict[str, tuple[int, Any]], list[str]]


def bag_lines(bag: Path, want: Mapping[str, tuple[int, int]]) -> Lines:
    """Raw lines of scenes from a bag's image strips, and the names of all its scenes.

    A scene's lines are counted from its first strip (strips arrive in line order, as the node
    assembles them). Only strips overlapping ``want[scene]`` (first, last + 1 line) are kept;
    a scene of ``want`` the bag has no strips of is left out.
    """
    reader = BagReader(bag)
    types = reader.topics()
    topics = [
        t for t, ty in types.items() if ty == "sensor_msgs/msg/Image" and contract.view_of(t)
    ]
    seen: dict[str, int] = {}
    kept: dict[str, list[tuple[int, Any]]] = {}
    if topics:
        for item in reader.messages(topics=topics):
            sid = str(item.msg.header.frame_id)
            line0 = seen.get(sid, 0)
            rows = int(item.msg.height)
            seen[sid] = line0 + rows
            span = want.get(sid)
            if span is None or line0 + rows <= span[0] or line0 >= span[1]:
                continue
            try:
                kept.setdefault(sid, []).append((line0, image_to_array(item.msg)))
            except ConversionError:
                continue
    out: dict[str, tuple[int, Any]] = {}
    for sid, parts in kept.items():
        first = parts[0][0]
        run = [parts[0][1]]
        for (line0, p), (prev0, prev) in zip(parts[1:], parts, strict=False):
            if line0 != prev0 + prev.shape[0] or p.shape[1:] != run[0].shape[1:]:
                break  # a strip left out (undecodable) or of another width: the run so far
            run.append(p)
        out[sid] = (first, np.concatenate(run, axis=0))
    return out, sorted(seen)


def correlation(
    side: SceneSide, first_line: int, raw: Any, pixel: float, y_origin: float
) -> tuple[float, int]:
    """Correlation of raw pixels and the normalized image where they land; (r, pixels used).

    ``raw`` holds raw lines ``first_line ..``; pixels with value 0 on either side (no data) and
    those landing outside the normalized image are left out. ``(nan, n)`` when fewer than
    :data:`MIN_PIXELS` are left or either side is constant.
    """
    raw = np.asarray(raw, dtype=np.float32)
    rows = np.arange(0, raw.shape[0], STRIDE)
    cols = np.arange(0, raw.shape[1], STRIDE)
    line = rows[:, None] + first_line - side.first_line + np.zeros((1, cols.size))
    sample = np.zeros((rows.size, 1)) + cols[None, :]
    col, row = normalized_px(
        side.params, side.to_normalized, side.x_origin, y_origin, pixel, line, sample
    )
    img = np.asarray(side.image, dtype=np.float32)
    v = cv2.remap(
        img,
        col.astype(np.float32),
        row.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    r = raw[np.ix_(rows, cols)]
    ok = (v != 0) & (r != 0) & np.isfinite(v) & np.isfinite(r)
    n = int(ok.sum())
    a, b = r[ok].astype(np.float64), v[ok].astype(np.float64)
    if n < MIN_PIXELS or a.std() == 0 or b.std() == 0:
        return float("nan"), n
    return float(np.corrcoef(a, b)[0, 1]), n


def check_same_input(
    out_bag: Path,
    lines_of: Any,
    *,
    option: str,
    source: str,
) -> list[tuple[str, float, int]]:
    """Refuse a truth source whose images are not those the outputs were computed from.

    Args:
        out_bag: the output bag (its first pair with images is compared).
        lines_of: ``want -> (lines, names)``: the truth source's raw lines of the scenes asked
            (``want``: scene -> (first, last + 1) line; a scene it lacks is absent) and the
            names of all its scenes (:data:`Lines`).
        option: the option named in the error (``--truth``, ``--scenario``).
        source: the truth source in words (its file or scenario name).

    Returns:
        ``(scene, correlation, pixels)`` per side compared (none: no verdict possible).

    Raises:
        InputError: a scene of the outputs the source has no image of, while it has images; or
            a side whose correlation is below :data:`MIN_CORRELATION`.
    """
    got = output_sides(out_bag)
    if got is None:
        return []
    sp, sides = got
    raw, names = lines_of({s.scene: s.lines for s in sides})
    checked = []
    for side in sides:
        if side.scene not in raw:
            if names and side.scene not in names:
                raise InputError(
                    option,
                    f"{source} has no image of scene {side.scene!r} of the outputs of "
                    f"{out_bag} (its scenes: {', '.join(names)}): the truth of another "
                    "acquisition; give the one the outputs were computed from",
                )
            continue
        first, image = raw[side.scene]
        r, n = correlation(side, first, image, float(sp.normalized_pixel_size), float(sp.y_origin))
        checked.append((side.scene, r, n))
        if np.isfinite(r) and r < MIN_CORRELATION:
            raise InputError(
                option,
                f"{source}: its images of scene {side.scene!r} are not those the outputs of "
                f"{out_bag} were computed from (mapped through the published transforms, "
                f"{n} of its pixels correlate {r:.2f} with the normalized image; the same "
                "acquisition gives 0.95 or more): the truth of another acquisition; give the "
                "one the outputs were computed from",
            )
    return checked


def truth_bag_lines(bag: Path) -> Any:
    """``lines_of`` for :func:`check_same_input` from a truth bag's image strips."""

    def lines_of(want: Mapping[str, tuple[int, int]]) -> Lines:
        return bag_lines(bag, want)

    return lines_of


def scenario_lines(name: str) -> Any:
    """``lines_of`` for :func:`check_same_input` rendering a simulated scenario's scenes."""

    def lines_of(want: Mapping[str, tuple[int, int]]) -> Lines:
        from ..sim.scenarios import SCENARIOS
        from ..sim.simulate import render_scene
        from ..sim.terrain import procedural_terrain

        scn = SCENARIOS[name]()
        ids = [scn.scene_id(i) for i in range(len(scn.scenes))]
        terrain = None
        out: dict[str, tuple[int, Any]] = {}
        for i, sid in enumerate(ids):
            span = want.get(sid)
            if span is None:
                continue
            lo, hi = max(0, span[0]), min(scn.scenes[i].lines, span[1])
            if hi <= lo:
                continue
            if terrain is None:
                terrain = procedural_terrain(
                    scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
                )
            out[sid] = (lo, render_scene(scn.model(i), terrain, lo, hi - lo, dtype=scn.dtype))
        return out, ids

    return lines_of


def describe(checked: Iterable[tuple[str, float, int]]) -> str:
    """The comparison in words, for logs (``scene r=0.99 (n px)``)."""
    return ", ".join(f"{s} r={r:.2f} ({n} px)" for s, r, n in checked)
