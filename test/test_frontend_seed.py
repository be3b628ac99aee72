"""Sparse-feature seeds of the dense flow (``vings_core/frontend/seed.py``) and their use by the
front end when the motion between two images is beyond the dense flow's reach."""
from __future__ import annotations

import numpy as np
import pytest

from vings_core.frontend import Frontend, FrontendConfig
from vings_core.frontend.seed import (SeedFeatures, SparseMatches, interpolate_displacements,
                                      match_features, pnp_seed, sample_grid)
from vings_core.frontend.synthetic import make_box_scene, orbit_trajectory, render_box
from vings_core.types import CameraModel, Frame, TrackState

CAM = CameraModel(160, 120, 110.0, 110.0, 79.5, 59.5)
K = np.array([[110.0, 0, 79.5], [0, 110.0, 59.5], [0, 0, 1]])


def _texture(h=240, w=320, seed=0) -> np.ndarray:
    import cv2
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return img.astype(np.uint8)


def test_sample_grid_matches_a_loop_reference():
    rng = np.random.default_rng(1)
    grid = rng.normal(size=(7, 9))
    pts = rng.uniform(-5, 80, size=(50, 2))
    stride, off = 8, 3.5
    ref = []
    for u, v in pts:          # slow, obvious reference: clamp, then bilinear by hand
        x = min(max((u - off) / stride, 0), 8)
        y = min(max((v - off) / stride, 0), 6)
        x0, y0 = min(int(x), 7), min(int(y), 5)
        ax, ay = x - x0, y - y0
        ref.append((1 - ay) * ((1 - ax) * grid[y0, x0] + ax * grid[y0, x0 + 1])
                   + ay * ((1 - ax) * grid[y0 + 1, x0] + ax * grid[y0 + 1, x0 + 1]))
    assert np.allclose(sample_grid(grid, pts, stride), ref, atol=1e-12)


@pytest.mark.parametrize("kind", [SeedFeatures.ORB, SeedFeatures.SIFT])
def test_matches_follow_a_shift_far_beyond_the_dense_flow(kind):
    img = _texture()
    shift = np.array([37.0, -21.0])
    moved = np.roll(img, (int(shift[1]), int(shift[0])), axis=(0, 1))
    m = match_features(img, moved, kind, 800)
    assert len(m) >= 50
    inside = ((m.p0[:, 0] < 320 - 45) & (m.p0[:, 0] > 5) & (m.p0[:, 1] > 30) & (m.p0[:, 1] < 235))
    d = (m.p1 - m.p0)[inside]
    good = np.linalg.norm(d - shift, axis=1) < 1.5
    assert good.mean() > 0.9


def test_no_seed_when_switched_off_or_blank():
    img = _texture()
    assert len(match_features(img, img, SeedFeatures.NONE)) == 0
    blank = np.full_like(img, 128)
    assert len(match_features(blank, img, SeedFeatures.ORB)) == 0


def _pose(rz_deg, t):
    import cv2
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.05, np.deg2rad(rz_deg), 0.02]))[0]
    T[:3, 3] = t
    return T


def test_pnp_seed_recovers_the_pose_from_grid_depth_and_rejects_outliers():
    rng = np.random.default_rng(3)
    h, w, stride = 15, 20, 8
    inv = 1.0 / (2.0 + 0.5 * np.sin(np.arange(w) / 4.0))[None].repeat(h, 0)      # smooth depth
    valid = np.ones((h, w), bool)
    valid[:, :3] = False                                                      # unknown depth there
    T0 = _pose(5, [0.1, 0.0, 0.2])
    T1 = _pose(-20, [0.5, -0.1, 0.3])                                         # a 25 degree turn
    p0 = rng.uniform([0, 0], [159, 119], size=(300, 2))
    d = sample_grid(inv, p0, stride)
    X_c0 = (np.linalg.inv(K) @ np.c_[p0, np.ones(300)].T).T / d[:, None]
    X_w = (X_c0 - T0[:3, 3]) @ T0[:3, :3]
    X_c1 = X_w @ T1[:3, :3].T + T1[:3, 3]
    p1 = (X_c1 @ K.T)[:, :2] / X_c1[:, 2:]
    p1[:60] += rng.uniform(-40, 40, size=(60, 2))                              # 20 % wrong matches
    seed = pnp_seed(SparseMatches(p0, p1), inv, valid, K, T0, stride, 20, 2.0)
    assert seed is not None and seed.inliers >= 150
    assert np.abs(seed.T_cw - T1).max() < 1e-4
    assert pnp_seed(SparseMatches(p0[:10], p1[:10]), inv, valid, K, T0, stride, 20, 2.0) is None
    assert pnp_seed(SparseMatches(p0, p1), inv, np.zeros_like(valid), K, T0, stride, 20, 2.0) is None


