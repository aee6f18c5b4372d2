"""What every ``parproj`` command shares: input errors, option types, bounded reads, safe outputs.

- :class:`InputError`: bad input a user can fix, naming the file (or option) and the problem.
  ``parproj`` prints it as ``parproj <command>: <file>: <problem>`` and exits with 2.
- Option types for argparse (:func:`number`, :func:`integer`): finite numbers in a range; NaN,
  Inf and out-of-range values are refused before any work starts.
- :func:`input_path`, :func:`read_bounded`: inputs that exist and are of the right kind (a FIFO
  or a device is refused before it is opened, so nothing blocks), read up to a size limit.
- :func:`file_stem`: a name read from a bag (a pair or scene id) made safe as part of a file
  name: it never leaves the output folder, hides the file or exceeds a file name's length.
- :func:`check_output`, :func:`staged_output`: an output is never the input, inside it or
  around it; an existing output is only replaced with ``--force`` (and then only when it is a
  bag, or a folder parproj wrote); it is written under a temporary name beside the target and
  renamed when complete, so an interrupted run never leaves an output that looks complete.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import shutil
import stat
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Literal

__all__ = [
    "MARKER",
    "InputError",
    "check_output",
    "file_stem",
    "input_path",
    "integer",
    "number",
    "read_bounded",
    "staged_output",
]

#: The file that marks a folder written by parproj (``--force`` replaces only such folders).
MARKER = ".parproj_output"

OutputKind = Literal["bag", "folder", "file"]


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like SIGINT's KeyboardInterrupt so that outputs in progress are undone."""


#: Set by the ``parproj`` SIGTERM handler. An exception raised by a signal handler can be lost
#: (one that fires inside a callback from C is printed and ignored): :func:`staged_output`
#: checks this too before it makes an output final.
STOP_REQUESTED = threading.Event()


class InputError(ValueError):
    """Bad input a user can fix: which file (or option) and what is wrong with it.

    Attributes:
        path: the file, folder or option at fault (as the user gave it).
        problem: what is wrong, and what to do about it when that is not obvious.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = str(path) or "''"
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


# ---- option types -------------------------------------------------------------------------------


def _range_text(lo: float | None, hi: float | None, lo_open: bool) -> str:
    if lo is not None and hi is not None:
        return f"{'>' if lo_open else '>='} {lo:g} and <= {hi:g}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    return f"<= {hi:g}" if hi is not None else "finite"


def number(
    lo: float | None = None, hi: float | None = None, *, lo_open: bool = False
) -> Callable[[str], float]:
    """An argparse ``type``: a finite float within [lo, hi] (``(lo, hi]`` with ``lo_open``)."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
        if (lo is not None and (v < lo or (lo_open and v == lo))) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(
                f"{text!r} is out of range (must be {_range_text(lo, hi, lo_open)})"
            )
        return v

    parse.__name__ = "number"  # argparse names the type in some messages
    return parse


def integer(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An argparse ``type``: an integer within [lo, hi]."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(
                f"{text!r} is out of range (must be {_range_text(lo, hi, False)})"
            )
        return v

    parse.__name__ = "integer"
    return parse


# ---- inputs -------------------------------------------------------------------------------------


def input_path(path: str | os.PathLike[str], kind: Literal["file", "dir", "bag"]) -> Path:
    """An input that exists and is of the right kind; raises :class:`InputError` otherwise.

    ``file``: a regular file (not a folder, FIFO, socket or device). ``dir``: a folder.
    ``bag``: a bag folder or a regular ``.mcap``-like file.
    """
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise InputError(p, "no such file or folder") from None
    except OSError as err:
        raise InputError(p, err.strerror or str(err)) from None
    if kind == "dir":
        if not stat.S_ISDIR(st.st_mode):
            raise InputError(p, "not a folder")
    elif kind == "file" or not stat.S_ISDIR(st.st_mode):
        if stat.S_ISDIR(st.st_mode):
            raise InputError(p, "is a folder, a file was expected")
        if not stat.S_ISREG(st.st_mode):
            raise InputError(p, "not a regular file (a FIFO, socket or device): not read")
    if not os.access(p, os.R_OK):
        raise InputError(p, "permission denied")
    return p


