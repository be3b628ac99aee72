"""The benchmark scripts' command lines and JSON output (no benchmark is run here)."""
from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("argv,msg", [(["--exp", "bogus"], "unknown experiment"),
                                      (["--exp", "room", "--kf-every", "1"], "--kf-every must be >= 2"),
                                      (["--sc-storage", "a"], "--sc-storage: expected comma-separated"),
                                      (["--exp", "pose", "--quick", "--kf-every", "15"], "fewer than 3 keyframes"),
                                      (["--max-novel", "0"], "--max-novel must be >= 1"),
                                      (["--score-scene", "moon"], "invalid choice")])
def test_mapping_benchmark_refuses_bad_arguments(argv, msg, capsys):
    with pytest.raises(SystemExit) as e:
        _load("mapping").main(argv)
    assert e.value.code == 2
    assert msg in capsys.readouterr().err


@pytest.mark.parametrize("argv,msg", [(["--sizes", "10k,1M"], "1M"), (["--repeat", "0"], "--repeat")])
def test_raster_benchmark_refuses_bad_arguments_before_running(argv, msg, capsys):
    with pytest.raises(SystemExit) as e:
        _load("raster").main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and msg in err


def test_mapping_benchmark_prints_json_when_an_experiment_fails(capsys, tmp_path):
    rc = _load("mapping").main(["--exp", "pose_frontend", "--pose-source", str(tmp_path / "missing")])
    assert rc == 1
    last = capsys.readouterr().out.strip().splitlines()[-1]
    res = json.loads(last)
    assert res["failed"] == ["pose_frontend"] and "error" in res["pose_frontend"]


def test_novel_views_are_never_keyframes_and_json_is_strict():
    m = _load("mapping")
    kf, novel = m.split_views(40, 2, 100)
    assert kf and novel and not set(kf) & set(novel)
    with pytest.raises(ValueError, match="kf_every must be >= 2"):
        m.split_views(40, 1, 100)
    out = m._json_safe({"a": float("inf"), "b": [np.float32(1.5), np.int64(3), np.bool_(True)],
                        "c": float("nan")})
    assert out == {"a": None, "b": [1.5, 3, True], "c": None}
    json.dumps(out, allow_nan=False)
    assert m._finite_mean([]) is None and m._finite_mean([1.0, 3.0]) == 2.0
    assert m.peak_rss_mb() > 10          # this very process holds more than 10 MB


def test_blend_errors_interpolate_between_start_and_refined_poses():
    """Half-way blends halve a pure correction; blending toward the truth lowers the error."""
    from vings_core.geometry import np_se3_exp
    m = _load("mapping")
    rng = np.random.default_rng(0)
    gt = {}
    for s in range(6):
        T = np.eye(4)
        T[:3, :3] = np_se3_exp(np.r_[0, 0, 0, 0.3 * rng.normal(size=3)])[:3, :3]
        T[:3, 3] = [s, 0.5 * s * s, np.sin(s)]
        gt[s] = T
    # every pose but the first off by 4 cm along x: the refinement brings them back to the truth
    start = {s: T.copy() for s, T in gt.items()}
    for s in range(1, 6):
        start[s][:3, 3] += [0.04, 0.0, 0.0]
    res = m._blend_errors(start, gt, gt)
    assert set(res) == {str(f) for f in m.BLEND_FRACTIONS}
    ate0 = m._errors_vs_gt(start, gt)["ate_sim3_m"]
    ates = [res[str(f)]["ate_sim3_m"] for f in m.BLEND_FRACTIONS]
    assert ate0 > ates[0] > ates[1] > ates[2] > 0
    # half the correction, about half the error (the Sim(3) alignment is refitted each time)
    assert math.isclose(ates[1], 0.5 * ate0, rel_tol=0.01)


def test_harness_always_prints_one_json_line_naming_what_failed(capsys):
    """A failing experiment, one with null figures and an interrupted one: the others' figures stay,
    ``failed`` names them, and the JSON is the last stdout line also when the interrupt goes on."""
    h = _load("_harness")
    out: dict = {}
    steps = [("a", lambda: {"x": 1}), ("b", lambda: 1 / 0), ("c", lambda: {"x": None, "incomplete": "x is null"})]
    assert h.run_experiments(steps, out, log=lambda *a: None) == 1
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last["a"] == {"x": 1} and last["b"]["error"].startswith("ZeroDivisionError")
    assert last["failed"] == ["b", "c"]

    def interrupted():
        raise KeyboardInterrupt
    out = {}
    with pytest.raises(KeyboardInterrupt):
        h.run_experiments([("a", lambda: {"x": 1}), ("i", interrupted), ("never", lambda: {})], out,
                          finish=lambda o: o.update(cleaned=True))
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last == {"a": {"x": 1}, "i": {"error": "interrupted (Ctrl-C)"}, "failed": ["i"], "cleaned": True}


def test_stage_profile_reports_tracking_and_mapping_steps(capsys):
    """A tiny profiled run: the table holds the tracking and mapping steps, nested totals hold
    their parts, and the last line is one JSON object."""
    _load("stage_profile").main(["--frames", "16", "--size", "128x96", "--sync"])
    out = capsys.readouterr().out.strip().splitlines()
    res = json.loads(out[-1])
    (run,) = res["runs"]
    steps = {(r["stage"], r["step"]): r for r in run["steps"]}
    assert run["frames"] == 16
    for key in [("tracking", "frame (total)"), ("tracking", "flow"), ("io", "read frame"), ("io", "write outputs")]:
        assert steps[key]["calls"] >= 1, key
    assert steps[("tracking", "frame (total)")]["calls"] == 16
    assert run["keyframes"] >= 1
    parts = sum(steps[("mapping", k)]["total_s"] for k in ("densify", "render", "loss", "backward", "pose refinement"))
    assert 0 < parts <= steps[("mapping", "keyframe (total)")]["total_s"]
