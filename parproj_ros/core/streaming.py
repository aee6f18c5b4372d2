"""Streaming normalization (paper 2 section 4 by column blocks) while the scenes still arrive.

Applies to two-view configurations (fore/aft cameras with one line clock) with a configured scene
length and navigation-derived parameters: when both views have started scene k and navigation
reaches the scenes' start, the motion is fitted on the latest navigation and extrapolated over the
scene (constant velocity and attitude, the model's own assumption), both scenes' parameters and
the normalization are derived, and the output grids are fixed. From then on every arriving strip
may complete column blocks of the normalized images: in along-track stereo the epipolar lines run
along track, so a normalized *row* spans the whole scene, while a block of normalized *columns*
needs only a window of scan lines. A block is resampled and emitted as soon as its last needed
line has arrived, and lines no later block needs are released, so memory and latency no longer
grow with the scene length. When both scenes are complete, the scene parameters and the pair
(without pixels) are emitted, and the extrapolated motion is checked against a fit on all the
navigation of the scene.

:class:`Streamer` is the policy: it reads the ledger (:class:`~parproj_ros.core.ledger.
PairLedger`: pairs streamed, not streamed, held for navigation; scenes waiting) and records its
decisions there; :func:`plan_blocks` and :func:`render_block` do the pixel work.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Mapping
from contextlib import closing
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry import GeometryError, PushbroomModel, parameters_from_navigation
from ..geometry.navigation import virtual_points
from ..imaging.assembly import OpenScene, Scene, SceneAssembler, SceneEnd
from ..imaging.kernels import max_support_lines
from ..imaging.resample import (
    OutputGrid,
    SceneGeometry,
    Tile,
    plan_tiles,
    reduce_block,
    render_block,
)
from .config import PipelineConfig
from .dem_terrain import DemTerrain, terrain_issue
from .gcp_store import GcpStore
from .ledger import Block, PairLedger, SideStream, StreamPair
from .navigation import NavigationFeed
from .normalization import interpolation_flag, pair_geometry
from .orientation import start_seen
from .publish import finish_pair
from .render_process import RenderProcess
from .results import BlockResult, Issue, Level, Outputs, SceneResult
from .terrain import TerrainSource
from .trajectory import NavigationError

FloatArray = NDArray[np.float64]

#: Columns per streamed block (the tile width of the resampler, so blocks hold whole tiles).
BLOCK_COLS = 256
#: Rows of a block's tiles before any split to meet the resampler's tolerance: one
#: ``cv2.warpAffine`` per tile, and each call gives the GIL back and waits to take it again.
#: With the node receiving 343 MB/s (its executor holds the GIL while it takes a strip) that
#: wait, not the resampling, was the time of a block (``python -m tools.bench``); 512 rows
#: halve the calls of 256 x 256 tiles within the same tolerance (0.0034 px at IKONOS size).
TILE_ROWS = 512
#: A view whose strips lag the other view's by more than a scene, and at least this many
#: seconds of sensor time, has stopped (a short scene): its pair is processed whole. Over DDS
#: one view's strips can arrive more than 1 s after the other's at the full IKONOS rate (a
#: reliable writer resending lost fragments; ``python -m tools.bench``), which half a scene,
#: the former bound, took for a stop.
STALE_MIN_S = 2.0
#: A side complete when its stream opens (fore/aft cameras: the fore scene of pair k+1 is
#: complete when the aft one begins) has its blocks emitted as the other side's are, this many
#: ahead, not all at once: at the IKONOS width its 55 blocks took 0.7-0.8 s in the input that
#: opened the stream, and the pair's first streamed DSM tile waited for all of them
#: (docs/stream_start.md). Ahead, so that a tile's left window, wider than the right one by
#: the disparities, is there when the right one is (4 blocks: 1024 columns).
PACED_LEAD_BLOCKS = 4
#: How draft blocks are sampled (:attr:`Streamer.draft`): the quick-look averages 4 x 4 to
#: 8 x 8 of their pixels, so nearest-neighbour sampling (at most half a pixel off, 1/16 of a
#: reduced pixel at 1/8) is all it needs, at 2.6 ms a block of the IKONOS width against 6.1
#: bilinear and 19 bicubic (27 warpAffine calls of 512 x 256, 1 thread). The render process
#: took 0.49 CPU s per sensor s at the IKONOS rate with the quick-look at 1/8, half the
#: machine's slack.
DRAFT_INTERPOLATION = cv2.INTER_NEAREST
#: Samples a draft's quick-look pixel averages at least, along each axis: a draft block is
#: sampled every ``factor // DRAFT_SAMPLES`` rows and columns (1/8: every 2nd, each reduced
#: pixel the mean of 4 x 4 samples instead of 8 x 8), a quarter of the pixels to render and
#: reduce: the render process took 0.41 CPU s per sensor s rendering and reducing every pixel
#: of the drafts at the IKONOS rate, with the machine's two cores 92 % busy.
DRAFT_SAMPLES = 4
#: How strided drafts are sampled: at the centre of each stride x stride pixels, bilinear
#: (the mean of the 2 x 2 pixels around it). Nearest-neighbour at those centres, half-way
#: between pixels, always rounds the same way in the source scene: at 1/8 on the airborne
#: pair, a bias of half a full-resolution pixel of disparity.
DRAFT_STRIDED_INTERPOLATION = cv2.INTER_LINEAR


def draft_stride(factors: tuple[int, ...]) -> int:
    """The stride draft blocks are sampled at for quick-look levels reduced by ``factors``.

    The largest that leaves every level (factor > 0) at least :data:`DRAFT_SAMPLES` samples
    per reduced pixel along each axis and divides each factor; 1 without a level.
    """
    levels = [f for f in factors if f > 0]
    if not levels:
        return 1
    s = max(1, min(levels) // DRAFT_SAMPLES)
    while any(f % s for f in levels):
        s -= 1
    return s


#: Lines of margin around the lines a tile's affine map reaches: the widest kernel's support
#: (imaging/kernels.py; bicubic: 2) and one more, whatever kernel is configured.
LINE_MARGIN = 1 + max_support_lines()


def _corner_lines(t: Tile) -> FloatArray:
    """Source lines of a tile's four corners by its affine map (the reference product)."""
    corners = np.array(
        [[0, 0, 1], [t.cols - 1, 0, 1], [0, t.rows - 1, 1], [t.cols - 1, t.rows - 1, 1]],
        dtype=float,
    )
    return np.asarray(corners @ t.affine[1], dtype=float)


