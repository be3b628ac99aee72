"""Dense BA math: analytic Jacobians, Schur solve, marginal covariance, reduced pose system."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vings_core.geometry import se3_exp
from vings_core.frontend import ba as BA
from vings_core.frontend.projective import (Intrinsics, adjoint, grid_points, linearize_edges,
                                            normalized_rays, project, transform_h, relative_poses)
from vings_core.frontend.uncertainty import (marginal_inv_depth_var_dense, window_inv_depth_var)

DT = torch.float64
K = Intrinsics(120.0, 118.0, 40.3, 29.7)


def _problem(M=4, w=10, h=8, seed=0, noise=0.0):
    """Random small window: M cameras looking at points 2-6 m away, true flow targets."""
    g = torch.Generator().manual_seed(seed)
    _, _, uv = grid_points(8 * w, 8 * h, 8)
    rays = normalized_rays(uv, K)
    P = uv.shape[0]
    xi = torch.randn(M, 6, generator=g, dtype=DT) * torch.tensor([0.3, 0.3, 0.3, 0.05, 0.05, 0.05],
                                                                dtype=DT)
    xi[0] = 0
    T = se3_exp(xi)
    d = 1.0 / (2.0 + 4.0 * torch.rand(M, P, generator=g, dtype=DT))
    ii, jj = torch.meshgrid(torch.arange(M), torch.arange(M), indexing="ij")
    m = ii != jj
    ii, jj = ii[m], jj[m]
    q = transform_h(relative_poses(T, ii, jj), rays, d[ii])
    target = project(q, K) + noise * torch.randn(q.shape[:-1] + (2,), generator=g, dtype=DT)
    weight = 0.5 + torch.rand(ii.shape[0], P, generator=g, dtype=DT)
    return T, d, ii, jj, rays, target, weight


def test_analytic_jacobians_match_finite_differences():
    T, d, ii, jj, rays, target, _ = _problem(M=3, w=4, h=3)
    lin = linearize_edges(T, d, ii, jj, rays, target, K)
    assert lin.valid.all()
    eps = 1e-6

    def res(Tp, dp):
        return linearize_edges(Tp, dp, ii, jj, rays, target, K).r

    # pose Jacobians: r = target - pi, so d pi / d xi = -(d r / d xi)
    for m in range(3):
        for k in range(6):
            dx = torch.zeros(6, dtype=DT)
            dx[k] = eps
            Tp, Tm = T.clone(), T.clone()
            Tp[m] = se3_exp(dx) @ T[m]
            Tm[m] = se3_exp(-dx) @ T[m]
            num = -(res(Tp, d) - res(Tm, d)) / (2 * eps)          # (E,P,2)
            ana = torch.zeros_like(num)
            ana += torch.where((ii == m)[:, None, None], lin.Ji[..., k], 0.0)
            ana += torch.where((jj == m)[:, None, None], lin.Jj[..., k], 0.0)
            assert torch.allclose(num, ana, atol=1e-5 * (1 + ana.abs().max())), (m, k)
    # inverse-depth Jacobian (one pixel at a time through a batched perturbation of all depths:
    # each residual depends only on its own pixel's depth)
    num = -(res(T, d + eps) - res(T, d - eps)) / (2 * eps)
    assert torch.allclose(num, lin.Jd, atol=1e-5 * (1 + lin.Jd.abs().max()))


def test_adjoint_identity():
    xi = torch.randn(6, dtype=DT) * 0.5
    T = se3_exp(torch.randn(6, dtype=DT))
    lhs = T @ se3_exp(xi) @ torch.linalg.inv(T)
    rhs = se3_exp(adjoint(T) @ xi)
    assert torch.allclose(lhs, rhs, atol=1e-10)


def test_schur_solve_equals_dense_solve():
    T, d, ii, jj, rays, target, weight = _problem(M=4, w=5, h=4, noise=0.5)
    # perturb the state so the gradient is non-zero
    T0 = T.clone()
    T0[1:] = se3_exp(torch.randn(3, 6, dtype=DT) * 0.01) @ T[1:]
    d0 = d * (1 + 0.05 * torch.randn_like(d))
    ne = BA.assemble(T0, d0, ii, jj, rays, target, weight, K, loss="huber", delta=1.0)
    # two fixed poses: the monocular gauge (rigid motion and scale) is fixed
    free = torch.tensor([2, 3])
    rs = BA.schur_reduce(ne, free, lam=0.0, eps_c=0.0)
    dxi, dd = BA.solve_reduced(rs, jitter=0.0)
    H, b = BA.dense_matrix(ne)
    M, P = d.shape
    keep = torch.cat([torch.arange(12, 24), 24 + torch.arange(M * P)])
    x = torch.linalg.solve(H[keep][:, keep], b[keep])
    assert torch.allclose(dxi.reshape(-1), x[:12], rtol=1e-7, atol=1e-10)
    assert torch.allclose(dd, x[12:], rtol=1e-7, atol=1e-10)


def test_marginal_covariance_equals_inverse_hessian_block():
    T, d, ii, jj, rays, target, weight = _problem(M=4, w=5, h=4, noise=0.3, seed=3)
    ne = BA.assemble(T, d, ii, jj, rays, target, weight, K, loss="none")
    free = torch.tensor([2, 3])
    fast = window_inv_depth_var(ne, free, eps_c=1e-9)
    ref = marginal_inv_depth_var_dense(ne, free, eps_c=1e-9)
    assert torch.allclose(fast, ref, rtol=1e-6, atol=0)


def test_bundle_adjust_recovers_truth_from_perturbed_start():
    T, d, ii, jj, rays, target, weight = _problem(M=4, w=8, h=6, seed=5)
    T0 = T.clone()
    T0[2:] = se3_exp(torch.randn(2, 6, dtype=DT) * 0.02) @ T[2:]
    d0 = d * (1 + 0.1 * torch.randn_like(d)).clamp_min(0.5)
    res = BA.bundle_adjust(T0, d0, ii, jj, rays, target, weight, K, n_fixed=2, iters=20)
    assert res.cost < 1e-6 * res.cost0
    assert torch.allclose(res.T_cw, T, atol=1e-5)
    assert torch.allclose(res.d, d, rtol=1e-4)


def test_motion_only_recovers_pose():
    T, d, ii, jj, rays, target, weight = _problem(M=2, w=8, h=6, seed=7)
    # edge 0 -> 1 only: the frame is camera 1
    sel = (ii == 0) & (jj == 1)
    T_init = se3_exp(torch.tensor([0.05, -0.03, 0.02, 0.01, -0.02, 0.01], dtype=DT)) @ T[1]
    out = BA.motion_only(T[:1], d[:1], rays, target[sel], weight[sel], K, T_init, iters=10)
    assert torch.allclose(out.T_cw, T[1], atol=1e-7)
    assert out.rms_px < 1e-5 and out.inlier_frac == pytest.approx(1.0)
    assert torch.linalg.eigvalsh(out.H).min() > 0


def test_reduced_pose_system_is_a_valid_gtsam_hessian_factor():
    gtsam = pytest.importorskip("gtsam")
    T, d, ii, jj, rays, target, weight = _problem(M=4, w=5, h=4, noise=0.3, seed=11)
    T0 = T.clone()
    T0[1:] = se3_exp(torch.randn(3, 6, dtype=DT) * 0.005) @ T[1:]
    ne = BA.assemble(T0, d, ii, jj, rays, target, weight, K, loss="none")
    ps = BA.reduced_pose_system(ne, T0, [10, 20, 30, 40])
    assert ps.H.shape == (24, 24) and ps.v.shape == (24,)
    # (a) energy of the reduced system equals the depth-minimised full quadratic at random x
    Hfull, bfull = BA.dense_matrix(ne)
    n = 24
    x = torch.randn(n, dtype=DT) * 1e-3
    Hreg = Hfull.clone()
    Hreg[n:, n:] += torch.eye(Hfull.shape[0] - n, dtype=DT) * 1e-9   # the eps_c of the export
    Edd = Hreg[n:, n:]
    y = torch.linalg.solve(Edd, bfull[n:] - Hreg[n:, :n] @ x)
    full = torch.cat([x, y])
    e_full = 0.5 * full @ Hreg @ full - full @ bfull
    e_red = 0.5 * x @ ps.H @ x - x @ ps.v
    const = -0.5 * bfull[n:] @ torch.linalg.solve(Edd, bfull[n:])
    assert float(e_full) == pytest.approx(float(e_red + const), rel=1e-6, abs=1e-9)
    # (b) in GTSAM: build the factor from 1- and 2-key blocks, fix pose 0, solve; compare with
    # our own Schur solve with pose 0 fixed
    G, g = ps.to_gtsam_ordering()
    G, g = G.numpy(), g.numpy()
    graph = gtsam.GaussianFactorGraph()
    keys = [gtsam.symbol("x", k) for k in range(4)]
    for a in range(4):
        for b in range(a, 4):
            Ga, Gb = slice(6 * a, 6 * a + 6), slice(6 * b, 6 * b + 6)
            if a == b:
                graph.push_back(gtsam.HessianFactor(keys[a], G[Ga, Ga], g[Ga], 0.0))
            else:
                z6 = np.zeros((6, 6))
                graph.push_back(gtsam.HessianFactor(keys[a], keys[b], z6, G[Ga, Gb], np.zeros(6),
                                                    z6, np.zeros(6), 0.0))
    hf = gtsam.HessianFactor(graph)
    assert hf.size() == 4
    lin = gtsam.GaussianFactorGraph()
    lin.push_back(hf)
    for k in (0, 1):   # gauge: hold the two oldest poses (as the front end does)
        lin.push_back(gtsam.JacobianFactor(keys[k], np.eye(6) * 1e6, np.zeros(6),
                                           gtsam.noiseModel.Unit.Create(6)))
    sol = lin.optimize()
    rs = BA.schur_reduce(ne, torch.tensor([2, 3]), eps_c=1e-9)
    dxi, _ = BA.solve_reduced(rs, jitter=0.0)
    P = np.array([3, 4, 5, 0, 1, 2])
    for k in (2, 3):
        got = sol.at(keys[k])
        assert np.allclose(got, -dxi[k - 2].numpy()[P], rtol=1e-4, atol=1e-9)
