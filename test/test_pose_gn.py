"""Gauss-Newton pose refinement pieces (vings_core.mapping.pose_gn) against references: the
adjoint against its definition, the point Jacobians and a render's linear model against finite
differences, the owner system against an explicitly built dense Jacobian, the damped step's
held owners and trust region."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vings_core.geometry import pose_inverse, se3_exp
from vings_core.mapping import pose_gn as GN
from vings_core.types import CameraModel

CAM = CameraModel(width=40, height=30, fx=35.0, fy=36.0, cx=19.5, cy=14.5)


def _rand_pose(g: torch.Generator) -> torch.Tensor:
    return se3_exp(torch.randn(6, generator=g, dtype=torch.float64) * torch.tensor([1, 1, 1, .7, .7, .7],
                                                                                     dtype=torch.float64))


def test_adjoint_matches_its_definition():
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        T = _rand_pose(g)
        xi = torch.randn(6, generator=g, dtype=torch.float64) * 0.3
        lhs = se3_exp(GN.se3_adjoint(T) @ xi)
        rhs = T @ se3_exp(xi) @ pose_inverse(T)
        assert torch.allclose(lhs, rhs, atol=1e-12)
    Ts = torch.stack([_rand_pose(g) for _ in range(3)])
    assert torch.allclose(GN.se3_adjoint(Ts)[1], GN.se3_adjoint(Ts[1]))


def test_point_jacobians_match_autograd():
    g = torch.Generator().manual_seed(1)
    P = 7
    u = torch.rand(P, generator=g, dtype=torch.float64) * CAM.width
    v = torch.rand(P, generator=g, dtype=torch.float64) * CAM.height
    z = 1.0 + 3.0 * torch.rand(P, generator=g, dtype=torch.float64)
    Ju, Jz = GN.point_jacobians(u, v, z, CAM)
    for p in range(P):
        X = torch.stack([(u[p] - CAM.cx) / CAM.fx * z[p], (v[p] - CAM.cy) / CAM.fy * z[p], z[p]])

        def proj(delta):                   # X -> X + v + w x X, then pinhole
            Y = X + delta[:3] + torch.linalg.cross(delta[3:], X)
            return torch.stack([CAM.fx * Y[0] / Y[2] + CAM.cx, CAM.fy * Y[1] / Y[2] + CAM.cy, Y[2]])

        J = torch.autograd.functional.jacobian(proj, torch.zeros(6, dtype=torch.float64))
        assert torch.allclose(Ju[p], J[:2], atol=1e-10)
        assert torch.allclose(Jz[p], J[2], atol=1e-10)


def test_image_gradient_and_blur():
    x = torch.arange(30, dtype=torch.float64)[:, None, None] * 0.5 + torch.arange(40, dtype=torch.float64)[None, :, None] * 2.0
    gr = GN.image_gradient(x)
    assert torch.allclose(gr[..., 0], torch.full_like(x, 2.0)) and torch.allclose(gr[..., 1], torch.full_like(x, 0.5))
    b = GN.blur_image(x, 1.5)
    # a linear ramp is kept by a normalised symmetric blur away from the border
    assert torch.allclose(b[6:-6, 6:-6], x[6:-6, 6:-6], atol=1e-9)
    assert GN.blur_image(x, 0.0) is x


def _dense_system(terms: GN.GNTerms, coeff: torch.Tensor, adj: torch.Tensor):
    """Reference: the full Jacobian d r / d xi, one owner block after another, then J^T Omega J."""
    P, V = coeff.shape
    # Q = sum_c w_c j_c^T j_c; rebuild a square root per pixel to form J explicitly
    L = torch.linalg.cholesky(terms.Q + 1e-12 * torch.eye(6, dtype=torch.float64))   # Q = L L^T
    y = torch.linalg.solve_triangular(L, terms.q[:, :, None], upper=False)[:, :, 0]  # L y = q
    rows = []
    for p in range(P):
        Jp = torch.cat([coeff[p, k] * (L[p].T @ adj[k]) for k in range(V)], 1)  # (6, 6V)
        rows.append(Jp)
    J = torch.cat(rows, 0)
    return J.T @ J, J.T @ y.reshape(-1)


def test_owner_system_matches_a_dense_jacobian():
    g = torch.Generator().manual_seed(2)
    P, V = 25, 3
    A = torch.randn(P, 4, 6, generator=g, dtype=torch.float64)
    r = torch.randn(P, 4, generator=g, dtype=torch.float64)
    terms = GN.GNTerms(Q=A.transpose(1, 2) @ A, q=(A * r[..., None]).sum(1), pix=torch.arange(P), cost=0.0)
    coeff = torch.rand(P, V, generator=g, dtype=torch.float64) - 0.5
    adj = GN.se3_adjoint(torch.stack([_rand_pose(g) for _ in range(V)]))
    H, b = GN.owner_system(terms, coeff, adj)
    Hr, br = _dense_system(terms, coeff, adj)
    assert torch.allclose(H, Hr, atol=1e-8) and torch.allclose(b, br, atol=1e-8)


def test_damped_step_holds_owners_and_respects_the_trust_region():
    g = torch.Generator().manual_seed(3)
    B = torch.randn(18, 18, generator=g, dtype=torch.float64)
    H = B @ B.T + torch.eye(18, dtype=torch.float64)
    x_true = torch.randn(18, generator=g, dtype=torch.float64) * 1e-3
    b = -H @ x_true
    free = torch.tensor([True, True, True])
    step = GN.damped_step(H, b, free, 0.0, max_trans=1.0, max_rot=1.0)
    assert torch.allclose(step.reshape(-1), x_true, atol=1e-9)     # undamped, inside the region: GN
    held = GN.damped_step(H, b, torch.tensor([True, False, True]), 0.0, 1.0, 1.0)
    assert torch.all(held[1] == 0)
    small = GN.damped_step(H, b, free, 0.0, max_trans=1e-4, max_rot=1.0)
    assert float(small[:, :3].norm(dim=1).max()) == pytest.approx(1e-4, rel=1e-9)
    assert torch.allclose(small / small.norm(), step / step.norm())    # shrunk, same direction
    assert torch.all(GN.damped_step(H, b, torch.zeros(3, dtype=torch.bool), 0.1, 1, 1) == 0)


def test_a_renders_linear_model_predicts_the_cost_change_of_a_camera_motion():
    """pixel_terms' Jacobian of a real 2DGS render of a textured plane (camera motion: content
    twist -xi) against central finite differences of the robust cost (inside Huber's quadratic
    zone, no blur): first-order change q . delta."""
    from vings_core.render import rasterize_2dgs
    g = torch.Generator().manual_seed(4)
    n = 90
    ys, xs = torch.meshgrid(torch.linspace(-1.8, 1.8, n), torch.linspace(-2.4, 2.4, n), indexing="ij")
    # tilted by non-commensurate slopes: no two splats tie in depth (a tie flips the sort order
    # under any rotation, a jump of the render that no linear model predicts)
    means = torch.stack([xs.reshape(-1), ys.reshape(-1), 3.0 + 0.3 * xs.reshape(-1) + 0.17 * ys.reshape(-1)], 1)
    quats = torch.tensor([[0.0, 0.0, 0.0, 1.0]]).expand(n * n, 4).contiguous()
    scales = torch.full((n * n, 2), 0.04)
    opac = torch.full((n * n,), 0.9)
    # a smooth texture (periods of 6-10 px): the finite-difference image gradient resolves it
    ph = torch.rand(3, generator=g) * 6.28
    colors = 0.5 + 0.35 * torch.sin(means[:, :1] * torch.tensor([5.0, 7.0, 4.0]) + means[:, 1:2] * torch.tensor(
        [3.0, -4.0, 6.0]) + ph)
    T = torch.eye(4)

    def render(xi):
        out = rasterize_2dgs(means, quats, scales, opac, colors, (se3_exp(-xi) @ T.double()).float(), CAM)
        return out

    base = render(torch.zeros(6, dtype=torch.float64))
    tgt_xi = torch.tensor([0.01, -0.006, 0.02, 0.004, -0.003, 0.002], dtype=torch.float64)
    tgt = render(tgt_xi)
    ed_t = (tgt.depth / tgt.alpha.clamp_min(1e-6)).detach()

    def terms(xi, s_rgb=0.05, s_d=0.02):
        o = render(xi)
        return GN.pixel_terms(o.color, o.depth / o.alpha.clamp_min(1e-6), o.alpha, tgt.color.detach(), ed_t,
                              torch.ones_like(ed_t), tgt.alpha.detach() > 0.5, CAM, sigma_rgb=s_rgb,
                              sigma_depth_rel=s_d, huber=1e6, blur_px=0.0)

    t0 = terms(torch.zeros(6, dtype=torch.float64))
    # pixels whose alpha crosses 0.5 change the residual set: compare on directions of small size
    for j in range(6):
        e = torch.zeros(6, dtype=torch.float64)
        e[j] = 2e-4
        fd = (terms(e).cost - terms(-e).cost) / 2
        pred = float(-(t0.q.sum(0) @ e))        # content twist = -camera twist
        assert fd == pytest.approx(pred, rel=0.25, abs=1e-4 * t0.cost), (j, fd, pred)
    # and one Gauss-Newton step moves the camera toward the target's pose
    H = t0.Q.sum(0)
    step = torch.linalg.solve(H, t0.q.sum(0))          # content twist -xi: xi = +H^-1 q
    assert float((step - tgt_xi).norm()) < 0.5 * float(tgt_xi.norm()), (step, tgt_xi)


def test_gn_multi_moves_only_keyframes_rendered_in_the_batch():
    """Gauss-Newton multi refinement: a keyframe that left the window (never rendered) keeps its
    pose and its Gaussians even though its Gaussians are in view and the gauge is free
    (refine_fix_first off), while window keyframes with a wrong pose are corrected."""
    sim = pytest.importorskip("vings_core.sim")
    from vings_core.geometry import np_se3_exp
    from vings_core.mapping import Mapper, MapperConfig
    from vings_core.types import Keyframe
    scene = sim.make_scene("room", seed=0)
    cam = sim.default_camera(128, 80)
    Ts = scene.T_wc(np.array([0.0, 0.2, 0.4]))
    m = Mapper(MapperConfig(points_per_keyframe=5000, iters_per_keyframe=10, sample_ratio=1.0, window_size=2,
                            refine_fix_first=False, refine_mode="multi", refine_solver="gn"))
    bad = np_se3_exp(np.array([0.015, -0.01, 0.0, 0.0, 0.006, 0.0]))
    for i, T in enumerate(Ts):
        rgb, d, _ = sim.render_view(scene, cam, T)
        T_in = T @ bad if i == 2 else T
        dd = torch.as_tensor(d, dtype=torch.float32)
        m.add_keyframe(Keyframe(stamp_ns=1_000 + i, image=torch.as_tensor(rgb, dtype=torch.float32) / 255.0,
                                T_wc=torch.as_tensor(T_in), depth=dd, inv_depth_var=torch.zeros_like(dd),
                                valid=dd > 0, camera=cam))
        m.train()
    assert [kf.stamp_ns for kf in m.window] == [1_001, 1_002]
    own0 = m.gm.kf_id == 1_000
    assert int(own0.sum()) > 100                                  # the old keyframe's Gaussians are there
    before_pose, before_means = m.keyframe_poses()[1_000].copy(), m.gm.means[own0].clone()
    err0 = np.linalg.norm(m.keyframe_poses()[1_002][:3, 3] - Ts[2][:3, 3])
    P = m.refine_poses(8)
    assert np.array_equal(P[1_000], before_pose)
    assert torch.equal(m.gm.means[m.gm.kf_id == 1_000], before_means)
    assert np.linalg.norm(P[1_002][:3, 3] - Ts[2][:3, 3]) < 0.7 * err0


def test_gn_decay_scales_each_keyframes_t_th_step_by_one_over_t():
    """refine_gn_decay: a keyframe's t-th Gauss-Newton step is scaled by 1/t (its own count, kept
    across refine_poses calls); keyframes held in a step neither move nor count."""
    from vings_core.mapping import Mapper, MapperConfig
    m = Mapper(MapperConfig())
    stamps = torch.tensor([10, 20, 30])
    f1 = m.refiner.gn_step_scale(stamps, torch.tensor([True, True, False]))
    f2 = m.refiner.gn_step_scale(stamps, torch.tensor([True, False, True]))
    f3 = m.refiner.gn_step_scale(stamps, torch.tensor([True, True, True]))
    assert f1.tolist() == [1.0, 1.0, 0.0]
    assert f2.tolist() == [0.5, 0.0, 1.0]
    assert f3.tolist() == pytest.approx([1 / 3, 1 / 2, 1 / 2])
    assert m.refiner.gn_steps == {10: 3, 20: 2, 30: 2}
