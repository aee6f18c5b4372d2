"""PairAdmission (core/admission.py): the sum it admits by, read with memory readings set here.

The live behaviour under overload is tests/ros/test_overload_live.py; here each term of the
rule (README, "Overload: memory_budget_mb") is checked on its own, in bytes.
"""

from __future__ import annotations

from typing import Any

import pytest

MB = 2**20
ROW = 2 * 1024  # bytes per line: 1024 detectors, uint16
LINES = 1024  # scene lines: a scene is 2 MB, a raw pair 4 MB


class Memory:
    """The readings the admission takes: resident memory and raw data held, bytes."""

    def __init__(self) -> None:
        self.rss = 100 * MB
        self.free = 0  # free heap glibc keeps (resident, reused before the resident grows)
        self.raw = 0

    def raw_held(self) -> int:
        return self.raw


@pytest.fixture
def mem(monkeypatch: pytest.MonkeyPatch) -> Memory:
    from parproj_ros.core import admission as node

    m = Memory()
    monkeypatch.setattr(node, "rss_bytes", lambda: m.rss)
    monkeypatch.setattr(node, "held_bytes", lambda rss=None: m.rss - m.free)
    monkeypatch.setattr(node, "malloc_trim", lambda: None)
    return m


def make(mem: Memory, usable_mb: float) -> Any:
    """An admission whose budget less the headroom is ``usable_mb``."""
    from parproj_ros.core.admission import HEADROOM, PairAdmission

    adm = PairAdmission(["left", "right"], usable_mb / (1 - HEADROOM) + 1e-6, LINES, mem.raw_held)
    assert adm.usable == int(usable_mb * MB)
    return adm


def first_strip(adm: Any, k: int, view: str = "left") -> tuple[bool, list[Any], bool]:
    """The first strip (100 lines) of scene k of a view."""
    return adm.admit(view, f"{view}_{k:04d}", 100, 100 * ROW)


def test_nothing_in_flight_is_always_admitted(mem: Memory) -> None:
    adm = make(mem, 64.0)  # start-up alone (100 MB) is over it
    ok, issues, _ = first_strip(adm, 0)
    assert ok and not issues and adm.in_flight == 1
    assert adm.base == 100 * MB


def test_admitted_while_the_sum_fits_then_shed_with_its_figures(mem: Memory) -> None:
    # start-up 100 MB; pair 4 MB; working set at least 2 pairs (8 MB) before it is learnt:
    # with n in flight the new pair needs 100 + (n + 1) x 4 + 8 MB.
    adm = make(mem, 100 + 3 * 4 + 8)  # fits 2 in flight + the new one, not 3
    for k in range(3):
        ok, issues, _ = first_strip(adm, k)
        assert ok and not issues, (k, issues)
    ok, issues, _ = first_strip(adm, 3)
    assert not ok and adm.in_flight == 3
    (iss,) = issues
    assert "overload: pair 3" in iss.message and "3 pairs in flight" in iss.message
    assert "would need 124 MB" in iss.message, iss.message  # 100 + 4 x 4 + 8
    assert adm.counts == {"pairs_shed": 1, "scenes_shed": 1, "strips_shed": 1}
    # The pair's next strip: shed too, without a second WARN.
    ok, issues, _ = adm.admit("left", "left_0003", 100, 100 * ROW)
    assert not ok and not issues and adm.counts["strips_shed"] == 2


def test_raw_data_held_counts_when_above_the_pairs_in_flight(mem: Memory) -> None:
    adm = make(mem, 100 + 3 * 4 + 8)
    first_strip(adm, 0)
    first_strip(adm, 1)
    # Line buffers kept and queued strips: 20 MB held, more than 2 pairs in flight + 1 (12 MB).
    mem.raw = 20 * MB
    mem.rss = 120 * MB  # the raw data is resident: the rest is still the start-up memory
    ok, issues, _ = first_strip(adm, 2)
    assert not ok
    assert "would need 128 MB" in issues[0].message  # 100 + 20 + 8


def test_working_set_is_the_peak_seen_between_decisions(mem: Memory) -> None:
    adm = make(mem, 1000.0)
    first_strip(adm, 0)
    mem.rss = 160 * MB  # the worker's reading during the pair: 60 MB beyond start-up
    adm.sample()
    mem.rss = 120 * MB  # lower again at the next decision (a transient)
    first_strip(adm, 1)
    assert adm.working_set == 60 * MB
    # Forgotten after WORKING_SET_SAMPLES later samples without it (the load dropped).
    from parproj_ros.core.admission import WORKING_SET_SAMPLES

    for k in range(2, 2 + WORKING_SET_SAMPLES):
        first_strip(adm, k)
    assert adm.working_set == 20 * MB


def test_memory_over_the_budget_sheds(mem: Memory) -> None:
    adm = make(mem, 200.0)
    first_strip(adm, 0)
    mem.rss = 210 * MB  # 110 MB held beyond start-up, none of it raw data: the working set
    ok, issues, _ = first_strip(adm, 1)
    assert not ok and "would need 218 MB" in issues[0].message  # 100 + 2 x 4 + 110


