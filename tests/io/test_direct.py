"""io/direct.py: a file written past the page cache holds exactly what was written."""

from __future__ import annotations

import errno
import fcntl
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
    """A file system that refuses O_DIRECT (EINVAL when the flag is set; ramfs, tmpfs before
    Linux 6.6, some network and FUSE file systems): an ordinary file, the same bytes. The file
    is created without the flag, so a refusal leaves nothing behind to collide with."""
    real = fcntl.fcntl

    def fcntl_(fd: int, cmd: int, arg: int = 0) -> int:
        if cmd == fcntl.F_SETFL and arg & getattr(os, "O_DIRECT", 0):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(fd, cmd, arg)

    monkeypatch.setattr(direct.fcntl, "fcntl", fcntl_)
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


def test_flush_puts_every_byte_in_the_file(tmp_path: Path) -> None:
    """BagWriter.flush's promise (a later cut loses nothing before): after flush the file holds
    every byte so far, the unaligned rest included; writing then goes on as before."""
    rng = np.random.default_rng(6)
    a, b = rng.bytes(3 * ALIGN + 123), rng.bytes(2 * 2**20 + 7)
    f = DirectFile(tmp_path / "out", buffer_bytes=2**20)
    f.write(a)
    f.flush()
    assert (tmp_path / "out").read_bytes() == a and f.direct
    f.write(b)
    f.flush()
    assert (tmp_path / "out").read_bytes() == a + b
    f.write(a)
    f.close()
    assert (tmp_path / "out").read_bytes() == a + b + a and f.tell() == 2 * len(a) + len(b)


def test_a_failed_write_leaves_the_file_failed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A write that stops part way (the disk full): the error is raised, later writes raise
    (the file's offset no longer matches tell()), and close only releases the file."""
    real = os.write
    calls = []

    def write(fd: int, data: object) -> int:
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, data)  # type: ignore[arg-type]

    monkeypatch.setattr(direct.os, "write", write)
    f = DirectFile(tmp_path / "out", buffer_bytes=2**20)
    f.write(b"x" * 2**20)
    with pytest.raises(OSError, match="No space"):
        f.write(b"y" * 2**20)
    with pytest.raises(OSError, match=r"an earlier write .* failed"):
        f.write(b"z")
    fd = calls[0]
    f.close()
    assert f.closed
    with pytest.raises(OSError):
        os.fstat(fd)  # the descriptor is closed
    assert (tmp_path / "out").stat().st_size == 2**20


def test_a_real_file_system_without_o_direct(tmp_path: Path) -> None:
    """ramfs refuses O_DIRECT (EINVAL when the flag is set): mounted in a mount namespace of
    its own (``unshare -m``; root, as CI runs here), a DirectFile and a BagWriter(direct=True)
    write there as ordinary files, every byte."""
    import subprocess
    import sys

    mnt = tmp_path / "ramfs"
    mnt.mkdir()
    script = (
        "import sys; from pathlib import Path\n"
        "from parproj_ros.io.direct import DirectFile\n"
        "from parproj_ros.ros.bag import BagReader, BagWriter\n"
        "m = Path(sys.argv[1]); data = bytes(range(256)) * 40000\n"
        "f = DirectFile(m / 'out.bin', buffer_bytes=2**20); f.write(data); f.close()\n"
        "assert not f.direct and (m / 'out.bin').read_bytes() == data\n"
        "with BagWriter(m / 'bag', direct=True) as bw:\n"
        "    bw.add_topic('t', 'std_msgs/msg/String')\n"
        "    bw.write_raw('t', b'\\x00\\x01\\x00\\x00\\x03\\x00\\x00\\x00ab\\x00', 5)\n"
        "got = [x.log_time_ns for x in BagReader(m / 'bag').raw_messages()]\n"
        "assert not bw.direct and got == [5], got\n"
        "print('ok')\n"
    )
    shell = f'mount -t ramfs none "$1" && exec "{sys.executable}" -c "$2" "$1"'
    run = subprocess.run(
        ["unshare", "-m", "sh", "-c", shell, "sh", str(mnt), script],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
    )
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr
