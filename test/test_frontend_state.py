"""Front-end state types (TrackState), the shared SO(3) projection, and pose increments applied to
the front end (``Frontend.apply_increments``)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from vings_core.errors import InputError
from vings_core.frontend import Frontend, FrontendConfig
from vings_core.frontend.synthetic import make_box_scene, orbit_trajectory, render_box
from vings_core.frontend.tracker import STATES
from vings_core.geometry import (np_project_rotation, np_so3_exp, orthonormalize_pose, project_rotation,
                                 sim3, sim3_apply_to_pose)
from vings_core.types import CameraModel, Frame, PoseEstimate, TrackState

CAM = CameraModel(160, 120, 110.0, 110.0, 79.5, 59.5)
STEP_NS = 50_000_000


def _cfg() -> FrontendConfig:
    return FrontendConfig(keyframe_flow_lr_px=1.2)


@pytest.fixture(scope="module")
def frames():
    scene = make_box_scene(seed=1)
    return [Frame(1_000_000_000 + k * STEP_NS, render_box(scene, CAM, T)[0], CAM)
            for k, T in enumerate(orbit_trajectory(36, radius=1.5, arc=1.6))]


def _run(frames, n: int) -> Frontend:
    fe = Frontend(_cfg(), CAM)
    for f in frames[:n]:
        fe.process(f)
        fe.pop_keyframes()
    return fe


# ----------------------------------------------------------------------------------- TrackState


def test_track_state_reads_as_its_string_value():
    assert STATES == (TrackState.WAITING, TrackState.TRACKING, TrackState.LOST, TrackState.INERTIAL)
    for st in TrackState:
        v = st.value
        assert st == v and v == st and hash(st) == hash(v) and {v: 1}[st] == 1
        assert str(st) == v and f"{st}" == v and "%s" % st == v and f"{st:>9}" == f"{v:>9}"
        assert json.dumps({"state": st}) == json.dumps({"state": v})
        assert json.dumps({st: 1}) == json.dumps({v: 1})
        assert st in (v,) and TrackState(v) is st
    est = PoseEstimate(1, np.eye(4), state="lost")
    assert est.state is TrackState.LOST and PoseEstimate(1, np.eye(4)).state is TrackState.TRACKING
    with pytest.raises(ValueError, match="not a valid TrackState"):
        PoseEstimate(1, np.eye(4), state="drifting")


def test_frontend_states_are_track_states(frames):
    fe = _run(frames, 14)
    assert fe.state is TrackState.TRACKING and fe.status()["state"] == "tracking"
    assert all(isinstance(s, TrackState) for s in fe.frame_states().values())
    assert len(fe.trajectory(states=("tracking",))) == len(fe.trajectory(states=STATES)) == 14


# ------------------------------------------------------------------------------ SO(3) projection


def test_project_rotation_is_the_nearest_proper_rotation():
    rng = np.random.default_rng(3)
    R = np_so3_exp(rng.normal(size=(20, 3)))
    noisy = R + rng.normal(scale=1e-3, size=R.shape)
    noisy[0] = np.diag([1.0, -1.0, 1.0]) @ noisy[0]              # a reflection
    P = project_rotation(torch.from_numpy(noisy)).numpy()
    assert np.allclose(np.swapaxes(P, 1, 2) @ P, np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(P), 1.0, atol=1e-12)
    assert np.abs(P[1:] - R[1:]).max() < 5e-3
    # the numpy entry point is the same computation, bit for bit
    assert np.array_equal(np_project_rotation(noisy), P)
    T = np.tile(np.eye(4), (20, 1, 1))
    T[:, :3, :3] = noisy
    T[:, :3, 3] = rng.normal(size=(20, 3))
    T[:, 3, :3] = 1e-3
    out = orthonormalize_pose(torch.from_numpy(T)).numpy()
    assert np.array_equal(out[:, :3, :3], P) and np.array_equal(out[:, :3, 3], T[:, :3, 3])
    assert np.array_equal(out[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (20, 1)))


# ------------------------------------------------------------------------------- increments


def _rigid():
    return sim3(np_so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, -0.5]))


def test_rigid_increments_equal_set_poses(frames):
    a, b = _run(frames, 22), _run(frames, 22)
    assert np.array_equal(a.trajectory().poses, b.trajectory().poses)
    C = _rigid()
    stamps = a.trajectory().stamps_ns.tolist()
    a.apply_increments({s: C for s in stamps})
    b.set_poses({s: C @ b.pose(s) for s in stamps})
    assert np.allclose(a.trajectory().poses, b.trajectory().poses, atol=1e-12)
    for ka, kb in zip(a.window, b.window):
        assert torch.allclose(ka.T_cw, kb.T_cw, atol=1e-12)
        assert torch.equal(ka.d, kb.d) and torch.equal(ka.var, kb.var)     # no rescale: rigid
    assert torch.allclose(a.motion.last.T_cw, b.motion.last.T_cw, atol=1e-12)
    # tracking goes on in the moved world frame
    for f in frames[22:28]:
        assert a.process(f)[-1].state == "tracking"


def test_sim3_increment_on_all_keyframes_scales_the_window_depths(frames):
    fe = _run(frames, 30)
    s_scale = 2.0
    C = sim3(np_so3_exp(np.array([0.0, 0.4, -0.1])), np.array([0.5, -1.0, 2.0]), s_scale)
    kfs = fe.keyframe_trajectory()
    assert len(fe.window) >= 3
    d0 = [k.d.clone() for k in fe.window]
    v0 = [k.var.clone() for k in fe.window]
    # frames after the newest keyframe are posed relative to it
    last_kf = fe.window[-1].stamp
    after = [int(s) for s in fe.trajectory().stamps_ns if s > last_kf]
    assert after
    rel0 = {s: np.linalg.inv(fe.pose(last_kf)) @ fe.pose(s) for s in after}
    fe.apply_increments({int(s): C for s in kfs.stamps_ns})
    for s, T in zip(kfs.stamps_ns, kfs.poses):
        assert np.allclose(fe.pose(int(s)), sim3_apply_to_pose(C, T), atol=1e-12)
    # uniform scale s: inverse depths scale by 1/s, their variances by 1/s^2
    for k, d, v in zip(fe.window, d0, v0):
        assert torch.allclose(k.d, d / s_scale, rtol=1e-9)
        m = torch.isfinite(v)
        assert torch.allclose(k.var[m], v[m] / s_scale ** 2, rtol=1e-9)
    for s in after:
        assert np.allclose(np.linalg.inv(fe.pose(last_kf)) @ fe.pose(s), rel0[s], atol=1e-9)
    for f in frames[30:34]:
        assert fe.process(f)[-1].state == "tracking"


def test_bad_increments_are_refused_before_any_change(frames):
    fe = _run(frames, 14)
    tr = fe.trajectory()
    s0 = int(tr.stamps_ns[0])
    with pytest.raises(InputError, match="frontend.apply_increments: stamp 123 was never processed"):
        fe.apply_increments({s0: _rigid(), 123: _rigid()})
    shear = np.eye(4)
    shear[0, 1] = 0.3
    with pytest.raises(InputError, match=f"frontend.apply_increments: increment for stamp {s0}"):
        fe.apply_increments({int(tr.stamps_ns[1]): _rigid(), s0: shear})
    with pytest.raises(InputError, match="not a similarity"):
        fe.apply_increments({s0: np.diag([1.0, 1.0, -1.0, 1.0])})
    with pytest.raises(InputError, match="never processed"):
        fe.set_poses({123: np.eye(4)})
    with pytest.raises(InputError, match="expected a 4x4 pose"):
        fe.set_poses({s0: np.eye(4)[None]})
    assert np.array_equal(fe.trajectory().poses, tr.poses)


def test_a_jump_moves_the_present_with_the_newest_corrected_keyframe(frames):
    """``apply_jump`` (a loop closer's batch): the keyframes named move by their own increments,
    every keyframe and frame newer than the newest of them by its increment; tracking goes on."""
    fe = _run(frames, 30)
    kf_stamps = [int(s) for s in fe.keyframe_trajectory().stamps_ns]
    assert len(kf_stamps) >= 3
    named = kf_stamps[:-1]                          # the newest keyframe is not in the batch
    C_old = _rigid()
    C_new = sim3(np_so3_exp(np.array([0.0, 0.0, 0.3])), np.array([0.2, 0.1, -0.3]), 1.0)
    incs = {s: C_old for s in named[:-1]}
    incs[named[-1]] = C_new
    before = {int(s): T for s, T in zip(fe.trajectory().stamps_ns, fe.trajectory().poses)}
    fe.apply_jump(incs)
    for s, T in before.items():
        if s in incs:
            want = sim3_apply_to_pose(incs[s], T)
        elif s > named[-1]:
            want = sim3_apply_to_pose(C_new, T)
        else:
            continue            # frames between named keyframes follow their reference keyframe
        assert np.allclose(fe.pose(s), want, atol=1e-9), s
    assert fe.stats["jumps"] == 1
    for f in frames[30:34]:
        assert fe.process(f)[-1].state == "tracking"
