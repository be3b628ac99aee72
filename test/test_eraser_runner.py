"""The dynamic eraser inside `vings run` (SlamRunner): masks/ and the metrics, --no-eraser, the
mask reaching the mapper and the front end, and a failing eraser that never stops the run."""
from __future__ import annotations

import numpy as np
import pytest

from vings_core.eraser import DynamicEraser, EraserConfig, read_mask_png


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from vings_core.sim import generate
    d = tmp_path_factory.mktemp("eraser_runner")
    generate("room", d / "room", frames=40, width=192, height=128, seed=5, dynamic=True, mcap=False)
    p = d / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 2\n"
                 "      points_per_keyframe: 1500\n      refine_iters: 2\n")
    return d


def _run(room, out, eraser_cfg=None):
    from vings_core.io import open_source
    from vings_core.loop import LoopConfig
    from vings_core.pipeline import RunConfig, SlamRunner
    r = SlamRunner(open_source(room / "room"), out, str(room / "p.yaml"),
                   RunConfig(sync=True, eval_keyframes=1, eval_novel=1, save_renders=0), progress=False,
                   loop_cfg=LoopConfig(enabled=False), eraser_cfg=eraser_cfg)
    return r, r.run()


def test_masks_and_metrics(room, tmp_path, monkeypatch):
    seen = {"mapper": 0, "frontend": 0}
    masked = {}
    real = DynamicEraser.process

    def process(self, kf, render):            # a known mask on every third keyframe
        res = real(self, kf, render)
        if len(masked) % 3 == 0:
            res.mask = np.zeros_like(res.mask)
            res.mask[: res.mask.shape[0] // 4, : res.mask.shape[1] // 4] = True
        masked[int(kf.stamp_ns)] = res.mask.copy()
        return res
    monkeypatch.setattr(DynamicEraser, "process", process)
    from vings_core.frontend import Frontend
    from vings_core.mapping import Mapper
    post, add = Frontend.post_dynamic_mask, Mapper.add_keyframe

    def post_spy(self, stamp, mask):
        seen["frontend"] += 1
        assert np.array_equal(mask, masked[int(stamp)])
        return post(self, stamp, mask)

    def add_spy(self, kf):
        if kf.dynamic is not None:
            seen["mapper"] += 1
            assert np.array_equal(kf.dynamic.numpy(), masked[int(kf.stamp_ns)])
        return add(self, kf)
    monkeypatch.setattr(Frontend, "post_dynamic_mask", post_spy)
    monkeypatch.setattr(Mapper, "add_keyframe", add_spy)
    r, m = _run(room, tmp_path / "out")
    files = sorted((tmp_path / "out" / "masks").glob("kf_*.png"))
    assert len(files) == m["keyframes"] == len(masked)
    for f in files:
        assert np.array_equal(read_mask_png(f), masked[int(f.stem[3:])])
    with_mask = sum(bool(v.any()) for v in masked.values())
    assert with_mask >= 2 and seen["mapper"] == with_mask and seen["frontend"] == with_mask
    assert m["masked_fraction"] == pytest.approx(np.mean([v.mean() for v in masked.values()]), abs=1e-6)
    assert m["eraser_ms_mean"] > 0 and m["eraser_error"] is None
    # --no-eraser: no masks (an earlier run's are removed), null figures
    r2, m2 = _run(room, tmp_path / "out", EraserConfig(enabled=False))
    assert r2.eraser is None and not list((tmp_path / "out" / "masks").glob("kf_*.png"))
    assert m2["masked_fraction"] is None and m2["eraser_ms_mean"] is None


def test_a_failing_eraser_stops_itself_not_the_run(room, tmp_path, monkeypatch):
    calls = []

    def boom(self, kf, render):
        calls.append(kf.stamp_ns)
        if len(calls) == 2:
            raise RuntimeError("simulated failure")
        return real(self, kf, render)
    real = DynamicEraser.process
    monkeypatch.setattr(DynamicEraser, "process", boom)
    r, m = _run(room, tmp_path / "out")
    assert len(calls) == 2 and "simulated failure" in m["eraser_error"]
    assert m["keyframes"] > 2 and m["frames_tracked"] == m["frames"]
    assert len(list((tmp_path / "out" / "masks").glob("kf_*.png"))) == 1