#: Bound on the rounding of a corner's line, relative to the sum of its terms' magnitudes:
#: three terms (two products and a sum, or fused) in any order are within 3 u / (1 - 3 u) of
#: the exact value (u = 2**-53), so two orders within twice that (3.3e-16); 16 epsilons
#: (3.6e-15) leave a margin.
_LINE_ROUNDING = 16 * float(np.finfo(float).eps)


def _tile_line_spans(tiles: list[Tile]) -> tuple[FloatArray, FloatArray]:
    """Smallest and largest source line each tile's affine map reaches at its corners.

    All tiles at once (an IKONOS-width side has 1540 tiles: 8 ms tile by tile, about 1 ms
    here). Only the whole line below the smallest and above the largest matters
    (:func:`plan_blocks`), and those are the reference product's (:func:`_corner_lines`): a
    corner whose line is within its rounding bound of a whole line, or not finite, has its
    tile recomputed by the reference product, so ``floor`` and ``ceil`` of every value are
    the reference's (and ``floor(min) = min(floor)``, ``ceil(max) = max(ceil)``).
    """
    a = np.array([t.affine[1] for t in tiles], dtype=float)  # (n, 3): line = a0 c + a1 r + a2
    c = np.array([t.cols - 1 for t in tiles], dtype=float)
    r = np.array([t.rows - 1 for t in tiles], dtype=float)
    zero = np.zeros_like(c)
    cc, rr = np.stack([zero, c, zero, c]), np.stack([zero, zero, r, r])  # (4, n) corners
    lines = (a[:, 0] * cc + a[:, 1] * rr) + a[:, 2]
    size = np.abs(a[:, 0]) * cc + np.abs(a[:, 1]) * rr + np.abs(a[:, 2])
    bound = _LINE_ROUNDING * size + 1e-300
    with np.errstate(invalid="ignore"):
        near = (lines - np.floor(lines) <= bound) | (np.ceil(lines) - lines <= bound)
    unsure = ~np.all(np.isfinite(lines), axis=0) | np.any(near, axis=0)
    for i in np.flatnonzero(unsure):
        lines[:, i] = _corner_lines(tiles[i])
    return lines.min(axis=0), lines.max(axis=0)


