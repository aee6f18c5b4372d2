"""The ``parproj`` command line: offline work with the parallel projection library.

This module parses and dispatches; each sub-command is a module of :mod:`.commands`.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import re
import signal
import sys
import traceback
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn, TextIO

from ..io.files import (
    STOP_REQUESTED,
    InputError,
    Terminated,
)
from .commands import COMMANDS

#: Exit codes of every ``parproj`` command (README, "Exit codes").
EXIT_OK, EXIT_NOT_MET, EXIT_BAD_INPUT, EXIT_INTERNAL = 0, 1, 2, 3
#: Exit codes after SIGINT and SIGTERM (128 + the signal number, as a shell reports them).
EXIT_SIGINT, EXIT_SIGTERM = 128 + signal.SIGINT, 128 + signal.SIGTERM


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``parproj <command>: <option>: <problem>``, exit 2.

    ``-1e4``, ``-.5e-3`` and ``-inf`` are taken as (negative) values, not as options (argparse
    only knows ``-1`` and ``-1.5``), so that ``--z-avg -1e4`` works and ``--rate -inf`` is
    refused for what it is.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(
            r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE
        )

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: {message} (see {self.prog} --help)\n")


def package_version() -> str:
    """The installed package's version (its metadata); the source's ``__version__`` if none."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("parproj_ros")
    except PackageNotFoundError:  # run from a checkout that is not installed
        from .. import __version__

        return __version__


