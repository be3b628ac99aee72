"""The mapping step shared by `vings run` and mapper_node (vings_core.stages.map_keyframe)."""
from __future__ import annotations

import numpy as np
import torch

from vings_core.exchange import PoseFollower
from vings_core.geometry import np_pose, np_so3_exp
from vings_core.mapping import MapperConfig
from vings_core.stages import map_keyframe
from vings_core.types import CameraModel, Keyframe


class CountingMapper:
    """Records what the step asks of it; its refinement moves keyframe 1 by a known increment."""

    def __init__(self, cfg: MapperConfig) -> None:
        self.cfg, self.poses, self.trained, self.refined = cfg, {}, 0, 0
        self.moved: list = []

    def add_keyframe(self, kf: Keyframe) -> None:
        self.poses[int(kf.stamp_ns)] = kf.T_wc.numpy().copy()

    def train(self, n: int) -> dict:
        self.trained += n
        return {"loss": 0.0}

    def keyframe_poses(self) -> dict:
        return {s: T.copy() for s, T in self.poses.items()}

    def refine_poses(self) -> dict:
        self.refined += 1
        self.poses[1] = np_pose(np_so3_exp(np.array([0.0, 0.01, 0.0])), np.zeros(3)) @ self.poses[1]
        return self.keyframe_poses()

    def apply_increments(self, incs: dict) -> None:
        self.moved.append(incs)


def _kf(stamp: int) -> Keyframe:
    cam = CameraModel(8, 8, 5.0, 5.0, 3.5, 3.5)
    z = torch.ones(8, 8)
    return Keyframe(stamp_ns=stamp, image=torch.zeros(8, 8, 3), T_wc=torch.eye(4, dtype=torch.float64),
                    depth=z, inv_depth_var=z * 0, valid=z > 0, camera=cam)


def test_full_step_trains_refines_and_sends_the_refinement():
    m = CountingMapper(MapperConfig(iters_per_keyframe=7, catch_up_backlog=2, catch_up_iters=3))
    f = PoseFollower("mapper", m)
    stats, batch = map_keyframe(m, f, _kf(1), chunk=2, backlog=1)
    assert m.trained == 7 and stats["iterations_total"] == 7 and not stats["light"]
    assert m.refined == 1 and batch is not None and list(batch.increments) == [1] and batch.seq >= 1


def test_a_keyframe_mapped_with_a_backlog_is_trained_lightly_and_kept():
    m = CountingMapper(MapperConfig(iters_per_keyframe=7, catch_up_backlog=2, catch_up_iters=3))
    f = PoseFollower("mapper", m)
    stats, batch = map_keyframe(m, f, _kf(1), backlog=2)
    assert m.trained == 3 and stats["light"] and m.refined == 0 and batch is None
    assert 1 in m.poses                     # in the map: never dropped


def test_catch_up_off_trains_every_keyframe_fully():
    m = CountingMapper(MapperConfig(iters_per_keyframe=7, catch_up_backlog=0))
    stats, _ = map_keyframe(m, PoseFollower("mapper", m), _kf(1), backlog=50)
    assert m.trained == 7 and not stats["light"]
