"""Trajectory evaluation: Umeyama, association, ATE, RPE (vings_core.eval.align / traj)."""
from __future__ import annotations

import numpy as np
import pytest

from vings_core.errors import InputError
from vings_core.eval.align import apply_sim3, umeyama
from vings_core.eval.traj import (associate, associate_indices, ate, default_rpe_lengths,
                                  evaluate_trajectory, interpolate_poses, rpe)
from vings_core.geometry import np_so3_exp, rotation_angle_deg
from vings_core.trajectory_io import read_tum
from vings_core.types import Trajectory

T0 = 1_400_000_000 * 10**9  # a realistic epoch in ns


def wavy(n: int, dt_ns: int = 50_000_000, t0: int = T0) -> Trajectory:
    """A smooth 3-D camera trajectory (a few tens of metres) with varying orientation."""
    t = np.arange(n) * dt_ns * 1e-9
    pos = np.stack([4 * np.cos(0.2 * t) + 0.5 * t, 4 * np.sin(0.25 * t), 0.5 * np.sin(0.7 * t)], 1)
    rv = np.stack([0.1 * np.sin(0.5 * t), 0.05 * np.cos(0.3 * t), 0.2 * t], 1)
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = np_so3_exp(rv)
    P[:, :3, 3] = pos
    return Trajectory(t0 + np.arange(n, dtype=np.int64) * dt_ns, P)


def sim3_copy(traj: Trajectory, s: float, rv, t) -> Trajectory:
    return Trajectory(traj.stamps_ns.copy(), apply_sim3(traj.poses, s, np_so3_exp(np.asarray(rv, float)),
                                                        np.asarray(t, float)))


# ------------------------------------------------------------------------------------ Umeyama


def test_umeyama_recovers_sim3_and_matches_evo():
    from evo.core.geometry import umeyama_alignment

    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    R = np_so3_exp(np.array([0.3, -1.2, 2.0]))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 3.0])
    s, Re, t = umeyama(src, dst, with_scale=True)
    assert s == pytest.approx(2.5, abs=1e-12)
    np.testing.assert_allclose(Re, R, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 3.0], atol=1e-12)
    # noisy case: same answer as evo's reference implementation
    noisy = dst + rng.normal(scale=0.3, size=dst.shape)
    for with_scale in (True, False):
        s, Re, t = umeyama(src, noisy, with_scale)
        r_ref, t_ref, c_ref = umeyama_alignment(src.T, noisy.T, with_scale)
        assert s == pytest.approx(c_ref, rel=1e-10)
        np.testing.assert_allclose(Re, r_ref, atol=1e-10)
        np.testing.assert_allclose(t, t_ref, atol=1e-10)
        assert np.linalg.det(Re) == pytest.approx(1.0)


def test_umeyama_reflection_gives_proper_rotation():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    dst = src * np.array([1, 1, -1])  # a mirror image: best *rotation* must still have det +1
    _, R, _ = umeyama(src, dst, with_scale=False)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_collinear_is_fine():
    src = np.stack([np.linspace(0, 10, 30), np.zeros(30), np.zeros(30)], 1)
    dst = 3 * src[:, [1, 0, 2]] + 1.0
    s, R, t = umeyama(src, dst, with_scale=True)
    assert s == pytest.approx(3.0)
    np.testing.assert_allclose(s * src @ R.T + t, dst, atol=1e-9)


