"""CPU 2DGS rasterizer (vings_core.render): numba kernels against the pure-torch reference.

The reference computes the ray-splat intersection differently (ray/plane in the camera frame) and
composites densely, so agreement checks the kernels' algebra, bounding boxes, sorting, early
termination and hand-written backward pass.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vings_core.errors import InputError
from vings_core.geometry import np_pose, np_pose_inverse, np_rotmat_to_quat, np_so3_exp
from vings_core.render import (gaussian_scores, rasterize_2dgs, render_reference,
                               select_sample_pixels)
from vings_core.render.rasterize import _camera_setup
from vings_core.types import CameraModel

F64 = torch.float64
OUT_KEYS = ("color", "depth", "normal", "alpha", "distortion")


def _scene(n: int, seed: int = 0, dtype=F64):
    """Random surfels in front of the camera, plus the awkward cases: tiny (low-pass) splats,
    near-edge-on splats, centres behind the camera, beyond the near plane, off-screen, clamped
    opacity, and one large splat crossing the camera plane."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor([1.0, 0.7, 0.5], dtype=F64)
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = torch.rand(n, 2, generator=g, dtype=F64) * 0.15 + 0.005
    opac = torch.rand(n, generator=g, dtype=F64) * 0.9 + 0.05
    cols = torch.rand(n, 3, generator=g, dtype=F64)
    k = 0
    scales[k:k + 6] = 0.0015                                   # sub-pixel: low-pass filter
    k += 6
    quats[k:k + 4] = torch.tensor([0.7071, 0.0, 0.0, 0.7071], dtype=F64)   # normal along y
    means[k:k + 4, 1] = 0.0                                    # -> almost edge-on at image centre
    k += 4
    means[k, 2] = -1.0                                         # behind the camera
    means[k + 1] = torch.tensor([0.0, 0.0, -0.095], dtype=F64)  # camera z ~ 0.005 < near
    means[k + 2] = torch.tensor([30.0, 0.0, 3.0], dtype=F64)   # far off-screen
    opac[k + 3] = 1.0                                          # clamped at 0.99
    k += 4
    means[k] = torch.tensor([0.2, 0.3, 0.4], dtype=F64)        # big splat through the camera plane
    quats[k] = torch.tensor([0.3, 0.0, 0.0, 0.954], dtype=F64)
    scales[k] = torch.tensor([0.8, 0.8], dtype=F64)
    return [t.to(dtype) for t in (means, quats, scales, opac, cols)]


CAM = CameraModel(width=64, height=48, fx=50.0, fy=52.0, cx=31.3, cy=23.7)
T_CW = np_pose(np_so3_exp(np.array([0.02, -0.03, 0.01])), np.array([0.05, -0.02, 0.1]))
BG = (0.1, 0.2, 0.3)


def _ref(g, **kw):
    return render_reference(*g, torch.tensor(T_CW), CAM, background=torch.tensor(BG, dtype=g[0].dtype),
                            **kw)


def _fast(g, **kw):
    return rasterize_2dgs(*g, T_CW, CAM, background=torch.tensor(BG, dtype=g[0].dtype), **kw)


def test_forward_matches_reference_float64():
    g = _scene(300)
    loss_map = torch.rand(CAM.height, CAM.width, dtype=F64)
    out = _fast(g, loss_map=loss_map)
    ref = _ref(g, loss_map=loss_map)
    for k in OUT_KEYS:
        a, b = getattr(out, k), ref[k]
        assert a.shape == b.shape
        assert torch.allclose(a, b, atol=1e-9, rtol=0), (k, float((a - b).abs().max()))
    assert float(out.alpha.max()) > 0.9 and float(out.alpha.min()) < 0.5   # non-trivial image
    assert torch.equal(out.n_contrib.to(F64), ref["n_contrib"])
    assert torch.equal(out.pixels_touched.to(F64), ref["pixels_touched"])
    assert torch.allclose(out.contribution, ref["contribution"], atol=1e-9)
    assert torch.allclose(out.error, ref["error"], atol=1e-9)
    # culled ones: behind the camera, inside near, off-screen
    assert out.radii[10] == 0 and out.radii[11] == 0 and out.radii[12] == 0
    assert out.contribution[10:13].abs().sum() == 0 and out.radii[14] > 0
    assert out.stats["pairs_evaluated"] >= out.stats["pairs_contributing"] > 0


def test_forward_float32_close_to_float64_reference():
    g64 = _scene(300)
    out = _fast([t.float() for t in g64])
    ref = _ref(g64)
    tol = {"color": 2e-4, "depth": 1e-3, "normal": 2e-4, "alpha": 2e-4, "distortion": 1e-6}
    for k in OUT_KEYS:
        err = float((getattr(out, k).double() - ref[k]).abs().max())
        assert err < tol[k], (k, err)


def test_reference_tile_culling_equals_dense():
    g = _scene(200, seed=3)
    a = _ref(g)
    b = _ref(g, tile_cull=True)
    for k in OUT_KEYS + ("contribution", "pixels_touched"):
        assert torch.allclose(a[k], b[k], atol=1e-12), k


def _grads(fn, g, upstream, sh_degree=None, **kw):
    leaves = [t.clone().requires_grad_(True) for t in g]
    bg = torch.tensor(BG, dtype=F64, requires_grad=True)
    pd = torch.zeros(6, dtype=F64, requires_grad=True)
    if fn is render_reference:
        out = fn(*leaves, torch.tensor(T_CW), CAM, background=bg, pose_delta=pd, sh_degree=sh_degree)
        o = [out[k] for k in OUT_KEYS]
    else:
        out = fn(*leaves, T_CW, CAM, background=bg, pose_delta=pd, sh_degree=sh_degree, **kw)
        o = [getattr(out, k) for k in OUT_KEYS]
    loss = sum((a * b).sum() for a, b in zip(o, upstream))
    loss.backward()
    return [t.grad for t in leaves] + [bg.grad, pd.grad], out


def _upstream(seed=1, dist_scale=100.0):
    gen = torch.Generator().manual_seed(seed)
    H, W = CAM.height, CAM.width
    return [torch.randn(H, W, 3, generator=gen, dtype=F64), torch.randn(H, W, generator=gen, dtype=F64),
            torch.randn(H, W, 3, generator=gen, dtype=F64), torch.randn(H, W, generator=gen, dtype=F64),
            dist_scale * torch.randn(H, W, generator=gen, dtype=F64)]


