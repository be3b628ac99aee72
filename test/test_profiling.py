"""Step timers (vings_core.profiling)."""
from __future__ import annotations

import threading
import time

from vings_core.profiling import PROFILE, format_table, profiled, timed


def test_timers_count_only_when_enabled_and_nest():
    PROFILE.disable()
    PROFILE.steps.clear()
    with timed("a", "outer"):
        pass
    assert PROFILE.steps == {}

    @profiled("a", "fn")
    def fn(x):
        time.sleep(0.01)
        return x + 1

    PROFILE.enable()
    try:
        with timed("a", "outer"):
            assert fn(1) == 2
            assert fn(2) == 3
        rows = {(r["stage"], r["step"]): r for r in PROFILE.table()}
    finally:
        PROFILE.disable()
    assert rows[("a", "fn")]["calls"] == 2 and rows[("a", "fn")]["total_s"] >= 0.02
    assert rows[("a", "outer")]["total_s"] >= rows[("a", "fn")]["total_s"]
    assert 0 < rows[("a", "outer")]["share"] <= 1.0 + 1e-9
    assert "| a | fn | 2 |" in format_table(list(rows.values()))


def test_timers_from_several_threads_all_count():
    PROFILE.enable()
    try:
        def work():
            for _ in range(200):
                with timed("t", "step"):
                    pass
        ts = [threading.Thread(target=work) for _ in range(4)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
        (row,) = [r for r in PROFILE.table() if r["stage"] == "t"]
    finally:
        PROFILE.disable()
    assert row["calls"] == 800


def test_a_timed_block_that_raises_still_counts():
    PROFILE.enable()
    try:
        try:
            with timed("e", "fails"):
                raise ValueError("x")
        except ValueError:
            pass
        assert [r["calls"] for r in PROFILE.table() if r["stage"] == "e"] == [1]
    finally:
        PROFILE.disable()