def test_a_budget_that_cannot_hold_two_pairs_says_which_would(mem: Memory) -> None:
    # Consecutive pairs overlap: with one in flight the least need is 100 + 2 x 4 + 8 = 116 MB,
    # 122.1 MB of budget with the 5 % headroom.
    adm = make(mem, 110.0)
    first_strip(adm, 0)
    ok, issues, _ = first_strip(adm, 1)
    assert not ok
    assert "cannot hold two pairs in flight" in issues[0].message
    assert "memory_budget_mb >= 123 would" in issues[0].message
    # A budget that holds two pairs does not say it.
    adm = make(mem, 130.0)
    shed = [first_strip(adm, k) for k in range(6)]
    assert [ok for ok, _, _ in shed] == [True] * 5 + [False]  # 100 + 6 x 4 + 8 > 130
    assert "cannot hold" not in shed[5][1][0].message


def test_published_pair_leaves_the_flight(mem: Memory) -> None:
    adm = make(mem, 100 + 2 * 4 + 8)  # fits 1 in flight + the new one
    first_strip(adm, 0)
    first_strip(adm, 1)
    assert not first_strip(adm, 2)[0]
    adm.published("left", "left_0001")  # pair 1 and every earlier one
    assert adm.in_flight == 0
    assert first_strip(adm, 3)[0]


def test_free_heap_kept_is_not_working_set(mem: Memory) -> None:
    """After a burst the resident memory stays up (glibc keeps the freed heap for reuse); the
    pairs that follow reuse it, so it does not count: the node catches up."""
    adm = make(mem, 100 + 2 * 4 + 8)  # fits 1 in flight + the new one
    first_strip(adm, 0)
    mem.rss, mem.free = 300 * MB, 200 * MB  # the burst is over: 200 MB of it free heap
    ok, issues, _ = first_strip(adm, 1)
    assert ok and not issues
    assert adm.working_set == 0


def test_working_set_floor_by_what_the_pairs_are() -> None:
    """Streamed only with streaming, a scene length and two views; otherwise whole images,
    whose floor is a fixed amount plus pairs, so that at IKONOS size (738 MB pairs) the
    default budget (6144 MB) still holds pairs in flight (review: 8 pairs shed every pair)."""
    from dataclasses import replace

    from parproj_ros.core.admission import (
        WHOLE_IMAGE_WORKING_SET_MB,
        WHOLE_IMAGE_WORKING_SET_PAIRS,
        WORKING_SET_PAIRS,
        working_set_floor,
    )
    from parproj_ros.core.config import PipelineConfig
    from parproj_ros.sim.synthetic import make_platform

    cfg = PipelineConfig(views=make_platform(2048, 2048).views, scene_lines=2048)
    whole = (WHOLE_IMAGE_WORKING_SET_PAIRS, WHOLE_IMAGE_WORKING_SET_MB)
    assert working_set_floor(cfg) == (WORKING_SET_PAIRS, 0.0)
    assert working_set_floor(replace(cfg, streaming=False)) == whole
    assert working_set_floor(replace(cfg, scene_lines=0)) == whole
    assert working_set_floor(replace(cfg, views=cfg.views[:1])) == whole
    # IKONOS size, whole images, the default budget: start-up 300 MB, one pair in flight.
    pair_mb = 738.0
    need_mb = 300 + 2 * pair_mb + whole[1] + whole[0] * pair_mb
    assert need_mb < 6144 * 0.95


def test_floor_mb_counts_in_the_need(mem: Memory) -> None:
    from parproj_ros.core.admission import HEADROOM, PairAdmission

    adm = PairAdmission(
        ["left", "right"], (100 + 2 * 4 + 10 + 1 * 4) / (1 - HEADROOM) + 0.01, LINES, mem.raw_held,
        floor_pairs=1, floor_mb=10,
    )  # fmt: skip
    first_strip(adm, 0)
    assert first_strip(adm, 1)[0]  # 100 + 2 x 4 + (10 + 4) = 122 fits
    ok, issues, _ = first_strip(adm, 2)
    assert not ok and "would need 126 MB" in issues[0].message


def test_the_policy_is_a_function_of_its_terms() -> None:
    """decide_admission: pure, admitted exactly while the sum fits the usable budget."""
    from parproj_ros.core.admission import HEADROOM, MemoryTerms, decide_admission

    terms = MemoryTerms(startup=100 * MB, raw=0, pair=4 * MB, work=8 * MB, budget=0, usable=0)
    # 2 in flight: 100 + 3 x 4 + 8 = 120 MB.
    fits = MemoryTerms(**{**vars(terms), "usable": 120 * MB, "budget": 200 * MB})
    assert decide_admission(2, fits) == (True, "")
    over = MemoryTerms(**{**vars(fits), "usable": 120 * MB - 1})
    ok, why = decide_admission(2, over)
    assert not ok and "would need 120 MB" in why and "2 pairs in flight" in why
    assert "cannot hold two pairs" not in why  # 100 + 2 x 4 + 8 = 116 MB fits
    # Raw data held above the pairs in flight counts instead of them.
    held = MemoryTerms(**{**vars(fits), "raw": 20 * MB})
    ok, why = decide_admission(2, held)
    assert not ok and "would need 128 MB" in why and "raw data 20 MB" in why
    # Nothing in flight: always admitted, whatever the budget.
    assert decide_admission(0, MemoryTerms(**{**vars(terms), "usable": 1})) == (True, "")
    # A budget below two pairs in flight says which would do: 116 MB / (1 - headroom).
    ok, why = decide_admission(1, MemoryTerms(**{**vars(terms), "usable": 110 * MB}))
    import math

    assert not ok and f"memory_budget_mb >= {math.ceil(116 / (1 - HEADROOM))} would" in why