@pytest.mark.parametrize("src,dst,msg", [
    (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3"),
    (np.ones((10, 3)), np.random.default_rng(0).normal(size=(10, 3)), "estimated positions are identical"),
    (np.random.default_rng(0).normal(size=(10, 3)), np.ones((10, 3)), "ground-truth positions are identical"),
    (np.zeros((5, 3)), np.zeros((6, 3)), "equal size"),
    (np.full((5, 3), np.nan), np.zeros((5, 3)), "non-finite"),
])
def test_umeyama_degenerate_errors(src, dst, msg):
    with pytest.raises(InputError, match=msg):
        umeyama(src, dst, with_scale=True)


# ------------------------------------------------------------------------------------------ ATE


def test_eval_against_itself_is_zero():
    gt = wavy(400)
    r = evaluate_trajectory(gt, gt)
    assert r["matched_poses"] == 400 and r["interpolated_poses"] == 0
    assert r["ate_sim3_m"] < 1e-9 and r["ate_se3_m"] < 1e-9
    assert r["sim3_scale"] == pytest.approx(1.0, abs=1e-9)
    assert r["rpe"] is not None
    for v in r["rpe"]["per_length"].values():
        assert v["trans_pct"] < 1e-6 and v["rot_deg_per_m"] < 1e-4


def test_eval_scaled_rotated_shifted_copy():
    gt = wavy(400)
    est = sim3_copy(gt, 2.5, [0.4, -0.3, 1.1], [10.0, -5.0, 2.0])
    r = evaluate_trajectory(est, gt)
    assert r["ate_sim3_m"] < 1e-6
    assert r["sim3_scale"] == pytest.approx(1 / 2.5, rel=1e-9)  # maps estimate units to GT metres
    assert r["ate_se3_m"] > 0.5  # a rigid alignment cannot undo the scale
    # RPE is computed after the Sim(3) scale correction: ~0 again
    assert r["rpe"]["trans_pct"] < 1e-6
    a = ate(*associate(est, gt), mode="se3")
    assert a["scale"] == 1.0 and a["rmse_m"] == pytest.approx(r["ate_se3_m"])


def test_ate_known_value():
    gt = wavy(200)
    est = Trajectory(gt.stamps_ns, gt.poses.copy())
    # alternate +-d along z: centred offset, not removable by any alignment -> RMSE exactly d
    d = 0.05
    est.poses[:, 2, 3] += d * np.where(np.arange(200) % 2 == 0, 1.0, -1.0)
    a = ate(est, gt, "se3")
    assert a["rmse_m"] == pytest.approx(d, rel=1e-3)
    assert a["max_m"] >= a["rmse_m"] >= a["mean_m"] - 1e-12


# ---------------------------------------------------------------------------------- association


def test_associate_offset_grid_nearest():
    gt = wavy(200)
    est = Trajectory(gt.stamps_ns + 3_000_000, gt.poses)  # same 20 Hz grid, 3 ms later
    e_sub, g_sub = associate(est, gt, max_dt_ns=10_000_000)
    # GT samples are 50 ms apart (> 2 * 10 ms): nearest sample, no interpolation
    assert len(e_sub) == 200
    np.testing.assert_array_equal(g_sub.stamps_ns, gt.stamps_ns)
    np.testing.assert_array_equal(g_sub.poses, gt.poses)
    a = associate_indices(est, gt, 10_000_000)
    assert not a["interpolated"].any() and np.all(a["dt_ns"] == 3_000_000)
    with pytest.raises(InputError, match="too few matched poses.*2 ms"):
        associate(est, gt, max_dt_ns=2_000_000)


def test_associate_each_gt_sample_used_once():
    gt = wavy(50)  # 20 Hz
    est = wavy(500, dt_ns=5_000_000)  # 200 Hz, same start
    e_sub, g_sub = associate(est, gt, max_dt_ns=10_000_000)
    assert len(g_sub) == len(np.unique(g_sub.stamps_ns)) == 50
    np.testing.assert_array_equal(e_sub.stamps_ns, gt.stamps_ns)  # the exact-stamp estimate wins


def test_associate_interpolates_denser_gt():
    # constant angular and linear velocity: SLERP + linear interpolation is exact
    w, v = np.array([0.1, -0.2, 0.3]), np.array([1.0, 0.5, -0.2])

    def pose_at(t_s):
        P = np.tile(np.eye(4), (len(t_s), 1, 1))
        P[:, :3, :3] = np_so3_exp(t_s[:, None] * w)
        P[:, :3, 3] = t_s[:, None] * v
        return P

    g_st = np.arange(0, 2001) * 5_000_000  # 200 Hz for 10 s
    gt = Trajectory(T0 + g_st, pose_at(g_st * 1e-9))
    e_st = np.arange(1, 200) * 50_000_000 + 2_300_000  # 20 Hz, off the GT grid
    est = Trajectory(T0 + e_st, pose_at(e_st * 1e-9))
    a = associate_indices(est, gt, 10_000_000)
    assert a["interpolated"].all()
    np.testing.assert_allclose(a["gt_poses"], est.poses, atol=1e-12)
    assert evaluate_trajectory(est, gt)["ate_se3_m"] < 1e-9
    # nearest-only would be off by the 2.3 ms (or 2.7 ms) offset
    _, g_near = associate(est, gt, interpolate=False)
    assert np.abs(g_near.positions - est.positions).max() > 1e-3
    # interpolate_poses at exact samples returns them
    np.testing.assert_allclose(interpolate_poses(gt, gt.stamps_ns[[0, 7, -1]]), gt.poses[[0, 7, -1]],
                               atol=1e-12)


def test_associate_no_overlap_and_sorting():
    gt = wavy(100)
    far = Trajectory(gt.stamps_ns + 10**12, gt.poses)
    with pytest.raises(InputError, match="no overlap in time"):
        evaluate_trajectory(far, gt)
    shuffled = np.random.default_rng(0).permutation(100)
    r = evaluate_trajectory(Trajectory(gt.stamps_ns[shuffled], gt.poses[shuffled]), gt)
    assert r["matched_poses"] == 100 and r["ate_se3_m"] < 1e-9
    dup = Trajectory(np.r_[gt.stamps_ns[:5], gt.stamps_ns[:5]], np.r_[gt.poses[:5], gt.poses[:5]])
    with pytest.raises(InputError, match="duplicated"):
        evaluate_trajectory(dup, gt)


def test_associate_partial_overlap():
    gt = wavy(200)
    est = Trajectory(gt.stamps_ns[100:] + 1_000_000, gt.poses[100:])
    gt_short = Trajectory(gt.stamps_ns[:150], gt.poses[:150])
    r = evaluate_trajectory(est, gt_short)
    assert r["matched_poses"] == 50 and r["estimate_poses"] == 100


# ------------------------------------------------------------------------------------------ RPE


def test_default_rpe_lengths_rule():
    assert default_rpe_lengths(3000) == [100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0]
    assert default_rpe_lengths(500) == [100.0, 200.0]
    assert default_rpe_lengths(90.6) == [5.0, 10.0, 25.0]
    assert default_rpe_lengths(12) == [5.0]
    assert default_rpe_lengths(6) == [1.0, 2.0]
    assert default_rpe_lengths(1.5) == []


def _drift_traj(eps: float, n: int, step: float):
    """GT: straight line along x at `step` m spacing, identity attitude. Estimate: the same speed
    but a heading drift of `eps` rad per metre (an arc of curvature eps)."""
    s = np.arange(n) * step
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3] = s
    est = np.tile(np.eye(4), (n, 1, 1))
    est[:, :3, :3] = np_so3_exp(np.stack([np.zeros(n), np.zeros(n), eps * s], 1))
    est[:, 0, 3] = np.sin(eps * s) / eps
    est[:, 1, 3] = (1 - np.cos(eps * s)) / eps
    st = T0 + np.arange(n, dtype=np.int64) * 100_000_000
    return Trajectory(st, est), Trajectory(st, gt), s


