"""Process memory for a node that must not stall: glibc keeps freed memory for reuse.

On the project's VMs a page touched for the first time (or again after the process gave it
back: the guest returns free memory to the host within seconds) costs about 2.2 ms per MB,
against 0.05 ms per MB for a page still resident (``python -m tools.bench``; BENCHMARKS.md,
"Memory reuse"). A node receiving 343 MB/s cannot afford that on every strip: it keeps the
memory it freed (:func:`tune_malloc`), can touch a reserve at start (:func:`prefault_heap`,
the ``prefault_mb`` parameter), and reads what it holds as its resident memory less the free
heap kept (:func:`held_bytes`). Line buffers are kept by :class:`~parproj_ros.imaging.assembly.
BufferPool`. Without glibc (another C library) every function is a no-op.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .config import PipelineConfig

#: glibc ``mallopt`` parameters (malloc.h) and what the node sets them to: allocations up to
#: 32 MiB (strips, column blocks, messages) come from the heap instead of mappings of their
#: own, and up to 256 MiB of free heap top is kept rather than given back. Memory given back
#: to the system costs 2.2 ms per MB to touch again on the project's VMs (it goes back to the
#: host within seconds); kept, it is reused at 0.05 ms per MB (BENCHMARKS.md, "Memory reuse").
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES = 32 * 2**20
TRIM_THRESHOLD_BYTES = 256 * 2**20


def raw_pair_bytes(config: PipelineConfig) -> int:
    """One raw input pair of the configured scenes, bytes (0 without ``scene_lines``).

    ``scene_lines`` x detectors x 2 bytes (uint16; an upper bound for 8-bit strips) summed
    over ``config.views``: 738 MB for two IKONOS-size views (14000 x 13816).
    """
    lines = config.scenes.lines
    if lines <= 0:
        return 0
    return int(sum(lines * vc.camera.detectors * 2 for vc in config.views))


def _libc() -> Any:
    """The C library (glibc) through ctypes, or None (another one: no tuning)."""
    global _LIBC
    if _LIBC is None:
        try:
            import ctypes

            lib = ctypes.CDLL("libc.so.6")
            lib.mallopt  # noqa: B018  (glibc only)
            lib.malloc_trim  # noqa: B018
            _LIBC = lib
        except (OSError, AttributeError):
            _LIBC = False
    return _LIBC or None


_LIBC: Any = None


def tune_malloc(keep_bytes: int = 0) -> bool:
    """Make glibc keep and reuse freed memory (:data:`MMAP_THRESHOLD_BYTES`, ...).

    ``keep_bytes``: free heap to keep at least (the ``prefault_mb`` reserve), besides
    :data:`TRIM_THRESHOLD_BYTES`.

    Returns whether it was applied (glibc present).
    """
    lib = _libc()
    if lib is None:
        return False
    ok = lib.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    trim = max(TRIM_THRESHOLD_BYTES, int(keep_bytes) + 64 * 2**20)
    return bool(lib.mallopt(M_TRIM_THRESHOLD, min(trim, 2**31 - 1)) == 1 and ok)


def prefault_heap(nbytes: int, chunk: int = 16 * 2**20) -> int:
    """Touch ``nbytes`` of heap and free it: glibc keeps it (:func:`tune_malloc`) for reuse.

    Chunks below the mmap threshold, so that they come from the calling thread's heap.
    Returns the bytes touched (0 without glibc).
    """
    lib = _libc()
    if lib is None or nbytes <= 0:
        return 0
    import ctypes

    lib.malloc.restype = ctypes.c_void_p
    lib.malloc.argtypes = [ctypes.c_size_t]
    lib.free.argtypes = [ctypes.c_void_p]
    ptrs = []
    try:
        for _ in range(max(1, int(nbytes) // chunk)):
            ptr = lib.malloc(chunk)
            if not ptr:
                break
            ctypes.memset(ptr, 0, chunk)
            ptrs.append(ptr)
    finally:
        for ptr in reversed(ptrs):
            lib.free(ptr)
    return len(ptrs) * chunk


def malloc_trim() -> None:
    """Give the heap's free memory back to the system (glibc ``malloc_trim``; else nothing).

    Only when memory is short (over ``memory_budget_mb``): free memory kept is what makes the
    next strips cheap to receive.
    """
    lib = _libc()
    if lib is not None:
        lib.malloc_trim(0)


def heap_free_bytes() -> int:
    """Free bytes glibc keeps in its heaps, all arenas (``mallinfo2().fordblks``; 0: unknown)."""
    lib = _libc()
    if lib is None:
        return 0
    try:
        import ctypes

        class _MallInfo2(ctypes.Structure):
            _fields_ = [
                (n, ctypes.c_size_t)
                for n in (
                    "arena", "ordblks", "smblks", "hblks", "hblkhd",
                    "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost",
                )
            ]  # fmt: skip

        fn = lib.mallinfo2
        fn.restype = _MallInfo2
        return int(fn().fordblks)
    except (AttributeError, OSError):
        return 0


def rss_bytes() -> int:
    """The resident memory of the node's process, bytes (0 when /proc cannot be read)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def held_bytes(rss: int | None = None) -> int:
    """What the node holds, bytes: its resident memory less the free heap glibc keeps for reuse.

    ``rss``: the resident memory already read (:func:`rss_bytes`), so as not to read it twice.
    """
    rss = rss_bytes() if rss is None else rss
    return max(0, rss - heap_free_bytes()) if rss else 0
