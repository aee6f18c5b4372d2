"""apps/process.py's read-ahead and write-behind threads: order, errors, draining."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest

from parproj_ros.apps.process import ReadAhead, WriteBehind


class _Bag:
    """Records what a BagWriter would write; fails on the topic 'bad'; slow when asked."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.written: list[tuple[str, Any, int]] = []
        self.delay_s = delay_s

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        time.sleep(self.delay_s)
        if topic == "bad":
            raise OSError("disk full")
        self.written.append((topic, msg, stamp_ns))

    def write_raw(self, topic: str, data: bytes, stamp_ns: int) -> None:
        self.write(topic, ("raw", data), stamp_ns)


def test_read_ahead_keeps_order_and_raises_the_source_error() -> None:
    def source() -> Iterator[int]:
        yield from range(50)
        raise ValueError("chunk 7 is corrupt")

    got: list[int] = []
    ra = ReadAhead(source(), depth=3)
    with pytest.raises(ValueError, match="chunk 7"):
        for x in ra:
            got.append(x)
    ra.close()
    assert got == list(range(50))


def test_read_ahead_close_stops_a_blocked_reader() -> None:
    ra = ReadAhead(iter(range(10_000)), depth=2)
    assert next(iter(ra)) == 0
    ra.close()  # the thread waits on a full queue: it must see the stop and end
    assert not ra._thread.is_alive()


def test_write_behind_order_raw_bytes_and_drain() -> None:
    bag = _Bag(delay_s=0.002)
    wb = WriteBehind(bag, depth=2)  # type: ignore[arg-type]
    for i in range(20):
        wb.write("t", i, i)
    wb.write("blocks", b"\x00\x01", 99)
    wb.drain()
    assert len(bag.written) == 21  # every message written when drain returns
    wb.close()
    assert [m for _, m, _ in bag.written[:20]] == list(range(20))
    assert bag.written[20] == ("blocks", ("raw", b"\x00\x01"), 99)


def test_write_behind_error_raised_and_later_messages_dropped() -> None:
    bag = _Bag()
    wb = WriteBehind(bag, depth=2)  # type: ignore[arg-type]
    wb.write("t", 1, 1)
    wb.write("bad", 2, 2)
    for i in range(10):  # never blocks: the thread keeps draining after the error
        try:
            wb.write("t", 3 + i, 3)
        except OSError:
            break
    with pytest.raises(OSError, match="disk full"):
        wb.close()
    assert bag.written[0] == ("t", 1, 1)
    assert all(m != 2 for _, m, _ in bag.written)
    assert not wb._thread.is_alive()


def test_error_path_never_hangs_on_a_queue_lock_a_signal_left_held() -> None:
    """A SIGTERM exception raised in the main thread just after it took a queue's lock (before
    the ``with`` block: bpo-29988) leaves the lock held; ``parproj process`` then hung in
    ReadAhead.close (seen under load: py-spy showed the reader waiting for the lock and the
    main thread joining it). The error path now waits a bounded time and leaves the daemon
    threads behind."""
    ra = ReadAhead(iter(range(10_000)), depth=2)
    assert next(iter(ra)) == 0
    ra._q.mutex.acquire()  # what the interrupted get() left
    t0 = time.monotonic()
    ra.close(timeout=0.5)
    assert time.monotonic() - t0 < 2.0
    bag = _Bag(delay_s=0.002)
    wb = WriteBehind(bag, depth=2)  # type: ignore[arg-type]
    for i in range(3):
        wb.write("t", i, i)
    wb._q.mutex.acquire()  # the same, in write()
    t0 = time.monotonic()
    wb.abort(timeout=0.5)
    assert time.monotonic() - t0 < 2.0


def test_write_behind_abort_writes_what_is_queued() -> None:
    bag = _Bag(delay_s=0.002)
    wb = WriteBehind(bag, depth=8)  # type: ignore[arg-type]
    for i in range(5):
        wb.write("t", i, i)
    wb.abort(timeout=5.0)
    assert not wb._thread.is_alive()
    assert [m for _, m, _ in bag.written] == list(range(5))
