"""The loop closer inside `vings run` (SlamRunner): loops.json and the metrics, --no-loop, and a
failing loop closer that never stops tracking or mapping."""
from __future__ import annotations

import json

import pytest

from vings_core.loop import LoopCloser, LoopConfig


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from vings_core.sim import generate
    d = tmp_path_factory.mktemp("loop_runner")
    generate("room", d / "room", frames=40, width=192, height=128, seed=5, mcap=False)
    p = d / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 2\n"
                 "      points_per_keyframe: 1500\n      refine_iters: 2\n    loop:\n      min_gap_keyframes: 2\n"
                 "      min_span_keyframes: 2\n      vocabulary_after: 3\n      vocabulary_words: 32\n")
    return d


def _run(room, out, loop_cfg=None):
    from vings_core.config import load_section
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    cfg = loop_cfg or load_section(LoopConfig, "loop", str(room / "p.yaml"))
    r = SlamRunner(open_source(room / "room"), out, str(room / "p.yaml"),
                   RunConfig(sync=True, eval_keyframes=1, eval_novel=1, save_renders=0), progress=False,
                   loop_cfg=cfg)
    return r, r.run()


def test_loops_json_and_metrics(room, tmp_path):
    r, m = _run(room, tmp_path / "out")
    d = json.loads((tmp_path / "out" / "loops.json").read_text())
    assert set(d) == {"candidates", "corrections", "retrains", "summary", "error"} and d["error"] is None
    assert d["candidates"], "no candidate was checked: the test shows nothing"
    assert all(c["reason"] and c["verdict"] in ("accepted", "rejected") for c in d["candidates"])
    assert m["loops_accepted"] == d["summary"]["loops_accepted"]
    assert m["loop_candidates_rejected"] == d["summary"]["loop_candidates_rejected"] == \
        sum(c["verdict"] == "rejected" for c in d["candidates"])
    assert m["loop_detect_ms_mean"] > 0
    assert r.loop.stats["keyframes"] == m["keyframes"]
    # --no-loop: no loop closer, no loops.json (an earlier run's is removed), null loop metrics
    cfg = LoopConfig(enabled=False)
    r2, m2 = _run(room, tmp_path / "out", cfg)
    assert r2.loop is None and not (tmp_path / "out" / "loops.json").exists()
    assert m2["loops_accepted"] is None and m2["loop_candidates_rejected"] is None


def test_a_failing_loop_closer_stops_itself_not_the_run(room, tmp_path, monkeypatch):
    calls = []

    def boom(self, kf):
        calls.append(kf.stamp_ns)
        if len(calls) == 3:
            raise RuntimeError("simulated failure")
        return None

    monkeypatch.setattr(LoopCloser, "add_keyframe", boom)
    r, m = _run(room, tmp_path / "out")
    assert len(calls) == 3 and m["keyframes"] > 3 and m["frames_tracked"] >= 20
    d = json.loads((tmp_path / "out" / "loops.json").read_text())
    assert "simulated failure" in d["error"] and str(calls[-1]) in d["error"]
    assert (tmp_path / "out" / "map.ply").exists()
