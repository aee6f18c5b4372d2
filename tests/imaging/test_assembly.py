"""SceneAssembler: strips -> scenes (length, gap, scene id, flush), gap filling, rejections."""

from __future__ import annotations

import numpy as np
import pytest

from parproj_ros.imaging.assembly import Scene, SceneAssembler, StripRejectedError

MS = 1_000_000  # ns per millisecond
LP = 1e-3  # line period of most tests: 1 ms, an integer number of nanoseconds
T0 = 1_700_000_000 * 1_000_000_000


def strip(lines: int, first_value: int, width: int = 4, dtype: type = np.uint16) -> np.ndarray:
    """Lines numbered first_value, first_value + 1, ... (every pixel of line i holds its value)."""
    col = np.arange(first_value, first_value + lines, dtype=np.int64)
    return np.repeat(col[:, None], width, axis=1).astype(dtype)


def stamp(line: int) -> int:
    """Exposure time of acquisition line ``line`` (1 ms line period from T0)."""
    return T0 + line * MS


# ---- closing by length --------------------------------------------------------------------------


def test_scene_closed_by_length_with_straddling_strip() -> None:
    asm = SceneAssembler("left", LP, scene_lines=10, max_gap_lines=4)
    assert asm.add(stamp(0), "a", strip(6, 0)) == []
    assert asm.is_open
    done = asm.add(stamp(6), "a", strip(6, 6))  # lines 6..11: 4 to scene 0, 2 start scene 1
    assert len(done) == 1
    s0 = done[0]
    assert (s0.view, s0.scene_id, s0.index, s0.reason) == ("left", "a", 0, "length")
    assert s0.lines == 10 and s0.detectors == 4 and s0.gaps == 0
    assert s0.first_line_ns == stamp(0)
    assert s0.last_line_ns == stamp(9)
    np.testing.assert_array_equal(s0.image[:, 0], np.arange(10))
    assert asm.is_open
    done = asm.add(stamp(12), "a", strip(3, 12))  # contiguous with the remainder: no gap
    assert done == []
    (s1,) = asm.flush()
    assert (s1.index, s1.reason, s1.gaps) == (1, "flush", 0)
    # The remainder (lines 10, 11) starts scene 1 at the exposure time of line 10.
    assert s1.first_line_ns == stamp(10)
    assert s1.lines == 5
    np.testing.assert_array_equal(s1.image[:, 0], np.arange(10, 15))
    assert s1.last_line_ns == stamp(14)
    assert not asm.is_open
    assert asm.flush() == []


def test_strip_spanning_several_scenes_is_cut_at_every_boundary() -> None:
    asm = SceneAssembler("v", LP, scene_lines=4)
    done = asm.add(stamp(0), "a", strip(11, 0))
    assert [s.lines for s in done] == [4, 4]
    assert [s.index for s in done] == [0, 1]
    assert [s.first_line_ns for s in done] == [stamp(0), stamp(4)]
    np.testing.assert_array_equal(done[1].image[:, 0], [4, 5, 6, 7])
    (last,) = asm.flush()
    assert last.first_line_ns == stamp(8) and last.lines == 3
    np.testing.assert_array_equal(last.image[:, 2], [8, 9, 10])


def test_straddle_time_with_non_integer_nanosecond_line_period() -> None:
    lp = 1.0 / 6500.0  # 153846.15... ns
    asm = SceneAssembler("pan", lp, scene_lines=100)
    stamps = [T0 + round(k * 64 * lp * 1e9) for k in range(4)]
    done: list[Scene] = []
    for k, st in enumerate(stamps):
        done += asm.add(st, "s", strip(64, 64 * k, width=3))
    done += asm.flush()
    assert [s.lines for s in done] == [100, 100, 56]
    assert [s.gaps for s in done] == [0, 0, 0]
    for s in done:
        exact = T0 + s.index * 100 * lp * 1e9  # acquisition line 100 k
        assert abs(s.first_line_ns - exact) <= 1.0, (s.index, s.first_line_ns - exact)
        assert int(s.image[0, 0]) == 100 * s.index
    assert abs(done[0].last_line_ns - (T0 + 99 * lp * 1e9)) <= 0.5


# ---- closing by gap, scene id and flush ---------------------------------------------------------