NAMES = ("means", "quats", "scales", "opacities", "colors", "background", "pose_delta")


def _assert_grads_close(ga, gb, rtol=1e-7) -> int:
    """Asserts every gradient pair agrees; returns how many pairs were compared."""
    n = 0
    for name, a, b in zip(NAMES, ga, gb):
        scale = float(b.abs().max())
        assert scale > 0, name
        err = float((a - b).abs().max())
        assert err <= rtol * scale + 1e-12, (name, err, scale)
        n += 1
    return n


def test_gradients_match_reference_float64():
    g = _scene(300, seed=5)
    up = _upstream()
    gk, _ = _grads(rasterize_2dgs, g, up)
    gr, _ = _grads(render_reference, g, up)
    # every gradient (means ... pose) compared, none dropped by a length mismatch
    assert _assert_grads_close(gk, gr) == len(gk) == len(gr) == len(NAMES)


def test_sh_colours_and_gradients_match_reference():
    g = _scene(120, seed=7)
    sh = torch.randn(120, 16, 3, generator=torch.Generator().manual_seed(2), dtype=F64) * 0.3
    g = g[:4] + [sh]
    up = _upstream(seed=3)
    gk, out = _grads(rasterize_2dgs, g, up, sh_degree=3)
    gr, ref = _grads(render_reference, g, up, sh_degree=3)
    assert torch.allclose(out.color, ref["color"], atol=1e-9)
    _assert_grads_close(gk, gr)


def test_numba_projection_matches_torch_projection():
    g = _scene(200, seed=9)
    T = torch.tensor(T_CW)
    outs = []
    for proj in ("numba", "torch"):
        leaves = [t.clone().requires_grad_(True) for t in g]
        pd = torch.zeros(6, dtype=F64, requires_grad=True)
        rec = _camera_setup(*leaves, T, CAM, None, pd, projector=proj)
        w = torch.randn(rec.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
        (rec * w).sum().backward()
        outs.append((rec.detach(), [t.grad for t in leaves] + [pd.grad]))
    assert torch.allclose(outs[0][0], outs[1][0], atol=1e-12)
    for a, b in zip(outs[0][1], outs[1][1]):
        assert torch.allclose(a, b, atol=1e-10 * float(b.abs().max()) + 1e-12)


def test_pose_gradient_matches_finite_differences():
    g = _scene(200, seed=11)
    target = torch.rand(CAM.height, CAM.width, 3, generator=torch.Generator().manual_seed(8), dtype=F64)

    def loss_at(delta: torch.Tensor) -> torch.Tensor:
        out = rasterize_2dgs(*g, T_CW, CAM, pose_delta=delta)
        return ((out.color - target) ** 2).sum() + (out.depth ** 2).sum() * 0.01

    d = torch.zeros(6, dtype=F64, requires_grad=True)
    loss_at(d).backward()
    fd = torch.zeros(6, dtype=F64)
    eps = 1e-6
    for i in range(6):
        e = torch.zeros(6, dtype=F64)
        e[i] = eps
        fd[i] = (loss_at(e) - loss_at(-e)) / (2 * eps)
    assert torch.allclose(d.grad, fd, rtol=1e-4, atol=1e-6 * float(fd.abs().max())), (d.grad, fd)


def test_sampled_backward_is_the_masked_full_backward():
    g = _scene(300, seed=13)
    up = _upstream(seed=6)
    score = torch.rand(CAM.height, CAM.width, generator=torch.Generator().manual_seed(5), dtype=F64)
    mask = select_sample_pixels(score, 0.5)
    # exactly ceil(r n) pixels per 16x16 tile, the best-scored ones
    for ty in range(0, CAM.height, 16):
        for tx in range(0, CAM.width, 16):
            m = mask[ty:ty + 16, tx:tx + 16]
            s = score[ty:ty + 16, tx:tx + 16]
            assert int(m.sum()) == math.ceil(0.5 * m.numel())
            assert float(s[m].min()) >= float(s[~m].max())
    gk, out = _grads(rasterize_2dgs, g, up, sample_ratio=0.5, loss_map=score)
    masked = [u * (mask[..., None] if u.dim() == 3 else mask).to(F64) for u in up]
    gr, _ = _grads(render_reference, g, masked)
    _assert_grads_close(gk, gr)
    # work of the backward pass halves
    _, full = _grads(rasterize_2dgs, g, up, sample_ratio=1.0)
    frac = out.stats["bwd_pairs_evaluated"] / full.stats["bwd_pairs_evaluated"]
    assert 0.3 < frac < 0.7, frac
    assert out.stats["bwd_pixels"] == int(mask.sum())


def test_sample_selection_ranks_nan_scores_last():
    # a NaN score (e.g. from a diverged pixel) must neither empty its tile's selection nor win
    score = torch.rand(CAM.height, CAM.width, generator=torch.Generator().manual_seed(21), dtype=F64)
    score[::3, ::5] = float("nan")
    for ratio in (0.5, 0.99):
        mask = select_sample_pixels(score, ratio)
        for ty in range(0, CAM.height, 16):
            for tx in range(0, CAM.width, 16):
                m = mask[ty:ty + 16, tx:tx + 16]
                s = score[ty:ty + 16, tx:tx + 16]
                k = math.ceil(ratio * m.numel())
                assert int(m.sum()) == k
                finite = ~torch.isnan(s)
                if k <= int(finite.sum()):     # enough numbers: no NaN pixel is taken
                    assert not bool((m & ~finite).any())
                else:                          # every number is taken, NaNs fill the rest
                    assert bool(m[finite].all())


def test_sample_map_set_after_forward_overrides_loss_map():
    """The map set after the forward decides which pixels back-propagate, over the forward's
    loss_map: the gradients equal the full backward with the upstream masked by its selection
    (the loss map would select other pixels: the right half)."""
    g = _scene(150, seed=17)
    score = torch.zeros(CAM.height, CAM.width, dtype=F64)
    score[:, :20] = 1.0                         # prefer the left columns
    loss = torch.zeros(CAM.height, CAM.width, dtype=F64)
    loss[:, CAM.width // 2:] = 1.0              # the forward's loss map prefers the right half
    up = _upstream(seed=2)
    leaves = [t.clone().requires_grad_(True) for t in g]
    bg = torch.tensor(BG, dtype=F64, requires_grad=True)
    pd = torch.zeros(6, dtype=F64, requires_grad=True)
    out = rasterize_2dgs(*leaves, T_CW, CAM, background=bg, pose_delta=pd, sample_ratio=0.25, loss_map=loss)
    out.set_sample_map(score)
    sum((getattr(out, k) * u).sum() for k, u in zip(OUT_KEYS, up)).backward()
    sel = select_sample_pixels(score, 0.25)
    assert out.stats["bwd_pixels"] == int(sel.sum())
    assert not torch.equal(sel, select_sample_pixels(loss, 0.25))
    masked = [u * (sel[..., None] if u.dim() == 3 else sel).to(F64) for u in up]
    gr, _ = _grads(rasterize_2dgs, g, masked)
    _assert_grads_close([t.grad for t in leaves] + [bg.grad, pd.grad], gr, rtol=1e-9)
    with pytest.raises(InputError):
        out.set_sample_map(torch.zeros(3, 3))


def test_scores_forward_only():
    g = _scene(250, seed=19)
    L = torch.rand(CAM.height, CAM.width, dtype=F64)
    sc = gaussian_scores(*g, T_CW, CAM, L)
    ref = _ref(g, loss_map=L)
    assert torch.allclose(sc["contribution"], ref["contribution"], atol=1e-9)
    assert torch.allclose(sc["error"], ref["error"], atol=1e-9)
    assert torch.equal(sc["pixels_touched"].to(F64), ref["pixels_touched"])
    # contribution of a visible Gaussian is at most the number of pixels it touches
    assert bool((sc["contribution"] <= sc["pixels_touched"].to(F64) + 1e-12).all())


def test_fronto_parallel_surfel_depth_normal_and_alpha():
    # one opaque-ish surfel facing the camera at z = 2: depth 2 and normal (0, 0, -1) at its centre
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=F64)
    quats = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=F64)
    scales = torch.tensor([[0.3, 0.2]], dtype=F64)
    cam = CameraModel(width=32, height=32, fx=40.0, fy=40.0, cx=15.0, cy=15.0)
    out = rasterize_2dgs(means, quats, scales, torch.tensor([0.9], dtype=F64),
                         torch.tensor([[1.0, 0.5, 0.25]], dtype=F64), np.eye(4), cam)
    assert abs(float(out.alpha[15, 15]) - 0.9) < 1e-9
    assert abs(float(out.expected_depth[15, 15]) - 2.0) < 1e-9
    n = out.normal[15, 15] / out.alpha[15, 15]
    assert torch.allclose(n, torch.tensor([0.0, 0.0, -1.0], dtype=F64), atol=1e-9)
    # anisotropy: at 3 px along x (u = 3/40*2/0.3 = 0.5) alpha = 0.9 exp(-0.125)
    assert abs(float(out.alpha[15, 18]) - 0.9 * math.exp(-0.5 * 0.5 ** 2)) < 1e-9
    # along y (v = 3/40*2/0.2 = 0.75)
    assert abs(float(out.alpha[18, 15]) - 0.9 * math.exp(-0.5 * 0.75 ** 2)) < 1e-9
    assert out.radii[0] > 0 and out.n_contrib[15, 15] == 1


