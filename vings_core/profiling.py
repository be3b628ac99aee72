"""Where the time of a run goes: wall-clock timers per stage and step.

``with timed("tracking", "flow"): ...`` adds the block's wall time to the process-wide
:data:`PROFILE` when it is enabled (``vings run --profile``, ``benchmarks/stage_profile.py``); disabled,
a timer costs one attribute read. Steps nest (a step's time includes its sub-steps'); the table
reports each (stage, step) pair with its calls, total, mean and share of the run's wall time.
Thread-safe: the mapper thread and the tracking thread add to the same table.
"""
from __future__ import annotations

import functools
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Iterator


@dataclass
class StepTime:
    """Accumulated wall time of one (stage, step) pair, in seconds."""

    calls: int = 0
    total_s: float = 0.0
    max_s: float = 0.0


@dataclass
class Profile:
    """Process-wide table of step times; off until :meth:`enable`."""

    enabled: bool = False
    steps: dict[tuple[str, str], StepTime] = field(default_factory=dict)
    started: float = 0.0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def enable(self) -> None:
        """Clear the table and start timing."""
        with self._lock:
            self.steps.clear()
            self.started = time.perf_counter()
            self.enabled = True

    def disable(self) -> None:
        self.enabled = False

    def add(self, stage: str, step: str, seconds: float) -> None:
        with self._lock:
            st = self.steps.setdefault((stage, step), StepTime())
            st.calls += 1
            st.total_s += seconds
            st.max_s = max(st.max_s, seconds)

    def snapshot(self) -> dict[tuple[str, str], float]:
        """Total seconds so far of every ``(stage, step)`` (a copy; the run's timeline takes
        differences of these)."""
        with self._lock:
            return {k: st.total_s for k, st in self.steps.items()}

    def table(self, wall_s: float | None = None) -> list[dict]:
        """Rows ``{stage, step, calls, total_s, mean_ms, max_ms, share}`` sorted by stage, then total
        time; ``share`` is the fraction of ``wall_s`` (default: the time since :meth:`enable`)."""
        wall = wall_s if wall_s is not None else time.perf_counter() - self.started
        with self._lock:
            rows = [{"stage": stage, "step": step, "calls": st.calls, "total_s": st.total_s,
                     "mean_ms": 1e3 * st.total_s / max(st.calls, 1), "max_ms": 1e3 * st.max_s,
                     "share": st.total_s / wall if wall > 0 else None}
                    for (stage, step), st in self.steps.items()]
        return sorted(rows, key=lambda r: (r["stage"], -r["total_s"]))


#: the process-wide profile every :func:`timed` block adds to
PROFILE = Profile()


@contextmanager
def timed(stage: str, step: str) -> Iterator[None]:
    """Time the block as ``(stage, step)`` when :data:`PROFILE` is enabled."""
    if not PROFILE.enabled:
        yield
        return
    t0 = time.perf_counter()
    try:
        yield
    finally:
        PROFILE.add(stage, step, time.perf_counter() - t0)


def format_table(rows: list[dict]) -> str:
    """The profile as a Markdown table (the form benchmarks/RESULTS.md keeps)."""
    out = ["| stage | step | calls | total s | mean ms | max ms | share of wall |", "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        share = "" if r["share"] is None else f"{100 * r['share']:.1f} %"
        out.append(f"| {r['stage']} | {r['step']} | {r['calls']} | {r['total_s']:.2f} | {r['mean_ms']:.1f} | "
                   f"{r['max_ms']:.1f} | {share} |")
    return "\n".join(out)


def profiled(stage: str, step: str):
    """Decorator: time every call of the function as ``(stage, step)`` (see :func:`timed`)."""
    def wrap(fn):
        @functools.wraps(fn)
        def inner(*args, **kwargs):
            if not PROFILE.enabled:
                return fn(*args, **kwargs)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                PROFILE.add(stage, step, time.perf_counter() - t0)
        return inner
    return wrap


def timed_iter(items, stage: str, step: str):
    """Yield from ``items``, timing each ``next()`` as ``(stage, step)`` (e.g. reading and decoding
    frames)."""
    it = iter(items)
    while True:
        with timed(stage, step):
            try:
                item = next(it)
            except StopIteration:
                return
        yield item
