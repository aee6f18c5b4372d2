"""The ledger of pairs: the one owner of every pair's record and state in the pipeline.

A pair's life (paper 2 section 4 applied to a stream) crosses several policies: the navigation
feed (a complete scene waits until navigation covers it), the pairing (an oriented scene waits
for its partner; single-camera selections), the streaming (a pair normalized by column blocks
while its scenes arrive, or a decision held until navigation reaches the scenes). Those policies
keep no state of their own: they read the :class:`PairLedger` and record their decisions in it,
so one object answers "where is pair k?" (:meth:`PairLedger.state`) and the node's summary
reports it (:meth:`PairLedger.counts`).

States (:class:`PairState`): ``waiting`` (scenes arriving, or waiting for navigation or their
partner), ``held`` (the streaming decision waits for navigation), ``streaming`` (column blocks
emitted as lines arrive), ``whole`` (decided: normalized from whole scenes), ``made`` (its
:class:`~parproj_ros.core.results.PairResult` returned), ``released`` (given up: its stream
broke after blocks were published; what was published stays valid). Pair k is the k-th
scenes of two views; single-camera pairs are named by their scene ids and their state is that
of their scenes. Times are nanoseconds.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

from ..imaging.assembly import Scene
from ..imaging.resample import OutputGrid, SceneGeometry, Tile
from .results import PairGeometry, SceneResult
from .terrain import Terrain

#: Scenes done with, and single-camera pairs made, remembered (the latest ones) so that late
#: inputs naming them are reported.
DONE_KEPT = 256
MADE_KEPT = 1024
#: Admission decisions and scenes' arrival pairs remembered (the latest ones; pairs still in
#: flight are always kept).
ADMISSION_KEPT = 64
ADMISSION_SCENES_KEPT = 256


class PairState(StrEnum):
    """Where a pair is (:meth:`PairLedger.state`)."""

    WAITING = "waiting"
    HELD = "held"
    STREAMING = "streaming"
    WHOLE = "whole"
    MADE = "made"
    RELEASED = "released"


@dataclass
class Block:
    """One column block of a streamed side: its tiles and the scan lines they need."""

    col0: int
    cols: int
    tiles: list[Tile]
    min_line: int
    max_line: int


@dataclass
class SideStream:
    """The streaming record of one side (left, right) of a pair."""

    side: str
    view: str
    result: SceneResult
    geom: SceneGeometry
    grid: OutputGrid
    lines: int
    blocks: list[Block]
    next_block: int = 0
    done: bool = False
    prefetched: bool = False
    #: Complete when its stream opened, and blocks of it still to emit: they go out as the
    #: other side's do (:data:`~parproj_ros.core.streaming.PACED_LEAD_BLOCKS` ahead).
    paced: bool = False

    def needed_from(self) -> int:
        """First line any block still to come needs."""
        rest = self.blocks[self.next_block :]
        return min((b.min_line for b in rest), default=self.lines)


@dataclass
class StreamPair:
    """The streaming record of pair k: its geometry, both sides, the scenes completed."""

    index: int
    geometry: PairGeometry
    sides: dict[str, SideStream]
    stamp_ns: int
    scenes: dict[str, Scene] = field(default_factory=dict)
    #: The heights its geometry was chosen at when a DEM gave them (source ``dem``), else
    #: None (its GCP's or the prior, taken again when it is finished).
    terrain: Terrain | None = None


class AdmissionBook:
    """The admission's records of pairs (:mod:`parproj_ros.core.admission`), kept here.

    The admission decides at a pair's first strip, in the node's subscription callbacks,
    before the pipeline sees the strip; so its pairs are numbered in arrival order, shed ones
    included (arrival pair g: the g-th scenes of each view since the start; single camera:
    scenes 2g and 2g+1), not as the pipeline numbers the pairs it receives. Records: the
    decision per arrival pair (admitted or shed), the pairs in flight (admitted, their
    StereoPair not yet published), each scene's arrival pair, and whether the quick-look
    tiles are shed. Thread-safe: the callbacks decide, the worker publishes, the summary
    reads.
    """

    def __init__(self) -> None:
        self._decided: dict[int, bool] = {}
        self._in_flight: set[int] = set()
        self._scene_pair: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()
        #: The quick-look tiles are shed (:func:`~parproj_ros.core.admission.decide_quicklook`):
        #: set by the admission, read by the pipeline's tile stage (one bool: no lock needed).
        self.quicklook_shed = False

    def decision(self, pair: int) -> bool | None:
        """Whether arrival pair ``pair`` was admitted; None: not decided."""
        with self._lock:
            return self._decided.get(pair)

    def decide(self, pair: int, admitted: bool) -> None:
        """Record the admission's decision for arrival pair ``pair`` (in flight if admitted)."""
        with self._lock:
            self._decided[pair] = admitted
            if admitted:
                self._in_flight.add(pair)
            if len(self._decided) > ADMISSION_KEPT:
                for g in sorted(self._decided)[: len(self._decided) - ADMISSION_KEPT]:
                    if g not in self._in_flight:
                        del self._decided[g]

    def scene(self, view: str, scene_id: str, pair: int) -> None:
        """Scene ``scene_id`` of ``view`` belongs to arrival pair ``pair``."""
        with self._lock:
            self._scene_pair[(view, scene_id)] = pair
            if len(self._scene_pair) > ADMISSION_SCENES_KEPT:
                for key in list(self._scene_pair)[: len(self._scene_pair) - ADMISSION_SCENES_KEPT]:
                    del self._scene_pair[key]

    def published(self, view: str, scene_id: str) -> None:
        """A pair with this scene was published: its arrival pair and earlier ones leave.

        A scene id of the pipeline's own (not an arrival's): pairs come out in order, so it is
        the oldest pair in flight.
        """
        with self._lock:
            pair = self._scene_pair.get((view, scene_id))
            if pair is None and self._in_flight:
                pair = min(self._in_flight)
            if pair is not None:
                self._in_flight = {g for g in self._in_flight if g > pair}

    def release_all(self) -> None:
        """Nothing is in flight any more (the flush at stop, or a scene timeout)."""
        with self._lock:
            self._in_flight.clear()

    @property
    def in_flight(self) -> int:
        """Arrival pairs admitted and not yet published."""
        with self._lock:
            return len(self._in_flight)