def test_tilted_surfel_gives_plane_depth():
    # a large surfel on the plane z = 2 + 0.5 x: every pixel's hit depth is the plane's depth
    # along its ray (2DGS intersection), not the centre depth
    a = math.atan(0.5)
    R = np_so3_exp(np.array([0.0, -a, 0.0]))   # normal (sin a, 0, -cos a) up to sign
    q = torch.tensor(np_rotmat_to_quat(R))[None]
    cam = CameraModel(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    out = rasterize_2dgs(torch.tensor([[0.0, 0.0, 2.0]], dtype=F64), q,
                         torch.tensor([[3.0, 3.0]], dtype=F64), torch.tensor([0.95], dtype=F64),
                         torch.ones(1, 3, dtype=F64), np.eye(4), cam)
    ys, xs = np.mgrid[0:24, 0:32]
    rx = (xs - cam.cx) / cam.fx
    n = R[:, 2]
    z = (n @ np.array([0.0, 0.0, 2.0])) / (n[0] * rx + n[2] * 1.0 + n[1] * (ys - cam.cy) / cam.fy)
    d = out.expected_depth.numpy()
    m = out.alpha.numpy() > 0.5
    assert m.sum() > 300
    assert np.abs(d[m] - z[m]).max() < 1e-9


def test_empty_and_all_culled_render_background():
    cam = CameraModel(width=20, height=10, fx=10.0, fy=10.0, cx=9.5, cy=4.5)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=F64)
    e = torch.zeros(0, 3, dtype=F64)
    out = rasterize_2dgs(e, torch.zeros(0, 4, dtype=F64), torch.zeros(0, 2, dtype=F64),
                         torch.zeros(0, dtype=F64), e, np.eye(4), cam, background=bg)
    assert torch.allclose(out.color, bg.expand(10, 20, 3)) and float(out.alpha.abs().max()) == 0
    means = torch.tensor([[0.0, 0.0, -2.0]], dtype=F64, requires_grad=True)
    out = rasterize_2dgs(means, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=F64),
                         torch.tensor([[0.5, 0.5]], dtype=F64), torch.tensor([0.9], dtype=F64),
                         torch.ones(1, 3, dtype=F64), np.eye(4), cam, background=bg)
    out.color.sum().backward()
    assert out.radii[0] == 0 and float(means.grad.abs().sum()) == 0



def test_two_clamped_splats_composite_alike_in_float32_and_float64():
    # opacity 1 clamps alpha to 0.99: after two splats T = (1 - 0.99)^2 = 1e-4 exactly, which float32
    # rounds below and float64 above the termination threshold; both must keep the second splat
    cam = CameraModel(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    g = [torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.5], [0.0, 0.0, 3.0]], dtype=F64),
         torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 3, dtype=F64), torch.full((3, 2), 2.0, dtype=F64),
         torch.ones(3, dtype=F64), torch.eye(3, dtype=F64)]
    ref = render_reference(*g, torch.eye(4, dtype=F64), cam)
    assert int(ref["n_contrib"][12, 16]) == 2
    for dt in (F64, torch.float32):
        out = rasterize_2dgs(*[t.to(dt) for t in g], np.eye(4), cam)
        assert torch.equal(out.n_contrib.to(torch.int64), ref["n_contrib"].to(torch.int64)), dt
        assert torch.allclose(out.color.double(), ref["color"], atol=1e-6), dt


