"""Row parts of an image handled by a few threads (OpenCV and numpy release the GIL).

The heights step's work around its two SGBM passes (the checks, the DSM gridding, the
ortho-image) is per row; split into as many parts as OpenCV has threads, it runs on the cores
the matcher itself uses (:func:`cv2.getNumThreads`), so that the step and a bare SGBM pass are
timed with the same threads.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import cv2

__all__ = ["row_parts", "run_parts", "workers"]

T = TypeVar("T")


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


def run_parts(fn: Callable[[tuple[int, int]], T], parts: list[tuple[int, int]]) -> list[T]:
    """``fn`` of every part, in order; on :func:`workers` threads when there are several."""
    n = min(workers(), len(parts))
    if n <= 1:
        return [fn(p) for p in parts]
    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="parproj-rows") as pool:
        return list(pool.map(fn, parts))
