"""Streamed blocks rendered in a process of their own, out of the node's GIL.

A column block is about 27 ``cv2.warpAffine`` calls (one per tile); each gives the GIL back
and must take it again. In the node the executor thread holds the GIL for tens of ms at a
time while it takes a 13.8 MB strip (rclpy copies it with the GIL held), so at the full
IKONOS rate the worker spent most of a block waiting for the GIL between tiles: the first
pair's 55 blocks took 8.6 s instead of 0.5 s (``python -m tools.bench``, BENCHMARKS.md). Here
the tiles run in a child process, which has a GIL of its own: the worker waits once per block
(on a pipe, GIL released) and the executor goes on taking strips meanwhile.

The scene lines are shared, not sent: the assemblers' line buffers are allocated in shared
memory (:meth:`RenderProcess.allocate`, the allocator of
:class:`~parproj_ros.imaging.assembly.BufferPool`), and a block's output comes back through
one of two shared output buffers. :meth:`RenderProcess.render_blocks` keeps one block ahead:
while the caller publishes block k from one buffer, the child renders block k + 1 into the
other, so the worker and the child no longer wait for each other block by block. A line
buffer the child cannot see (not from :meth:`allocate`), a block larger than an output
buffer, or a child that died: the block is rendered in the calling thread, as without this
module, and :attr:`fallbacks` counts it.

Draft blocks (quick-look only, nobody taking the blocks themselves) are not waited for at all
(:meth:`RenderProcess.submit_reduced`): the child renders each and reduces it for the
quick-look levels, writes the reductions into a shared ring and answers; the caller collects
the answers when it next polls (:meth:`RenderProcess.poll`) or must have them
(:meth:`RenderProcess.drain`: before a pair is made, before its line buffer moves lines, before
the next full block). At the IKONOS rate, waiting for the child block by block and reducing
each draft took 35 % of the node's worker (py-spy, docs/quicklook_bench.md).
"""

from __future__ import annotations

import multiprocessing as mp
import threading
import weakref
from collections import OrderedDict, deque
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass
from multiprocessing import shared_memory
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Each of the two output buffers of the child, bytes: a block of 256 columns of a 14010-row
#: uint16 grid is 7 MB; 64 MiB holds float32 blocks of 65,000 rows.
OUTPUT_BYTES = 64 * 2**20
#: Shared line buffers the child keeps attached (the most recently used).
ATTACHED_MAX = 8
#: OpenCV threads in the child. A block is about 27 small warpAffine calls (tiles of 512 x
#: 256); on the 2-core machine, shared with the node's threads and the sensor, OpenCV's second
#: thread cost more than it gave: at the full IKONOS rate (10 pairs, every default, SHM) the
#: child took 51-60 % of a core with 2 threads and 41-48 % with 1, the worker waiting on it
#: 31-33 % and 20-24 % (bench/BENCHMARKS.md, 2026-11-24).
RENDER_THREADS = 1
#: The shared ring the child writes draft blocks' reductions into, bytes (a block of 256
#: columns of a 14010-row uint16 grid reduced by 8 is 110 KiB; by 2, 1.7 MiB).
RING_BYTES = 32 * 2**20
#: Draft blocks asked for and not yet collected, at most (then the oldest is waited for).
DRAFTS_IN_FLIGHT = 64
#: Alignment of a reduction in the ring, bytes.
_ALIGN = 64
#: Lines beyond a block's own (which hold its kernel's margin) counted as read by its draft.
_READ_MARGIN = 8

#: The reductions of a draft block, one per factor asked (None for a factor of 0).
Reductions = list[NDArray[np.generic] | None]