def test_decisions_are_recorded_in_the_ledger(mem: Memory) -> None:
    """The admission keeps no pair state: the pipeline ledger's book has the decisions and
    the pairs in flight, and the publication of a pair is read from it."""
    from parproj_ros.core.admission import HEADROOM, PairAdmission
    from parproj_ros.core.ledger import PairLedger

    ledger = PairLedger(["left", "right"])
    usable = 100 + 2 * 4 + 8  # one in flight + the new one
    adm = PairAdmission(
        ["left", "right"], usable / (1 - HEADROOM) + 1e-6, LINES, mem.raw_held,
        book=ledger.admission,
    )  # fmt: skip
    assert [first_strip(adm, k)[0] for k in range(3)] == [True, True, False]
    book = ledger.admission
    assert (book.decision(0), book.decision(1), book.decision(2)) == (True, True, False)
    assert book.in_flight == 2 and adm.in_flight == 2
    adm.published("left", "left_0000")
    assert book.in_flight == 1
    ok, issues, _ = first_strip(adm, 3)
    assert ok and not issues and book.decision(3) is True and book.in_flight == 2


def test_quicklook_is_shed_one_pair_before_any_pair(mem: Memory) -> None:
    """heights_quicklook on: the quick-look tiles are shed at the pair after which one more
    pair in flight would not fit, one pair before the first pair is shed, with a WARN; they
    resume, with an OK line, when two more pairs in flight would fit again."""
    from parproj_ros.core.admission import HEADROOM, PairAdmission
    from parproj_ros.core.ledger import PairLedger
    from parproj_ros.core.results import Level

    ledger = PairLedger(["left", "right"])
    # start-up 100 MB, pairs of 4 MB, working set 8 MB: n in flight + the new one need
    # 100 + 4 (n + 1) + 8 MB; 120 MB fits pairs 0, 1, 2 in flight, not pair 3.
    adm = PairAdmission(
        ["left", "right"], 120 / (1 - HEADROOM) + 1e-6, LINES, mem.raw_held,
        book=ledger.admission, quicklook=True,
    )  # fmt: skip
    said = []
    for k in range(4):
        ok, issues, _ = first_strip(adm, k)
        said.append((k, ok, [(i.level, i.message) for i in issues]))
    assert [ok for _, ok, _ in said] == [True, True, True, False]
    assert said[0][2] == [] and said[1][2] == []  # 1 more in flight: 116, then 120 MB: fit
    ((level, msg),) = said[2][2]  # pair 2 admitted; one more (3 in flight): 124 MB
    assert level is Level.WARN and "quick-look tiles shed from pair 2 on" in msg
    assert "would need 124 MB, over 120 MB usable" in msg and ledger.admission.quicklook_shed
    assert len(said[3][2]) == 1 and "pair 3 (this scene" in said[3][2][0][1]  # no second WARN
    for k in range(3):
        adm.published("left", f"left_{k:04d}")
    ok, issues, _ = first_strip(adm, 4)  # nothing in flight: 2 more would need 120 MB: fit
    assert ok and [(i.level, i.message.split(":")[0]) for i in issues] == [
        (Level.OK, "quick-look tiles resumed from pair 4 on")
    ]
    assert not ledger.admission.quicklook_shed
    assert dict(adm.memory_values())["quicklook_sheds"] == 1


def test_streamed_tiles_count_in_the_sum(mem: Memory) -> None:
    """The bytes the tile stage holds are their own term of the sum (and not working set)."""
    from parproj_ros.core.admission import HEADROOM, PairAdmission

    tiles = {"held": 0}
    adm = PairAdmission(
        ["left", "right"], 120 / (1 - HEADROOM) + 1e-6, LINES, mem.raw_held,
        tiles_held=lambda: tiles["held"],
    )  # fmt: skip
    assert first_strip(adm, 0)[0] and first_strip(adm, 1)[0]  # 116 MB with 1 in flight
    tiles["held"] = 6 * MB
    mem.rss += 6 * MB  # what the tiles hold is resident
    ok, issues, _ = first_strip(adm, 2)  # 100 + 3 x 4 + 6 + 8 = 126 MB
    assert not ok and "would need 126 MB" in issues[0].message
    assert "streamed tiles 6 MB" in issues[0].message
    assert adm.working_set == 0  # the 6 MB the tiles hold are not learnt as working set
