"""Front-end building blocks: flow targets, graph, depth upsampling/validity, config, plug-ins."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vings_core.config import load_section
from vings_core.errors import ConfigError
from vings_core.frontend import FrontendConfig
from vings_core.frontend.depth import (dense_depth, joint_bilateral_upsample, upsample_reference,
                                       validity_mask)
from vings_core.frontend.flow import (DISFlow, TorchScriptFlow, dense_from_grid, grid_flow,
                                      make_flow_estimator, texture_weight)
from vings_core.frontend.graph import CovisibilityGraph, Edge, select_edges
from vings_core.frontend.projective import Intrinsics, grid_points, normalized_rays
from vings_core.geometry import se3_exp


def _texture(h=96, w=128, seed=0):
    import cv2
    rng = np.random.default_rng(seed)
    n = rng.random((h // 4, w // 4)).astype(np.float32)
    img = cv2.resize(n, (w, h), interpolation=cv2.INTER_CUBIC)
    img = (img - img.min()) / (img.max() - img.min())
    return (20 + 210 * img).astype(np.uint8)


def test_dis_flow_recovers_translation_and_grid_reduction():
    big = _texture(140, 180)
    a = np.ascontiguousarray(big[10:106, 10:138])
    b = np.ascontiguousarray(big[7:103, 15:143])     # content moves by (-5, +3) px
    est = DISFlow("medium", 1)
    f = est.flow(a, b)
    g = est.flow(b, a)
    assert f.shape == (96, 128, 2) and f.dtype == np.float32
    _, _, uv = grid_points(128, 96, 8)
    cfg = FrontendConfig()
    gf = grid_flow(f, g, a, b, uv.numpy(), 8, cfg)
    ok = gf.weight > 0.3
    assert ok.mean() > 0.5
    disp = gf.target[ok] - uv.numpy()[ok]
    assert np.median(disp[:, 0]) == pytest.approx(-5.0, abs=0.1)
    assert np.median(disp[:, 1]) == pytest.approx(3.0, abs=0.1)
    assert gf.mean_flow == pytest.approx(np.hypot(5, 3), abs=0.3)


def test_confidence_drops_for_flat_and_inconsistent_regions():
    a = _texture()
    a[:, :48] = 128                                       # textureless left part
    tex = texture_weight(a, 12, 16, 8, 4.0).reshape(12, 16)
    assert tex[:, :5].max() < 0.05 and np.median(tex[:, 7:]) > 0.5
    _, _, uv = grid_points(128, 96, 8)
    cfg = FrontendConfig()
    f = np.zeros((96, 128, 2), np.float32)
    consistent = grid_flow(f, -f, a, a, uv.numpy(), 8, cfg)
    inconsistent = grid_flow(f, f + 4.0, a, a, uv.numpy(), 8, cfg)
    col = np.arange(uv.shape[0]) % 16
    right, left = col >= 7, col < 5
    assert consistent.weight[right].mean() > 5 * inconsistent.weight[right].mean()
    assert consistent.weight[left].max() < 0.05


def test_dense_from_grid_is_bilinear_at_block_centres():
    h, w = 4, 5
    g = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2).astype(np.float32)
    dense = dense_from_grid(g, h, w, 8 * h + 3, 8 * w + 5, 8)
    assert dense.shape == (8 * h + 3, 8 * w + 5, 2)
    # midway between two block centres (pixel 7.5 -> average of cells 0 and 1)
    assert dense[3, 7:9, 0].mean() == pytest.approx(0.5, abs=1e-5)
    assert dense[3, 11:13, 0].mean() == pytest.approx(1.0, abs=1e-5)


def test_joint_bilateral_upsample_matches_reference_and_respects_edges():
    rng = np.random.default_rng(0)
    h, w, s = 5, 6, 8
    inv = np.ones((h, w), np.float32) * 0.25
    inv[:, 3:] = 1.0                                      # depth edge between columns 2 and 3
    var = (rng.random((h, w)) * 1e-3 + 1e-4).astype(np.float32)
    guide = np.full((h * s, w * s), 60, np.float32)
    guide[:, 3 * s:] = 200                                # the image edge coincides
    fast_i, fast_v = joint_bilateral_upsample(inv, var, guide, s, 0.8, 12.0, True)
    ref_i, ref_v = upsample_reference(inv, var, guide, s, 0.8, 12.0, True)
    assert np.allclose(fast_i, ref_i, rtol=1e-5, atol=1e-6)
    assert np.allclose(fast_v, ref_v, rtol=1e-4, atol=1e-9)
    # edge-aware: pixels right next to the edge keep their side's depth
    assert np.allclose(fast_i[:, 3 * s - 1], 0.25, atol=1e-3)
    assert np.allclose(fast_i[:, 3 * s], 1.0, atol=1e-3)
    # without a guide edge the interpolation blurs across it and the spread raises the variance
    flat = np.full_like(guide, 100)
    bi, bv = joint_bilateral_upsample(inv, var, flat, s, 0.8, 12.0, True)
    assert 0.3 < bi[10, 3 * s] < 0.95
    assert bv[10, 3 * s] > 10 * bv[10, 4]


@pytest.mark.parametrize("frac", [0.3, 0.7])
def test_unobserved_cells_do_not_leak_whatever_their_fraction(frac):
    """Cells no residual observes have infinite variance (window_inv_depth_var): they take no part
    in the upsampling and a pixel next to one is unknown, the same with 30 % or 70 % of the frame
    unobserved (a finite placeholder variance would become the median above 50 % and leak into
    observed pixels)."""
    h, w, s = 6, 10, 8
    inv = np.full((h, w), 0.5, np.float32)
    var = np.full((h, w), 1e-4, np.float32)
    n_un = int(round(frac * w))
    var[:, w - n_un:] = np.inf
    inv[:, w - n_un:] = 2.0                         # whatever the solver left there: not a depth edge
    guide = np.full((h * s, w * s), 100, np.float32)
    fi, fv = joint_bilateral_upsample(inv, var, guide, s, 0.8, 12.0, True)
    ri, rv = upsample_reference(inv, var, guide, s, 0.8, 12.0, True)
    assert np.array_equal(np.isfinite(fv), np.isfinite(rv))
    fin = np.isfinite(rv)
    assert np.allclose(fi[fin], ri[fin], rtol=1e-5) and np.allclose(fv[fin], rv[fin], rtol=1e-4)
    first_un = (w - n_un) * s                       # first pixel column of an unobserved cell
    assert not np.isfinite(fv[:, first_un - s // 2:]).any()      # the support touches it
    obs = fv[:, : first_un - s]                     # observed pixels away from the boundary
    assert np.isfinite(obs).all() and np.allclose(obs, 1e-4, rtol=1e-3)


def test_window_variance_of_unobserved_depths_is_infinite():
    from vings_core.frontend.ba import NormalEquations
    from vings_core.frontend.uncertainty import window_inv_depth_var
    M, P = 2, 5
    C = torch.full((M, P), 4.0, dtype=torch.float64)
    C[1, 2] = 0.0                                   # no residual touches this depth
    f64 = torch.float64
    ne = NormalEquations(B=torch.eye(6, dtype=f64).repeat(M, M, 1, 1) * 10, v=torch.zeros(M, 6, dtype=f64),
                         E=torch.zeros(M, M, P, 6, dtype=f64), C=C, z=torch.zeros(M, P, dtype=f64),
                         cost=0.0, W=torch.zeros(0, P, dtype=f64))
    var = window_inv_depth_var(ne, torch.arange(1, M))
    assert torch.isinf(var[1, 2]) and torch.allclose(var[0], torch.full((P,), 0.25, dtype=torch.float64))


def test_validity_mask_drops_uncertain_excessive_and_flat_far():
    H, W = 40, 48
    guide = _texture(H, W)
    guide[:10] = 180                                      # flat band ("sky")
    inv = np.full((H, W), 0.5, np.float32)                # 2 m
    inv[:10] = 0.05                                       # 20 m, flat -> invalid
    var = np.full((H, W), 1e-4, np.float32)
    var[20:25, 10:20] = 1.0                               # uncertain patch
    inv[30:, 40:] = 0.01                                  # 100 m, textured -> excessive
    ok = validity_mask(inv, var, guide, 2.0, 0.1, 8.0, 3.0, 3.0)
    assert not ok[:10].any()
    assert not ok[20:25, 10:20].any()
    assert not ok[30:, 40:].any()
    assert ok[12:20].mean() > 0.9
    dd = dense_depth(np.full((5, 6), 0.5, np.float32), np.full((5, 6), 1e-4, np.float32),
                     _texture(40, 48), 8, 0.8, 12.0, True, 0.1, 8.0, 3.0, 3.0)
    assert dd.valid.mean() > 0.9
    assert np.allclose(dd.depth[dd.valid], 2.0, rtol=1e-3)


def test_select_edges_temporal_plus_proximity():
    K = Intrinsics(100.0, 100.0, 63.5, 47.5)
    _, _, uv = grid_points(128, 96, 8)
    rays = normalized_rays(uv, K)
    # keyframes 0..5 moving right 0.3 m each, keyframe 6 returns next to keyframe 0
    xs = [0.0, 0.3, 0.6, 0.9, 1.2, 1.5, 0.02]
    T_wc = torch.stack([se3_exp(torch.tensor([x, 0, 0, 0, 0, 0.0], dtype=torch.float64)) for x in xs])
    T_cw = torch.linalg.inv(T_wc)
    d = torch.full((7, uv.shape[0]), 0.25, dtype=torch.float64)
    sel = select_edges(T_cw, d, 6, rays, uv, K, 128, 96, temporal_radius=2, proximity_px=20.0,
                       max_proximity=2)
    assert 4 in sel and 5 in sel          # temporal
    assert 0 in sel and 1 in sel          # proximity (closest first, capped at 2)
    assert 2 not in sel and 3 not in sel
    g = CovisibilityGraph()
    P = uv.shape[0]
    for i, j in [(10, 20), (20, 10), (20, 30)]:
        g.add(Edge(i, j, np.zeros((P, 2)), np.ones(P)))
    g.remove_keyframe(10)
    assert len(g) == 1 and g.has(20, 30)
    ii, jj, tg, w = g.tensors([20, 30])
    assert ii.tolist() == [0] and jj.tolist() == [1] and tg.shape == (1, P, 2)


def test_config_from_params_yaml_and_validation(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    frontend:\n      keyframe_flow_lr_px: 3.0\n"
                 "      window: 6\n")
    cfg = load_section(FrontendConfig, "frontend", p)
    assert cfg.keyframe_flow_lr_px == 3.0 and cfg.window == 6
    p.write_text("/**:\n  ros__parameters:\n    frontend:\n      robust_loss: tukey\n")
    with pytest.raises(ConfigError, match="robust_loss"):
        load_section(FrontendConfig, "frontend", p)
    p.write_text("/**:\n  ros__parameters:\n    frontend:\n      windw: 6\n")
    with pytest.raises(ConfigError, match="windw"):
        load_section(FrontendConfig, "frontend", p)
    with pytest.raises(ConfigError, match="flow_weights_path"):
        load_section(FrontendConfig, "frontend", None, {"flow_method": "torchscript"})
    # NaN would disable the check it feeds; contradictory or out-of-range values
    for bad, what in (({"keyframe_flow_lr_px": float("nan")}, "keyframe_flow_lr_px"),
                      ({"min_inv_depth": 100.0, "max_inv_depth": 1.0}, "min_inv_depth"),
                      ({"keyframe_conf_ratio": -1.0}, "keyframe_conf_ratio"),
                      ({"relocalize_frames": 0}, "relocalize_frames")):
        with pytest.raises(ConfigError, match=what):
            load_section(FrontendConfig, "frontend", None, bad)


def test_torchscript_flow_plugin_loads_local_file_only(tmp_path):
    class Const(torch.nn.Module):
        def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
            out = torch.zeros(a.shape[0], 2, a.shape[2], a.shape[3])
            out[:, 0] = 1.5
            return out

    path = tmp_path / "flow.pt"
    torch.jit.script(Const()).save(str(path))
    est = make_flow_estimator(FrontendConfig(flow_method="torchscript", flow_weights_path=str(path)))
    assert isinstance(est, TorchScriptFlow)
    f = est.flow(np.zeros((16, 24), np.uint8), np.zeros((16, 24), np.uint8))
    assert f.shape == (16, 24, 2) and np.allclose(f[..., 0], 1.5) and np.allclose(f[..., 1], 0)
    with pytest.raises(ConfigError, match="not found"):
        TorchScriptFlow(str(tmp_path / "missing.pt"))
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(ConfigError, match="TorchScript"):
        TorchScriptFlow(str(tmp_path / "junk.pt"))


def test_flow_composition_inversion_and_refinement_around_a_prior():
    from vings_core.frontend.flow import compose_flow, flow_around, invert_flow
    H, W = 64, 80
    base = np.zeros((H, W, 2), np.float32)
    base[..., 0], base[..., 1] = 5.0, -3.0
    res = np.zeros_like(base)
    res[..., 0], res[..., 1] = 1.0, 2.0
    assert np.allclose(compose_flow(base, res)[10:50, 10:60], [6.0, -1.0], atol=1e-5)
    # inverse of a smooth non-constant field: g(y) = -f(y + g(y))
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    f = np.stack([2.0 + 0.05 * xs, -1.0 + 0.03 * ys], -1).astype(np.float32)
    g = invert_flow(f, iters=6)
    import cv2
    back = cv2.remap(f, xs + g[..., 0], ys + g[..., 1], cv2.INTER_LINEAR)
    assert np.allclose((g + back)[8:-8, 8:-8], 0, atol=1e-3)
    # refinement around a prior: a 30 px shift with a prior 4 px off
    big = _texture(120, 200, seed=3)
    a = np.ascontiguousarray(big[20:84, 60:140])
    b = np.ascontiguousarray(big[20:84, 30:110])     # content moves +30 px in x
    prior = np.zeros((64, 80, 2), np.float32)
    prior[..., 0] = 26.0
    est = DISFlow("medium", 1)
    fl = flow_around(est, a, b, prior)
    assert np.median(fl[16:48, 8:40, 0]) == pytest.approx(30.0, abs=0.1)
    assert np.median(np.abs(fl[16:48, 8:40, 1])) < 0.1


def test_triangulate_grid_finds_depth_by_1d_search():
    from vings_core.frontend.ba import triangulate_grid
    from vings_core.frontend.projective import project_edges
    K = Intrinsics(100.0, 100.0, 63.5, 47.5)
    _, _, uv = grid_points(128, 96, 8)
    rays = normalized_rays(uv, K)
    T = torch.stack([torch.eye(4, dtype=torch.float64),
                     se3_exp(torch.tensor([-0.3, 0.05, 0.1, 0.0, 0.02, 0.0], dtype=torch.float64))])
    rng = np.random.default_rng(0)
    cands = 1.0 / torch.logspace(-0.5, 2.0, 64, dtype=torch.float64)
    true = cands[torch.from_numpy(rng.integers(5, 40, (2, uv.shape[0])))]
    ii, jj = torch.tensor([0, 1]), torch.tensor([1, 0])
    tg, _ = project_edges(T, true, ii, jj, rays, K)
    w = torch.ones(2, uv.shape[0], dtype=torch.float64)
    w[1, :10] = 0                                         # unobserved pixels of keyframe 1
    d = triangulate_grid(T, ii, jj, rays, tg, w, K, cands)
    assert torch.allclose(d[0], true[0])
    assert torch.allclose(d[1, 10:], true[1, 10:])
    assert torch.allclose(d[1, :10], true[1, 10:].median().expand(10))


def test_gain_offset_and_rotation_only_residual():
    from vings_core.frontend.flow import gain_offset
    from vings_core.frontend.initialise import rotation_only_residual
    from vings_core.geometry import np_so3_exp
    img = _texture().astype(np.float32)
    mask = np.ones(img.shape, bool)
    a, b = gain_offset(img, 1.3 * img - 20.0, mask)
    assert abs(a - 1.3) < 0.05 and abs(b + 20.0) < 3.0
    assert gain_offset(img, img, np.zeros_like(mask)) == (1.0, 0.0)   # too few pixels: identity
    K = np.array([[200.0, 0, 64], [0, 200.0, 48], [0, 0, 1]])
    rng = np.random.default_rng(0)
    P = np.c_[rng.uniform(-1, 1, (200, 2)), rng.uniform(2, 6, 200)]
    R = np_so3_exp(np.array([0.02, -0.05, 0.01]))

    def proj(X):
        q = X @ K.T
        return q[:, :2] / q[:, 2:]
    p0 = proj(P)
    assert rotation_only_residual(p0, proj(P @ R.T), K) < 1e-6
    assert rotation_only_residual(p0, proj(P @ R.T + np.array([0.2, 0.0, 0.0])), K) > 2.0


def _triangulation_angles_reference(P: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Angle at each 3-D point ``P`` (reference frame) between the rays to the two camera centres."""
    C1 = -R.T @ t                          # second camera centre in the reference frame
    a = P / np.linalg.norm(P, axis=1, keepdims=True)
    b = (P - C1) / np.linalg.norm(P - C1, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1, 1)))


