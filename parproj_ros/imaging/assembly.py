"""Assembling scenes from image strips (blocks of consecutive scan lines).

A strip is a 2-D array (lines, detectors) whose first line was exposed at ``stamp_ns``; line i of
the strip was exposed at ``stamp_ns + i * line_period``. A scene ends when it reaches its
configured length, when the next strip starts after a time gap, or when the scene id of the strip
(the image header's frame_id) changes. Bad strips are rejected with a reason and never reach a
scene; the caller logs and reports them.
"""

from __future__ import annotations

import sys
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from .resample import ENCODINGS


class SceneEnd(StrEnum):
    """Why a scene was closed (:attr:`Scene.reason`)."""

    LENGTH = "length"  # it reached ``scene_lines``
    GAP = "gap"  # the next strip came more than ``max_gap_lines`` lines later
    SCENE_CHANGE = "scene_change"  # the next strip has another frame_id
    FLUSH = "flush"  # end of data, or the strips stopped coming
    STREAMING = "streaming"  # not closed: the placeholder of a scene still arriving (streaming)


class OpenScene(NamedTuple):
    """The scene a :class:`SceneAssembler` is assembling (:meth:`SceneAssembler.open_scene`)."""

    scene_id: str
    index: int  # type: ignore[assignment]  # the scene's index in its view (shadows tuple.index)
    first_line_ns: int
    lines: int  # received so far


@dataclass(frozen=True)
class Scene:
    """A complete scene of one view.

    Attributes:
        view: the camera/view name ("left", "fore", ...).
        scene_id: identifier (the strips' frame_id, or view + sequence number).
        index: sequence number of this scene within its view, from 0.
        first_line_ns: exposure time of line 0, nanoseconds.
        line_period: seconds between lines.
        image: (lines, detectors) pixels, uint8 / uint16 / float32.
        gaps: number of missing lines that were filled with no-data.
        reason: why the scene was closed (a plain string is accepted and stored as the member).
        released: lines at the start of the scene that a streaming consumer had already used
            and released; ``image`` holds lines ``released`` .. ``released + len(image) - 1``.
        part: 0 for the first (or only) scene of a frame_id, k for ``"<frame_id>#<k>"``.
        acquisition: sequence number within the view of the scene's frame_id (of its first
            part), from 0: the parts of one acquisition share it.
    """

    view: str
    scene_id: str
    index: int
    first_line_ns: int
    line_period: float
    image: NDArray[np.generic]
    gaps: int = 0
    reason: SceneEnd = SceneEnd.LENGTH
    released: int = 0
    part: int = 0
    acquisition: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "reason", SceneEnd(self.reason))

    @property
    def lines(self) -> int:
        """Number of lines of the scene (released ones included)."""
        return int(self.image.shape[0]) + self.released

    @property
    def detectors(self) -> int:
        """Number of detectors."""
        return int(self.image.shape[1])

    @property
    def last_line_ns(self) -> int:
        """Exposure time of the last line, nanoseconds."""
        return self.first_line_ns + round((self.lines - 1) * self.line_period * 1e9)


class StripRejectedError(ValueError):
    """A strip that cannot be used, with the reason (the scene it would belong to is unchanged)."""


def _private(nbytes: int) -> NDArray[np.uint8]:
    return np.empty(nbytes, dtype=np.uint8)


def _nothing(dest: NDArray[np.generic]) -> None:
    """The default :attr:`BufferPool.fence`."""