def test_reference_is_finite_for_a_centre_in_the_camera_plane():
    # camera z of the second centre is exactly 0 (culled by both): the reference's low-pass screen
    # position and distortion depth mapping must not divide by it (distortion and gradients stay finite)
    cam = CameraModel(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    g = [torch.tensor([[0.0, 0.0, 2.0], [0.3, 0.1, 0.0]], dtype=F64),
         torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 2, dtype=F64), torch.full((2, 2), 0.2, dtype=F64),
         torch.tensor([0.8, 0.8], dtype=F64), torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3]], dtype=F64)]
    res = []
    for fn in (rasterize_2dgs, render_reference):
        leaves = [t.clone().requires_grad_(True) for t in g]
        pd = torch.zeros(6, dtype=F64, requires_grad=True)
        out = fn(*leaves, torch.eye(4, dtype=F64), cam, pose_delta=pd)
        o = [out[k] if isinstance(out, dict) else getattr(out, k) for k in OUT_KEYS]
        assert all(bool(torch.isfinite(x).all()) for x in o), fn.__name__
        sum((x * (i + 1)).sum() for i, x in enumerate(o)).backward()
        res.append([t.grad for t in leaves] + [pd.grad])
    for a, b in zip(*res):
        assert bool(torch.isfinite(b).all())
        assert torch.allclose(a, b, atol=1e-9 * float(b.abs().max()) + 1e-12)


def test_raw_pose_matrix_gradient_matches_reference():
    # dL/dT_cw for a T_cw tensor with requires_grad: every entry, off the rotation manifold too
    # (the reference solves for the splat coordinates instead of assuming orthonormal axes)
    g = _scene(150, seed=29)
    up = _upstream(seed=9)
    res = []
    for fn in (rasterize_2dgs, render_reference):
        T = torch.tensor(T_CW, requires_grad=True)
        out = fn(*g, T, CAM)
        o = [out[k] if isinstance(out, dict) else getattr(out, k) for k in OUT_KEYS]
        sum((x * u).sum() for x, u in zip(o, up)).backward()
        res.append(T.grad)
    assert float((res[0] - res[1]).abs().max()) <= 1e-8 * float(res[1].abs().max())

def test_bad_inputs_raise_input_error():
    g = _scene(30)
    with pytest.raises(InputError, match="means"):
        rasterize_2dgs(g[0][:, :2], *g[1:], T_CW, CAM)
    with pytest.raises(InputError, match="scales"):
        rasterize_2dgs(g[0], g[1], torch.ones(30, 3, dtype=F64), *g[3:], T_CW, CAM)
    with pytest.raises(InputError, match="T_cw"):
        rasterize_2dgs(*g, np.eye(3), CAM)
    with pytest.raises(InputError, match="sample_ratio"):
        rasterize_2dgs(*g, T_CW, CAM, sample_ratio=0.0)
    with pytest.raises(InputError, match="loss_map"):
        rasterize_2dgs(*g, T_CW, CAM, loss_map=np.zeros((3, 3)))
    with pytest.raises(InputError, match="distortion"):
        rasterize_2dgs(*g, T_CW, CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0, "radtan",
                                             np.array([0.1, 0.0, 0.0, 0.0])))
    with pytest.raises(InputError, match="sh_degree"):
        rasterize_2dgs(*g[:4], torch.zeros(30, 4, 3, dtype=F64), T_CW, CAM, sh_degree=2)


def test_bad_poses_maps_and_types_raise_input_error():
    g = _scene(30)
    T_nan = T_CW.copy()
    T_nan[0, 3] = np.nan
    for kw, what in ((dict(T_cw=T_nan), "T_cw"), (dict(T_cw="eye"), "T_cw"),
                     (dict(pose_delta=torch.full((6,), float("nan"), dtype=F64)), "pose_delta"),
                     (dict(loss_map=np.full((CAM.height, CAM.width), np.nan)), "loss_map"),
                     (dict(background=(np.nan, 0.0, 0.0)), "background"),
                     (dict(background="abc"), "background")):
        args = dict(T_cw=T_CW)
        args.update(kw)
        with pytest.raises(InputError, match=what):
            rasterize_2dgs(*g, args.pop("T_cw"), CAM, **args)
    with pytest.raises(InputError, match="sh_degree"):
        rasterize_2dgs(*g[:4], torch.zeros(30, 4, 3, dtype=F64), T_CW, CAM, sh_degree=1.7)
    # a pose delta given as a plain array, and SH coefficients as numpy, work as tensors do
    d = np.array([0.01, 0.0, -0.02, 0.0, 0.01, 0.0])
    a = rasterize_2dgs(*g, T_CW, CAM, pose_delta=d)
    b = rasterize_2dgs(*g, T_CW, CAM, pose_delta=torch.tensor(d))
    assert torch.equal(a.color, b.color)
    sh = np.zeros((30, 4, 3))
    sh[:, 0] = 0.3
    assert torch.equal(rasterize_2dgs(*g[:4], sh, T_CW, CAM, sh_degree=1).color,
                       rasterize_2dgs(*g[:4], torch.tensor(sh), T_CW, CAM, sh_degree=1).color)


def test_camera_model_checks_its_numbers():
    c = CameraModel(width=64.0, height=48.0, fx=50.0, fy=52.0, cx=31.3, cy=23.7)
    assert (c.width, c.height) == (64, 48) and isinstance(c.width, int)
    with pytest.raises(ValueError, match="width"):
        CameraModel(width=64.5, height=48, fx=50.0, fy=52.0, cx=31.3, cy=23.7)
    with pytest.raises(ValueError, match="cx"):
        CameraModel(width=64, height=48, fx=50.0, fy=52.0, cx=float("nan"), cy=23.7)


@pytest.mark.parametrize("bad", ["zero_quat", "nan_quat", "nan_scale", "inf_scale", "inf_opacity",
                                 "nan_color"])