def test_interpolated_displacements_reproduce_a_rigid_shift():
    rng = np.random.default_rng(4)
    p0 = rng.uniform(0, 150, size=(200, 2))
    m = SparseMatches(p0, p0 + [30.0, 12.0])
    uv = np.stack(np.meshgrid(np.arange(3.5, 160, 8), np.arange(3.5, 120, 8)), -1).reshape(-1, 2)
    disp = interpolate_displacements(m, uv)
    assert disp is not None and np.allclose(disp, [30.0, 12.0], atol=1e-9)
    assert interpolate_displacements(SparseMatches(p0[:5], p0[:5]), uv) is None


def _turn_run(seed_features: str):
    """The box orbit with a sudden, unpredicted 16 degree turn of the camera after frame 14 (about
    25 px at 160x120): the constant-velocity prior is far off and the dense flow cannot follow."""
    import cv2
    scene = make_box_scene(seed=1)
    poses = orbit_trajectory(36, radius=1.5, arc=1.6)
    R = np.eye(4)
    R[:3, :3] = cv2.Rodrigues(np.array([0.0, np.deg2rad(16.0), 0.0]))[0]
    poses = np.array([p if k < 15 else p @ R for k, p in enumerate(poses)])
    fe = Frontend(FrontendConfig(keyframe_flow_lr_px=1.2, seed_features=seed_features), CAM)
    states = {}
    for k in range(24):
        img, _ = render_box(scene, CAM, poses[k])
        for e in fe.process(Frame(1_000_000_000 + k * 50_000_000, img, CAM)):
            states[k] = e.state
        fe.pop_keyframes()
    return fe, states, poses


def test_a_sudden_turn_beyond_the_dense_flow_is_tracked_by_seeding():
    fe, states, poses = _turn_run("orb")
    assert fe.stats["seeded"] >= 1
    assert all(states[k] == TrackState.TRACKING for k in range(15, 24))
    assert fe.stats["segments"] == 1
    # the turn itself is measured: rotation 14 -> 15 against the truth
    tr = fe.trajectory(states=("tracking",))
    P = {int(round((s - 1_000_000_000) / 50_000_000)): T for s, T in zip(tr.stamps_ns, tr.poses)}
    R_est = P[14][:3, :3].T @ P[15][:3, :3]
    R_gt = poses[14][:3, :3].T @ poses[15][:3, :3]
    err_deg = np.rad2deg(np.arccos(np.clip((np.trace(R_est.T @ R_gt) - 1) / 2, -1, 1)))
    assert err_deg < 0.5


def test_without_seeding_the_same_turn_loses_tracking():
    fe, states, _ = _turn_run("none")
    assert fe.stats["seeded"] == 0
    assert states[15] != TrackState.TRACKING


def _far_start_run(seed_features: str):
    """The first image, then the orbit seen 6 frames later and turned by 16 degrees: the second
    image is ~40 px away from the first, beyond the dense flow."""
    import cv2
    scene = make_box_scene(seed=1)
    poses = orbit_trajectory(36, radius=1.5, arc=1.6)
    R = np.eye(4)
    R[:3, :3] = cv2.Rodrigues(np.array([0.0, np.deg2rad(16.0), 0.0]))[0]
    keep = [0] + list(range(6, 14))
    fe = Frontend(FrontendConfig(keyframe_flow_lr_px=1.2, seed_features=seed_features), CAM)
    for k in keep:
        img, _ = render_box(scene, CAM, poses[k] if k == 0 else poses[k] @ R)
        fe.process(Frame(1_000_000_000 + k * 50_000_000, img, CAM))
        fe.pop_keyframes()
    return fe, fe.frame_states()


def test_initialisation_across_a_large_motion_is_seeded():
    fe, states = _far_start_run("orb")
    assert fe.stats["seeded"] >= 1
    assert states[1_000_000_000] == TrackState.TRACKING            # the first image is a keyframe
    assert sum(s == TrackState.TRACKING for s in states.values()) >= 8
    _, states_off = _far_start_run("none")
    assert sum(s == TrackState.TRACKING for s in states_off.values()) == 0
