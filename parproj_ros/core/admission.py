"""Admission of whole pairs under a memory budget: the node's overload policy, ROS-free.

The node asks :class:`PairAdmission` at the first strip of each scene whether its pair may be
taken (its subscription callbacks run it, so it is thread-safe); a pair refused is shed whole,
before conversion or queueing (docs/node.md, "Overload"). The policy itself is pure:
:func:`decide_admission` takes the pairs in flight and the memory terms (:class:`MemoryTerms`)
and returns the decision with its reason. :class:`PairAdmission` does the rest: it follows each
view's strips to tell which pair a strip belongs to, reads the process memory
(:mod:`parproj_ros.core.memory`) and the raw data the node holds, learns the working set, and
records each decision in the ledger's :class:`~parproj_ros.core.ledger.AdmissionBook` (pairs
admitted or shed, pairs in flight). It knows nothing of rclpy.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..imaging.assembly import SceneAssembler
from .ledger import AdmissionBook
from .memory import (
    held_bytes,
    malloc_trim,
    prefault_heap,
    raw_pair_bytes,
    rss_bytes,
    tune_malloc,
)
from .results import Issue, Level


def auto_prefault_mb(config: Any) -> float:
    """``prefault_mb`` -1: two raw pairs of the configured scenes, MB (0 without scene_lines).

    scene_lines x detectors x 2 bytes (uint16; an upper bound for 8-bit strips) summed over
    the views, twice: 1476 MB for two IKONOS-size views (14000 x 13816), the reserve with
    which the node keeps up at the full rate (bench/BENCHMARKS.md).
    """
    return float(2.0 * raw_pair_bytes(config) / 2**20)


#: Raw pairs' worth of memory the node is first assumed to need besides the pairs in flight
#: (the normalized images of the pair being finished, the messages being serialized); the
#: admission then learns the working set from the resident memory (the benchmark, streaming:
#: peak RSS 3.6 raw pairs above the start-up memory with 2-3 pairs in flight; whole images at
#: 2048 x 2048: about 13).
WORKING_SET_PAIRS = 2
#: The same when pairs are normalized as whole images (not streamed: ``streaming`` false, or
#: ``scene_lines`` 0, or one view), as raw pairs plus a fixed amount: both normalized images,
#: their messages and what DDS copies of them. At 2048 x 2048 (16 MB pairs) the memory held
#: beyond start-up and raw data was 52-89 MB and the resident memory 100-145 MB
#: (tests/ros/test_overload_live.py, 2026-11-24); 64 MB + 4 pairs (128 MB there) kept the
#: resident memory under the budget in that test, and at IKONOS size (738 MB pairs) it is
#: 3 GB, so that the default budget still holds 3 pairs.
WHOLE_IMAGE_WORKING_SET_PAIRS = 4
WHOLE_IMAGE_WORKING_SET_MB = 64.0
#: Least time between two returns of the free heap to the system by :meth:`PairAdmission.sample`
#: (each costs milliseconds, and the pages given back cost 2.2 ms per MB to touch again), s.
TRIM_INTERVAL_S = 1.0
#: :meth:`PairAdmission.sample` reads the memory at most this often, seconds. Each reading
#: gives the GIL back twice (``/proc/self/statm``, ``mallinfo2``) and the worker then waits
#: for the executor to finish taking a strip (rclpy holds the GIL for it): at the IKONOS rate
#: the readings after every input were 10 % of the worker's samples (py-spy, 10 pairs, 1/8).
SAMPLE_INTERVAL_S = 0.05
#: Resident memory samples (two per pair: at its decision and at its publication) over which
#: the working set is the largest.
WORKING_SET_SAMPLES = 4
#: Share of ``memory_budget_mb`` the admission leaves free: what it cannot foresee, the strips
#: DDS holds before the executor takes them and heap fragmentation (the overload test went
#: 1-4 % over its budget without it, 2026-11-24).
HEADROOM = 0.05


def working_set_floor(config: Any) -> tuple[float, float]:
    """(raw pairs, MB): the least working set the admission assumes for this configuration.

    Streamed pairs (``streaming``, a ``scene_lines``, two views: what :class:`Streamer` needs)
    hold column blocks; the others are normalized as whole images.
    """
    if config.stream.enabled and config.scenes.lines > 0 and not config.single_camera:
        return float(WORKING_SET_PAIRS), 0.0
    return float(WHOLE_IMAGE_WORKING_SET_PAIRS), WHOLE_IMAGE_WORKING_SET_MB


@dataclass(frozen=True)
class MemoryTerms:
    """The figures an admission decision reads, bytes (:class:`PairAdmission`'s rule).

    ``startup``: memory held at the first strip less its raw data; ``raw``: raw scene data held
    now; ``pair``: one raw pair (both scenes); ``work``: the working set counted (learnt, or
    its floor); ``budget``: ``memory_budget_mb``; ``usable``: the budget less
    :data:`HEADROOM`; ``tiles``: what the streamed DSM tiles hold now (the columns kept for
    tiles still to come: :meth:`~parproj_ros.core.tiles.TileStage.held_bytes`).
    """

    startup: int
    raw: int
    pair: int
    work: int
    budget: int
    usable: int
    tiles: int = 0

    def need(self, in_flight: int, raw: int = 0) -> int:
        """Memory to admit a pair with ``in_flight`` pairs already in flight, bytes."""
        return self.startup + max(raw, (in_flight + 1) * self.pair) + self.tiles + self.work


def decide_admission(in_flight: int, terms: MemoryTerms) -> tuple[bool, str]:
    """The admission policy: whether a new pair may be taken, and why not. Pure.

    With nothing in flight a pair is always admitted (the node can hold no less). Otherwise it
    is admitted when start-up + max(raw data held, (pairs in flight + 1) x raw pair) + the
    streamed tiles' columns + working set is within the usable budget. The reason names every
    term, and, when the budget cannot hold two pairs in flight (consecutive pairs overlap in
    time, so it sheds at any rate), the budget that would.
    """
    if not in_flight:
        return True, ""
    need = terms.need(in_flight, terms.raw)
    if need <= terms.usable:
        return True, ""
    mb = 2**20
    least = terms.need(1)
    short = (
        f" (the budget cannot hold two pairs in flight, which consecutive pairs need at "
        f"any rate: memory_budget_mb >= {math.ceil(least / (1 - HEADROOM) / mb)} would)"
        if least > terms.usable
        else ""
    )
    n, pair = in_flight, terms.pair
    tiles = f" + streamed tiles {terms.tiles / mb:.0f} MB" if terms.tiles else ""
    return False, (
        f"{n} pairs in flight; with this one it would need {need / mb:.0f} MB "
        f"(start-up {terms.startup / mb:.0f} MB + raw data "
        f"{max(terms.raw, (n + 1) * pair) / mb:.0f} MB, {n + 1} x {pair / mb:.0f} MB or what is "
        f"held{tiles} + working set {terms.work / mb:.0f} MB), over {terms.usable / mb:.0f} MB "
        f"(memory_budget_mb {terms.budget / mb:.0f} MB less {HEADROOM:.0%} headroom)"
        f"{short}"
    )


def decide_quicklook(
    in_flight: int, terms: MemoryTerms, admitted: bool, shed: bool
) -> tuple[bool, str]:
    """Whether the quick-look tiles are shed from the pair just decided on, and why. Pure.

    The quick-look (``heights_quicklook``) is the work the node gives up first: it is shed one
    pair before any pair is, when the pair just decided on (with ``in_flight`` pairs in flight
    before it) was shed, or when one more pair in flight after it would not fit the usable
    budget (:meth:`MemoryTerms.need` of ``in_flight`` + 1 pairs and a pair more raw data).
    Shed (``shed``), it resumes when two more pairs would fit. Returns the new state and, when
    it changes, the reason (else "").
    """
    mb = 2**20
    ahead = terms.need(in_flight + 1, terms.raw + terms.pair)
    if not shed and (not admitted or ahead > terms.usable):
        why = (
            "the pair itself was shed"
            if not admitted
            else f"one more pair in flight would need {ahead / mb:.0f} MB, over "
            f"{terms.usable / mb:.0f} MB usable: shed before any pair is"
        )
        return True, why
    if shed and admitted:
        room = terms.need(in_flight + 2, terms.raw + 2 * terms.pair)
        if room <= terms.usable:
            return False, (
                f"two more pairs in flight would fit ({room / mb:.0f} MB of "
                f"{terms.usable / mb:.0f} MB usable)"
            )
    return shed, ""


@dataclass
class _ViewStream:
    """Where a view's strip stream is: its current scene (frame_id), lines in it, ordinal."""

    frame_id: str | None = None
    lines: int = 0
    ordinal: int = -1
    max_lines: int = 0  # longest scene seen, lines (the size of a pair when scene_lines = 0)
    row_bytes: int = 0


class PairAdmission:
    """Admission of whole pairs under ``memory_budget_mb`` (README, "Overload").

    The decision is taken for a pair at the first strip of either of its scenes (scene k of each
    view; scenes 2k and 2k+1 in single-camera mode) and holds for every strip of both: a pair is
    processed whole or not at all, and shedding both scenes of it keeps the pipeline's pairing
    by scene order intact. A scene starts at a new frame_id, or after ``scene_lines`` lines.

    The memory the node holds (resident, less the free heap glibc keeps for reuse:
    :func:`held_bytes`) is read in two parts: the raw scene data (``raw_held``: the
    assemblers' line buffers, kept or in use, and the strips queued for the worker), and the
    rest. The start-up memory is the rest at the first strip; the working set (normalized
    images, messages being sent, DDS buffers, a strip backlog in DDS) is the largest excess of
    the rest over the start-up memory in the last :data:`WORKING_SET_SAMPLES` samples, taken at
    each decision and each pair published, each holding the peak the worker read (:meth:`sample`,
    after every input) since the one before; a burst's transient is forgotten once the load
    drops. It is at least ``floor_mb`` + ``floor_pairs`` raw pairs (:data:`WORKING_SET_PAIRS`;
    :data:`WHOLE_IMAGE_WORKING_SET_MB` + :data:`WHOLE_IMAGE_WORKING_SET_PAIRS` when pairs are
    normalized as whole images). A pair
    is admitted when

        start-up + max(raw data held, (pairs in flight + 1) x raw pair) + working set

    is within the budget less :data:`HEADROOM` (when the resident memory is over the budget,
    the free heap is first given back). Otherwise every strip of the pair is shed (dropped in
    the subscription callback, before conversion or queueing) and one WARN says so. A pair is
    in flight from its admission until its StereoPair is published (with every earlier one),
    or the flush. With nothing in flight a pair is always admitted (the node can hold no
    less); when the budget cannot hold two pairs in flight (consecutive pairs overlap in time:
    the fore view's next scene begins before the aft view's scene ends), the WARN says so and
    names the budget that would.

    Thread-safe: callbacks call :meth:`admit`, the worker :meth:`published`.
    """

    def __init__(
        self,
        views: Sequence[str],
        budget_mb: float,
        scene_lines: int,
        raw_held: Callable[[], int] = lambda: 0,
        floor_pairs: float = WORKING_SET_PAIRS,
        floor_mb: float = 0.0,
        book: AdmissionBook | None = None,
        tiles_held: Callable[[], int] = lambda: 0,
        quicklook: bool = False,
    ) -> None:
        self.views = list(views)
        #: Where the decisions and the pairs in flight are recorded (the pipeline ledger's).
        self.book = AdmissionBook() if book is None else book
        #: The working set is at least ``floor_mb`` MB + this many raw pairs.
        self.floor_pairs = float(floor_pairs)
        self.floor = int(floor_mb * 2**20)
        self._trimmed = 0.0  # monotonic time of sample()'s last malloc_trim
        self._sampled = -math.inf  # monotonic time of sample()'s last reading
        #: Bytes of raw scene data held (line buffers, queued strips), read apart from the rest.
        self.raw_held = raw_held
        #: Bytes the streamed DSM tiles hold, read apart from the rest too.
        self.tiles_held = tiles_held
        #: Whether quick-look tiles are made (``heights_quicklook`` on): shed before pairs.
        self.quicklook = quicklook
        self.single = len(self.views) == 1
        self.budget = int(budget_mb * 2**20)
        self.scene_lines = int(scene_lines)
        self.base = 0  # memory held at the first strip less its raw data, bytes
        self.working_set = 0  # largest excess of the non-raw memory over base, recent, bytes
        self._samples: deque[int] = deque(maxlen=WORKING_SET_SAMPLES)
        self._peak_rest = 0  # the largest non-raw memory read by sample() since the last sample
        self._streams = {v: _ViewStream() for v in self.views}
        self._lock = threading.Lock()
        self.counts = {"pairs_shed": 0, "scenes_shed": 0, "strips_shed": 0}
        self.quicklook_sheds = 0  # times the quick-look tiles were shed

    def pair_bytes(self) -> int:
        """One raw pair (both scenes), bytes, as far as known (0 before any strip)."""
        lines = self.scene_lines or max(s.max_lines for s in self._streams.values())
        # A view with no strip yet: taken as wide as the widest seen (its scene is coming).
        widest = max(s.row_bytes for s in self._streams.values())
        per_view = [lines * (s.row_bytes or widest) for s in self._streams.values()]
        return 2 * per_view[0] if self.single else sum(per_view)

    def admit(
        self, view: str, frame_id: str, rows: int, nbytes: int
    ) -> tuple[bool, list[Issue], bool]:
        """Whether to take this strip; the WARN when it sheds a pair; whether to close the view.

        The last: this strip begins a shed scene right after an admitted one, which the pipeline
        would otherwise close only at the view's next admitted strip.
        """
        issues: list[Issue] = []
        close = False
        with self._lock:
            st = self._streams.get(view)
            if st is None:  # not a configured view: the pipeline reports it
                return True, issues, close
            if not self.base:
                self.base = max(1, self._memory()[2])
            if rows > 0:
                st.row_bytes = max(st.row_bytes, nbytes // rows)
            new_scene = st.frame_id != frame_id or (
                self.scene_lines > 0 and st.lines >= self.scene_lines
            )
            previous = self._group_of(st.ordinal) if st.ordinal >= 0 else None
            if new_scene:
                st.frame_id, st.lines, st.ordinal = frame_id, 0, st.ordinal + 1
            st.lines += rows
            st.max_lines = max(st.max_lines, st.lines)
            group = self._group_of(st.ordinal)
            if new_scene:
                self.book.scene(view, frame_id, group)
            if self.book.decision(group) is None:
                n = self.book.in_flight
                ok, why, terms = self._decide()
                self.book.decide(group, ok)
                if not ok:
                    self.counts["pairs_shed"] += 1
                    issues.append(
                        Issue(
                            Level.WARN,
                            f"{view}/{frame_id}",
                            f"overload: pair {group} (this scene and the other scene of its "
                            f"pair) shed whole: {why}; {self.counts['pairs_shed']} pairs shed "
                            "so far",
                        )
                    )
                if self.quicklook:
                    issues += self._quicklook(n, terms, ok, group, f"{view}/{frame_id}")
            ok = bool(self.book.decision(group))
            if not ok:
                self.counts["strips_shed"] += 1
                if new_scene:
                    self.counts["scenes_shed"] += 1
                    close = previous is not None and bool(self.book.decision(previous))
            return ok, issues, close

    def _memory(self) -> tuple[int, int, int]:
        """(resident memory, raw data held, the rest of what is held), bytes.

        Held: resident less the free heap glibc keeps for reuse (:func:`held_bytes`), which the
        next allocations take before the resident memory grows again.
        """
        rss = rss_bytes()
        held = held_bytes(rss)
        raw = min(held, max(0, int(self.raw_held())))
        tiles = min(held - raw, self._tiles())
        return rss, raw, held - raw - tiles

    def _tiles(self) -> int:
        """Bytes the streamed tiles hold (0 when they cannot be read now)."""
        try:
            return max(0, int(self.tiles_held()))
        except Exception:  # read from another thread while the worker changes them
            return 0

    def _quicklook(
        self, in_flight: int, terms: MemoryTerms, admitted: bool, pair: int, where: str
    ) -> list[Issue]:
        """Shed or resume the quick-look tiles (:func:`decide_quicklook`), saying so."""
        was = self.book.quicklook_shed
        shed, why = decide_quicklook(in_flight, terms, admitted, was)
        if shed == was:
            return []
        self.book.quicklook_shed = shed
        if shed:
            self.quicklook_sheds += 1
            return [
                Issue(
                    Level.WARN,
                    where,
                    f"overload: quick-look tiles shed from pair {pair} on ({why}); the "
                    "quick-look tiles under way stop, the pairs keep coming; "
                    f"{self.quicklook_sheds} times so far",
                )
            ]
        return [Issue(Level.OK, where, f"quick-look tiles resumed from pair {pair} on: {why}")]

    def _group_of(self, ordinal: int) -> int:
        return ordinal // 2 if self.single else ordinal

    def _learn(self, rest: int) -> None:
        """Update the working set from a sample of the non-raw memory (lock held).

        The sample is the largest of ``rest`` and what :meth:`sample` saw since the last one.
        """
        if self.base:
            self._samples.append(max(0, max(rest, self._peak_rest) - self.base))
            self.working_set = max(self._samples)
        self._peak_rest = 0

    def sample(self) -> None:
        """Read the memory now (the worker, after each input): keeps the peak between samples.

        The reading is of memory still in use after the input (the free heap left out), so a
        transient the input freed is not seen: the floor of the working set and
        :data:`HEADROOM` are for those. When the resident memory is over the budget less the
        headroom, the free heap is given back (``malloc_trim``, at most every
        :data:`TRIM_INTERVAL_S`): a fragmented heap otherwise grew the resident memory pair by
        pair after a burst. At most every :data:`SAMPLE_INTERVAL_S`: a peak shorter than that
        may be missed (the floor and the headroom again).
        """
        now = time.monotonic()
        if now - self._sampled < SAMPLE_INTERVAL_S:
            return
        self._sampled = now
        rss, _, rest = self._memory()
        if rss > self.usable and now - self._trimmed >= TRIM_INTERVAL_S:
            self._trimmed = now  # the free heap kept beyond what the budget leaves: given back
            malloc_trim()
        with self._lock:
            self._peak_rest = max(self._peak_rest, rest)

    @property
    def usable(self) -> int:
        """The budget less :data:`HEADROOM`, bytes: what admitted pairs may need."""
        return int(self.budget * (1 - HEADROOM))

    def _work(self, pair: int) -> int:
        """The working set counted for a pair of ``pair`` bytes: learnt, or the floor, bytes."""
        return max(self.working_set, self.floor + int(self.floor_pairs * pair))

    def terms(self, raw: int = 0, tiles: int = 0) -> MemoryTerms:
        """The memory terms of a decision now.

        With ``raw`` bytes of raw data held and ``tiles`` bytes held by the streamed tiles.
        """
        pair = self.pair_bytes()
        return MemoryTerms(self.base, raw, pair, self._work(pair), self.budget, self.usable, tiles)

    def need(self, in_flight: int, raw: int = 0) -> int:
        """Memory to admit a pair with ``in_flight`` pairs already in flight, bytes."""
        return self.terms().need(in_flight, raw)

    def _decide(self) -> tuple[bool, str, MemoryTerms]:
        """Read the memory (given back first when over the budget), learn, and ask the policy.

        Returns its decision, its reason and the terms it read.
        """
        if rss_bytes() > self.budget:
            malloc_trim()
        _rss, raw, rest = self._memory()
        self._learn(rest)
        terms = self.terms(raw, self._tiles())
        return (*decide_admission(self.book.in_flight, terms), terms)

    def published(self, view: str, scene_id: str) -> None:
        """A pair with this scene (of ``view``) was published: it and earlier pairs leave."""
        rest = self._memory()[2]  # the pair's working set is still held
        with self._lock:
            self._learn(rest)
        self.book.published(view, scene_id)

    def release_all(self) -> None:
        """Nothing is in flight any more (the flush at stop, or a scene timeout)."""
        self.book.release_all()
        malloc_trim()

    def memory_values(self) -> list[tuple[str, str | int]]:
        """The summary's view of the admission: pairs in flight and the memory terms, MB."""
        mb = 2**20
        return [
            ("pairs_in_flight", self.in_flight),
            ("working_set_mb", f"{self.working_set / mb:.0f}"),
            ("raw_mb", f"{self.raw_held() / mb:.0f}"),
            ("startup_mb", f"{self.base / mb:.0f}"),
            ("held_mb", f"{held_bytes() / mb:.0f}"),
            ("rss_mb", f"{rss_bytes() / mb:.0f}"),
            ("memory_budget_mb", f"{self.budget / mb:.0f}"),
            *(
                [
                    ("tiles_mb", f"{self._tiles() / mb:.0f}"),
                    ("quicklook", "shed" if self.book.quicklook_shed else "on"),
                    ("quicklook_sheds", self.quicklook_sheds),
                ]
                if self.quicklook
                else []
            ),
        ]

    @property
    def in_flight(self) -> int:
        """Pairs admitted and not yet published (the book's)."""
        return self.book.in_flight


def prefault(config: Any, prefault_mb: float, assemblers: Mapping[str, SceneAssembler]) -> str:
    """Keep freed memory for reuse (process-wide), and touch the ``prefault_mb`` reserve.

    ``prefault_mb`` -1: :func:`auto_prefault_mb`. The line buffers of each view's scenes are
    touched too (``scene_lines`` set). Returns what was touched, in words ("" if nothing).
    """
    if prefault_mb < 0:
        prefault_mb = auto_prefault_mb(config)
    tune_malloc(int(prefault_mb * 2**20))
    if prefault_mb <= 0:
        return ""
    t0 = time.monotonic()
    heap = prefault_heap(int(prefault_mb * 2**20))
    lines = 0
    if config.scenes.lines > 0:
        for vc in config.views:
            asm = assemblers[vc.name]
            asm.pool.prefault(config.scenes.lines * vc.camera.detectors * 2)
            lines += asm.pool.held_bytes
    return (
        f"prefault_mb: {heap / 2**20:.0f} MB of heap and {lines / 2**20:.0f} MB of line "
        f"buffers touched in {time.monotonic() - t0:.1f} s"
    )