def read_bounded(path: str | os.PathLike[str], limit: int, what: str = "file") -> bytes:
    """The bytes of a regular file of at most ``limit`` bytes.

    The file is opened without blocking and checked with ``fstat`` before anything is read, so
    a FIFO (or a device) is refused instead of waiting for a writer forever.

    Raises:
        InputError: not a regular file, larger than ``limit``, or unreadable.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise InputError(p, "no such file") from None
    except IsADirectoryError:
        raise InputError(p, f"is a folder, a {what} was expected") from None
    except OSError as err:
        raise InputError(p, err.strerror or str(err)) from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise InputError(p, f"is a folder, a {what} was expected")
        if not stat.S_ISREG(st.st_mode):
            raise InputError(p, f"not a regular file (a FIFO, socket or device): {what} not read")
        if st.st_size > limit:
            raise InputError(
                p, f"{st.st_size} bytes, more than the {limit} bytes a {what} may have"
            )
    except BaseException:
        os.close(fd)
        raise
    with os.fdopen(fd, "rb") as fh:
        try:
            data = fh.read(limit + 1)
        except OSError as err:
            raise InputError(p, err.strerror or str(err)) from None
    if len(data) > limit:  # grew while being read
        raise InputError(p, f"more than the {limit} bytes a {what} may have")
    return data


def decode_utf8(path: str | os.PathLike[str], data: bytes) -> str:
    """``data`` as UTF-8 text (a BOM is dropped); :class:`InputError` naming the bad byte."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise InputError(
            path, f"not UTF-8 text (byte 0x{data[err.start]:02x} at offset {err.start})"
        ) from None


# ---- outputs ------------------------------------------------------------------------------------


def _resolved(p: Path) -> Path:
    return Path(os.path.abspath(p)).resolve(strict=False)


def _is_bag(p: Path) -> bool:
    """A folder of nothing but ``metadata.yaml`` and ``.mcap`` files (what BagWriter makes)."""
    try:
        entries = list(p.iterdir())
    except OSError:
        return False
    return all(e.is_file() and (e.name == "metadata.yaml" or e.suffix == ".mcap") for e in entries)


def _replaceable(target: Path, kind: OutputKind) -> str | None:
    """Why an existing ``target`` may not be replaced even with --force (None: it may)."""
    if target.is_symlink():
        return "is a symbolic link: not replaced, even with --force"
    if kind == "file":
        return None if target.is_file() else "exists and is not a file: not replaced"
    if not target.is_dir():
        return "exists and is not a folder: not replaced, even with --force"
    if kind == "bag":
        if _is_bag(target):
            return None
        return "exists and is not a bag (only metadata.yaml and .mcap files): not replaced"
    if (target / MARKER).is_file() or not any(target.iterdir()):
        return None
    if _is_bag(target):  # a bag (parproj import's, or process's) where a folder goes
        return (
            "is a bag, and this command writes a folder of files (not a bag): not replaced, "
            "even with --force; give another -o (or remove the bag first)"
        )
    return f"exists and was not written by parproj (no {MARKER}): not replaced, remove it first"


