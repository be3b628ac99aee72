"""Visual-inertial fusion pieces (vings_core/vio): pre-integration, the visual factor on body poses,
the alignment and the smoother's marginalisation."""
from __future__ import annotations

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from vings_core.sim.imu import G_WORLD, simulate_imu  # noqa: E402
from vings_core.sim.trajectory import random_handheld  # noqa: E402
from vings_core.types import ImuSample  # noqa: E402
from vings_core.vio.align import align, excitation, gravity_alignment  # noqa: E402
from vings_core.vio.fusion import ImuBuffer  # noqa: E402
from vings_core.vio.preint import (ImuArrays, ImuNoiseConfig, gtsam_params, gtsam_preintegrate,  # noqa: E402
                                   predict, preintegrate)
from vings_core.vio.smoother import NavEstimate, WindowSmoother, _keys  # noqa: E402
from vings_core.vio.visual_factor import camera_to_body_system, visual_factor  # noqa: E402


def _pose(rng, rot=0.5, trans=1.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Expmap(rng.normal(size=3) * rot).matrix()
    T[:3, 3] = rng.normal(size=3) * trans
    return T


@pytest.fixture(scope="module")
def motion():
    """A handheld motion, its exact 200 Hz IMU, and a non-identity camera-to-body extrinsic."""
    rng = np.random.default_rng(1)
    m = random_handheld(rng, np.zeros(3), np.array([1.0, 1.0]), 1.2, 0.9)
    t = np.arange(0, 6, 0.005)
    d = simulate_imu(m, t)
    T_bc = np.eye(4)
    T_bc[:3, :3] = gtsam.Rot3.Ypr(0.1, -0.2, 1.5).matrix()
    T_bc[:3, 3] = [0.05, -0.02, 0.01]
    return m, ImuArrays((t * 1e9).round().astype(np.int64), d.gyro, d.accel), T_bc


def test_preintegration_predicts_the_simulators_exact_motion(motion):
    m, imu, _ = motion
    pre = preintegrate(imu, 1_000_000_000, 1_500_000_000)
    s = m.sample(np.array([1.0, 1.5]))
    R, p, v = predict(pre, s.R[0], s.p[0], s.v[0], G_WORLD)
    # zero-order hold of 200 Hz readings: sub-millimetre over 0.5 s
    assert np.abs(p - s.p[1]).max() < 5e-4
    assert np.abs(v - s.v[1]).max() < 2e-3
    assert np.abs(R - s.R[1]).max() < 5e-4


def test_reference_preintegration_equals_gtsam_and_bias_jacobians_hold(motion):
    _, imu, _ = motion
    pre = preintegrate(imu, 1_000_000_000, 1_500_000_000)
    pim = gtsam_preintegrate(imu, 1_000_000_000, 1_500_000_000, gtsam_params(ImuNoiseConfig()))
    assert np.abs(pim.deltaRij().matrix() - pre.dR).max() < 1e-6
    assert np.abs(pim.deltaPij() - pre.dp).max() < 1e-6
    assert np.abs(pim.deltaVij() - pre.dv).max() < 1e-6
    bg, ba = np.array([0.01, -0.02, 0.015]), np.array([0.05, 0.02, -0.03])
    exact = preintegrate(imu, 1_000_000_000, 1_500_000_000, bg, ba)
    dR, dv, dp = pre.corrected(bg, ba)
    first_order = max(np.abs(dR - exact.dR).max(), np.abs(dv - exact.dv).max(), np.abs(dp - exact.dp).max())
    uncorrected = np.abs(pre.dv - exact.dv).max()
    assert first_order < 0.02 * uncorrected


def test_visual_factor_on_body_poses_matches_finite_differences():
    rng = np.random.default_rng(0)
    T_bc, M = _pose(rng), 3
    A = rng.normal(size=(6 * M, 6 * M))
    G, g = A @ A.T + np.eye(6 * M), rng.normal(size=6 * M)
    T_wb = [_pose(rng) for _ in range(M)]
    keys = [gtsam.symbol("x", i) for i in range(M)]
    f = visual_factor(G, g, T_bc, keys, T_wb)
    v0, v1 = gtsam.Values(), gtsam.Values()
    d_b = rng.normal(size=6 * M) * 1e-4
    d_c = []
    for i, (k, T) in enumerate(zip(keys, T_wb)):
        moved = gtsam.Pose3(T).retract(d_b[6 * i:6 * i + 6])
        v0.insert(k, gtsam.Pose3(T))
        v1.insert(k, moved)
        # the camera perturbation the body perturbation causes, measured on the poses
        d_c.append(gtsam.Pose3.Logmap(gtsam.Pose3(T @ T_bc).between(moved * gtsam.Pose3(T_bc))))
    d_c = np.concatenate(d_c)
    expected = 0.5 * d_c @ G @ d_c - d_c @ g
    assert f.error(v1) - f.error(v0) == pytest.approx(expected, rel=1e-6, abs=1e-12)
    assert f.error(v0) >= 0.0                      # LM moves: the constant keeps the error >= 0
    Gb, gb = camera_to_body_system(G, g, T_bc)
    assert np.allclose(Gb, Gb.T) and np.linalg.eigvalsh(Gb).min() > 0


def _visual_world(m, T_bc, kt, Rw, s_true):
    s = m.sample(kt)
    out = []
    for R, p in zip(s.R, s.p):
        T_wb = np.eye(4)
        T_wb[:3, :3], T_wb[:3, 3] = R, p
        T = T_wb @ T_bc
        Tv = np.eye(4)
        Tv[:3, :3], Tv[:3, 3] = Rw @ T[:3, :3], Rw @ T[:3, 3] / s_true
        out.append(Tv)
    return out


def test_alignment_recovers_scale_gravity_and_gyro_bias(motion):
    m, imu, T_bc = motion
    bg_true = np.array([0.01, -0.02, 0.005])
    biased = ImuArrays(imu.stamps_ns, imu.gyro + bg_true, imu.accel)
    kt = np.arange(1.0, 3.01, 0.1)
    Rw, s_true = gtsam.Rot3.Ypr(0.7, 0.3, -0.4).matrix(), 2.5
    T_wc = _visual_world(m, T_bc, kt, Rw, s_true)
    ns = (kt * 1e9).round().astype(np.int64)
    pres = [preintegrate(biased, int(a), int(b)) for a, b in zip(ns[:-1], ns[1:])]
    assert excitation(pres) > 0.25
    al = align(T_wc, T_bc, pres)
    assert al.ok, al.why
    assert al.scale == pytest.approx(s_true, rel=0.005)
    assert np.abs(al.bg - bg_true).max() < 1e-3
    g_true = Rw @ G_WORLD
    assert np.degrees(np.arccos(al.g_w @ g_true / 9.81 ** 2)) < 0.1
    # the similarity takes the visual world to the metric z-up frame: true gravity becomes -z
    R = al.C[:3, :3] / al.scale
    assert np.allclose(R @ g_true / 9.81, [0, 0, -1], atol=2e-3)
    assert np.allclose(gravity_alignment(np.array([0, 0, -9.81])), np.eye(3))


def test_alignment_is_refused_when_the_imu_contradicts_the_images(motion):
    m, imu, T_bc = motion
    kt = np.arange(1.0, 3.01, 0.1)
    T_wc = _visual_world(m, T_bc, kt, np.eye(3), 2.0)
    ns = (kt * 1e9).round().astype(np.int64)
    # accelerometer in g instead of m/s^2: |g| comes out far from 9.81
    wrong = ImuArrays(imu.stamps_ns, imu.gyro, imu.accel / 9.81)
    al = align(T_wc, T_bc, [preintegrate(wrong, int(a), int(b)) for a, b in zip(ns[:-1], ns[1:])])
    assert not al.ok and al.C is None
    assert "gravity" in al.why or "scale" in al.why or "residual" in al.why


def _relative_pose_system(T_true, T_lin, sigma=0.01):
    """Dense information of relative-pose measurements between consecutive camera poses (truth),
    linearised at ``T_lin`` (a stand-in for the dense BA's pose system)."""
    keys = [gtsam.symbol("c", i) for i in range(len(T_lin))]
    vals, graph = gtsam.Values(), gtsam.NonlinearFactorGraph()
    for k, T in zip(keys, T_lin):
        vals.insert(k, gtsam.Pose3(T))
    for i in range(len(T_lin) - 1):
        z = gtsam.Pose3(T_true[i]).between(gtsam.Pose3(T_true[i + 1]))
        graph.add(gtsam.BetweenFactorPose3(keys[i], keys[i + 1], z, gtsam.noiseModel.Isotropic.Sigma(6, sigma)))
    order = gtsam.Ordering()
    for k in keys:
        order.push_back(k)
    return graph.linearize(vals).hessian(order)


def _keyframe_truth(m):
    """Keyframe stamps every 0.1 s from 1 to 2.2 s, the motion's samples there and the true body poses."""
    kt = np.arange(1.0, 2.21, 0.1)
    s = m.sample(kt)
    T_wb = []
    for R, p in zip(s.R, s.p):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, p
        T_wb.append(T)
    return (kt * 1e9).round().astype(np.int64), s, T_wb


def test_smoother_converges_and_its_marginalisation_prior_is_the_schur_complement(motion):
    m, imu, T_bc = motion
    rng = np.random.default_rng(2)
    params = gtsam_params(ImuNoiseConfig())
    ns, s, T_wb = _keyframe_truth(m)
    sm = WindowSmoother(params, T_bc)
    sm.start(NavEstimate(int(ns[0]), T_wb[0], s.v[0], np.zeros(3), np.zeros(3)), [1e-3] * 6, 1e-2, 0.1, 0.01)
    for k in range(1, len(ns)):
        guess = T_wb[k].copy()
        guess[:3, 3] += rng.normal(size=3) * 0.05                     # 5 cm off
        sm.add(int(ns[k]), gtsam_preintegrate(imu, int(ns[k - 1]), int(ns[k]), params), guess)
    lin = [sm.estimate(int(t)).T_wb @ T_bc for t in ns]
    H, eta = _relative_pose_system([T @ T_bc for T in T_wb], lin)
    sm.set_visual(H, eta, list(ns), lin)
    sm.optimize(10)
    err = max(np.abs(sm.estimate(int(t)).T_wb[:3, 3] - T[:3, 3]).max() for t, T in zip(ns, T_wb))
    assert err < 2e-3

    # the prior left by marginalising the oldest state = Schur complement of the factors touching it
    old = sm.states[0]
    touching = [t for t in sm.priors + sm.imu if old in t.states]
    graph = gtsam.NonlinearFactorGraph()
    for t in touching:
        graph.add(t.factor)
    others = sorted({x for t in touching for x in t.states} - {old})
    order = gtsam.Ordering()
    rest_keys = [k for o in others for k in _keys(o)]
    for k in list(_keys(old)) + rest_keys:
        order.push_back(k)
    Hf, _ = graph.linearize(sm.values).hessian(order)
    Hs = Hf[15:, 15:] - Hf[15:, :15] @ np.linalg.solve(Hf[:15, :15], Hf[:15, 15:])
    sm.marginalize_oldest()
    prior = gtsam.NonlinearFactorGraph()
    for t in sm.priors:
        prior.add(t.factor)
    order2 = gtsam.Ordering()
    for k in rest_keys:
        order2.push_back(k)
    H2, _ = prior.linearize(sm.values).hessian(order2)
    assert np.abs(H2 - Hs).max() <= 1e-9 * np.abs(Hs).max()
    assert len(sm.states) == len(ns) - 1 and int(ns[0]) not in sm.window_stamps()
    sm.optimize(3)
    assert max(np.abs(sm.estimate(int(t)).T_wb[:3, 3] - T[:3, 3]).max() for t, T in zip(ns[1:], T_wb[1:])) < 2e-3


def test_imu_buffer_refuses_and_counts_bad_readings():
    buf = ImuBuffer(td_ns=5_000_000)
    ok = lambda t: ImuSample(t, np.zeros(3), np.array([0, 0, 9.81]))  # noqa: E731
    assert buf.add(ok(100_000_000))
    assert not buf.add(ok(100_000_000))                     # duplicate
    assert not buf.add(ok(50_000_000))                      # out of order
    assert not buf.add(ImuSample(200_000_000, np.array([np.nan, 0, 0]), np.zeros(3)))
    assert buf.refused == {"out_of_order": 1, "duplicate": 1, "non_finite": 1}
    for t in range(105_000_000, 400_000_000, 5_000_000):
        buf.add(ok(t))
    # camera clock t_imu - td, centred holds: back by half the 5 ms period
    assert buf.arrays().stamps_ns[0] == 95_000_000 - 2_500_000
    buf.td_ns = 15_000_000                                   # a new offset re-reads every stamp
    assert buf.arrays().stamps_ns[0] == 85_000_000 - 2_500_000
    assert buf.covers(100_000_000, 300_000_000, 0.1) is None
    assert buf.covers(10_000_000, 300_000_000, 0.1).startswith("no IMU before")
    assert buf.covers(300_000_000, 600_000_000, 0.1).startswith("IMU not there yet")
    buf.add(ok(700_000_000))                                 # a 0.3 s gap
    assert buf.covers(300_000_000, 690_000_000, 0.1).startswith("IMU gap")


def test_so3_log_matches_scipy_everywhere():
    from scipy.spatial.transform import Rotation
    from vings_core.vio.preint import so3_log_np
    rng = np.random.default_rng(5)
    vecs = list(rng.normal(size=(50, 3))) + [np.array([1e-9, 0, 0]), np.array([0, 0, np.pi - 1e-6]),
                                              np.array([np.pi - 1e-3, 0, 0]) / np.sqrt(1.0)]
    for v in vecs:
        v = np.asarray(v, float)
        if np.linalg.norm(v) > np.pi:
            v = v / np.linalg.norm(v) * (np.linalg.norm(v) % np.pi)
        R = Rotation.from_rotvec(v).as_matrix()
        assert np.allclose(so3_log_np(R), Rotation.from_matrix(R).as_rotvec(), atol=1e-5)


def test_a_keyframe_packet_moves_into_the_metric_frame_with_its_depth():
    import torch
    from vings_core.geometry import sim3_apply_to_pose
    from vings_core.types import CameraModel, Keyframe
    from vings_core.vio.fusion import scale_keyframe
    cam = CameraModel(16, 8, 10.0, 10.0, 7.5, 3.5)
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.3]
    kf = Keyframe(5, torch.zeros(8, 16, 3), torch.from_numpy(T), torch.full((8, 16), 2.0),
                  torch.full((8, 16), 0.04), torch.ones(8, 16, dtype=torch.bool), cam)
    C = np.eye(4)
    C[:3, :3] = 3.0 * gtsam.Rot3.Ypr(0.3, 0.1, -0.2).matrix()
    C[:3, 3] = [1.0, -1.0, 0.5]
    out = scale_keyframe(kf, C)
    assert np.allclose(out.T_wc.numpy(), sim3_apply_to_pose(C, T))
    # a point seen at depth d along the optical axis lands where C maps it
    p_old = T[:3, :3] @ np.array([0, 0, 2.0]) + T[:3, 3]
    p_new = out.T_wc.numpy()[:3, :3] @ np.array([0, 0, float(out.depth[0, 0])]) + out.T_wc.numpy()[:3, 3]
    assert np.allclose(p_new, C[:3, :3] @ p_old + C[:3, 3])
    assert float(out.inv_depth_var[0, 0]) == pytest.approx(0.04 / 9.0)