def _reduced_shapes(height: int, cols: int, factors: Sequence[int]) -> list[tuple[int, int]]:
    """The shape of each reduction :func:`~..imaging.resample.reduce_block` makes (0: none)."""
    return [(height // f, cols // f) if f > 0 else (0, 0) for f in factors]


def _ring_bytes(shapes: Sequence[tuple[int, int]], itemsize: int) -> list[int]:
    """Byte offsets of each reduction from the start of the draft's space, and the total."""
    offsets = [0]
    for r, c in shapes:
        offsets.append(offsets[-1] + -(-r * c * itemsize // _ALIGN) * _ALIGN)
    return offsets


def _child(conn: Any, out_names: list[str], ring_name: str) -> None:
    """The render loop: (output, segment, offset, shape, dtype, first line, block, ...).

    Output -1: a draft, reduced by each of the request's factors into the ring at its offset.
    """
    import cv2

    from ..imaging.resample import reduce_block, render_block

    cv2.setNumThreads(RENDER_THREADS)

    # Attached segments are registered with the parent's resource tracker (a spawned child
    # shares it) under the names the parent registered: the parent's unlink unregisters them.
    outs = [shared_memory.SharedMemory(name=n) for n in out_names]
    ring = shared_memory.SharedMemory(name=ring_name)
    scratch = np.empty(0, dtype=np.uint8)  # a draft's full-resolution pixels
    segs: OrderedDict[str, shared_memory.SharedMemory] = OrderedDict()
    try:
        while True:
            req = conn.recv()
            if req is None:
                return
            slot, name, offset, shape, dtype, first, block, height, nodata, interp = req[:10]
            try:
                seg = segs.get(name)
                if seg is None:
                    seg = shared_memory.SharedMemory(name=name)
                    segs[name] = seg
                    while len(segs) > ATTACHED_MAX:
                        segs.popitem(last=False)[1].close()
                segs.move_to_end(name)
                data = np.ndarray(shape, dtype=dtype, buffer=seg.buf, offset=offset)
                stride = 1 if slot >= 0 else int(req[12])
                if slot >= 0:
                    out = np.ndarray((height, block.cols), dtype=dtype, buffer=outs[slot].buf)
                else:
                    shape_s = (height // stride, block.cols // stride)
                    need = shape_s[0] * shape_s[1] * data.itemsize
                    if scratch.nbytes < need:
                        scratch = np.empty(need, dtype=np.uint8)
                    out = scratch[:need].view(dtype).reshape(shape_s)
                render_block(
                    block, data, first, None, nodata=nodata, interpolation=interp, out=out,
                    stride=stride,
                )  # fmt: skip
                if slot < 0:
                    factors, at = req[10], req[11]
                    shapes = _reduced_shapes(height, block.cols, factors)
                    offsets = _ring_bytes(shapes, out.itemsize)
                    for f, shp, off in zip(factors, shapes, offsets, strict=False):
                        if f > 0:
                            dst = np.ndarray(shp, dtype=dtype, buffer=ring.buf, offset=at + off)
                            dst[...] = reduce_block(out, f // stride, nodata)
                            del dst
                del data, out
                conn.send(None)
            except Exception as err:
                conn.send(f"{type(err).__name__}: {err}")
    except (EOFError, OSError, KeyboardInterrupt):
        return
    finally:
        for seg in segs.values():
            seg.close()
        for out_shm in outs:
            out_shm.close()
        ring.close()


@dataclass
class _Draft:
    """A draft block asked of the child: what to collect, and whom to give it to."""

    block: Any
    data: NDArray[np.generic]  # the lines it reads: held, so their array is not reused
    height: int
    factors: tuple[int, ...]
    at: int  # byte offset of its reductions in the ring
    nbytes: int  # bytes it takes in the ring
    deliver: Callable[[Reductions | None], None]
    reads: tuple[int, int]  # the addresses of the lines it reads: [first byte, end)


class RenderProcess:
    """The child process that renders streamed blocks, and the shared memory it reads.

    Thread-safe for one caller at a time (the node's worker); :meth:`close` at the end.
    """

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")  # no fork of a process with DDS threads
        self._outs: list[shared_memory.SharedMemory] = []
        self._ring: shared_memory.SharedMemory | None = None
        try:
            for _ in range(2):
                self._outs.append(shared_memory.SharedMemory(create=True, size=OUTPUT_BYTES))
            self._ring = shared_memory.SharedMemory(create=True, size=RING_BYTES)
        except BaseException:
            self._free_outputs()
            raise
        self._conn, child_conn = ctx.Pipe()
        self._proc = ctx.Process(
            target=_child,
            args=(child_conn, [o.name for o in self._outs], self._ring.name),
            daemon=True,
            name="parproj_render",
        )
        try:
            self._proc.start()
        except BaseException:
            self._conn.close()
            child_conn.close()
            self._free_outputs()
            raise
        child_conn.close()
        self._segments: dict[int, tuple[int, str]] = {}  # buffer address -> (size, name)
        self._lock = threading.Lock()
        self.rendered = 0  # blocks rendered by the child
        self.fallbacks = 0  # blocks rendered in the calling thread instead
        self.drafts = 0  # draft blocks rendered and reduced by the child
        self.error: str | None = None  # why the child stopped being used, if it did
        self._pending: deque[_Draft] = deque()  # drafts asked for, in the order asked
        self._ring_head = 0  # where the next draft's reductions go in the ring

    @property
    def alive(self) -> bool:
        """Whether the child is running and in use."""
        return self.error is None and self._proc.is_alive()

    def allocate(self, nbytes: int) -> NDArray[np.uint8]:
        """A uint8 array of ``nbytes`` in shared memory (freed with the array); else np.empty."""
        try:
            shm = shared_memory.SharedMemory(create=True, size=max(1, int(nbytes)))
        except OSError:  # /dev/shm full or missing: a private array, rendered in-thread
            return np.empty(int(nbytes), dtype=np.uint8)
        arr = np.ndarray(int(nbytes), dtype=np.uint8, buffer=shm.buf)
        addr = arr.__array_interface__["data"][0]
        with self._lock:
            self._segments[addr] = (int(nbytes), shm.name)
        weakref.finalize(arr, self._release, addr, shm)
        return arr

    def _release(self, addr: int, shm: shared_memory.SharedMemory) -> None:
        with self._lock:
            self._segments.pop(addr, None)
        _free(shm)

    def _locate(self, data: NDArray[np.generic]) -> tuple[str, int] | None:
        """(segment name, byte offset) of ``data`` if it lies in a segment of ours."""
        if not data.flags.c_contiguous:
            return None
        addr = data.__array_interface__["data"][0]
        with self._lock:
            for base, (size, name) in self._segments.items():
                if base <= addr and addr + data.nbytes <= base + size:
                    return name, addr - base
        return None

    def render_blocks(
        self,
        blocks: Sequence[Any],
        data: NDArray[np.generic],
        first_line: int,
        height: int,
        *,
        nodata: float,
        interpolation: int,
    ) -> Generator[tuple[Any, NDArray[np.generic] | None], None, None]:
        """(block, its pixels) for each of ``blocks`` in order, the child one block ahead.

        The pixels are a view of an output buffer, valid until the next item is asked for
        (copy them to keep them); None: render that block yourself (counted in
        :attr:`fallbacks`). ``data`` (the lines from ``first_line``) must not change until the
        iterator is exhausted or closed: close it (``contextlib.closing``) when leaving early,
        so the block still in the child is waited for. Drafts still in the child are collected
        first (:meth:`drain`).
        """
        self.drain()
        where = self._locate(data) if self.alive else None
        if where is None or height * max((b.cols for b in blocks), default=0) * data.itemsize > (
            OUTPUT_BYTES
        ):
            for b in blocks:
                self.fallbacks += 1
                yield b, None
            return
        name, offset = where
        head = (name, offset, data.shape, data.dtype.str, first_line)
        tail = (height, float(nodata), int(interpolation))
        in_flight = False

        def submit(k: int) -> bool:
            """Ask the child for block k into output k % 2; False: the child is gone."""
            try:
                self._conn.send((k % 2, *head, blocks[k], *tail))
            except OSError as err:
                self.error = f"render process gone: {type(err).__name__}: {err}"
                return False
            return True

        def reply() -> bool:
            """The child's answer to the block in flight: whether it rendered it."""
            try:
                answer = self._conn.recv()
            except (EOFError, OSError) as err:
                self.error = f"render process gone: {type(err).__name__}: {err}"
                return False
            return answer is None

        try:
            in_flight = bool(blocks) and submit(0)
            for k, b in enumerate(blocks):
                ok = False
                if in_flight:
                    in_flight = False
                    ok = reply()
                    if k + 1 < len(blocks) and self.error is None:
                        in_flight = submit(k + 1)
                if not ok:
                    self.fallbacks += 1
                    yield b, None
                    continue
                out = np.ndarray((height, b.cols), dtype=data.dtype, buffer=self._outs[k % 2].buf)
                self.rendered += 1
                yield b, out
                del out
        finally:
            if in_flight:  # left early: the child's answer must not be read as the next one's
                reply()

    def submit_reduced(
        self,
        block: Any,
        data: NDArray[np.generic],
        first_line: int,
        height: int,
        *,
        nodata: float,
        interpolation: int,
        factors: Sequence[int],
        stride: int = 1,
        deliver: Callable[[Reductions | None], None],
    ) -> bool:
        """Ask the child for a draft block reduced by each of ``factors``; do not wait.

        The child samples it every ``stride`` pixels (``render_block``'s), then reduces that
        by ``factor // stride`` (each factor a multiple of ``stride``).

        ``deliver(reductions)`` is called on the caller's thread by a later :meth:`poll` or
        :meth:`drain` (in the order asked): one array per factor, None for a factor of 0; or
        None, the child could not (counted in :attr:`fallbacks`): render it yourself. ``data``
        (the lines from ``first_line``) is held until then and must not change: call
        :meth:`drain` before writing over them. False: not asked (a line buffer the child
        cannot see, a block too large, no child): render it yourself now.
        """
        where = self._locate(data) if self.alive else None
        if where is None or height * int(block.cols) * data.itemsize > OUTPUT_BYTES:
            return False
        facs = tuple(int(f) for f in factors)
        if not any(f > 0 for f in facs):
            return False
        nbytes = _ring_bytes(_reduced_shapes(height, int(block.cols), facs), data.itemsize)[-1]
        at = self._ring_space(nbytes)
        if at is None:
            return False
        try:
            self._conn.send(
                (-1, *where, data.shape, data.dtype.str, first_line, block, height,
                 float(nodata), int(interpolation), facs, at, int(stride))
            )  # fmt: skip
        except OSError as err:
            self.error = f"render process gone: {type(err).__name__}: {err}"
            return False
        # The lines the block reads (its tiles' lines and kernel margin, and a few more).
        row = data.strides[0]
        lo = min(max(int(block.min_line) - first_line - _READ_MARGIN, 0), data.shape[0])
        hi = min(max(int(block.max_line) - first_line + 1 + _READ_MARGIN, lo), data.shape[0])
        base = int(data.__array_interface__["data"][0])
        self._pending.append(
            _Draft(block, data, height, facs, at, nbytes, deliver,
                   (base + lo * row, base + hi * row))
        )  # fmt: skip
        self._ring_head = at + nbytes
        return True

    def _ring_space(self, nbytes: int) -> int | None:
        """Where ``nbytes`` of reductions go in the ring; None: larger than the ring.

        Collects the oldest drafts (waiting for them) until there is room and fewer than
        :data:`DRAFTS_IN_FLIGHT` are pending.
        """
        size = RING_BYTES
        if nbytes >= size:
            return None
        while True:
            if not self._pending:
                self._ring_head = 0
                return 0
            if len(self._pending) < DRAFTS_IN_FLIGHT:
                # In use: from the oldest's start (tail) to the newest's end (head), wrapped
                # when head < tail. Strict bounds, so that head == tail never means full.
                tail, head = self._pending[0].at, self._ring_head
                if head > tail:
                    if head + nbytes <= size:
                        return head
                    if nbytes < tail:
                        return 0
                elif head + nbytes < tail:
                    return head
            self._answer()

    @property
    def pending(self) -> int:
        """Draft blocks asked for and not yet collected."""
        return len(self._pending)

    def poll(self) -> int:
        """Collect the drafts the child has finished (not waiting); how many."""
        n = 0
        try:
            while self._pending and self.error is None and self._conn.poll(0):
                self._answer()
                n += 1
        except (EOFError, OSError) as err:
            self.error = f"render process gone: {type(err).__name__}: {err}"
        if self.error is not None:
            n += self.drain()
        return n

    def _last_reading(self, dest: NDArray[np.generic]) -> int:
        """Index of the newest pending draft that reads any byte of ``dest``; -1: none."""
        lo = int(dest.__array_interface__["data"][0])
        hi = lo + int(dest.nbytes)
        last = -1
        for k, d in enumerate(self._pending):
            if d.reads[0] < hi and lo < d.reads[1]:
                last = k
        return last

    def reading(self, dest: NDArray[np.generic]) -> bool:
        """Whether a draft still pending reads any byte of ``dest``."""
        return self._last_reading(dest) >= 0

    def drain_over(self, dest: NDArray[np.generic]) -> int:
        """Collect drafts, oldest first, until none pending reads ``dest``; how many.

        The fence of the line buffers (:attr:`~..imaging.assembly.BufferPool.fence`): lines
        about to be written over. A draft reads the lines of its block only, so at the IKONOS
        rate most moves wait for none.
        """
        n = self._last_reading(dest) + 1
        for _ in range(n):
            self._answer()
        return n

    def drain(self) -> int:
        """Collect every draft asked for (waiting for the child); how many."""
        n = 0
        while self._pending:
            self._answer()
            n += 1
        return n

    def _answer(self) -> None:
        """Collect the oldest draft: its reductions copied out of the ring, or None."""
        d = self._pending.popleft()
        images: Reductions | None = None
        if self.error is None:
            try:
                answer = self._conn.recv()
            except (EOFError, OSError) as err:
                self.error = f"render process gone: {type(err).__name__}: {err}"
            else:
                if answer is None and self._ring is not None:
                    shapes = _reduced_shapes(d.height, int(d.block.cols), d.factors)
                    offsets = _ring_bytes(shapes, d.data.itemsize)
                    images = [
                        np.ndarray(shp, dtype=d.data.dtype, buffer=self._ring.buf,
                                   offset=d.at + off).copy()
                        if f > 0 else None
                        for f, shp, off in zip(d.factors, shapes, offsets, strict=False)
                    ]  # fmt: skip
                    self.drafts += 1
        if images is None:
            self.fallbacks += 1
        d.deliver(images)

    def close(self) -> None:
        """Stop the child and free the output buffer (line buffers go with their arrays).

        Drafts still pending are collected (delivered) first.
        """
        self.drain()
        try:
            self._conn.send(None)
        except (OSError, BrokenPipeError):
            pass
        self._proc.join(timeout=5.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=5.0)
        self._conn.close()
        self._free_outputs()

    def _free_outputs(self) -> None:
        for out in self._outs:
            _free(out)
        if self._ring is not None:
            _free(self._ring)


def _free(shm: shared_memory.SharedMemory) -> None:
    """Close and unlink a segment of ours."""
    try:
        shm.close()
    except BufferError:  # a view still exported: the mapping goes with the process
        pass
    try:
        shm.unlink()
    except FileNotFoundError:
        pass