def check_output(
    target: str | os.PathLike[str],
    *,
    inputs: Iterable[str | os.PathLike[str] | None] = (),
    force: bool = False,
    kind: OutputKind = "bag",
) -> Path:
    """Refuse an output that would destroy data; returns the output path.

    Args:
        target: the output (a bag folder, a folder of results, or a file).
        inputs: every input of the command (None entries are ignored).
        force: replace an existing output (a bag, a folder with :data:`MARKER`, or a file).
        kind: what the output is.

    Raises:
        InputError: the output is an input, inside one or holds one; it exists and ``force``
            is not given or it may not be replaced; its folder cannot be made or written.
    """
    out = Path(target)
    if str(target) == "" or out.name in ("", ".", ".."):
        raise InputError(target, "not a usable output name")
    r_out = _resolved(out)
    for src in inputs:
        if src is None:
            continue
        r_in = _resolved(Path(src))
        if r_out == r_in:
            raise InputError(out, f"is the input {src}: refusing to overwrite the input")
        if r_out.is_relative_to(r_in):
            raise InputError(out, f"is inside the input {src}: refusing to write there")
        if r_in.is_relative_to(r_out):
            raise InputError(out, f"holds the input {src}: refusing to replace it")
    if r_out == _resolved(Path.cwd()) or _resolved(Path.cwd()).is_relative_to(r_out):
        raise InputError(out, "is the current folder or holds it: refusing to replace it")
    if out.exists() or out.is_symlink():
        if not force:
            raise InputError(out, "exists (add --force to replace it)")
        why = _replaceable(out, kind)
        if why:
            raise InputError(out, why)
    # The nearest existing ancestor must be a folder we may write in.
    parent = r_out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(out, f"cannot be made: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(out, f"cannot be made: no permission to write in {parent}")
    return out


@contextlib.contextmanager
def staged_output(
    target: str | os.PathLike[str], *, force: bool = False, kind: OutputKind = "bag"
) -> Iterator[Path]:
    """Write an output under a temporary name beside ``target``; rename it when complete.

    Yields the path to write to: ``<parent>/.<name>.<random>.partial/<name>`` (so a bag's MCAP
    file gets its final name). When the block ends normally the result is renamed to ``target``
    (an existing ``target`` is replaced only with ``force``, as :func:`check_output` allows);
    when it raises (an error, SIGINT, SIGTERM), the temporary folder is removed and ``target``
    is left as it was. A killed process (SIGKILL) leaves only the hidden ``.partial`` folder.
    Folders (``kind="folder"``) get a :data:`MARKER` file.
    """
    out = Path(target)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    except OSError as err:
        raise InputError(out, f"cannot be made: {err.strerror or err}") from None
    work = stage / out.name
    try:
        if kind == "folder":
            work.mkdir()
            (work / MARKER).write_text("written by parproj; --force may replace this folder\n")
        yield work
        if STOP_REQUESTED.is_set():
            raise Terminated
        if not (work.exists() or work.is_symlink()):
            return  # the command wrote nothing
        if out.exists() or out.is_symlink():
            why = "exists (add --force to replace it)" if not force else _replaceable(out, kind)
            if why:
                raise InputError(out, why)
            os.replace(out, stage / ".old")
            try:
                os.replace(work, out)
            except OSError:
                os.replace(stage / ".old", out)
                raise
        else:
            os.replace(work, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


#: Longest :func:`file_stem`, characters (file names end with a suffix such as ``_dsm.tif``; a
#: file name has at most 255 bytes).
FILE_STEM_CHARS = 80


def file_stem(name: str, *, plus: str = "_") -> str:
    """``name`` (a pair or scene id, as a bag gives it) as the stem of a file name in a folder.

    ``+`` (between a pair's scene ids) becomes ``plus``; a path separator (a slash or a
    backslash), a NUL or other control character becomes ``_``, and so does a leading ``.``
    (no hidden file, no ``..``): the file stays in its folder whatever the bag holds. A stem
    longer than :data:`FILE_STEM_CHARS` keeps its start and ends with 8 hex digits of its hash
    (distinct long names stay distinct). Empty: ``pair``.
    """
    import hashlib

    out = "".join(
        plus if ch == "+" else "_" if ch in "/\\" or not ch.isprintable() else ch for ch in name
    )
    if out.startswith("."):
        out = "_" + out[1:]
    if len(out) > FILE_STEM_CHARS or len(out.encode()) > 2 * FILE_STEM_CHARS:
        digest = hashlib.sha1(name.encode()).hexdigest()[:8]
        keep = out[: FILE_STEM_CHARS - 9]
        while len(keep.encode()) > 2 * FILE_STEM_CHARS - 9:
            keep = keep[:-1]
        out = f"{keep}_{digest}"
    return out or "pair"