def test_gap_larger_than_max_closes_the_scene() -> None:
    asm = SceneAssembler("v", LP, scene_lines=0, max_gap_lines=5)
    asm.add(stamp(0), "a", strip(8, 0))
    done = asm.add(stamp(8 + 6), "a", strip(3, 14))  # 6 missing lines > 5
    assert len(done) == 1
    s0 = done[0]
    assert (s0.reason, s0.lines, s0.gaps, s0.index) == ("gap", 8, 0, 0)
    np.testing.assert_array_equal(s0.image[:, 0], np.arange(8))
    (s1,) = asm.flush()
    # A new scene of the same frame_id gets a part number: scene ids stay unique in a run.
    assert (s1.first_line_ns, s1.lines, s1.index, s1.scene_id) == (stamp(14), 3, 1, "a#1")


def test_gap_of_max_gap_lines_is_filled_with_nodata_and_counted() -> None:
    asm = SceneAssembler("v", LP, max_gap_lines=5, nodata=65000)
    asm.add(stamp(0), "a", strip(8, 0))
    assert asm.add(stamp(13), "a", strip(4, 13)) == []  # lines 8..12 missing: exactly 5
    assert asm.add(stamp(18), "a", strip(2, 18)) == []  # line 17 missing: 1 more
    (s,) = asm.flush()
    assert s.reason == "flush"
    assert s.gaps == 6
    assert s.lines == 20
    assert s.first_line_ns == stamp(0) and s.last_line_ns == stamp(19)
    expected = np.arange(20)
    expected[8:13] = 65000
    expected[17] = 65000
    np.testing.assert_array_equal(s.image[:, 0], expected)
    assert s.image.dtype == np.uint16
    # Every real line sits at row (t - first_line) / line period: times are kept through the fill.
    for row in (13, 16, 18, 19):
        assert s.first_line_ns + row * MS == stamp(int(s.image[row, 0]))


def test_float_gap_filled_with_nan_nodata() -> None:
    asm = SceneAssembler("v", LP, max_gap_lines=3, nodata=float("nan"))
    asm.add(stamp(0), "a", strip(2, 0, dtype=np.float32))
    asm.add(stamp(4), "a", strip(2, 4, dtype=np.float32))
    (s,) = asm.flush()
    assert s.gaps == 2 and s.image.dtype == np.float32
    assert np.isnan(s.image[2:4]).all()
    np.testing.assert_array_equal(s.image[[0, 1, 4, 5], 0], [0, 1, 4, 5])


def test_stamp_jitter_below_half_a_line_is_not_a_gap() -> None:
    asm = SceneAssembler("v", LP, max_gap_lines=2)
    asm.add(stamp(0), "a", strip(5, 0))
    asm.add(stamp(5) + 400_000, "a", strip(5, 5))  # 0.4 line late
    asm.add(stamp(10) - 400_000, "a", strip(5, 10))  # 0.4 line early
    (s,) = asm.flush()
    assert (s.lines, s.gaps) == (15, 0)
    np.testing.assert_array_equal(s.image[:, 0], np.arange(15))


def test_scene_id_change_closes_the_scene() -> None:
    asm = SceneAssembler("right", LP)
    asm.add(stamp(0), "scene_a", strip(4, 0))
    asm.add(stamp(4), "scene_a", strip(4, 4))
    done = asm.add(stamp(8), "scene_b", strip(4, 8, width=6))  # contiguous but another scene
    assert len(done) == 1
    a = done[0]
    assert (a.scene_id, a.reason, a.lines, a.index, a.detectors) == (
        "scene_a",
        "scene_change",
        8,
        0,
        4,
    )
    (b,) = asm.flush()
    assert (b.scene_id, b.reason, b.lines, b.index, b.detectors) == ("scene_b", "flush", 4, 1, 6)
    assert b.first_line_ns == stamp(8)


def test_flush_without_data_and_indices_continue_after_flush() -> None:
    asm = SceneAssembler("v", LP)
    assert asm.flush() == []
    asm.add(stamp(0), "a", strip(3, 0))
    (s0,) = asm.flush()
    asm.add(stamp(100), "a", strip(3, 100))
    (s1,) = asm.flush()
    assert (s0.index, s1.index) == (0, 1)
    assert s1.first_line_ns == stamp(100)


