"""A file written past the page cache (``O_DIRECT``): large outputs without fresh memory.

Writing a file through the page cache takes a page of memory for every 4 KiB written. On the
VMs here a page the guest has freed goes back to the host within about 2 s (``virtio_balloon``
free page reporting) and costs 1-1.5 ms per MB to touch again, so a bag of 2.2 GB written
through the cache ran at about 400 MB/s (``dd``, the first time), against 2.2-3.2 GB/s with
``O_DIRECT`` (bench/BENCHMARKS.md, "Offline"). :class:`DirectFile` copies what it is given into
one aligned buffer, reused, and writes it out whole; what is left at :meth:`DirectFile.close`
(less than an aligned block) is written without ``O_DIRECT``.

Where the file system refuses ``O_DIRECT`` (tmpfs, some network and FUSE file systems: the open
or a write fails with ``EINVAL``), the file goes on as an ordinary one: :attr:`DirectFile.direct`
tells which. The file is written sequentially: ``write`` and ``tell``, no ``seek``, no ``read``.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
from pathlib import Path
from typing import Any

#: Alignment of the buffer, of every write's length and of the file offset, bytes: the page
#: size, a multiple of every logical block size in use.
ALIGN = mmap.PAGESIZE
#: Bytes gathered before a write: large enough for the disk's speed (2-3 GB/s here with 8 MiB).
BUFFER_BYTES = 8 * 2**20


class DirectFile:
    """A new file, written with ``O_DIRECT`` where the file system allows it.

    Args:
        path: the file to create (it must not exist).
        buffer_bytes: bytes gathered per write, a multiple of :data:`ALIGN`.

    Raises:
        FileExistsError: ``path`` exists.
        OSError: the file cannot be created.
    """

    def __init__(self, path: str | os.PathLike[str], buffer_bytes: int = BUFFER_BYTES) -> None:
        if buffer_bytes <= 0 or buffer_bytes % ALIGN:
            raise ValueError(f"buffer_bytes must be a positive multiple of {ALIGN}")
        self.path = Path(path)
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
        direct = getattr(os, "O_DIRECT", 0)
        #: Whether the file is written with O_DIRECT (all but its last partial block).
        self.direct = bool(direct)
        try:
            self._fd = os.open(self.path, flags | direct, 0o644)
        except OSError as err:
            if not direct or err.errno != errno.EINVAL:
                raise
            self.direct = False  # the file system refuses O_DIRECT: an ordinary file
            self._fd = os.open(self.path, flags, 0o644)
        self._buf = mmap.mmap(-1, buffer_bytes)  # page-aligned, reused for every write
        self._view = memoryview(self._buf)
        self._fill = 0  # bytes waiting in the buffer
        self._written = 0  # bytes in the file
        self.closed = False

    def write(self, data: Any) -> int:
        """Append ``data`` (bytes-like); returns its length."""
        if self.closed:
            raise ValueError("write to a closed DirectFile")
        src = memoryview(data).cast("B")
        n = len(src)
        size = len(self._view)
        i = 0
        while i < n:
            k = min(n - i, size - self._fill)
            self._view[self._fill : self._fill + k] = src[i : i + k]
            self._fill += k
            i += k
            if self._fill == size:
                self._write_out(size)
        return n

    def tell(self) -> int:
        """Bytes written so far (the position of the next write)."""
        return self._written + self._fill

    def flush(self) -> None:
        """Nothing to do: whole buffers are written as they fill, the rest at :meth:`close`."""

    def _write_out(self, nbytes: int) -> None:
        """Write the first ``nbytes`` of the buffer; the rest moves to its start."""
        done = 0
        while done < nbytes:
            try:
                done += os.write(self._fd, self._view[done:nbytes])
            except OSError as err:
                if err.errno != errno.EINVAL or not self.direct:
                    raise
                self._no_direct()  # refused at the first write: an ordinary file from here
        self._written += nbytes
        rest = self._fill - nbytes
        if rest:
            self._view[:rest] = self._view[nbytes : self._fill]
        self._fill = rest

    def _no_direct(self, tail: bool = False) -> None:
        """Go on without O_DIRECT: refused (:attr:`direct` false), or for the ``tail``."""
        flags = fcntl.fcntl(self._fd, fcntl.F_GETFL)
        fcntl.fcntl(self._fd, fcntl.F_SETFL, flags & ~getattr(os, "O_DIRECT", 0))
        if not tail:
            self.direct = False

    def close(self) -> None:
        """Write what is left and close the file. Safe to call more than once."""
        if self.closed:
            return
        try:
            whole = self._fill - self._fill % ALIGN
            if whole:
                self._write_out(whole)
            if self._fill:  # less than one aligned block: not with O_DIRECT
                self._no_direct(tail=True)
                self._write_out(self._fill)
        finally:
            self.closed = True
            os.close(self._fd)
            self._view.release()
            self._buf.close()

    def __enter__(self) -> DirectFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
