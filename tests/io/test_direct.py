"""io/direct.py: a file written past the page cache holds exactly what was written."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from parproj_ros.io import direct
from parproj_ros.io.direct import ALIGN, DirectFile


def _pieces(rng: np.random.Generator, total: int) -> list[bytes]:
    """Random bytes in pieces of every kind of size: tiny, unaligned, over the buffer."""
    sizes = [1, ALIGN - 1, ALIGN, ALIGN + 1, 3 * ALIGN, 70_001, 5]
    while sum(sizes) < total:
        sizes.append(int(rng.integers(1, 3 * 2**20)))
    return [rng.integers(0, 256, n, dtype=np.uint8).tobytes() for n in sizes]


def _write(path: Path, pieces: list[bytes], buffer_bytes: int) -> DirectFile:
    f = DirectFile(path, buffer_bytes=buffer_bytes)
    pos = 0
    for p in pieces:
        assert f.tell() == pos
        assert f.write(p) == len(p)
        pos += len(p)
    assert f.tell() == pos
    f.close()
    f.close()  # twice is fine
    return f


def test_the_file_holds_every_byte(tmp_path: Path) -> None:
    """On this machine's disk (ext4) with O_DIRECT: pieces of every size, buffers of 2 sizes."""
    rng = np.random.default_rng(3)
    pieces = _pieces(rng, 12 * 2**20)
    for buf in (ALIGN * 4, 2**20):
        path = tmp_path / f"out{buf}"
        f = _write(path, pieces, buf)
        assert f.direct, "the test disk should take O_DIRECT"
        assert path.read_bytes() == b"".join(pieces)


def test_refused_at_open(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A file system that refuses O_DIRECT at open (EINVAL; tmpfs before Linux 6.6, some
    network and FUSE file systems): an ordinary file, the same bytes."""
    real = os.open

    def open_(path: object, flags: int, mode: int = 0o777) -> int:
        if flags & getattr(os, "O_DIRECT", 0):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(path, flags, mode)  # type: ignore[arg-type]

    monkeypatch.setattr(direct.os, "open", open_)
    pieces = _pieces(np.random.default_rng(4), 3 * 2**20)
    f = _write(tmp_path / "out", pieces, 2**20)
    assert not f.direct
    assert (tmp_path / "out").read_bytes() == b"".join(pieces)


def test_refused_at_the_first_write(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A file system that opens with O_DIRECT and refuses the write (EINVAL): the file goes on
    without it, nothing lost."""
    real = os.write
    refused = []

    def write(fd: int, data: object) -> int:
        if not refused:
            refused.append(fd)
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(fd, data)  # type: ignore[arg-type]

    monkeypatch.setattr(direct.os, "write", write)
    pieces = _pieces(np.random.default_rng(5), 3 * 2**20)
    f = _write(tmp_path / "out", pieces, 2**20)
    assert refused and not f.direct
    assert (tmp_path / "out").read_bytes() == b"".join(pieces)


def test_existing_file_and_bad_buffer(tmp_path: Path) -> None:
    (tmp_path / "there").write_bytes(b"x")
    with pytest.raises(FileExistsError):
        DirectFile(tmp_path / "there")
    with pytest.raises(ValueError, match="multiple"):
        DirectFile(tmp_path / "new", buffer_bytes=ALIGN + 1)
    f = DirectFile(tmp_path / "new")
    f.close()
    with pytest.raises(ValueError, match="closed"):
        f.write(b"late")
    assert (tmp_path / "new").read_bytes() == b""
