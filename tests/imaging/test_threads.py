"""Row parts on threads (imaging/threads.py): the heights step's results do not depend on them.

The checks of the matcher, the DSM gridding and the ortho-image run by row parts on OpenCV's
thread count; with one thread or two, in small blocks or one, the disparity map, the DSM (its
sums are added block by block in row order) and the ortho-image are the same to the bit.
"""

from __future__ import annotations

import os
import re
import threading
import time
from collections.abc import Iterator

import cv2
import numpy as np
import pytest

from parproj_ros.geometry import AffineModel
from parproj_ros.imaging.dense import SgbmParams, match_pair
from parproj_ros.imaging.heights import GroundMapping, make_dsm, orthoimage
from parproj_ros.imaging.resample import OutputGrid
from parproj_ros.imaging.threads import row_parts, run_parts


@pytest.fixture
def cv2_threads() -> Iterator[None]:
    """Restore OpenCV's thread count after the test."""
    n = cv2.getNumThreads()
    yield
    cv2.setNumThreads(n)


@pytest.mark.parametrize(("rows", "parts", "min_rows"), [(1083, 2, 64), (100, 4, 64), (7, 3, 1)])
def test_row_parts_cover_the_rows_once(rows: int, parts: int, min_rows: int) -> None:
    spans = row_parts(rows, parts, min_rows)
    assert spans[0][0] == 0 and spans[-1][1] == rows
    assert all(a < b for a, b in spans)
    assert all(spans[i][1] == spans[i + 1][0] for i in range(len(spans) - 1))
    assert len(spans) == max(1, min(parts, rows // min_rows))
    sizes = [b - a for a, b in spans]
    assert max(sizes) - min(sizes) <= 1  # equal parts


def test_run_parts_keeps_the_order(cv2_threads: None) -> None:
    cv2.setNumThreads(2)
    spans = row_parts(1000, 8, 1)
    assert run_parts(lambda p: p[1] - p[0], spans) == [b - a for a, b in spans]


def test_run_parts_keeps_its_threads_between_calls(cv2_threads: None) -> None:
    cv2.setNumThreads(2)
    spans = row_parts(400, 4, 1)
    seen: set[threading.Thread] = set()  # the objects: a new thread may reuse a name

    def who(p: tuple[int, int]) -> int:
        seen.add(threading.current_thread())
        time.sleep(0.01)  # long enough for the pool thread to take parts too
        return p[0]

    for _ in range(5):
        assert run_parts(who, spans) == [a for a, _ in spans]
    # the caller and one pool thread, the same one in every call
    assert len(seen) == 2 and threading.current_thread() in seen


def test_run_parts_within_a_part_and_a_failing_part(cv2_threads: None) -> None:
    cv2.setNumThreads(2)
    spans = row_parts(100, 4, 1)
    inner = [run_parts(lambda p: p[1] - p[0], row_parts(b - a, 3, 1)) for a, b in spans]
    # a part that runs parts itself (in its own thread: no wait on the pool from the pool)
    got = run_parts(
        lambda p: run_parts(lambda q: q[1] - q[0], row_parts(p[1] - p[0], 3, 1)), spans
    )
    assert got == inner
    ended: list[int] = []

    def fail_second(p: tuple[int, int]) -> int:
        time.sleep(0.005)
        ended.append(p[0])
        if p == spans[1]:
            raise ValueError(f"part {p}")
        return p[0]

    with pytest.raises(ValueError, match=re.escape(f"part {spans[1]}")):
        run_parts(fail_second, spans)
    assert sorted(ended) == [a for a, _ in spans]  # every part ran to its end before the raise


def test_a_forked_child_runs_parts_on_threads_of_its_own(cv2_threads: None) -> None:
    import multiprocessing as mp

    cv2.setNumThreads(2)
    spans = row_parts(64, 4, 1)
    assert run_parts(lambda p: p[0], spans) == [a for a, _ in spans]  # the parent's pool
    from parproj_ros.imaging import threads

    ctx = mp.get_context("fork")
    with threads._lock:  # the child is forked while a thread of the parent holds the lock
        pool = ctx.Pool(1)
    try:
        got = pool.apply_async(_parts_in_child, (spans,)).get(timeout=30)
    finally:
        pool.terminate()
    assert got == ([a for a, _ in spans], True)


def _parts_in_child(spans: list[tuple[int, int]]) -> tuple[list[int], bool]:
    from parproj_ros.imaging import threads

    cv2.setNumThreads(2)
    out = run_parts(lambda p: p[0], spans)
    return out, threads._pool is not None and threads._pool_pid == os.getpid()


def test_a_caller_does_not_wait_for_another_callers_parts(cv2_threads: None) -> None:
    """With the pool's one thread busy with B's part, A runs all its parts and returns."""
    cv2.setNumThreads(2)  # the pool: 1 thread
    go, entered = threading.Event(), threading.Semaphore(0)

    def blocked(p: tuple[int, int]) -> int:
        entered.release()
        assert go.wait(30.0)
        return p[0]

    b_out: list[list[int]] = []
    b = threading.Thread(target=lambda: b_out.append(run_parts(blocked, [(0, 1), (1, 2)])))
    b.start()
    for _ in range(2):  # B's caller and the pool thread are both inside B's parts
        assert entered.acquire(timeout=30.0)
    a_out: list[list[int]] = []
    a = threading.Thread(target=lambda: a_out.append(run_parts(lambda p: p[1], [(0, 5), (5, 9)])))
    a.start()
    a.join(30.0)
    done_while_b_blocked = not a.is_alive() and not go.is_set()
    go.set()
    a.join(30.0)
    b.join(30.0)
    assert done_while_b_blocked and a_out == [[5, 9]] and b_out == [[0, 1]]


def _pair(size: int = 256, shift: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.uniform(0, 2047, (size, size + 32)).astype(np.float32), (0, 0), 1)
    left = tex[:, 16 : 16 + size]
    cols = np.arange(size, dtype=np.float32)[None, :] + 16 + shift
    rows = np.broadcast_to(np.arange(size, dtype=np.float32)[:, None], (size, size))
    right = cv2.remap(tex, np.ascontiguousarray(cols + 0 * rows), np.ascontiguousarray(rows), 1)
    return (np.clip(left, 1, 2047).astype(np.uint16), np.clip(right, 1, 2047).astype(np.uint16))


@pytest.mark.parametrize("lr_check", ["flip", "reduced"])
def test_heights_are_the_same_on_one_thread_or_two(cv2_threads: None, lr_check: str) -> None:
    left, right = _pair()
    grid = OutputGrid(0.5, 0.0, 0.0, left.shape[1], left.shape[0])
    mapping = GroundMapping(
        grid,
        np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
        AffineModel.from_array([1, 0.1, 0.3, 0, -0.1, 1, 0.05, 0]),
    )
    out = []
    for threads, block_px in ((1, 1 << 22), (2, 1 << 22), (2, 5000)):
        cv2.setNumThreads(threads)
        res = match_pair(
            left,
            right,
            d_range=(0, 16),
            params=SgbmParams(lr_check=lr_check),  # type: ignore[arg-type]
        )
        dsm = make_dsm(res.disparity, 0.8, 100.0, mapping, fill="nearest", block_px=block_px)
        med = make_dsm(res.disparity, 0.8, 100.0, mapping, reducer="median", block_px=block_px)
        itp = make_dsm(res.disparity, 0.8, 100.0, mapping, reducer="interpolated")
        ortho = orthoimage(left, dsm, mapping, block_rows=37)
        out.append((res.disparity, dsm.heights, dsm.count, med.heights, itp.heights, ortho))
    assert np.isfinite(out[0][0]).mean() > 0.8  # it matched
    for other in out[1:]:
        for a, b in zip(out[0], other, strict=True):
            assert np.array_equal(a, b, equal_nan=True)
