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
"""

from __future__ import annotations

import multiprocessing as mp
import threading
import weakref
from collections import OrderedDict
from collections.abc import Generator, Sequence
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


def _child(conn: Any, out_names: list[str]) -> None:
    """The render loop: (output, segment, offset, shape, dtype, first line, block, ...)."""
    import cv2

    from ..imaging.resample import render_block

    cv2.setNumThreads(RENDER_THREADS)

    # Attached segments are registered with the parent's resource tracker (a spawned child
    # shares it) under the names the parent registered: the parent's unlink unregisters them.
    outs = [shared_memory.SharedMemory(name=n) for n in out_names]
    segs: OrderedDict[str, shared_memory.SharedMemory] = OrderedDict()
    try:
        while True:
            req = conn.recv()
            if req is None:
                return
            slot, name, offset, shape, dtype, first, block, height, nodata, interp = req
            try:
                seg = segs.get(name)
                if seg is None:
                    seg = shared_memory.SharedMemory(name=name)
                    segs[name] = seg
                    while len(segs) > ATTACHED_MAX:
                        segs.popitem(last=False)[1].close()
                segs.move_to_end(name)
                data = np.ndarray(shape, dtype=dtype, buffer=seg.buf, offset=offset)
                out = np.ndarray((height, block.cols), dtype=dtype, buffer=outs[slot].buf)
                render_block(
                    block, data, first, None, nodata=nodata, interpolation=interp, out=out
                )
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


class RenderProcess:
    """The child process that renders streamed blocks, and the shared memory it reads.

    Thread-safe for one caller at a time (the node's worker); :meth:`close` at the end.
    """

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")  # no fork of a process with DDS threads
        self._outs: list[shared_memory.SharedMemory] = []
        try:
            for _ in range(2):
                self._outs.append(shared_memory.SharedMemory(create=True, size=OUTPUT_BYTES))
        except BaseException:
            self._free_outputs()
            raise
        self._conn, child_conn = ctx.Pipe()
        self._proc = ctx.Process(
            target=_child,
            args=(child_conn, [o.name for o in self._outs]),
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
        self.error: str | None = None  # why the child stopped being used, if it did

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
        so the block still in the child is waited for.
        """
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

    def close(self) -> None:
        """Stop the child and free the output buffer (line buffers go with their arrays)."""
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
