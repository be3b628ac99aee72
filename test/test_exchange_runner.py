"""`vings run` with a third pose writer in the exchange: front end and mapper end at its correction."""
from __future__ import annotations

import numpy as np
import pytest

from vings_core.exchange import ExchangeConfig, IncrementBatch, PoseFollower, WritebackPolicy
from vings_core.geometry import np_pose, np_so3_exp, sim3_apply_to_pose
from vings_core.types import Keyframe


class FixerStage:
    """A fake writer: after ``after`` keyframes it moves every keyframe it knows by ``G`` (a known
    rigid correction, as a loop closer would) and sends that through the exchange."""

    name = "fixer"

    def __init__(self, G: np.ndarray, after: int) -> None:
        self.G, self.after = G, after
        self.poses: dict[int, np.ndarray] = {}
        self.emitted: dict[int, np.ndarray] = {}
        self.follower = PoseFollower(self.name, self)
        self.fixed: set[int] = set()

    def apply_increments(self, incs: dict[int, np.ndarray]) -> None:
        for s, C in incs.items():
            self.poses[s] = sim3_apply_to_pose(C, self.poses[s])

    def add_keyframe(self, kf: Keyframe) -> None:
        s, T = int(kf.stamp_ns), kf.T_wc.numpy().astype(np.float64)
        self.poses[s], self.emitted[s] = T.copy(), T.copy()
        self.follower.keyframe_added(s, T)

    def receive(self, batch: IncrementBatch) -> None:
        self.follower.receive(batch)

    def poll(self):
        if self.fixed or len(self.poses) < self.after:
            return None
        incs = {s: self.G for s in self.poses}
        self.apply_increments(incs)
        self.fixed = set(incs)
        return self.follower.send(incs)


@pytest.mark.parametrize("sync", [True, False])
def test_vings_run_third_writer_correction_reaches_front_end_and_mapper(tmp_path, sync):
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    from vings_core.sim import generate

    generate("room", tmp_path / "room", frames=40, width=192, height=128, seed=5, mcap=False)
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 2\n"
                 "      points_per_keyframe: 1500\n      refine_iters: 2\n")
    G = np_pose(np_so3_exp(np.array([0.0, 0.05, 0.0])), np.array([0.3, 0.0, -0.2]))
    fixer = FixerStage(G, after=2)
    r = SlamRunner(open_source(tmp_path / "room"), tmp_path / "out", str(p),
                   RunConfig(sync=sync, eval_keyframes=1, eval_novel=1, save_renders=0), progress=False,
                   stages=(fixer,), exchange_cfg=ExchangeConfig(mapper=WritebackPolicy.NONE))
    r.run()
    kf = r.mapper.keyframe_poses()
    assert fixer.fixed and fixer.fixed <= set(kf)
    assert len(kf) > len(fixer.fixed), "no keyframe after the correction: the test shows nothing"
    # every stage ends at the same keyframe poses (nothing lost, nothing applied twice)
    for s, P in kf.items():
        np.testing.assert_allclose(P, r.frontend.pose(s), atol=1e-9)
        np.testing.assert_allclose(fixer.poses[s], P, atol=1e-9)
    # the first keyframe holds the gauge (the window BA never moves it) and the mapper's refinements
    # are refused: it ends exactly at the correction of its emitted pose
    first = min(kf)
    np.testing.assert_allclose(kf[first], G @ fixer.emitted[first], atol=1e-9)
    assert r.keeper.stats["applied"] >= len(fixer.fixed)


def test_vings_run_ends_with_front_end_and_mapper_agreeing(tmp_path):
    """With every mapper refinement applied, the front end's and the mapper's keyframe poses agree
    at the end of `vings run`: each stage's moves reach the other, none is lost or undone."""
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    from vings_core.sim import generate

    generate("room", tmp_path / "room", frames=24, width=192, height=128, seed=5, mcap=False)
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 2\n"
                 "      points_per_keyframe: 1500\n      refine_iters: 2\n    exchange:\n      mapper: all\n")
    r = SlamRunner(open_source(tmp_path / "room"), tmp_path / "out", str(p),
                   RunConfig(sync=True, eval_keyframes=1, eval_novel=1, save_renders=0), progress=False)
    m = r.run()
    kf = r.mapper.keyframe_poses()
    assert len(kf) >= 2 and m["frames_tracked"] >= 12
    assert r.keeper.stats["applied"] > 0, "no refinement was exchanged"
    assert max(np.abs(P - r.frontend.pose(s)).max() for s, P in kf.items()) < 1e-9