def test_rpe_known_heading_drift():
    eps, step = 0.002, 0.1  # 0.1146 deg per metre
    est, gt, s = _drift_traj(eps, 1001, step)  # 100 m
    r = rpe(est, gt, correct_scale=False)
    assert r["lengths_m"] == [5.0, 10.0, 25.0, 50.0]
    for L in r["lengths_m"]:
        # evo (all pairs, from the GT): for every start i the GT pose whose path distance is
        # closest to L, accepted within +-10 %; near the end segments are up to 10 % short
        Ls = []
        for i in range(len(s) - 1):
            d = s[i + 1:] - s[i]
            j = int(np.argmin(np.abs(d - L)))
            if abs(d[j] - L) <= 0.1 * L:
                Ls.append(d[j])
        Ls = np.array(Ls)
        terr = np.hypot(np.sin(eps * Ls) / eps - Ls, (1 - np.cos(eps * Ls)) / eps)
        rec = r["per_length"][f"{L:g}"]
        assert rec["pairs"] == len(Ls)
        assert rec["trans_pct"] == pytest.approx(100 * terr.mean() / L, rel=1e-6)
        assert rec["rot_deg_per_m"] == pytest.approx(np.degrees(eps * Ls).mean() / L, rel=1e-5)
    # rotation drift per metre is the injected one
    assert r["rot_deg_per_m"] == pytest.approx(np.degrees(eps), rel=0.02)


