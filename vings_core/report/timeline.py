"""``timeline.jsonl``: one JSON line per mapped keyframe, the data the run report draws over time.

A line (keys always present, ``null`` where a stage is off)::

    {"index": 12, "stamp_ns": 1700000001200000000, "t_s": 14.2,
     "steps": {"tracking": {"frame (total)": 0.81, "flow": 0.40, ...}, "mapping": {...}, ...},
     "stage_s": {"tracking": 0.81, "mapping": 1.52, "eraser": 0.11, "loop": 0.09, "io": 0.02},
     "gaussians": {"active": 41000, "passive": 12000, "on_disk": 0, "total": 53000},
     "rss_mb": 812.4, "tracking": "tracking", "vi_state": "visual-inertial",
     "mapper": {"light": false, "backlog": 0},
     "loop": {"candidates": 1, "accepted": 0} | null,
     "eraser": {"masked_fraction": 0.04, "time_ms": 110.2, "proposals": 212,
                "dynamic_rerender": 3, "dynamic_motion": 2} | null}

* ``t_s``: wall seconds from the start of the run to the end of this keyframe's mapping;
* ``steps``: seconds spent in each profiled (stage, step) since the previous line, by every thread
  (tracking of the frames in between included); steps nest (a step includes its sub-steps, see
  :mod:`vings_core.profiling`), so only ``stage_s`` adds up: each stage's ``... (total)`` step
  (``tracking``: frames, ``mapping``, ``eraser``, ``loop``: keyframes) and ``io``'s frame reading;
* ``gaussians``: after this keyframe: in the active set, in the passive store (``on_disk`` of
  those spilled to disk), total;
* ``rss_mb``: resident memory of the process (MiB) at that moment;
* ``tracking`` / ``vi_state``: the front end's state and the visual-inertial state (null without
  a front end, e.g. ``--gt-poses``);
* ``loop``: candidates the loop closer checked for this keyframe and how many it accepted;
* ``eraser``: the dynamic eraser's masked fraction and time for this keyframe, its proposals and
  how many of them each cue found dynamic.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Optional

from ..errors import InputError
from ..profiling import PROFILE, Profile

TIMELINE_FILE = "timeline.jsonl"
#: the non-overlapping per-stage totals (stage -> its outermost step)
STAGE_TOTALS = {"io": "read frame", "tracking": "frame (total)", "eraser": "keyframe (total)",
                "mapping": "keyframe (total)", "loop": "keyframe (total)"}


def current_rss_mb() -> Optional[float]:
    """Resident memory of this process now (MiB; ``/proc/self/statm``), None where unavailable."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except (OSError, ValueError, IndexError):
        return None


class Timeline:
    """Collects the timeline's lines during a run (:meth:`record` from the mapper's thread after
    each keyframe). The step times come from ``profile`` (enabled by the runner)."""

    def __init__(self, profile: Profile = PROFILE, t0: Optional[float] = None) -> None:
        self.profile = profile
        self.t0 = time.perf_counter() if t0 is None else t0
        self.lines: list[dict] = []
        self._last = profile.snapshot()

    def record(self, stamp_ns: int, gaussians: dict, tracking: Optional[str], vi_state: Optional[str],
               mapper: dict, loop: Optional[dict], eraser: Optional[dict]) -> dict:
        """Append the line of keyframe ``stamp_ns`` (see the module doc) and return it."""
        now = self.profile.snapshot()
        steps: dict[str, dict[str, float]] = {}
        for (stage, step), total in now.items():
            d = total - self._last.get((stage, step), 0.0)
            if d > 0:
                steps.setdefault(stage, {})[step] = round(d, 6)
        self._last = now
        stage_s = {st: steps.get(st, {}).get(step, 0.0) for st, step in STAGE_TOTALS.items()}
        rss = current_rss_mb()
        line = {"index": len(self.lines), "stamp_ns": int(stamp_ns),
                "t_s": round(time.perf_counter() - self.t0, 4), "steps": steps, "stage_s": stage_s,
                "gaussians": {k: int(v) for k, v in gaussians.items()},
                "rss_mb": None if rss is None else round(rss, 1), "tracking": tracking,
                "vi_state": vi_state, "mapper": mapper, "loop": loop, "eraser": eraser}
        self.lines.append(line)
        return line

    def text(self) -> str:
        return "".join(json.dumps(ln, allow_nan=False) + "\n" for ln in self.lines)


def read_timeline(path: str | Path) -> list[dict]:
    """The lines of a ``timeline.jsonl`` (an :class:`InputError` naming the line when one is not
    a JSON object)."""
    out = []
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise InputError(f"{path}: cannot read the timeline ({e.strerror or e})") from None
    for no, ln in enumerate(text.splitlines(), 1):
        if not ln.strip():
            continue
        try:
            d = json.loads(ln)
        except json.JSONDecodeError as e:
            raise InputError(f"{path}: line {no} is not JSON ({e.msg})") from None
        if not isinstance(d, dict) or "stamp_ns" not in d:
            raise InputError(f"{path}: line {no} is not a timeline record (no stamp_ns)")
        out.append(d)
    return out