def test_non_finite_gaussians_are_culled(bad):
    """One broken Gaussian draws nothing and gets zero gradients; the others render and
    differentiate exactly as without it (its NaN must not reach their transmittance)."""
    g = _scene(30)
    k = 20
    broken = [t.clone() for t in g]
    {"zero_quat": lambda: broken[1][k].zero_(), "nan_quat": lambda: broken[1][k].fill_(float("nan")),
     "nan_scale": lambda: broken[2][k].fill_(float("nan")),
     "inf_scale": lambda: broken[2][k].fill_(float("inf")),
     "inf_opacity": lambda: broken[3][k:k + 1].fill_(float("inf")),
     "nan_color": lambda: broken[4][k].fill_(float("nan"))}[bad]()
    keep = torch.arange(30) != k
    up = _upstream()
    gb, ob = _grads(rasterize_2dgs, broken, up)
    gk, ok = _grads(rasterize_2dgs, [t[keep] for t in g], up)
    for key in OUT_KEYS:
        assert torch.allclose(getattr(ob, key), getattr(ok, key), atol=1e-12), key
    assert int(ob.radii[k]) == 0
    for a, b in zip(gb[:5], gk[:5]):
        assert torch.isfinite(a).all() and float(a[k].abs().sum()) == 0
        assert torch.allclose(a[keep], b, atol=1e-10)
    for a, b in zip(gb[5:], gk[5:]):     # background and pose
        assert torch.allclose(a, b, atol=1e-10)


def test_in_place_change_before_backward_is_refused():
    """The backward must not read a tensor the caller changed after the forward (a numpy view of
    it would silently give wrong gradients); autograd's version check refuses it instead."""
    g = [t.clone().requires_grad_(True) for t in _scene(30)]
    out = _fast(g)
    with torch.no_grad():
        g[1].mul_(1.7)
    with pytest.raises(RuntimeError, match="inplace"):
        out.color.sum().backward()
    # a sample map changed after set_sample_map does not change the selection either
    g = [t.detach().clone().requires_grad_(True) for t in _scene(30)]
    score = torch.rand(CAM.height, CAM.width, generator=torch.Generator().manual_seed(3), dtype=F64)
    grads = []
    for mutate in (False, True, None):      # None: the negated map itself, set before the backward
        out = _fast(g, sample_ratio=0.5)
        s = score.clone() if mutate is not None else -score
        out.set_sample_map(s)
        if mutate:
            s.neg_()
        for t in g:
            t.grad = None
        out.color.sum().backward()
        grads.append([t.grad.clone() for t in g])
    for a, b in zip(grads[0], grads[1]):
        assert torch.equal(a, b)
    # and the negated map does select other pixels (so the equality above is not vacuous)
    assert not torch.equal(grads[0][0], grads[2][0])


def test_tiny_sample_ratio_selects_no_pixel():
    score = torch.rand(40, 50, generator=torch.Generator().manual_seed(0), dtype=F64)
    assert int(select_sample_pixels(score, 1e-12).sum()) == 0
    assert int(select_sample_pixels(score, 0.5).sum()) > 0
    for bad in (0.0, -1.0, float("nan"), 1.5):
        with pytest.raises(InputError, match="ratio"):
            select_sample_pixels(score, bad)
    with pytest.raises(InputError, match="H, W"):
        select_sample_pixels(torch.rand(3, 4, 5), 0.5)
    g = [t.clone().requires_grad_(True) for t in _scene(30)]
    out = _fast(g, sample_ratio=1e-12)
    out.color.sum().backward()
    assert out.stats["bwd_pixels"] == 0 and all(float(t.grad.abs().sum()) == 0 for t in g)


def test_world_normals_and_pose_conventions():
    # the same surfel seen from a moved camera: T_cw is world->camera; normal_world is consistent
    g = _scene(50, seed=23)
    T_wc = np_pose_inverse(T_CW)
    out = _fast(g)
    nw = out.normal_world(T_wc)
    assert torch.allclose(nw @ torch.tensor(T_wc[:3, :3]), out.normal, atol=1e-12)


def _gsplat_ok() -> bool:
    from vings_core.render.gsplat_backend import gsplat_available
    return gsplat_available()


def _room_map_scene(width: int = 160, height: int = 112):
    """Gaussians as the map initialises them from one simulated `room` keyframe (every pixel with
    depth; scale from the neighbours' spacing, opacity 0.8), the camera moved a little for the
    render. Returns (means, quats, scales, opacities, colours) float32, camera, T_cw."""
    from vings_core.mapping.init import gaussians_from_pixels
    from vings_core.sim import default_camera, make_scene, render_view
    from vings_core.types import Keyframe
    scene = make_scene("room", seed=0)
    cam = default_camera(width, height)
    T_wc = scene.T_wc(np.array([0.8]))[0]
    rgb, depth, _ = render_view(scene, cam, T_wc)
    kf = Keyframe(stamp_ns=1, image=torch.from_numpy(rgb.astype(np.float32) / 255.0), T_wc=T_wc,
                  depth=torch.from_numpy(depth), inv_depth_var=torch.zeros_like(torch.from_numpy(depth)),
                  valid=torch.from_numpy(depth > 0), camera=cam)
    rc = torch.nonzero(torch.from_numpy(depth > 0))
    m = gaussians_from_pixels(kf, rc, sh_degree=0, init_opacity=0.8, scale_factor=1.0,
                              min_scale_px=0.5, max_scale_px=4.0)
    g = [m.means, m.quats, m.scales(), m.opacities(), m.rgb()]
    T_wc_view = T_wc @ np_pose(np_so3_exp(np.radians(2.0) * np.array([0.3, 0.9, 0.3])), [0.03, -0.02, 0.035])
    return [t.detach().float().contiguous() for t in g], cam, np_pose_inverse(T_wc_view)