def test_gap_filled_across_the_scene_length_keeps_scene_lines() -> None:
    # 8 lines, 3 missing lines (filled), then 6 lines: with scene_lines = 10, the first scene
    # must hold exactly 10 lines (8 real + 2 filled); the rest of the fill and the strip go on.
    asm = SceneAssembler("v", LP, scene_lines=10, max_gap_lines=5, nodata=0)
    asm.add(stamp(0), "a", strip(8, 1))  # values 1..8 (0 is nodata)
    done = asm.add(stamp(11), "a", strip(6, 12))  # lines 11..16, values 12..17
    done += asm.flush()
    assert done[0].lines == 10, f"scene of {done[0].lines} lines with scene_lines = 10"
    assert done[0].gaps == 2
    np.testing.assert_array_equal(done[0].image[:, 0], [1, 2, 3, 4, 5, 6, 7, 8, 0, 0])
    assert all(s.lines <= 10 for s in done)
    # Every real line of the second strip keeps its exposure time.
    for s in done:
        for row in np.flatnonzero(s.image[:, 0] >= 12):
            assert s.first_line_ns + row * MS == stamp(int(s.image[row, 0]) - 1)


# ---- rejected strips ----------------------------------------------------------------------------


def _started() -> SceneAssembler:
    asm = SceneAssembler("v", LP, max_gap_lines=8)
    asm.add(stamp(0), "a", strip(5, 0))
    asm.add(stamp(5), "a", strip(5, 5))
    return asm


def _finish_and_check(asm: SceneAssembler) -> None:
    """After a rejection the open scene is unchanged: a good strip continues it exactly."""
    assert asm.add(stamp(10), "a", strip(5, 10)) == []
    (s,) = asm.flush()
    np.testing.assert_array_equal(s.image, strip(15, 0))
    assert s.image.dtype == np.uint16
    assert (s.first_line_ns, s.lines, s.gaps, s.index) == (stamp(0), 15, 0, 0)


@pytest.mark.parametrize(
    ("bad", "text"),
    [
        (np.zeros((0, 4), np.uint16), "shape"),
        (np.zeros((3, 0), np.uint16), "shape"),
        (np.zeros(4, np.uint16), "shape"),
        (np.zeros((3, 4, 1), np.uint16), "shape"),
        (np.zeros((3, 4), np.int32), "int32"),
        (np.zeros((3, 4), np.float64), "float64"),
        (np.zeros((3, 4), np.uint8), "uint8"),  # dtype change inside a scene
        (np.zeros((3, 5), np.uint16), "5 px"),  # width change inside a scene
    ],
    ids=["no-lines", "no-detectors", "1-d", "3-d", "int32", "float64", "dtype-change", "width"],
)
def test_rejected_strip_leaves_the_scene_unchanged(bad: np.ndarray, text: str) -> None:
    asm = _started()
    with pytest.raises(StripRejectedError, match=text):
        asm.add(stamp(10), "a", bad)
    _finish_and_check(asm)


def test_duplicate_strip_rejected() -> None:
    asm = _started()
    with pytest.raises(StripRejectedError, match=r"5 lines before .*duplicate or out of order"):
        asm.add(stamp(5), "a", strip(5, 5))
    _finish_and_check(asm)


def test_out_of_order_overlapping_strip_rejected() -> None:
    asm = _started()
    with pytest.raises(StripRejectedError, match="8 lines before"):
        asm.add(stamp(2), "a", strip(5, 2))
    _finish_and_check(asm)


def test_late_strip_after_a_filled_gap_rejected() -> None:
    asm = SceneAssembler("v", LP, max_gap_lines=8)
    asm.add(stamp(0), "a", strip(5, 0))
    asm.add(stamp(8), "a", strip(2, 8))  # lines 5..7 filled
    with pytest.raises(StripRejectedError, match="5 lines before"):
        asm.add(stamp(5), "a", strip(3, 5))  # the missing lines, too late
    (s,) = asm.flush()
    assert (s.lines, s.gaps) == (10, 3)
    np.testing.assert_array_equal(s.image[:, 0], [0, 1, 2, 3, 4, 0, 0, 0, 8, 9])


def test_width_and_dtype_may_change_with_a_new_scene() -> None:
    asm = SceneAssembler("v", LP)
    asm.add(stamp(0), "a", strip(2, 0))
    (a,) = asm.add(stamp(2), "b", np.ones((2, 7), np.float32))
    (b,) = asm.flush()
    assert a.image.dtype == np.uint16 and b.image.dtype == np.float32 and b.detectors == 7


def test_duplicate_of_a_strip_that_completed_a_scene_rejected() -> None:
    # The docstring: a strip that overlaps lines already received is rejected. The strip that
    # closed scene 0 by length arrives a second time; it must not become a second scene.
    asm = SceneAssembler("v", LP, scene_lines=10)
    asm.add(stamp(0), "a", strip(5, 0))
    (s0,) = asm.add(stamp(5), "a", strip(5, 5))
    assert s0.lines == 10
    with pytest.raises(StripRejectedError):
        asm.add(stamp(5), "a", strip(5, 5))
    assert asm.flush() == []