def plan_blocks(geom: SceneGeometry, grid: OutputGrid, lines: int) -> list[Block]:
    """Column blocks of the output with the tiles they contain and the lines they need."""
    tiles = plan_tiles(geom, grid, tile=BLOCK_COLS, tile_rows=TILE_ROWS)
    groups: dict[int, list[int]] = {}
    for i, t in enumerate(tiles):
        groups.setdefault(t.col0 // BLOCK_COLS, []).append(i)
    tile_lo, tile_hi = _tile_line_spans(tiles) if tiles else (np.empty(0), np.empty(0))
    blocks = []
    for b in sorted(groups):
        idx = groups[b]
        lo, hi = float(tile_lo[idx].min()), float(tile_hi[idx].max())
        col0 = b * BLOCK_COLS
        cols = min(BLOCK_COLS, grid.width - col0)
        blocks.append(
            Block(
                col0,
                cols,
                [tiles[i] for i in idx],
                int(np.clip(np.floor(lo) - LINE_MARGIN, 0, lines)),
                int(np.clip(np.ceil(hi) + LINE_MARGIN, 0, lines - 1)),
            )
        )
    return blocks


class Decision(StrEnum):
    """What the streaming policy decides for a pair (:func:`decide_streams`)."""

    HOLD = "hold"  # the decision waits until navigation reaches ``until_ns``
    WHOLE = "whole"  # not streamed: its scenes are processed whole
    STREAM = "stream"  # stream it: predict the open scenes' parameters and open the stream


#: A side of a pair as the policy sees it: a scene still arriving (or a complete scene held
#: for the decision, as if open), or a scene already oriented (its result).
Part = tuple[str, OpenScene | SceneResult]


@dataclass(frozen=True)
class StreamDecision:
    """The streaming policy's decision for pair ``pair``; the :class:`Streamer` carries it out.

    ``parts``: the sides to stream, in view order (STREAM). ``held``: complete scenes held for
    the decision, by view, streamed at once (STREAM). ``until_ns``: the time navigation must
    reach (HOLD) or the decision time, the first line of the pair's later scene (STREAM).
    ``issue``: what to report (WHOLE; None: nothing to say).
    """

    pair: int
    kind: Decision
    parts: tuple[Part, ...] = ()
    held: Mapping[str, Scene] = field(default_factory=dict)
    until_ns: int = 0
    issue: Issue | None = None


@dataclass(frozen=True)
class NavState:
    """What the streaming policy reads of navigation.

    The newest and the first sample (ns, or None before any) and the largest gap between
    samples inside a scene (s).
    """

    last_ns: int | None
    first_ns: int | None
    max_gap_s: float


def undecided(ledger: PairLedger, scene: Scene) -> bool:
    """Whether ``scene``'s pair waits for navigation to decide streaming (held).

    Only a scene still arriving at the decision time counts: one complete before it would
    have been processed whole anyway.
    """
    t = ledger.held_until.get(scene.index)
    return t is not None and not ledger.decided(scene.index) and scene.last_line_ns >= t


def held(ledger: PairLedger, scene: Scene, nav_last_ns: int | None) -> bool:
    """Whether a complete scene is held for its pair's streaming decision.

    Undecided (:func:`undecided`), and navigation (newest sample ``nav_last_ns``) has not
    passed the scene yet (the bound).
    """
    return undecided(ledger, scene) and (nav_last_ns is None or nav_last_ns <= scene.last_line_ns)


def decide_streams(
    ledger: PairLedger,
    opened: Mapping[str, OpenScene | None],
    nav: NavState,
    config: PipelineConfig,
) -> list[StreamDecision]:
    """The streaming policy: a decision for each pair that can be decided now, in pair order.

    Pure: reads the ledger, the scenes open in each view (``opened``, in the configured view
    order) and navigation; changes nothing. A pair both of whose sides have begun (a scene
    open, a complete scene held for the decision, or an oriented scene waiting for its
    partner) is streamed, unless a held scene ended short, pair 0 may have begun before the
    pipeline listened (start unseen), or one view's strips stopped arriving (a short scene:
    processed whole). A pair with one side begun whose other scene, complete, waits for
    navigation that lags far behind is held (:meth:`Streamer.start` explains the hold). A
    pair with nothing to decide yet gets no decision. The decision for pair k reads only
    pair k's records, so the decisions may be carried out in order.
    """
    names = list(opened)
    pending = {o.index for o in opened.values() if o is not None} | set(ledger.held_until)
    lines = config.scenes.lines
    periods = {v.name: v.camera.line_period for v in config.views}
    decisions: list[StreamDecision] = []
    for k in sorted(pending):
        if ledger.decided(k):
            continue
        parts: list[Part] = []
        held_now: dict[str, Scene] = {}  # complete scenes held for the decision, by view
        waiting = False  # a complete scene of the pair waits for navigation
        for n in names:
            o = opened[n]
            sc = next((w for w in ledger.waiting if w.view == n and w.index == k), None)
            if o is not None and o.index == k:
                parts.append((n, o))
            elif k in ledger.ready[n]:
                parts.append((n, ledger.ready[n][k]))
            elif sc is not None and held(ledger, sc, nav.last_ns):
                held_now[n] = sc
                parts.append((n, OpenScene(sc.scene_id, k, sc.first_line_ns, sc.lines)))
            elif sc is not None:
                waiting = True
        if len(parts) < 2:
            opens = [p.first_line_ns for _, p in parts if not isinstance(p, SceneResult)]
            if (
                waiting
                and opens
                and k not in ledger.held_until
                and (nav.last_ns is None or nav.last_ns < max(opens) - nav.max_gap_s * 1e9)
            ):
                # The other scene, complete, waits for navigation, which lags far behind
                # this one's start: the decision waits for navigation.
                decisions.append(StreamDecision(k, Decision.HOLD, until_ns=max(opens)))
            continue
        short = [sc for sc in held_now.values() if sc.lines != lines]
        if short:
            issue = Issue(
                Level.WARN,
                f"pair {k}",
                "not streamed: navigation lagged behind the strips until "
                + ", ".join(f"{sc.view}/{sc.scene_id}" for sc in short)
                + f" ended short ({short[0].lines} of {lines} lines): processed whole",
            )
            decisions.append(StreamDecision(k, Decision.WHOLE, issue=issue))
            continue
        if k == 0 and any(
            not isinstance(part, SceneResult)
            and not start_seen(part.first_line_ns, nav.first_ns, config.navigation.start_margin_s)
            for _, part in parts
        ):
            # Perhaps the rest of a scene under way when the pipeline started: it will be
            # skipped when complete (orientation.start_unseen), not streamed.
            decisions.append(StreamDecision(k, Decision.WHOLE))
            continue
        # Time of the line after the last one received, per open scene (the period of the
        # first view with that open scene).
        ends = {
            o.scene_id: o.first_line_ns
            + o.lines * (next(periods[n] for n in names if opened[n] == o) * 1e9)
            for o in opened.values()
            if o is not None
        }
        newest = max(ends.values(), default=0)
        duration = lines * max(periods.values())
        stale_ns = max(STALE_MIN_S, duration) * 1e9
        overdue = [
            part
            for _, part in parts
            if not isinstance(part, SceneResult)
            and part.scene_id in ends
            and newest - ends[part.scene_id] > stale_ns
        ]
        if overdue:
            # Strips of a scene stopped coming while the other view went on (by more than
            # a scene, at least STALE_MIN_S): it is short (end of a pass) and its length is
            # unknown, so it is processed whole. A view merely delivered late is not stale.
            issue = Issue(
                Level.OK,
                f"pair {k}",
                "not streamed: the strips of "
                + ", ".join(p[0] for p in overdue)
                + " stopped arriving (a short scene): processed whole",
            )
            decisions.append(StreamDecision(k, Decision.WHOLE, issue=issue))
            continue
        decide_ns = max((p[2] for _, p in parts if not isinstance(p, SceneResult)), default=0)
        decisions.append(
            StreamDecision(k, Decision.STREAM, tuple(parts), held_now, until_ns=decide_ns)
        )
    return decisions


class SideEnd(StrEnum):
    """What a streamed side's complete scene means for its pair (:func:`side_end`)."""

    AS_PLANNED = "as_planned"  # its last blocks; the pair is made when both sides are done
    WHOLE = "whole"  # ended short before anything was published: the pair is made whole
    ABANDON = "abandon"  # ended short after blocks were published: the pair is released


def side_end(stream: StreamPair, scene: Scene) -> SideEnd:
    """The streaming policy at the end of a streamed side's scene. Pure.

    A scene of the planned length ends as planned. One that ended short (a stop, a gap) breaks
    the stream: when nothing was published or released yet the pair falls back to whole
    scenes, unseen; otherwise it is abandoned (what was published stays valid).
    """
    side = next(s for s in stream.sides.values() if s.view == scene.view)
    if scene.lines == side.lines:
        return SideEnd.AS_PLANNED
    if all(s.next_block == 0 for s in stream.sides.values()) and scene.released == 0:
        return SideEnd.WHOLE
    return SideEnd.ABANDON


def _next_block(
    stream: StreamPair, side: SideStream, b: Block, image: NDArray[np.generic], draft: bool
) -> BlockResult:
    """``side``'s next block ``b`` with its pixels ``image``, counted as emitted."""
    side.next_block += 1
    return BlockResult(
        stream.geometry.pair_id,
        side.side,
        side.next_block - 1,
        b.col0,
        image,
        side.grid,
        stream.stamp_ns,
        side.next_block == len(side.blocks),
        draft,
    )


class DraftReducer(Protocol):
    """Where draft blocks go when the render process reduces them (:attr:`Streamer.drafts`).

    The pipeline's: its quick-look tile levels.
    """

    def factors(self, stream: StreamPair) -> tuple[int, ...]:
        """The reduction each tile level holds of ``stream``'s blocks (0: that level none)."""
        ...

    def deliver(self, blk: BlockResult, reductions: list[NDArray[np.generic] | None]) -> None:
        """A draft block's reductions, one per level (``blk.image`` holds no pixels)."""
        ...


class Streamer:
    """The streaming of two-view pairs: the decisions, recorded in the ledger.

    It reads the pipeline's components (passed in, not owned): the assemblers (scenes under
    way and their retained lines), the navigation feed (samples), the GCP store (a scene with
    GCP is processed whole), and the ledger, where the pairs' state is (streams, pairs not
    streamed, decisions held for navigation, scenes waiting for navigation or their partner).
    A complete scene it does not stream is handed back (:meth:`scene_closed` returns None) for
    the pipeline to process whole. Times are nanoseconds.
    """

    def __init__(
        self,
        config: PipelineConfig,
        assemblers: Mapping[str, SceneAssembler],
        feed: NavigationFeed,
        gcps: GcpStore,
        ledger: PairLedger,
    ) -> None:
        self.config = config
        self.views = {v.name: v for v in config.views}
        self.assemblers = assemblers
        self.nav = feed.buffer
        self.feed = feed
        self.gcps = gcps
        self.ledger = ledger
        #: Renders blocks out of the caller's GIL (the node's), or None: in the calling thread.
        self.renderer: RenderProcess | None = None
        #: The DEM a stream's extent and heights are chosen at (the pipeline's, set by
        #: :meth:`~.pipeline.Pipeline.use_dem`), or None: its GCP's or the prior.
        self.dem: DemTerrain | None = None
        #: Takes each block as soon as it is rendered, instead of :attr:`Outputs.blocks`; its
        #: pixels may be a view of the render process's output, valid only during the call
        #: (copy them to keep them). With the render process the next block is rendered
        #: meanwhile. None: blocks are returned in the outputs.
        self.block_sink: Callable[[BlockResult], None] | None = None
        #: Side -> whether its next blocks may be drafts (:data:`DRAFT_INTERPOLATION`): they
        #: only feed the quick-look tiles, nobody takes the blocks themselves. None: never.
        self.draft: Callable[[str], bool] | None = None
        #: Takes the draft blocks' reductions (:meth:`_emit_drafts`: in the render process,
        #: not waited for, when there is one; else here), instead of the block sink taking
        #: the drafts at full resolution. None: drafts go through the block sink.
        self.drafts: DraftReducer | None = None

    def undecided(self, scene: Scene) -> bool:
        """Whether ``scene``'s pair waits for navigation to decide (:func:`undecided`)."""
        return undecided(self.ledger, scene)

    def held(self, scene: Scene) -> bool:
        """Whether a complete scene is held for its pair's streaming decision (:func:`held`)."""
        return held(self.ledger, scene, self.nav.last_ns)

    @property
    def can_stream(self) -> bool:
        """Whether streaming applies: enabled, two views, a configured scene length."""
        c = self.config
        return c.stream.enabled and not c.single_camera and c.scenes.lines > 0

    def scene_closed(self, scene: Scene) -> Outputs | None:
        """A scene is complete: the end of its stream; None: not streamed, to process whole."""
        stream = self.ledger.streams.get(scene.index)
        if stream is None or scene.view not in [s.view for s in stream.sides.values()]:
            return None
        return self._close(stream, scene)

    def start(self) -> Outputs:
        """Start streaming pair k once the scenes of both sides have begun (or one is done).

        A side whose scene is still arriving gets parameters extrapolated from the latest
        navigation; a side whose scene is already complete (fore/aft cameras: the aft camera
        sees the same ground later) keeps its parameters, and its blocks are emitted as the
        other side's are (paced, :data:`PACED_LEAD_BLOCKS` ahead).
        When navigation lags behind the strips (separate topics, no ordering between them), the
        decision is held (:attr:`PairLedger.held_until`: pair -> the decision time, the first
        line of the later scene) until navigation reaches that time; a scene still arriving
        then but completed in the meantime is held too (it waits for navigation anyway) and
        streamed at once, and a scene completed before it is processed whole first, as it would
        have been. So the outputs do not depend on the order in which the topics were delivered.
        """
        out = Outputs()
        ledger = self.ledger
        ledger.release_decided_holds()
        opened = {v.name: self.assemblers[v.name].open_scene() for v in self.config.views}
        nav = NavState(self.nav.last_ns, self.feed.first_ns, self.nav.max_gap_s)
        for decision in decide_streams(ledger, opened, nav, self.config):
            if decision.kind is not Decision.STREAM:
                self._record(decision, out)
                continue
            k = decision.pair
            results: list[SceneResult] = []
            for name, part in decision.parts:
                if isinstance(part, SceneResult):
                    results.append(part)
                    continue
                sc = decision.held.get(name)
                res = self._predict_scene(
                    name, part, decision.until_ns, None if sc is None else sc.image.dtype
                )
                if not isinstance(res, SceneResult):
                    if res is not None:
                        self._record(res, out)
                    return out
                results.append(res)
            if k in ledger.not_streamed:
                continue
            out.extend(self._open_stream(k, results))
            stream = ledger.streams.get(k)
            if stream is not None:
                if k in ledger.held_until:
                    out.issues.append(
                        Issue(
                            Level.OK,
                            f"pair {stream.geometry.pair_id}",
                            "navigation reached the scenes' start after their first strips: "
                            "streaming decision held until then",
                        )
                    )
                for sc in decision.held.values():
                    ledger.waiting.remove(sc)
                    closed = self._close(stream, sc)
                    if closed is None:  # not streamed after all: waits for navigation again
                        ledger.waiting.append(sc)
                    else:
                        out.extend(closed)
        return out

    def _record(self, decision: StreamDecision, out: Outputs) -> None:
        """Record a HOLD or WHOLE decision in the ledger; its issue, if any, goes to ``out``."""
        if decision.kind is Decision.HOLD:
            self.ledger.hold(decision.pair, decision.until_ns)
        elif decision.kind is Decision.WHOLE:
            self.ledger.not_stream(decision.pair)
        if decision.issue is not None:
            out.issues.append(decision.issue)

    def _predict_scene(
        self,
        name: str,
        opened: OpenScene,
        decide_ns: int,
        dtype: np.dtype | None = None,
    ) -> SceneResult | StreamDecision | None:
        """Parameters of a scene that has just started, from the latest navigation.

        ``decide_ns``: the decision time (the first line of the pair's later scene). When
        navigation has not reached within ``max_gap_s`` of the scene start then (it lags:
        separate topics), the pair waits (held) until navigation reaches the
        decision time, and the motion is then fitted on the navigation up to that time only,
        as an on-time decision would have been. None: not yet possible (navigation has not
        reached the decision time); a HOLD or WHOLE decision: not possible now, for
        :meth:`_record`.
        """
        sid, k, t0, _ = opened
        if self.gcps.count(sid) >= self.config.orientation.min_gcp:
            return StreamDecision(k, Decision.WHOLE)  # GCP-based parameters: the whole scene
        view = self.views[name]
        lines = self.config.scenes.lines
        until = self.ledger.held_until.get(k)
        last = self.nav.last_ns
        if until is not None and (last is None or last < until):
            return None  # navigation has not reached the decision time yet: keep waiting
        try:
            fit = self.nav.fit_recent(t0, view.mounting, until_ns=until)
        except NavigationError as err:
            if until is None:  # navigation lags: wait for it (see above)
                return StreamDecision(k, Decision.HOLD, until_ns=decide_ns)
            return StreamDecision(
                k,
                Decision.WHOLE,
                issue=Issue(
                    Level.WARN,
                    f"{name}/{sid}",
                    f"not streamed (navigation at the scene start: {err}): processed whole",
                ),
            )
        model = PushbroomModel(view.camera, fit.motion)
        try:
            nav = parameters_from_navigation(
                model,
                line_mid=(lines - 1) / 2.0,
                z_avg=self.config.orientation.z_avg,
                scene_lines=lines,
                height_range=self.config.orientation.height_range,
                crab_tolerance_px=self.config.orientation.crab_tolerance_px,
            )
        except GeometryError as err:
            return StreamDecision(
                k,
                Decision.WHOLE,
                issue=Issue(
                    Level.WARN, f"{name}/{sid}", f"cannot stream ({err}): whole-scene processing"
                ),
            )
        if dtype is None:
            dtype = self.assemblers[name].retained()[1].dtype
        placeholder = Scene(
            name,
            sid,
            k,
            t0,
            view.camera.line_period,
            np.empty((0, view.camera.detectors), dtype=dtype),
            0,
            SceneEnd.STREAMING,
            lines,
        )
        return SceneResult.from_navigation(
            placeholder,
            nav,
            model,
            view.camera,
            note_suffix="; extrapolated from the navigation at the scene start (streaming)",
        )

    def _open_stream(self, k: int, results: list[SceneResult]) -> Outputs:
        out = Outputs()
        lines = (results[0].scene.lines, results[1].scene.lines)
        made = pair_geometry(results[0], results[1], lines, self.config, self.gcps, self.dem)
        if self.dem is not None:  # the DEM's issues with this pair, whatever came of it
            out.issues += self.dem.take_issues()
        if isinstance(made, Issue):
            self._record(StreamDecision(k, Decision.WHOLE, issue=made), out)
            return out
        geo, terrain = made
        sides: dict[str, SideStream] = {}
        for name, res, geom, grid in (
            ("left", results[0], geo.left_geom, geo.left_grid),
            ("right", results[1], geo.right_geom, geo.right_grid),
        ):
            sides[name] = SideStream(
                name,
                res.scene.view,
                res,
                geom,
                grid,
                res.scene.lines,
                plan_blocks(geom, grid, res.scene.lines),
            )
        stamp = max(r.scene.last_line_ns for r in results)
        from_dem = terrain if terrain.source == TerrainSource.DEM else None
        stream = StreamPair(k, geo, sides, stamp, terrain=from_dem)
        self.ledger.stream(stream)
        if from_dem is not None:  # which heights its extent and tiles search, and whence
            out.issues.append(terrain_issue(geo.pair_id, from_dem))
        out.issues.append(
            Issue(
                Level.OK,
                f"pair {geo.pair_id}",
                f"streaming: {geo.left_grid.width} x {geo.left_grid.height} px in "
                f"{len(sides['left'].blocks)} + {len(sides['right'].blocks)} column blocks",
            )
        )
        for side in sides.values():
            if side.result.scene.image.shape[0] > 0:  # a side that was already complete
                self.ledger.ready[side.view].pop(k, None)
                closed = self._close(stream, side.result.scene, prefetched=True)
                if closed is None:  # not streamed after all: it waits for its partner again
                    self.ledger.ready[side.view][k] = side.result
                else:
                    out.extend(closed)
        return out

    def _emit_blocks(
        self,
        stream: StreamPair,
        side: SideStream,
        received: int,
        data: NDArray[np.generic],
        first: int,
        complete: bool,
        limit: int | None = None,
    ) -> Outputs:
        """Render and emit ``side``'s next blocks that ``received`` lines complete.

        ``complete``: every line is there (the scene is complete); ``limit``: emit none of
        index ``limit`` or more (a paced side).
        """
        out = Outputs()
        ready = []
        for b in side.blocks[side.next_block : limit]:
            if not complete and b.max_line >= received:
                break
            ready.append(b)
        if not ready:
            return out
        interp = interpolation_flag(self.config.output)
        draft = self.draft is not None and self.draft(side.side)
        if draft:
            interp = DRAFT_INTERPOLATION
            if self.drafts is not None:
                self._emit_drafts(stream, side, ready, data, first, self.drafts)
                return out
        nodata = self.config.output.nodata
        sink = self.block_sink
        rendered: Generator[tuple[Block, NDArray[np.generic] | None], None, None]
        if self.renderer is not None:
            rendered = self.renderer.render_blocks(
                ready, data, first, side.grid.height, nodata=nodata,
                interpolation=interp,
            )  # fmt: skip
        else:
            rendered = ((b, None) for b in ready)
        with closing(rendered):
            for b, img in rendered:
                if img is None:
                    img = render_block(
                        b,
                        data,
                        first,
                        side.grid,
                        nodata=nodata,
                        interpolation=interp,
                    )
                elif sink is None:
                    img = img.copy()  # a view of the render process's output buffer
                blk = _next_block(stream, side, b, img, draft)
                if sink is None:
                    out.blocks.append(blk)
                else:
                    sink(blk)
        return out

    def _emit_drafts(
        self,
        stream: StreamPair,
        side: SideStream,
        ready: list[Block],
        data: NDArray[np.generic],
        first: int,
        to: DraftReducer,
    ) -> None:
        """``ready`` as draft blocks, sampled every :func:`draft_stride` pixels and reduced.

        With the render process, there and not waited for: each block's reductions reach
        ``to`` when its answers are collected (:meth:`RenderProcess.poll`,
        :meth:`RenderProcess.drain`); a block it cannot render is rendered and reduced here,
        then or at once. Without, here at once. The block handed over holds no pixels (a
        read-only broadcast of the no-data value, of the block's shape).
        """
        renderer = self.renderer
        factors = to.factors(stream)
        stride = draft_stride(factors)
        interp = DRAFT_INTERPOLATION if stride == 1 else DRAFT_STRIDED_INTERPOLATION
        nodata = self.config.output.nodata
        grid = side.grid
        for b in ready:
            none = np.broadcast_to(np.asarray(nodata, dtype=data.dtype), (grid.height, b.cols))
            blk = _next_block(stream, side, b, none, True)

            def deliver(
                reductions: list[NDArray[np.generic] | None] | None,
                b: Block = b,
                blk: BlockResult = blk,
            ) -> None:
                if reductions is None:  # no process, or it could not: here
                    img = render_block(
                        b, data, first, grid, nodata=nodata, interpolation=interp,
                        stride=stride,
                    )  # fmt: skip
                    reductions = [
                        reduce_block(img, f // stride, nodata) if f > 0 else None for f in factors
                    ]
                to.deliver(blk, reductions)

            if not any(f > 0 for f in factors):
                to.deliver(blk, [None] * len(factors))  # no level takes it: nothing to render
            elif renderer is None or not renderer.submit_reduced(
                b, data, first, grid.height, nodata=nodata, interpolation=interp,
                factors=factors, stride=stride, deliver=deliver,
            ):  # fmt: skip
                deliver(None)

    def advance(self, view: str) -> Outputs:
        """Emit the blocks of ``view``'s streamed scene that its lines received so far complete.

        Lines no later block needs are released from the assembler.
        """
        out = Outputs()
        asm = self.assemblers[view]
        opened = asm.open_scene()
        if opened is None:
            return out
        stream = self.ledger.streams.get(opened.index)
        if stream is None:
            return out
        for side in stream.sides.values():
            if side.view != view or side.done:
                continue
            first, data = asm.retained()
            out.extend(self._emit_blocks(stream, side, opened.lines, data, first, False))
            if side.next_block > 0:  # keep every line until the stream has really begun
                asm.release(side.needed_from())
        out.extend(self._emit_paced(stream))
        return out

    def _emit_paced(self, stream: StreamPair, flush: bool = False) -> Outputs:
        """The blocks of ``stream``'s paced sides (complete at its opening) now due.

        Due: up to :data:`PACED_LEAD_BLOCKS` beyond the other side's emitted blocks, or all
        of them (``flush``: the other side is complete too).
        """
        out = Outputs()
        for side in stream.sides.values():
            if not side.paced:
                continue
            other = next(s for s in stream.sides.values() if s is not side)
            limit = None if flush else other.next_block + PACED_LEAD_BLOCKS
            sc = stream.scenes[side.side]
            out.extend(
                self._emit_blocks(stream, side, sc.lines, sc.image, sc.released, True, limit)
            )
            side.paced = side.next_block < len(side.blocks)
        return out

    def _close(self, stream: StreamPair, scene: Scene, prefetched: bool = False) -> Outputs | None:
        """A streamed side's scene is complete: its last blocks, and the pair if both are.

        ``prefetched``: the scene was complete before the stream started (its result is known;
        no parameters are published for it again). None: the scene ended short before anything
        was published: the pair is not streamed, the scene is to be processed whole.
        """
        out = Outputs()
        side = next(s for s in stream.sides.values() if s.view == scene.view)
        where = f"{scene.view}/{scene.scene_id}"
        end = side_end(stream, scene)
        if end is not SideEnd.AS_PLANNED:
            self.ledger.end_stream(stream.index)
            self.ledger.not_stream(stream.index)
            if end is SideEnd.WHOLE:
                # Nothing was published or released yet: fall back to whole scenes, unseen.
                for s in stream.sides.values():
                    if s.prefetched or (s.done and s.result.scene.image.shape[0] > 0):
                        self.ledger.ready[s.view][stream.index] = s.result
                return None
            self.ledger.release(stream.index)
            out.issues.append(
                Issue(
                    Level.ERROR,
                    where,
                    f"scene ended after {scene.lines} of {side.lines} lines ({scene.reason}): "
                    f"streamed pair {stream.geometry.pair_id} abandoned after "
                    f"{side.next_block} of {len(side.blocks)} blocks; the blocks published "
                    "so far stay valid, the pair is not completed",
                )
            )
            return out
        side.done = True
        side.prefetched = prefetched
        stream.scenes[side.side] = scene
        # A side complete when its stream opens is paced: its blocks go out with the other
        # side's (:meth:`_emit_paced`), not all in the input that opened the stream.
        side.paced = prefetched
        both = all(s.done for s in stream.sides.values())
        if not prefetched:
            out.extend(
                self._emit_blocks(stream, side, scene.lines, scene.image, scene.released, True)
            )
        out.extend(self._emit_paced(stream, flush=both))
        if not both:
            return out
        self.ledger.end_stream(stream.index)
        results = []
        for s in (stream.sides["left"], stream.sides["right"]):
            results.append(s.result)
            if s.prefetched:
                continue  # published when its scene completed
            check = self._check_extrapolation(s)
            if check is not None:
                out.issues.append(check)
            out.scenes.append(s.result)
            self.ledger.done_with(s.result.scene, s.result.method)
        out.pairs.append(
            finish_pair(
                results[0],
                results[1],
                stream.geometry,
                (None, None),
                stream.stamp_ns,
                config=self.config,
                gcps=self.gcps,
                ledger=self.ledger,
                terrain=stream.terrain,
            )
        )
        return out

    def _check_extrapolation(self, side: SideStream) -> Issue | None:
        """Compare the extrapolated motion with a fit on the scene's own navigation."""
        res = side.result
        sc = res.scene
        if res.model is None or not self.nav.covers(sc.first_line_ns, sc.last_line_ns):
            return None
        try:
            fit = self.nav.fit(sc.first_line_ns, sc.last_line_ns, self.views[sc.view].mounting)
        except NavigationError:
            return None
        actual = PushbroomModel(res.camera, fit.motion)
        pts = virtual_points(
            res.model,
            (0.0, sc.lines - 1.0),
            [
                self.config.orientation.z_avg - self.config.orientation.height_range,
                self.config.orientation.z_avg + self.config.orientation.height_range,
            ],
            grid=5,
        )
        diff = float(np.abs(actual.project(pts) - res.model.project(pts)).max())
        if diff > 0.1:
            return Issue(
                Level.WARN,
                f"{sc.view}/{sc.scene_id}",
                (
                    f"the motion extrapolated at the scene start differs from the scene's "
                    f"navigation by up to {diff:.3f} px: the streamed pair carries that error"
                ),
            )
        return None