def test_rpe_scale_correction_and_explicit_lengths():
    gt = wavy(400)
    est = sim3_copy(gt, 2.5, [0, 0, 0], [0, 0, 0])
    r_raw = rpe(est, gt, lengths_m=[2.0, 4.0], correct_scale=False)
    assert r_raw["lengths_m"] == [2.0, 4.0] and r_raw["scale_corrected"] is False
    # relative translations are 2.5x too long: error 1.5x the segment length
    assert r_raw["per_length"]["2"]["trans_pct"] == pytest.approx(150, rel=0.12)
    assert r_raw["rot_deg_per_m"] < 1e-4
    r = rpe(est, gt, lengths_m=[2.0, 4.0], correct_scale=True)
    assert r["trans_pct"] < 1e-6
    assert rpe(est, gt, lengths_m=[]) is None
    assert rpe(est, gt, lengths_m=[1e6]) is None  # no pair that far apart
    twice = rpe(est, gt, lengths_m=[4.0, 2.0, 4.0], correct_scale=False)   # a repeated length counts once
    assert twice["lengths_m"] == [2.0, 4.0] and twice["pairs"] == r_raw["pairs"]


def test_rpe_none_for_short_path():
    gt = wavy(10)  # ~1 m
    r = evaluate_trajectory(gt, gt)
    assert r["path_length_m"] < 2 and r["rpe"] is None


def test_rotation_angle_matches_evo_convention():
    R = np_so3_exp(np.array([0.0, 0.0, np.radians(30)]))
    assert rotation_angle_deg(R) == pytest.approx(30)


def test_nearly_orthonormal_rotations_are_projected():
    """KITTI-style poses printed with few digits are not exactly orthonormal; that must not show
    up as rotation error (nor crash), while clearly broken rotations are rejected."""
    gt = wavy(300)
    noisy = Trajectory(gt.stamps_ns, gt.poses.copy())
    noisy.poses[:, :3, :3] += np.random.default_rng(0).normal(scale=1e-6, size=(300, 3, 3))
    r = evaluate_trajectory(noisy, noisy)
    assert r["rpe"]["rot_deg_per_m"] < 1e-6 and r["ate_se3_m"] < 1e-9
    bad = Trajectory(gt.stamps_ns, gt.poses.copy())
    bad.poses[5, :3, :3] *= 2
    with pytest.raises(InputError, match="not orthonormal"):
        evaluate_trajectory(bad, gt)


def test_different_time_bases_are_an_error_not_a_meaningless_ate(tmp_path):
    gt = wavy(160, dt_ns=103_600_000, t0=0)          # ~9.65 Hz (KITTI-like), seconds since start
    # the same poses stamped with the frame index as seconds: a few coincidental matches
    est = Trajectory(np.arange(160, dtype=np.int64) * 1_000_000_000, gt.poses.copy())
    with pytest.raises(InputError, match="different time bases"):
        evaluate_trajectory(est, gt)
    # a denser estimate than the ground truth is fine (each GT sample matches once)
    dense = wavy(1600, dt_ns=10_000_000, t0=0)
    assert evaluate_trajectory(dense, gt, interpolate=False)["matched_poses"] >= 150


def test_tum_stamps_in_nanoseconds_are_a_clear_error(tmp_path):
    p = tmp_path / "est_ns.tum"
    p.write_text("1700000000000000000 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"est_ns.tum:1: .*must be in seconds"):
        read_tum(p)
    p.write_text("inf 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"est_ns.tum:1: not a finite time stamp"):
        read_tum(p)


def test_reflected_rotations_are_refused():
    from vings_core.errors import InputError
    from vings_core.eval.traj import evaluate_trajectory
    from vings_core.types import Trajectory
    P = np.tile(np.eye(4), (6, 1, 1))
    P[:, 0, 3] = np.arange(6.0)
    P[:, 1, 3] = np.arange(6.0) ** 2 * 0.1
    P[:, :3, :3] = np.diag([1.0, -1.0, 1.0])
    st = np.arange(6, dtype=np.int64) * 10**8
    good = P.copy()
    good[:, :3, :3] = np.eye(3)
    with pytest.raises(InputError, match="reflections"):
        evaluate_trajectory(Trajectory(st, P), Trajectory(st, good))