class PairLedger:
    """Every pair's record and state; the policies read it and record their decisions here.

    Attributes:
        waiting: complete scenes that navigation does not cover yet, in completion order.
        ready: oriented scenes waiting for their partner: view -> pair index (single camera:
            the acquisition) -> result.
        streams: the streamed pairs under way, by pair index.
        not_streamed: pairs decided not to stream (made from whole scenes).
        held_until: pairs whose streaming decision waits for navigation -> the time it must
            reach (the first line of the pair's later scene).
        done: the latest scenes done with (processed or skipped): scene id -> (view, method).
        selection: single-camera pair selection still to make ((left, right) scene ids, in
            order); None: acquisitions 2k and 2k+1 pair up.
        made: the latest single-camera pairs made (their two scene ids).
        pairs_made: pairs whose result was returned.
        admission: the node's admission records (:class:`AdmissionBook`: pairs admitted or
            shed as they arrive, pairs in flight).
    """

    def __init__(self, views: Sequence[str]) -> None:
        self.waiting: list[Scene] = []
        self.ready: dict[str, dict[int, SceneResult]] = {v: {} for v in views}
        self.streams: dict[int, StreamPair] = {}
        self.not_streamed: set[int] = set()
        self.held_until: dict[int, int] = {}
        self.done: dict[str, tuple[str, str]] = {}
        self.selection: list[tuple[str, str]] | None = None
        self.made: dict[frozenset[str], None] = {}
        self.pairs_made = 0
        self._made_index: dict[int, None] = {}
        self._released: dict[int, None] = {}
        self.admission = AdmissionBook()

    # ---- what the policies record ----------------------------------------------------------
    def stream(self, stream: StreamPair) -> None:
        """Pair ``stream.index`` streams from now on."""
        self.streams[stream.index] = stream

    def end_stream(self, index: int) -> None:
        """Pair ``index`` streams no more (complete, or abandoned)."""
        self.streams.pop(index, None)

    def not_stream(self, index: int) -> None:
        """Pair ``index`` is not streamed: its scenes are processed whole."""
        self.not_streamed.add(index)

    def hold(self, index: int, until_ns: int) -> None:
        """Pair ``index``'s streaming decision waits until navigation reaches ``until_ns``."""
        self.held_until[index] = until_ns

    def decided(self, index: int) -> bool:
        """Whether pair ``index`` streams or was decided not to."""
        return index in self.streams or index in self.not_streamed

    def release_decided_holds(self) -> None:
        """Forget the holds of the pairs decided since."""
        for k in [k for k in self.held_until if self.decided(k)]:
            del self.held_until[k]

    def end_of_data(self) -> None:
        """No more data: no streaming decision waits for navigation any more."""
        self.held_until.clear()

    def pair_made(self, index: int) -> None:
        """The result of pair ``index`` was returned: nothing about it needs remembering."""
        self.pairs_made += 1
        self.not_streamed.discard(index)
        self._made_index[index] = None
        while len(self._made_index) > MADE_KEPT:
            del self._made_index[next(iter(self._made_index))]

    def release(self, index: int) -> None:
        """Pair ``index`` is given up (its stream broke): it will not be made (nor streamed)."""
        self.end_stream(index)
        self.not_streamed.add(index)
        self._released[index] = None
        while len(self._released) > MADE_KEPT:
            del self._released[next(iter(self._released))]

    def done_with(self, scene: Scene, method: str) -> None:
        """A scene is done with (``method``, or "skipped"); the latest :data:`DONE_KEPT` kept."""
        self.done[scene.scene_id] = (scene.view, method)
        while len(self.done) > DONE_KEPT:
            del self.done[next(iter(self.done))]

    def mark_made(self, left: str, right: str) -> None:
        """A single-camera pair was made (the latest :data:`MADE_KEPT` kept)."""
        self.made[frozenset((left, right))] = None
        while len(self.made) > MADE_KEPT:
            del self.made[next(iter(self.made))]

    # ---- what anyone may ask ----------------------------------------------------------------
    def selected_scene_ids(self) -> set[str]:
        """Scene ids that a selected pair not made yet still needs."""
        return {s for pair in self.selection or () for s in pair}

    def state(self, index: int) -> PairState:
        """Where pair ``index`` (two views: the k-th scenes) is."""
        if index in self.streams:
            return PairState.STREAMING
        if index in self._released:
            return PairState.RELEASED
        if index in self.held_until and index not in self.not_streamed:
            return PairState.HELD
        if index in self.not_streamed:
            return PairState.WHOLE
        if index in self._made_index:
            return PairState.MADE
        return PairState.WAITING

    def first_lines(self) -> list[int]:
        """First line times of the streamed pairs' scenes (the navigation they still need)."""
        return [
            side.result.scene.first_line_ns
            for stream in self.streams.values()
            for side in stream.sides.values()
        ]

    def counts(self) -> dict[str, int]:
        """The ledger at a glance (the node's summary): pairs and scenes in each state.

        Read from another thread (the node's 1 Hz summary), so only whole-dict copies are
        iterated.
        """
        return {
            "pairs_streaming": len(self.streams),
            "pairs_held": sum(1 for k in list(self.held_until) if not self.decided(k)),
            "scenes_waiting_navigation": len(self.waiting),
            "scenes_waiting_partner": sum(len(r) for r in self.ready.values()),
            "pairs_made": self.pairs_made,
            "pairs_released": len(self._released),
        }
