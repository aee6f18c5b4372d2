"""Row parts of an image handled by a few threads (OpenCV and numpy release the GIL).

The heights step's work around its two SGBM passes (the checks, the DSM gridding, the
ortho-image) is per row; split into as many parts as OpenCV has threads, it runs on the cores
the matcher itself uses (:func:`cv2.getNumThreads`), so that the step and a bare SGBM pass are
timed with the same threads.

The threads are kept between calls (one pool per process, grown to the largest count asked
for): starting 8 threads per heights step cost some 0.02 s of its wall time. The calling
thread takes parts too; a part that calls :func:`run_parts` again runs its own parts in its
thread (no pool thread ever waits for the pool).
"""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import TypeVar, cast

import cv2

__all__ = ["row_parts", "run_parts", "workers"]

T = TypeVar("T")

_lock = threading.Lock()
_local = threading.local()
_pool: ThreadPoolExecutor | None = None
_pool_pid = 0
_pool_size = 0


def _after_fork_in_child() -> None:
    """A forked child has none of the parent's threads, and its lock may be held by one."""
    global _lock, _pool, _pool_pid, _pool_size
    _lock = threading.Lock()
    _pool, _pool_pid, _pool_size = None, 0, 0


os.register_at_fork(after_in_child=_after_fork_in_child)


def workers() -> int:
    """Threads to use: OpenCV's (``cv2.setNumThreads``), at least 1."""
    return max(1, int(cv2.getNumThreads()))


def row_parts(rows: int, parts: int, min_rows: int = 64) -> list[tuple[int, int]]:
    """``rows`` cut into at most ``parts`` equal (start, stop) spans of >= ``min_rows`` rows.

    At least one span (``[(0, rows)]`` for a small image); no empty span.
    """
    k = max(1, min(parts, rows // max(1, min_rows)))
    edges = [round(i * rows / k) for i in range(k + 1)]
    return [(a, b) for a, b in itertools.pairwise(edges) if b > a] or [(0, rows)]


def _mark_worker() -> None:
    _local.in_pool = True


def _submit(fn: Callable[[], None], size: int) -> list[Future[None]]:
    """``fn`` submitted ``size`` times to this process's pool of at least ``size`` threads.

    Under the lock that may replace the pool (a larger one, or a new one after a fork), so
    that nothing is submitted to a pool that was just shut down.
    """
    global _pool, _pool_pid, _pool_size
    with _lock:
        pid = os.getpid()
        if _pool is None or _pool_pid != pid or _pool_size < size:
            old = _pool if _pool_pid == pid else None
            _pool = ThreadPoolExecutor(
                max_workers=size, thread_name_prefix="parproj-rows", initializer=_mark_worker
            )
            _pool_pid, _pool_size = pid, size
            if old is not None:
                old.shutdown(wait=False)  # its threads end once their work is done
        return [_pool.submit(fn) for _ in range(size)]


def run_parts(fn: Callable[[tuple[int, int]], T], parts: list[tuple[int, int]]) -> list[T]:
    """``fn`` of every part, results in order; on :func:`workers` threads when there are several.

    The caller and up to ``workers() - 1`` pool threads take the parts in turn, each the next
    one not taken yet (a pool thread that starts late finds none left: a caller never waits
    for another caller's work). All parts have ended when it returns, also when one raised
    (then the first exception, in part order, is raised).
    """
    n = min(workers(), len(parts))
    if n <= 1 or getattr(_local, "in_pool", False):
        return [fn(p) for p in parts]
    results: list[T | None] = [None] * len(parts)
    errors: dict[int, BaseException] = {}
    order = iter(range(len(parts)))
    take = threading.Lock()

    def runner() -> None:
        while True:
            with take:
                i = next(order, None)
            if i is None:
                return
            try:
                results[i] = fn(parts[i])
            except BaseException as exc:  # raised in the caller below
                errors[i] = exc

    futures = _submit(runner, n - 1)
    runner()
    # a runner still queued (the pool busy with another caller's parts) has nothing left to
    # take: it is dropped, not waited for; a running one is finishing one of these parts
    # (concurrent.futures.wait would wait for the pool to dequeue a cancelled one)
    wait([f for f in futures if not f.cancel()])
    if errors:
        raise errors[min(errors)]
    return cast("list[T]", results)