# ------------------------------------------------------------------ standstill, units, offset

def _still_stream(acc_mean, vib=1.0, seconds=2.0, rate=200.0, seed=0, gyro_bias=(0.0, 0.02, 0.08)):
    """A platform at rest with rotor vibration: per-reading noise of ``vib`` m/s^2 around the mean."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate)
    t = (np.arange(n) / rate * 1e9).astype(np.int64)
    acc = np.asarray(acc_mean, float) + rng.normal(0, vib, (n, 3))
    gyro = np.asarray(gyro_bias, float) + rng.normal(0, 0.02, (n, 3))
    return ImuArrays(t, gyro, acc)


def test_standstill_test_accepts_a_vibrating_platform_and_refuses_motion():
    from vings_core.vio.standstill import attitude_from_gravity, imu_still
    R_true = gtsam.Rot3.Ypr(0.3, 0.4, -0.2).matrix()          # R_wb
    a_rest = R_true.T @ np.array([0, 0, 9.81])
    imu = _still_stream(a_rest)
    test = imu_still(imu, int(1.9e9), 1.0, 0.25, 0.02, 0.2)
    assert test is not None and test.still, test
    quiet = imu_still(_still_stream(a_rest, vib=0.2), int(1.9e9), 1.0, 0.25, 0.02, 0.2)
    R = attitude_from_gravity(quiet.acc_mean)
    z = np.array([0, 0, 1.0])
    # roll and pitch: the body's up direction agrees with the truth (to the readings' noise)
    assert np.degrees(np.arccos(np.clip((R.T @ z) @ (R_true.T @ z), -1, 1))) < 0.5
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
    # too short a window: no verdict
    assert imu_still(imu, int(0.3e9), 1.0, 0.25, 0.02, 0.2) is None
    # a push of 0.5 m/s^2 for 0.25 s, or a slow turn of 0.1 rad/s, is motion
    pushed = ImuArrays(imu.stamps_ns, imu.gyro, imu.accel.copy())
    pushed.accel[330:380] += [0.5, 0, 0]                    # within the newest block
    assert not imu_still(pushed, int(1.9e9), 1.0, 0.25, 0.02, 0.2).still
    turned = ImuArrays(imu.stamps_ns, imu.gyro.copy(), imu.accel)
    turned.gyro[330:380] += [0, 0, 0.1]
    assert not imu_still(turned, int(1.9e9), 1.0, 0.25, 0.02, 0.2).still


def test_units_at_rest_are_checked():
    from vings_core.vio.standstill import units_problem
    assert units_problem(9.80, 9.81) is None
    assert "in g" in units_problem(1.0, 9.81)
    assert "gravity was removed" in units_problem(0.05, 9.81)
    assert "not 9.81" in units_problem(7.0, 9.81)


def test_fusion_refuses_an_imu_in_g_at_standstill_and_stops_taking_readings():
    from vings_core.types import Calibration, CameraModel
    from vings_core.vio.config import ViConfig, ViState
    from vings_core.vio.fusion import ViFusion
    cal = Calibration(CameraModel(376, 240, 200.0, 200.0, 188.0, 120.0), T_bc=np.eye(4),
                      gyro_noise_density=1.7e-4, gyro_random_walk=2e-5, accel_noise_density=2e-3,
                      accel_random_walk=3e-3, gravity=9.81, T_bc_known=True)
    vio = ViFusion(ViConfig(), cal)
    imu = _still_stream([0.0, 0.0, 1.0], vib=0.01)          # in g
    for t, g, a in zip(imu.stamps_ns, imu.gyro, imu.accel):
        vio.add_imu(ImuSample(int(t), g, a))
    assert vio.standstill(int(1.9e9)) is None
    assert vio.state == ViState.VISUAL_ONLY and "in g" in vio.units_error
    assert vio.status()["vi_error"] == vio.units_error
    assert not vio.add_imu(ImuSample(int(2e9), np.zeros(3), np.array([0, 0, 1.0])))


def test_time_offset_estimate_recovers_a_known_offset(motion):
    from vings_core.sim.imu import ImuNoise
    from vings_core.vio.preint import centred
    from vings_core.vio.time_offset import estimate_td
    m, _, T_bc = motion
    t = np.arange(0, 6, 0.005)
    d = simulate_imu(m, t, ImuNoise(), np.random.default_rng(3))
    cam = np.arange(0.5, 5.5, 0.05)
    R_wb = m.sample(cam).R
    for td in (0.015, -0.008):
        # the reading taken at true time t is stamped t + td (t_imu = t_cam + td)
        imu = centred(ImuArrays(((t + td) * 1e9).round().astype(np.int64), d.gyro, d.accel))
        e = estimate_td(imu, (cam * 1e9).round().astype(np.int64), list(R_wb))
        assert e.ok, e.why
        assert abs(e.delta_s - td) < 3e-4, (td, e.delta_s)
        assert np.abs(e.gyro_bias - d.bias_gyro[0]).max() < 1e-3
    # no rotation: refused, not guessed
    still = [np.eye(3)] * len(cam)
    e = estimate_td(imu, (cam * 1e9).round().astype(np.int64), still)
    assert not e.ok and "not observable" in e.why


def test_a_loop_correction_moves_the_smoother_and_its_prior_with_the_states(motion):
    """``WindowSmoother.move`` with a gravity-preserving correction (yaw and translation, as a
    visual-inertial loop closure gives): after it the window optimises to the moved truth (the
    prior left by marginalisation no longer pulls the states back), velocities rotated."""
    m, imu, T_bc = motion
    params = gtsam_params(ImuNoiseConfig())
    ns, s, T_wb = _keyframe_truth(m)
    sm = WindowSmoother(params, T_bc)
    sm.start(NavEstimate(int(ns[0]), T_wb[0], s.v[0], np.zeros(3), np.zeros(3)), [1e-3] * 6, 1e-2, 0.1, 0.01)
    for k in range(1, len(ns)):
        sm.add(int(ns[k]), gtsam_preintegrate(imu, int(ns[k - 1]), int(ns[k]), params), T_wb[k])
    sm.optimize(5)
    sm.marginalize_oldest()
    sm.marginalize_oldest()
    C = np.eye(4)
    C[:3, :3] = gtsam.Rot3.Yaw(0.7).matrix()
    C[:3, 3] = [3.0, -2.0, 0.5]
    assert sm.move({int(t): C for t in ns}) == len(sm.states)
    sm.optimize(5)
    for t, T, v in zip(ns[2:], T_wb[2:], s.v[2:]):
        e = sm.estimate(int(t))
        assert np.abs(e.T_wb[:3, 3] - (C @ T)[:3, 3]).max() < 2e-3
        assert np.abs(e.v - C[:3, :3] @ v).max() < 2e-2