@pytest.mark.skipif(not _gsplat_ok(), reason="needs CUDA and the gsplat package")
def test_cpu_matches_gsplat():  # pragma: no cover - needs a GPU
    """Forward and gradients of the numba path against gsplat's CUDA 2DGS on a map-like scene.

    Not bit-equal by design (docs/rasterizer.md): gsplat bins a splat into tiles by a 3.33-sigma
    box without the low-pass footprint, so a few pixels near sub-pixel splats differ, and its depth
    channel is the centre depth; hence statistics, not a max-error bound, for colour/alpha/normal.
    """
    g, cam, T_cw = _room_map_scene()
    H, W = cam.height, cam.width
    gen = torch.Generator().manual_seed(5)
    up = {"color": torch.randn(H, W, 3, generator=gen), "alpha": torch.randn(H, W, generator=gen),
          "normal": torch.randn(H, W, 3, generator=gen)}
    loss_map = torch.rand(H, W, generator=gen)
    outs, grads, scores = {}, {}, {}
    for dev in ("cpu", "cuda"):
        leaves = [t.to(dev).clone().requires_grad_(True) for t in g]
        pd = torch.zeros(6, dtype=torch.float64, device=dev, requires_grad=True)
        out = rasterize_2dgs(*leaves, torch.tensor(T_cw, device=dev), cam, pose_delta=pd,
                             loss_map=loss_map.to(dev), backend="numba" if dev == "cpu" else "gsplat")
        sum((getattr(out, k) * u.to(dev)).sum() for k, u in up.items()).backward()
        outs[dev] = {k: getattr(out, k).detach().cpu().double() for k in ("color", "alpha", "normal", "depth")}
        grads[dev] = [t.grad.detach().cpu().double().flatten() for t in leaves + [pd]]
        scores[dev] = {k: getattr(out, k).cpu().double().flatten()
                       for k in ("contribution", "error", "pixels_touched", "n_contrib")}
    stats = {}
    # per-Gaussian scores (the score manager's inputs): same totals, same Gaussians
    for k in ("contribution", "error", "pixels_touched", "n_contrib"):
        a, b = scores["cpu"][k], scores["cuda"][k]
        stats[k] = (float(a @ b / (a.norm() * b.norm())), float(b.sum() / a.sum()))
    for k in ("color", "alpha", "normal"):
        d = (outs["cpu"][k] - outs["cuda"][k]).abs().flatten()
        stats[k] = (float(d.mean()), float(d.quantile(0.999)))
    # expected depth: ray-splat hit depth here, centre depth there: close on a smooth surface
    e = [outs[d]["depth"] / outs[d]["alpha"].clamp_min(1e-6) for d in ("cpu", "cuda")]
    stats["depth_median_rel"] = float((e[0] - e[1]).abs().median() / e[0].median())
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "pose_delta"), *grads.values()):
        stats[name] = (float(a @ b / (a.norm() * b.norm())), float(a.norm() / b.norm()))
    print("numba vs gsplat:", stats)
    assert float(outs["cpu"]["alpha"].mean()) > 0.9  # the view is covered
    for k in ("color", "alpha", "normal"):
        assert stats[k][0] < 1e-4 and stats[k][1] < 5e-3, (k, stats)
    assert stats["depth_median_rel"] < 0.01, stats
    for name in ("means", "quats", "scales", "opacities", "colors", "pose_delta"):
        cos, ratio = stats[name]
        assert cos > 0.999 and abs(ratio - 1.0) < 0.02, (name, stats)
    for name in ("contribution", "error", "pixels_touched", "n_contrib"):
        cos, ratio = stats[name]
        assert cos > 0.99 and abs(ratio - 1.0) < 0.02, (name, stats)


def test_parallel_path_matches_serial_and_reference(monkeypatch):
    # small problems run on one thread; force the multi-threaded path (chunked binning,
    # tile-parallel kernels) and check it gives the same numbers
    from vings_core.render import rasterize as rz
    g = _scene(300, seed=31)
    up = _upstream(seed=9)
    gs, out_s = _grads(rasterize_2dgs, g, up)
    monkeypatch.setattr(rz._Threads, "SMALL_PIXELS", 0)
    monkeypatch.setattr(rz._Threads, "SMALL_GAUSSIANS", 0)
    gp, out_p = _grads(rasterize_2dgs, g, up)
    for k in OUT_KEYS:
        assert torch.equal(getattr(out_s, k), getattr(out_p, k)), k
    for a, b in zip(gs, gp):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
    gr, _ = _grads(render_reference, g, up)
    _assert_grads_close(gp, gr)


@pytest.mark.skipif(_gsplat_ok(), reason="gsplat is available here")
def test_gsplat_backend_unavailable_is_a_clear_error():
    g = _scene(20)
    with pytest.raises(InputError, match="gsplat"):
        rasterize_2dgs(*g, T_CW, CAM, backend="gsplat")
    with pytest.raises(InputError, match="backend"):
        rasterize_2dgs(*g, T_CW, CAM, backend="cuda")


# camera whose size is not a multiple of the 16x16 tile (partial tiles on the right and bottom)
CAM_ODD = CameraModel(width=70, height=45, fx=55.0, fy=53.0, cx=34.6, cy=22.1)
# larger than the serial-path limit (128 x 128 px), so the tile kernels run on the thread pool
CAM_PAR = CameraModel(width=200, height=100, fx=120.0, fy=118.0, cx=99.2, cy=49.6)


def _grads_cam(g, cam, upstream, **kw):
    leaves = [t.clone().requires_grad_(True) for t in g]
    bg = torch.tensor(BG, dtype=g[0].dtype, requires_grad=True)
    pd = torch.zeros(6, dtype=F64, requires_grad=True)
    out = rasterize_2dgs(*leaves, T_CW, cam, background=bg, pose_delta=pd, **kw)
    loss = sum((getattr(out, k) * u.to(g[0].dtype)).sum() for k, u in zip(OUT_KEYS, upstream))
    loss.backward()
    return [t.grad for t in leaves] + [bg.grad, pd.grad], out


def _upstream_cam(cam, seed):
    gen = torch.Generator().manual_seed(seed)
    H, W = cam.height, cam.width
    return [torch.randn(H, W, 3, generator=gen, dtype=F64), torch.randn(H, W, generator=gen, dtype=F64),
            torch.randn(H, W, 3, generator=gen, dtype=F64), torch.randn(H, W, generator=gen, dtype=F64),
            100.0 * torch.randn(H, W, generator=gen, dtype=F64)]


def test_partial_tiles_forward_and_gradients_match_reference():
    g = _scene(250, seed=23)
    up = _upstream_cam(CAM_ODD, seed=9)
    gk, out = _grads_cam(g, CAM_ODD, up)
    leaves = [t.clone().requires_grad_(True) for t in g]
    bg = torch.tensor(BG, dtype=F64, requires_grad=True)
    pd = torch.zeros(6, dtype=F64, requires_grad=True)
    ref = render_reference(*leaves, torch.tensor(T_CW), CAM_ODD, background=bg, pose_delta=pd)
    for k in OUT_KEYS:
        assert torch.allclose(getattr(out, k), ref[k], atol=1e-9, rtol=0), k
    sum((ref[k] * u).sum() for k, u in zip(OUT_KEYS, up)).backward()
    _assert_grads_close(gk, [t.grad for t in leaves] + [bg.grad, pd.grad])


