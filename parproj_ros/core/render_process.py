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
one shared output buffer, copied out by the caller. A line buffer the child cannot see (not
from :meth:`allocate`), a block larger than the output buffer, or a child that died: the block
is rendered in the calling thread, as without this module, and :attr:`fallbacks` counts it.
"""

from __future__ import annotations

import multiprocessing as mp
import threading
import weakref
from collections import OrderedDict
from multiprocessing import shared_memory
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Output buffer of the child, bytes: a block of 256 columns of a 14010-row uint16 grid is 7 MB;
#: 64 MiB holds float32 blocks of 65,000 rows.
OUTPUT_BYTES = 64 * 2**20
#: Shared line buffers the child keeps attached (the most recently used).
ATTACHED_MAX = 8
#: OpenCV threads in the child. A block is about 27 small warpAffine calls (tiles of 512 x
#: 256); on the 2-core machine, shared with the node's threads and the sensor, OpenCV's second
#: thread cost more than it gave: at the full IKONOS rate (10 pairs, every default, SHM) the
#: child took 51-60 % of a core with 2 threads and 41-48 % with 1, the worker waiting on it
#: 31-33 % and 20-24 % (bench/BENCHMARKS.md, 2026-11-24).
RENDER_THREADS = 1


def _child(conn: Any, out_name: str) -> None:
    """The render loop: (segment, offset, shape, dtype, first line, block, ...) -> rendered."""
    import cv2

    from ..imaging.resample import render_block

    cv2.setNumThreads(RENDER_THREADS)

    # Attached segments are registered with the parent's resource tracker (a spawned child
    # shares it) under the names the parent registered: the parent's unlink unregisters them.
    out_shm = shared_memory.SharedMemory(name=out_name)
    segs: OrderedDict[str, shared_memory.SharedMemory] = OrderedDict()
    try:
        while True:
            req = conn.recv()
            if req is None:
                return
            name, offset, shape, dtype, first, block, height, nodata, interp = req
            try:
                seg = segs.get(name)
                if seg is None:
                    seg = shared_memory.SharedMemory(name=name)
                    segs[name] = seg
                    while len(segs) > ATTACHED_MAX:
                        segs.popitem(last=False)[1].close()
                segs.move_to_end(name)
                data = np.ndarray(shape, dtype=dtype, buffer=seg.buf, offset=offset)
                out = np.ndarray((height, block.cols), dtype=dtype, buffer=out_shm.buf)
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
        out_shm.close()


class RenderProcess:
    """The child process that renders streamed blocks, and the shared memory it reads.

    Thread-safe for one caller at a time (the node's worker); :meth:`close` at the end.
    """

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")  # no fork of a process with DDS threads
        self._out = shared_memory.SharedMemory(create=True, size=OUTPUT_BYTES)
        self._conn, child_conn = ctx.Pipe()
        self._proc = ctx.Process(
            target=_child, args=(child_conn, self._out.name), daemon=True, name="parproj_render"
        )
        self._proc.start()
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
        try:
            shm.close()
        except BufferError:  # a view still exported: the mapping goes with the process
            pass
        try:
            shm.unlink()
        except FileNotFoundError:
            pass

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

    def render(
        self,
        block: Any,
        data: NDArray[np.generic],
        first_line: int,
        height: int,
        *,
        nodata: float,
        interpolation: int,
    ) -> NDArray[np.generic] | None:
        """The block rendered by the child (a new array), or None: render it yourself."""
        where = self._locate(data) if self.alive else None
        if where is None or height * block.cols * data.itemsize > OUTPUT_BYTES:
            self.fallbacks += 1
            return None
        name, offset = where
        try:
            self._conn.send(
                (name, offset, data.shape, data.dtype.str, first_line, block, height,
                 float(nodata), int(interpolation))
            )  # fmt: skip
            reply = self._conn.recv()
        except (EOFError, OSError, BrokenPipeError) as err:
            self.error = f"render process gone: {type(err).__name__}: {err}"
            self.fallbacks += 1
            return None
        if reply is not None:
            self.fallbacks += 1
            return None
        out = np.ndarray((height, block.cols), dtype=data.dtype, buffer=self._out.buf)
        img = out.copy()
        del out
        self.rendered += 1
        return img

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
        self._out.close()
        try:
            self._out.unlink()
        except FileNotFoundError:
            pass