class _VersionAction(argparse.Action):
    """``--version``: ``parproj <version>`` on stdout, exit 0 (the metadata read only then)."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        kwargs.setdefault("help", "print parproj's version and exit")
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        print(f"{parser.prog} {package_version()}")
        parser.exit(EXIT_OK)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``parproj`` (one sub-command per offline job)."""
    parser = _Parser(prog="parproj", description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--version", action=_VersionAction, dest="version")
    parser.add_argument(
        "--debug",
        action="store_true",
        help="on an error, show the Python traceback instead of the one-line message",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    STOP_REQUESTED.set()
    raise Terminated


#: What the commands raise for input a user can fix (exit 2): domain errors of the readers,
#: and the operating system's errors on the files named.
def _input_errors(command: str) -> tuple[type[BaseException], ...]:
    import yaml

    from ..io.gcp_file import GcpFileError
    from ..ros.bag import BagError

    kinds: list[type[BaseException]] = [InputError, BagError, GcpFileError, OSError]
    kinds += [UnicodeDecodeError, yaml.YAMLError]
    with contextlib.suppress(ImportError):
        from ..rpc import RPCError

        kinds.append(RPCError)
    if command in ("import", "ventoux-eval"):
        # their readers (scene_import, rpc, ventoux, tifffile) report bad files as ValueError
        kinds.append(ValueError)
    return tuple(kinds)


def _shown(name: Any, outputs: Sequence[Any]) -> str:
    """A file as the user knows it: ``<out> (<file>)`` for one inside an output's staging folder.

    Outputs are written in ``.<out>.<random>.partial/<out>``
    (:func:`~parproj_ros.io.files.staged_output`), a name the user never gave.
    """
    path = Path(str(name))
    for out in outputs:
        if not out:
            continue
        o = Path(str(out))
        for parent in path.parents:
            if (
                parent.parent == o.parent
                and parent.name.startswith(f".{o.name}.")
                and parent.name.endswith(".partial")
            ):
                rel = path.relative_to(parent).parts
                rel = rel[1:] if rel[:1] == (o.name,) else rel  # the output is <stage>/<name>
                return f"{o} ({Path(*rel)})" if rel else str(o)
    return str(name)


def describe(err: BaseException, inputs: Sequence[Any] = (), outputs: Sequence[Any] = ()) -> str:
    """One line ``<file>: <problem>`` for a bad-input exception.

    The file is the one the exception names; failing that, for an operating-system error
    (disk full, ...) the outputs being written, and for any other error the inputs.
    """
    if isinstance(err, OSError):
        if err.filename is not None:
            names = _shown(err.filename, outputs)
            names += f" -> {_shown(err.filename2, outputs)}" if err.filename2 else ""
            return f"{names}: {err.strerror or err}"
        if err.strerror:  # "[Errno 28] No space left on device" without its number
            named = ", ".join(str(f) for f in (outputs or inputs) if f)
            return f"{named}: {err.strerror}" if named else str(err.strerror)
        inputs = outputs or inputs
    text = " ".join(str(err).split()) or type(err).__name__
    path = getattr(err, "path", None)
    if path and not text.startswith(str(path)):
        return f"{path}: {text}"
    if path or any(f and str(f) in text for f in inputs):
        return text
    named = ", ".join(str(f) for f in inputs if f)
    return f"{named}: {text}" if named else text


#: Python warnings that say nothing to a ``parproj`` user, silenced (message regex, why):
#: rasterio's NotGeoreferencedWarning on every image without a map georeferencing, which is
#: the rule for images with RPC (their grid is the RPC's; the crop origin is read separately).
QUIET_WARNINGS = (r"Dataset has no geotransform, gcps, or rpcs",)


@contextlib.contextmanager
def one_line_warnings(name: str) -> Iterator[None]:
    """Python warnings as one line each, ``<name>: note: <message>`` on stderr; some silenced.

    Python prints a warning as ``file.py:123: SomeWarning: text`` and the source line that
    raised it (rasterio, numpy, ...): a traceback-like pair of lines that names our code's
    innards, not the input. Inside this block each warning is one line saying what it says;
    deprecation warnings and :data:`QUIET_WARNINGS` are not shown at all.
    GDAL's warnings, which rasterio logs (logger ``rasterio``), become ``<name>: note: GDAL:
    <text>`` too.
    """

    def show(
        message: Warning | str,
        category: type[Warning],
        filename: str,
        lineno: int,
        file: TextIO | None = None,
        line: str | None = None,
    ) -> None:
        text = " ".join(str(message).split())
        print(f"{name}: note: {text}", file=sys.stderr if file is None else file)

    class GdalNotes(logging.Handler):
        """GDAL's own warnings, which rasterio logs as ``CPLE_AppDefined in <text>``."""

        def emit(self, record: logging.LogRecord) -> None:
            text = re.sub(r"^CPLE_\w+ in ", "", " ".join(record.getMessage().split()))
            print(f"{name}: note: GDAL: {text}", file=sys.stderr)

    gdal_log = logging.getLogger("rasterio")
    handler = GdalNotes(logging.WARNING)
    propagate = gdal_log.propagate
    gdal_log.addHandler(handler)
    gdal_log.propagate = False
    try:
        with warnings.catch_warnings():
            # deprecations speak to developers (Python ignores them outside __main__; pytest and
            # -W show them: --debug does too), never to a user of the command
            for category in (DeprecationWarning, PendingDeprecationWarning):
                warnings.simplefilter("ignore", category)
            for pattern in QUIET_WARNINGS:
                warnings.filterwarnings("ignore", message=pattern)
            warnings.showwarning = show
            yield
    finally:
        gdal_log.removeHandler(handler)
        gdal_log.propagate = propagate


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``parproj`` console script; returns the exit code (README)."""
    args = build_parser().parse_args(argv)
    name = f"parproj {args.command}"
    previous = signal.getsignal(signal.SIGTERM)
    previous_int = signal.getsignal(signal.SIGINT)
    with contextlib.suppress(ValueError):  # not the main thread: leave the signals alone
        signal.signal(signal.SIGTERM, _on_sigterm)
        # SIGINT stops a command (exit 130) even when it was started with SIGINT ignored, as
        # a shell starts a background job (`parproj replay bag &`, then `kill -INT`): Python
        # leaves an ignored SIGINT ignored
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with contextlib.nullcontext() if args.debug else one_line_warnings(name):
            return int(args.func(args))
    except KeyboardInterrupt as err:
        if args.debug:
            traceback.print_exc()
        which = "SIGTERM" if isinstance(err, Terminated) else "SIGINT"
        outs = [str(o) for o in getattr(args, "outputs", []) if o]
        undone = f"; {', '.join(outs)} not written" if outs else ""
        print(f"{name}: stopped by {which}{undone}", file=sys.stderr)
        return EXIT_SIGTERM if isinstance(err, Terminated) else EXIT_SIGINT
    except MemoryError as err:
        if args.debug:
            raise
        print(f"{name}: out of memory ({err})", file=sys.stderr)
        return EXIT_INTERNAL
    except _input_errors(args.command) as err:
        if args.debug:
            raise
        where = describe(err, getattr(args, "inputs", []), getattr(args, "outputs", []))
        print(f"{name}: {where}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as err:
        if args.debug:
            raise
        print(
            f"{name}: internal error (a bug, not your input): {type(err).__name__}: "
            f"{' '.join(str(err).split())[:300]}; rerun with --debug for the traceback",
            file=sys.stderr,
        )
        return EXIT_INTERNAL
    finally:
        with contextlib.suppress(ValueError, TypeError):
            signal.signal(signal.SIGTERM, previous)
            signal.signal(signal.SIGINT, previous_int)


if __name__ == "__main__":
    sys.exit(main())