class BufferPool:
    """Line-buffer arrays an assembler keeps and reuses from scene to scene.

    A scene of 14000 lines x 13816 detectors of uint16 is a 387 MB array. Allocated afresh
    for every scene, each of its pages is first touched while the strips are copied in; on the
    project's VMs that costs 2.2 ms per MB (freed memory goes back to the host within seconds
    and comes back zeroed page by page: about 0.85 s per scene, measured with
    ``python -m tools.bench``), against 0.05 ms per MB for a page already resident. The pool
    keeps up to ``keep`` arrays and hands out one that nothing refers to any more: every numpy
    view of an array (a :class:`Scene`'s ``image``, the lines a streaming consumer is
    rendering) holds a reference to it, so an array still in use is never handed out.

    Args:
        keep: arrays kept (an array allocated while ``keep`` are held and in use is not kept).
    """

    def __init__(self, keep: int = 2) -> None:
        self.keep = int(keep)
        #: Makes a uint8 array of n bytes (shared memory for a render process, say).
        self.allocate: Callable[[int], NDArray[np.uint8]] = _private
        #: Called with the lines a line buffer is about to write over when it moves its
        #: retained lines within its array (another process may still be reading them: the
        #: render process's drafts); returns once nobody does. Default: nothing.
        self.fence: Callable[[NDArray[np.generic]], object] = _nothing
        self._arrays: list[NDArray[np.uint8]] = []  # raw bytes, viewed as the type asked for
        self.reused = 0  # arrays handed out again
        self.allocated = 0  # arrays allocated
        self._live = 0  # bytes of the arrays allocated here and still alive (kept or in use)
        self._live_lock = threading.Lock()

    def take(self, rows: int, width: int, dtype: np.dtype) -> NDArray[np.generic]:
        """An array of (rows, width) of ``dtype``: a free kept one, else a new one.

        Returns a view of the kept array, so that it stays in use (referenced) for as long as
        the caller holds it.
        """
        rows = max(1, rows)
        need = rows * width * np.dtype(dtype).itemsize
        for i in range(len(self._arrays)):
            # References: the list, and getrefcount's own argument.
            if sys.getrefcount(self._arrays[i]) > 2 or self._arrays[i].nbytes < need:
                continue
            self.reused += 1
            return self._arrays[i][:need].view(dtype).reshape(rows, width)
        raw = self._new(need)
        self.allocated += 1
        self._keep(raw)
        return raw.view(dtype).reshape(rows, width)

    def _new(self, nbytes: int) -> NDArray[np.uint8]:
        """A new array from :attr:`allocate`, counted in :attr:`live_bytes` while it lives."""
        raw = self.allocate(int(nbytes))
        with self._live_lock:
            self._live += raw.nbytes
        weakref.finalize(raw, self._freed, raw.nbytes)
        return raw

    def _freed(self, nbytes: int) -> None:
        with self._live_lock:
            self._live -= nbytes

    def _keep(self, raw: NDArray[np.uint8]) -> None:
        if len(self._arrays) < self.keep:
            self._arrays.append(raw)
            return
        # The pool is full: replace a free (smaller or older) array by this one, if any.
        for i in range(len(self._arrays)):
            if sys.getrefcount(self._arrays[i]) <= 2:
                self._arrays[i] = raw
                return

    def prefault(self, nbytes: int) -> None:
        """Allocate the kept arrays now, ``nbytes`` each, and touch every page of them."""
        while len(self._arrays) < self.keep:
            raw = self._new(int(nbytes))
            raw[::4096] = 0  # one byte per page faults the page in
            self._arrays.append(raw)

    @property
    def held_bytes(self) -> int:
        """Bytes of the arrays the pool keeps (in use or not)."""
        return sum(a.nbytes for a in self._arrays)

    @property
    def live_bytes(self) -> int:
        """Bytes of every array allocated here and still alive: kept, or in use by a scene.

        An array allocated while the pool was full is not kept, but lives while used.
        """
        with self._live_lock:
            return self._live

    def clear(self) -> None:
        """Forget the kept arrays (those in use stay alive with their users)."""
        self._arrays.clear()


class _LineBuffer:
    """Lines of one scene in one array: appended at the end, released at the front.

    Appending copies the strip once; releasing only moves the start. Once the released lines
    at the front could hold the retained ones and the new strip, the retained lines are moved
    to the front (a streamed scene thus keeps reusing the first few strips' worth of the
    array, whose pages stay resident); when the end reaches the capacity, the array grows by
    doubling. The cost per line stays constant and no concatenation of the whole scene is
    ever needed. Arrays come from the assembler's :class:`BufferPool`.
    """

    def __init__(self, width: int, dtype: np.dtype, capacity: int, pool: BufferPool) -> None:
        self.pool = pool
        self.buf = pool.take(max(1, capacity), width, dtype)
        self.start = 0
        self.end = 0
        self.high = 0  # the furthest line of the array ever written (its touched part)

    def append(self, block: NDArray[np.generic]) -> None:
        n = block.shape[0]
        keep = self.end - self.start
        if self.start > 0 and self.start >= max(keep, n):
            # The front is free and large enough: move the retained lines there (no overlap).
            self.pool.fence(self.buf[:keep])
            self.buf[:keep] = self.buf[self.start : self.end]
            self.start, self.end = 0, keep
        if self.end + n > self.buf.shape[0]:
            cap = self.buf.shape[0]
            grown = self.pool.take(max(2 * cap, keep + n), self.buf.shape[1], self.buf.dtype)
            grown[:keep] = self.buf[self.start : self.end]
            self.buf = grown
            self.start, self.end = 0, keep
        self.buf[self.end : self.end + n] = block
        self.end += n
        self.high = max(self.high, self.end)

    def view(self) -> NDArray[np.generic]:
        return self.buf[self.start : self.end]

    def drop(self, k: int) -> None:
        self.start = min(self.end, self.start + k)