@pytest.mark.parametrize("cam", [CAM_ODD, CAM_PAR], ids=["partial-tiles", "thread-pool"])
@pytest.mark.parametrize("ratio", [0.25, 0.5])
def test_sampled_backward_equals_full_backward_of_restricted_loss(cam, ratio):
    """The sampled backward (r < 1) gives the gradients that the full backward (r = 1) gives for
    the loss restricted to the selected pixels (upstream gradients zeroed elsewhere), while
    evaluating only about r of the pixel-Gaussian pairs."""
    g = _scene(400, seed=29)
    up = _upstream_cam(cam, seed=int(ratio * 100))
    score = torch.rand(cam.height, cam.width, generator=torch.Generator().manual_seed(3), dtype=F64)
    mask = select_sample_pixels(score, ratio)
    gs, out_s = _grads_cam(g, cam, up, sample_ratio=ratio, loss_map=score)
    restricted = [u * (mask[..., None] if u.dim() == 3 else mask).to(F64) for u in up]
    gf, out_f = _grads_cam(g, cam, restricted, sample_ratio=1.0)
    _assert_grads_close(gs, gf, rtol=1e-12)
    assert out_s.stats["bwd_pixels"] == int(mask.sum())
    frac = out_s.stats["bwd_pairs_evaluated"] / out_f.stats["bwd_pairs_evaluated"]
    assert abs(frac - ratio) < 0.2, frac
    # float32 kernels: same agreement up to float32 rounding
    g32 = [t.float() for t in g]
    gs32, _ = _grads_cam(g32, cam, up, sample_ratio=ratio, loss_map=score)
    gf32, _ = _grads_cam(g32, cam, restricted, sample_ratio=1.0)
    for name, a, b in zip(NAMES, gs32, gf32):
        assert torch.allclose(a.double(), b.double(), rtol=1e-4, atol=1e-5 * float(b.abs().max())), name


@pytest.mark.parametrize("cam", [CAM_ODD, CAM_PAR], ids=["partial-tiles", "thread-pool"])
def test_backward_evaluates_exactly_the_composited_pairs(cam):
    """The forward records, per (tile, Gaussian) pair, the pixels it was composited into; the
    full backward evaluates exactly those pixel-Gaussian pairs (none outside a splat's cut-off or
    behind a pixel's early termination), and the sampled one exactly those at selected pixels."""
    g = _scene(400, seed=31)
    up = _upstream_cam(cam, seed=4)
    _, out = _grads_cam(g, cam, up, sample_ratio=1.0)
    assert out.stats["bwd_pairs_evaluated"] == int(out.n_contrib.sum()) > 0
    assert out.stats["pairs_evaluated"] > out.stats["bwd_pairs_evaluated"]   # the forward tries more
    score = torch.rand(cam.height, cam.width, generator=torch.Generator().manual_seed(5), dtype=F64)
    mask = select_sample_pixels(score, 0.5)
    _, out_s = _grads_cam(g, cam, up, sample_ratio=0.5, loss_map=score)
    assert out_s.stats["bwd_pairs_evaluated"] == int((out_s.n_contrib * mask).sum())