# ---- Scene arithmetic ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("lines", "lp", "expected"),
    [
        (1, 1e-3, 0),
        (2, 1e-3, 1_000_000),
        (768, 1.0 / 6500.0, 118_000_000),  # 767 / 6500 s = 118 ms exactly
        (100, 1.0 / 6500.0, 15_230_769),  # 99 / 6500 s = 15230769.23 ns
        (3, 0.1234567891, 246_913_578),  # 0.2469135782 s, rounded to the nanosecond
    ],
)
def test_scene_last_line_ns(lines: int, lp: float, expected: int) -> None:
    img = np.zeros((lines, 2), np.uint8)
    s = Scene("v", "a", 0, 5_000_000_000, lp, img)
    assert s.last_line_ns == 5_000_000_000 + expected
    assert isinstance(s.last_line_ns, int)
    assert (s.lines, s.detectors) == (lines, 2)


# ---- line buffers reused from scene to scene (BufferPool) --------------------------------------


def test_a_scene_still_held_keeps_its_buffer_and_a_released_one_is_reused() -> None:
    """Scene k's array is handed to a later scene only once nothing refers to scene k's image;
    every scene's pixels stay its own (no scene is overwritten by the next)."""
    asm = SceneAssembler("v", LP, scene_lines=10)
    held = []
    for k in range(4):
        held += asm.add(stamp(10 * k), "s", strip(10, 10 * k))
    # Four scenes held: two arrays kept by the pool, the others allocated and not kept.
    assert [int(sc.image[0, 0]) for sc in held] == [0, 10, 20, 30]
    assert [int(sc.image[-1, 0]) for sc in held] == [9, 19, 29, 39]
    assert asm.pool.reused == 0 and asm.pool.allocated == 4
    del held[:]  # every scene let go: the next ones reuse the kept arrays
    out = []
    for k in range(4, 8):
        out += asm.add(stamp(10 * k), "s", strip(10, 10 * k))
        out = out[-1:]  # the consumer keeps only the latest scene
    assert asm.pool.reused >= 3 and asm.pool.allocated <= 5
    assert int(out[0].image[0, 0]) == 70 and int(out[0].image[-1, 0]) == 79


def test_pool_never_hands_out_an_array_in_use() -> None:
    from parproj_ros.imaging.assembly import BufferPool

    pool = BufferPool(keep=2)
    a = pool.take(5, 3, np.dtype(np.uint16))
    b = pool.take(5, 3, np.dtype(np.uint16))
    a[:] = 1
    b[:] = 2
    view_of_a = a[1:3]  # a view holds the array too
    del a
    c = pool.take(5, 3, np.dtype(np.uint16))  # both kept arrays in use: a new one
    c[:] = 3
    assert (view_of_a == 1).all() and (b == 2).all()
    del view_of_a
    d = pool.take(4, 3, np.dtype(np.uint16))  # a's array is free now
    assert pool.reused == 1 and d.shape == (4, 3)
    assert pool.take(9, 3, np.dtype(np.uint16)).shape == (9, 3)  # too small to reuse


def test_streamed_scene_reuses_the_front_of_its_buffer() -> None:
    """Lines released by a streaming consumer make room: the retained lines move to the front
    and the array touched stays a few strips long, whatever the scene length."""
    asm = SceneAssembler("v", LP, scene_lines=0)
    for k in range(50):
        asm.add(stamp(8 * k), "s", strip(8, 8 * k))
        first, data = asm.retained()
        assert int(data[0, 0]) == first and int(data[-1, 0]) == 8 * k + 7
        asm.release(8 * k + 4)  # keep the last 4 lines
    assert asm._open is not None and asm._open.data is not None
    assert asm._open.data.high <= 32  # of the 400 lines that went through it


def test_pool_live_bytes_count_every_array_alive_kept_or_not() -> None:
    """live_bytes: the arrays kept plus those allocated while the pool was full, as long as a
    scene holds them (what the overload admission reads as raw data held)."""
    from parproj_ros.imaging.assembly import BufferPool

    pool = BufferPool(keep=1)
    a = pool.take(4, 10, np.dtype(np.uint16))  # kept
    b = pool.take(4, 10, np.dtype(np.uint16))  # pool full, a in use: not kept, alive via b
    assert pool.held_bytes == 80
    assert pool.live_bytes == 160
    del b
    assert pool.live_bytes == 80
    del a  # kept by the pool: still alive
    assert pool.live_bytes == 80
    pool.clear()
    assert pool.live_bytes == 0
