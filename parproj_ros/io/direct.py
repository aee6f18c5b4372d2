"""A file written past the page cache (``O_DIRECT``): large outputs without fresh memory.

Writing a file through the page cache takes a page of memory for every 4 KiB written. On the
VMs here a page the guest has freed goes back to the host within about 2 s (``virtio_balloon``
free page reporting) and costs 1-1.5 ms per MB to touch again, so a bag of 2.2 GB written
through the cache ran at about 400 MB/s (``dd``, the first time), against 2.2-3.2 GB/s with
``O_DIRECT`` (bench/BENCHMARKS.md, "Offline"). :class:`DirectFile` copies what it is given into
one aligned buffer, reused, and writes it out whole; what is left at :meth:`DirectFile.close`
(less than an aligned block) is written without ``O_DIRECT``.

The file is created without ``O_DIRECT`` and the flag set afterwards (``fcntl``): Linux creates
the file before it checks the flag, so a refused open would leave it behind. Where the file
system refuses ``O_DIRECT`` (ramfs, tmpfs before Linux 6.6, some network and FUSE file systems:
setting the flag or a write fails with ``EINVAL``), the file goes on as an ordinary one:
:attr:`DirectFile.direct` tells which. The file is written sequentially: ``write``, ``tell`` and
``flush``, no ``seek``, no ``read``. A write that fails (``ENOSPC``, ``EIO``) leaves the file
failed: the error is raised, later writes raise, and :meth:`DirectFile.close` only releases it.
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
        self.closed = False
        #: The error of a write that failed; the file is then only released.
        self.failed: OSError | None = None
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
        self._fd = os.open(self.path, flags, 0o644)
        try:
            self._buf = mmap.mmap(-1, buffer_bytes)  # page-aligned, reused for every write
        except BaseException:
            os.close(self._fd)
            self.path.unlink(missing_ok=True)
            raise
        self._view = memoryview(self._buf)
        self._fill = 0  # bytes waiting in the buffer
        self._written = 0  # bytes in the file, from the buffer's start
        #: Whether the file is written with O_DIRECT (all but a last partial block).
        self.direct = self._set_direct(True)

    def _set_direct(self, on: bool) -> bool:
        """Set or clear O_DIRECT on the file; whether it is set (EINVAL: refused)."""
        flag = getattr(os, "O_DIRECT", 0)
        if not flag:
            return False
        flags = fcntl.fcntl(self._fd, fcntl.F_GETFL)
        try:
            fcntl.fcntl(self._fd, fcntl.F_SETFL, (flags | flag) if on else (flags & ~flag))
        except OSError as err:
            if err.errno != errno.EINVAL:
                raise
            return False
        return on

    def write(self, data: Any) -> int:
        """Append ``data`` (bytes-like); returns its length."""
        self._check()
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
        """Put every byte written so far in the file (not fsync).

        The whole aligned blocks are written; the rest without O_DIRECT at its place, and it
        stays in the buffer, to be written again with what follows.
        """
        self._check()
        self._write_aligned()
        if not self._fill:
            return
        if self.direct:
            self._set_direct(False)
        try:
            done = 0
            while done < self._fill:
                done += os.pwrite(self._fd, self._view[done : self._fill], self._written + done)
        except OSError as err:
            self.failed = err
            raise
        finally:
            if self.direct:
                self._set_direct(True)

    def _check(self) -> None:
        if self.closed:
            raise ValueError("I/O on a closed DirectFile")
        if self.failed is not None:
            raise OSError(f"an earlier write to {self.path} failed: {self.failed}")

    def _write_aligned(self) -> None:
        """Write the whole aligned blocks in the buffer; less than one block stays."""
        whole = self._fill - self._fill % ALIGN
        if whole:
            self._write_out(whole)

    def _write_out(self, nbytes: int) -> None:
        """Write the first ``nbytes`` of the buffer; the rest moves to its start."""
        done = 0
        try:
            while done < nbytes:
                try:
                    done += os.write(self._fd, self._view[done:nbytes])
                except OSError as err:
                    # Refused with O_DIRECT (at the first write, or a partial write left the
                    # offset unaligned): an ordinary file from here.
                    if err.errno != errno.EINVAL or not self.direct:
                        raise
                    self.direct = self._set_direct(False)
        except OSError as err:
            self.failed = err  # the file's offset no longer matches tell(): give up on it
            raise
        self._written += nbytes
        rest = self._fill - nbytes
        if rest:
            self._view[:rest] = self._view[nbytes : self._fill]
        self._fill = rest

    def close(self) -> None:
        """Write what is left and close the file; a failed one is only released.

        Safe to call more than once.
        """
        if self.closed:
            return
        try:
            if self.failed is None:
                self._write_aligned()
                if self._fill:  # less than one aligned block: not with O_DIRECT
                    if self.direct:
                        self._set_direct(False)
                    self._write_out(self._fill)
        finally:
            self.closed = True
            try:
                os.close(self._fd)
            finally:
                self._view.release()
                try:
                    self._buf.close()
                except BufferError:  # a slice still held (by a traceback): freed with it
                    pass

    def __enter__(self) -> DirectFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