@dataclass
class _Open:
    scene_id: str
    first_line_ns: int
    base_id: str = ""
    part: int = 0
    acquisition: int = 0
    data: _LineBuffer | None = None
    lines: int = 0
    gaps: int = 0
    dtype: np.dtype | None = None
    width: int = 0
    released: int = 0


class SceneAssembler:
    """Collects strips of one view into scenes.

    Args:
        view: view name.
        line_period: seconds between lines.
        scene_lines: close a scene after this many lines (0 = no length limit).
        max_gap_lines: a jump of more than this many lines between strips closes the scene;
            a smaller positive jump is filled with ``nodata`` lines and counted in ``gaps``.
        nodata: fill value for missing lines.
        pool_buffers: line-buffer arrays kept for reuse by later scenes (:class:`BufferPool`;
            two: a complete scene waiting for its pair and the scene being assembled).
    """

    def __init__(
        self,
        view: str,
        line_period: float,
        *,
        scene_lines: int = 0,
        max_gap_lines: int = 64,
        nodata: float = 0.0,
        pool_buffers: int = 2,
    ) -> None:
        self.view = view
        self.line_period = float(line_period)
        self.scene_lines = int(scene_lines)
        self.max_gap_lines = int(max_gap_lines)
        self.nodata = nodata
        self._open: _Open | None = None
        self._count = 0
        # (frame_id, part, time of the line after the last) of the scene last closed
        self._last: tuple[str, int, int] | None = None
        # time of the line after the last line received on this view (any scene), ns
        self._latest_ns: int | None = None
        # next part number of each frame_id, so that scene ids never repeat
        self._parts: dict[str, int] = {}
        # acquisition number of each frame_id (in the order of their first strips)
        self._acquisitions: dict[str, int] = {}
        # Line buffers reused from scene to scene (see BufferPool).
        self.pool = BufferPool(pool_buffers)

    def _close(self, reason: SceneEnd) -> Scene | None:
        op = self._open
        self._open = None
        if op is None or op.lines == 0:
            return None
        self._last = (
            op.base_id,
            op.part,
            op.first_line_ns + round(op.lines * self.line_period * 1e9),
        )
        if op.data is not None:
            image = op.data.view()
        else:
            image = np.empty((0, op.width), dtype=op.dtype)
        scene = Scene(
            self.view,
            op.scene_id,
            self._count,
            op.first_line_ns,
            self.line_period,
            image,
            op.gaps,
            reason,
            op.released,
            op.part,
            op.acquisition,
        )
        self._count += 1
        return scene

    @property
    def is_open(self) -> bool:
        """Whether a scene is being assembled."""
        return self._open is not None

    @property
    def latest_ns(self) -> int | None:
        """Time of the line after the last line received on this view, ns (None: nothing yet).

        No later scene of this view can start before it: earlier strips are dropped.
        """
        return self._latest_ns

    def open_scene(self) -> OpenScene | None:
        """The open scene (id, index, first line time, lines received so far), or None."""
        op = self._open
        if op is None:
            return None
        return OpenScene(op.scene_id, self._count, op.first_line_ns, op.lines)

    def retained(self) -> tuple[int, NDArray[np.generic]]:
        """(first retained line, lines retained so far) of the open scene, as one array."""
        op = self._open
        if op is None:
            raise ValueError("no open scene")
        if op.data is None:
            return op.released, np.empty((0, op.width), dtype=op.dtype)
        return op.released, op.data.view()

    def release(self, upto_line: int) -> None:
        """Drop the open scene's lines before ``upto_line`` (a streaming consumer is done)."""
        op = self._open
        if op is None or upto_line <= op.released:
            return
        first, data = self.retained()
        drop = min(upto_line - first, data.shape[0])
        if op.data is not None:
            op.data.drop(drop)
        op.released += drop

    def flush(self) -> list[Scene]:
        """Close the open scene (end of data)."""
        s = self._close(SceneEnd.FLUSH)
        return [s] if s is not None else []

    def add(self, stamp_ns: int, scene_id: str, strip: NDArray[np.generic]) -> list[Scene]:
        """Add one strip; return the scenes it completed.

        ``scene_id`` is the strips' frame_id. A scene cut by length (or closed by a gap) and
        continued by strips of the same frame_id gets the id ``"<frame_id>#<part>"`` for parts
        1, 2, ...; the first part keeps the plain frame_id, so GCP observations keyed by it
        refer to the scene's own line numbers.

        Raises:
            StripRejectedError: the strip is empty, of an unsupported type, of another width or
                type than the open scene, or overlaps lines already received (duplicate or out
                of order, also against the scene last closed). Nothing is changed then.
        """
        if strip.ndim != 2 or strip.shape[0] == 0 or strip.shape[1] == 0:
            raise StripRejectedError(
                f"strip has shape {strip.shape}: expected (lines >= 1, detectors)"
            )
        if strip.dtype not in ENCODINGS:
            raise StripRejectedError(f"unsupported pixel type {strip.dtype}")
        period_ns = self.line_period * 1e9
        done: list[Scene] = []
        op = self._open
        if self._latest_ns is not None:
            behind = -round((stamp_ns - self._latest_ns) / period_ns)
            if behind > 0:
                raise StripRejectedError(
                    f"strip at {stamp_ns} ns starts {behind} lines before data already received "
                    f"on view {self.view} (duplicate or out of order, or stamps going "
                    "backwards): "
                    "dropped"
                )
        if op is not None:
            expected = op.first_line_ns + round(op.lines * period_ns)
            jump = round((stamp_ns - expected) / period_ns)
            if scene_id != op.base_id:
                done += [sc for sc in [self._close(SceneEnd.SCENE_CHANGE)] if sc]
            elif jump < 0:
                raise StripRejectedError(
                    f"strip at {stamp_ns} ns starts {-jump} lines before the end of "
                    "scene data already received (duplicate or out of order): dropped"
                )
            elif strip.shape[1] != op.width or strip.dtype != op.dtype:
                raise StripRejectedError(
                    f"strip is {strip.shape[1]} px {strip.dtype}, scene {op.scene_id} is "
                    f"{op.width} px {op.dtype}: dropped"
                )
            elif jump > self.max_gap_lines:
                done += [sc for sc in [self._close(SceneEnd.GAP)] if sc]
            elif jump > 0:
                fill = np.full((jump, op.width), self.nodata, dtype=op.dtype)
                done += self._push(fill, scene_id, expected, filled=True)
        start = stamp_ns
        if self._open is not None:
            start = self._open.first_line_ns + round(self._open.lines * period_ns)
        done += self._push(np.ascontiguousarray(strip), scene_id, start, filled=False)
        return done

    def _push(
        self, block: NDArray[np.generic], base_id: str, start_ns: int, *, filled: bool
    ) -> list[Scene]:
        """Append lines (first one exposed at ``start_ns``), cutting scenes at the length."""
        done: list[Scene] = []
        period_ns = self.line_period * 1e9
        while block.shape[0] > 0:
            if self._open is None:
                part = self._parts.get(base_id, 0)
                self._parts[base_id] = part + 1
                acq = self._acquisitions.setdefault(base_id, len(self._acquisitions))
                sid = base_id if part == 0 else f"{base_id}#{part}"
                self._open = _Open(
                    sid,
                    int(start_ns),
                    base_id,
                    part,
                    acq,
                    dtype=block.dtype,
                    width=block.shape[1],
                )
            op = self._open
            room = self.scene_lines - op.lines if self.scene_lines > 0 else block.shape[0]
            take = block[:room]
            if op.data is None:
                cap = self.scene_lines if self.scene_lines > 0 else max(1024, 4 * take.shape[0])
                op.data = _LineBuffer(op.width, np.dtype(op.dtype), cap, self.pool)
            op.data.append(take)
            op.lines += take.shape[0]
            if filled:
                op.gaps += take.shape[0]
            block = block[room:]
            start_ns = op.first_line_ns + round(op.lines * period_ns)
            if self.scene_lines > 0 and op.lines >= self.scene_lines:
                closed = self._close(SceneEnd.LENGTH)
                if closed:
                    done.append(closed)
        self._latest_ns = int(start_ns)
        return done