def _large_slanted_scene(n: int, seed: int):
    """Large surfels at grazing angles (thin slanted ellipses whose boxes span many tiles), some
    close to the camera (hyperbolic footprints through the camera plane get the whole image as
    their box), mixed with ordinary ones."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor([0.8, 0.6, 0.4], dtype=F64)
    means[:, 2] += 2.0
    means[: n // 5, 2] = torch.rand(n // 5, generator=g, dtype=F64) * 0.4 + 0.12   # near the camera
    axis = torch.randn(n, 3, generator=g, dtype=F64)
    axis[:, 2] *= 0.05                               # rotation axes in the image plane: grazing normals
    axis = axis / axis.norm(dim=1, keepdim=True)
    ang = (torch.rand(n, generator=g, dtype=F64) * 0.3 + 1.3)   # ~75-92 deg: near edge-on
    quats = torch.cat([torch.cos(ang / 2)[:, None], torch.sin(ang / 2)[:, None] * axis], 1)
    scales = torch.rand(n, 2, generator=g, dtype=F64) * torch.tensor([0.5, 0.03], dtype=F64) + 0.01
    opac = torch.rand(n, generator=g, dtype=F64) * 0.9 + 0.05
    cols = torch.rand(n, 3, generator=g, dtype=F64)
    return [means, quats, scales, opac, cols]


def test_exact_tile_coverage_matches_reference_and_cuts_pairs():
    """Boxes over many tiles are binned by exact per-row footprints (kernels._row_span): outputs,
    touched-pixel counts and gradients still equal the dense reference, while the tile list is
    shorter than the boxes'."""
    cam = CameraModel(width=160, height=112, fx=120.0, fy=118.0, cx=79.2, cy=55.9)
    g = _large_slanted_scene(120, seed=5)
    T = torch.tensor(T_CW)
    bg = torch.tensor(BG, dtype=F64)
    out = rasterize_2dgs(*g, T, cam, background=bg)
    ref = render_reference(*g, T, cam, background=bg)
    for k in OUT_KEYS:
        assert torch.allclose(getattr(out, k), ref[k], atol=1e-9, rtol=0), k
    assert torch.equal(out.pixels_touched.to(F64), ref["pixels_touched"])
    assert torch.allclose(out.contribution, ref["contribution"], atol=1e-9)
    # the tile list is the exact one: shorter than the boxes' tiles (radii give the box half-size)
    vis = out.radii > 0
    assert int(vis.sum()) > 50 and int((out.radii > 60).sum()) >= 5
    box_tiles = int((((2 * out.radii[vis] + 1) // 16 + 1) ** 2).clamp(max=70).sum())
    assert out.stats["tile_pairs"] < 0.8 * box_tiles, (out.stats["tile_pairs"], box_tiles)
    up = _upstream_cam(cam, seed=6)
    gk, _ = _grads_cam(g, cam, up)
    leaves = [t.clone().requires_grad_(True) for t in g]
    bgl = torch.tensor(BG, dtype=F64, requires_grad=True)
    pd = torch.zeros(6, dtype=F64, requires_grad=True)
    ref = render_reference(*leaves, T, cam, background=bgl, pose_delta=pd)
    sum((ref[k] * u).sum() for k, u in zip(OUT_KEYS, up)).backward()
    _assert_grads_close(gk, [t.grad for t in leaves] + [bgl.grad, pd.grad])


def test_rendered_normal_is_the_surfels_normal_facing_the_camera():
    """One opaque surfel filling the view, with a known world normal: the rendered (alpha-weighted)
    camera-frame normal is R_cw n turned towards the camera, and normal_world brings back n."""
    from vings_core.geometry import np_quat_to_rotmat
    axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    q = np.r_[axis * math.sin(math.radians(15)), math.cos(math.radians(15))]     # xyzw, 30 deg
    n_w = np_quat_to_rotmat(q)[:, 2]
    T_wc = np_pose_inverse(T_CW)
    mean = (T_wc @ np.array([0.0, 0.0, 3.0, 1.0]))[:3]
    g = [torch.tensor(mean[None], dtype=F64), torch.tensor(q[None], dtype=F64),
         torch.tensor([[3.0, 3.0]], dtype=F64), torch.tensor([1.0], dtype=F64),
         torch.tensor([[0.5, 0.5, 0.5]], dtype=F64)]
    out = _fast(g)
    a = float(out.alpha[24, 31])
    assert a > 0.98
    n_c = T_CW[:3, :3] @ n_w
    mean_c = (T_CW @ np.r_[mean, 1.0])[:3]
    n_c = n_c if n_c @ mean_c < 0 else -n_c                  # the side the camera sees
    np.testing.assert_allclose(out.normal[24, 31].numpy() / a, n_c, atol=1e-6)
    np.testing.assert_allclose(out.normal_world(T_wc)[24, 31].numpy() / a, n_c @ T_CW[:3, :3], atol=1e-6)
    assert abs(abs(float(out.normal_world(T_wc)[24, 31].numpy() @ n_w)) / a - 1.0) < 1e-6


def test_backward_scratch_reuse_keeps_earlier_gradients():
    # the backward's per-pair rows live in per-thread scratch reused by the next backward: gradients
    # already returned must not change, and two renders back-propagated together must give the
    # sum of their separate gradients
    from vings_core.render import rasterize as rz
    ga, gb = _scene(300, seed=41), _scene(250, seed=43)
    up_a, up_b = _upstream(seed=5), _upstream(seed=6)
    states = [_fast(g)._state for g in (ga, gb)]
    rows_a, _ = rz._backward_numpy(states[0], *[u.numpy() for u in up_a])
    keep = rows_a.copy()
    rows_b, _ = rz._backward_numpy(states[1], *[u.numpy() for u in up_b])
    assert np.array_equal(rows_a, keep) and not np.array_equal(rows_b[:50], keep[:50])
    # one graph, two renders sharing the leaves: both backward passes run before either
    # projection backward consumes its rows
    leaves = [t.clone().requires_grad_(True) for t in ga]
    o1 = rasterize_2dgs(*leaves, T_CW, CAM, sample_ratio=0.5)
    o2 = rasterize_2dgs(*leaves, np_pose(np_so3_exp(np.array([0.0, 0.05, 0.0])), np.zeros(3)) @ T_CW, CAM)
    loss = sum((getattr(o, k) * u).sum() for o, u in ((o1, up_a), (o2, up_b)) for k, u in zip(OUT_KEYS, u))
    loss.backward()
    ref = [t.clone().requires_grad_(True) for t in ga]
    r1 = rasterize_2dgs(*ref, T_CW, CAM, sample_ratio=0.5)
    sum((getattr(r1, k) * u).sum() for k, u in zip(OUT_KEYS, up_a)).backward()
    first = [t.grad.clone() for t in ref]
    for t in ref:
        t.grad = None
    r2 = rasterize_2dgs(*ref, np_pose(np_so3_exp(np.array([0.0, 0.05, 0.0])), np.zeros(3)) @ T_CW, CAM)
    sum((getattr(r2, k) * u).sum() for k, u in zip(OUT_KEYS, up_b)).backward()
    for t, f, r in zip(leaves, first, ref):
        assert torch.allclose(t.grad, f + r.grad, rtol=1e-10, atol=1e-12)


def test_clipping_planes_and_the_opacity_cut():
    """Centres beyond ``far`` (or before ``near``) and splats with opacity below 1/255 are culled
    (radius 0, nothing rendered); ``near >= far`` is refused."""
    one = [torch.tensor([[0.0, 0.0, 3.0]], dtype=F64), torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=F64),
           torch.tensor([[0.3, 0.3]], dtype=F64), torch.tensor([0.9], dtype=F64),
           torch.tensor([[0.8, 0.2, 0.1]], dtype=F64)]
    eye = np.eye(4)
    seen = rasterize_2dgs(*one, eye, CAM)
    assert int(seen.radii[0]) > 0 and float(seen.alpha.max()) > 0.5
    for kw in ({"far": 2.5}, {"near": 3.5, "far": 10.0}):
        out = rasterize_2dgs(*one, eye, CAM, **kw)
        assert int(out.radii[0]) == 0 and float(out.alpha.max()) == 0.0, kw
    faint = list(one)
    faint[3] = torch.tensor([1.0 / 300.0], dtype=F64)
    out = rasterize_2dgs(*faint, eye, CAM)
    assert int(out.radii[0]) == 0 and float(out.alpha.max()) == 0.0
    faint[3] = torch.tensor([1.0 / 200.0], dtype=F64)       # above the cut: rendered
    assert float(rasterize_2dgs(*faint, eye, CAM).alpha.max()) > 0
    for near, far in ((1.0, 1.0), (2.0, 1.0)):
        with pytest.raises(InputError, match="near"):
            rasterize_2dgs(*one, eye, CAM, near=near, far=far)


def test_bad_arguments_are_input_errors_naming_them():
    g = _scene(20)
    for kw, match in (({"sample_ratio": "x"}, "sample_ratio must be a number"),
                      ({"near": "a"}, "near must be a number"),
                      ({"far": None}, "far must be a number")):
        with pytest.raises(InputError, match=match):
            _fast(g, **kw)
    op = g[3].clone()
    op[4] = 5.0                                  # a logit, not an activated opacity
    with pytest.raises(InputError, match=r"opacities must be activated, in \[0, 1\]; got 5 \(Gaussian 4\)"):
        _fast([*g[:3], op, g[4]])
    with pytest.raises(InputError, match="quats are on meta"):
        _fast([g[0], g[1].to("meta"), *g[2:]])
    with pytest.raises(InputError, match="larger than 16384 px"):
        rasterize_2dgs(*g, T_CW, CameraModel(70000, 70000, 5e4, 5e4, 35000.0, 35000.0))
    with pytest.raises(InputError, match="means must have shape"):
        render_reference(g[0][:, :2], *g[1:], torch.tensor(T_CW), CAM)
    with pytest.raises(InputError, match="loss_map .* is required"):
        gaussian_scores(*g, T_CW, CAM, None)
    with pytest.raises(InputError, match="ratio must be a number"):
        select_sample_pixels(torch.rand(16, 16), "a")