def test_triangulation_angles_match_the_geometry_under_forward_and_sideways_motion():
    from vings_core.frontend.initialise import triangulation_angles_deg
    from vings_core.geometry import np_so3_exp
    K = np.array([[360.0, 0, 306], [0, 360.0, 92], [0, 0, 1]])
    rng = np.random.default_rng(1)
    P = np.c_[rng.uniform(-8, 8, (300, 2)), rng.uniform(4, 60, 300)]
    R = np_so3_exp(np.array([0.01, 0.04, -0.02]))

    def proj(X):
        q = X @ K.T
        return q[:, :2] / q[:, 2:]
    for t in (np.array([0.0, 0.0, -1.5]), np.array([0.8, 0.0, 0.0])):    # forward, sideways
        X1 = P @ R.T + t
        ang = triangulation_angles_deg(proj(P), proj(X1), K, R)
        assert np.allclose(ang, _triangulation_angles_reference(P, R, t), atol=1e-6)
    # forward motion: small angles near the focus of expansion, wide ones towards the border
    t = np.array([0.0, 0.0, -1.5])
    ang = triangulation_angles_deg(proj(P), proj(P @ R.T + t), K, R)
    off_axis = np.hypot(P[:, 0], P[:, 1]) / P[:, 2]
    assert ang[off_axis > 0.5].mean() > 3 * ang[off_axis < 0.1].mean()
    assert np.allclose(triangulation_angles_deg(proj(P), proj(P @ R.T), K, R), 0, atol=1e-4)
