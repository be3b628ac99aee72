"""Unit tests of vings_core.mapping (fast: tiny images, few iterations)."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from vings_core.config import load_section
from vings_core.errors import ConfigError, InputError
from vings_core.geometry import np_pose, np_rotmat_to_quat, np_se3_exp, quat_to_rotmat, rotation_angle_deg
from vings_core.mapping import GaussianMap, Mapper, MapperConfig, read_ply
from vings_core.mapping import scores as S
from vings_core.mapping.init import (depth_normals, empty_mask, fill_depth, frame_from_normals,
                                     gaussians_from_pixels, num_to_add, sample_pixels, usable_depth_mask)
from vings_core.mapping.losses import (accumulation_loss, depth_loss, normals_from_depth, sep_blur, ssim_map,
                                       ssim_map_fast, ssim_reference, ssim_target_stats)
from vings_core.mapping.optim import reference_adam_rows, sparse_adam_step, sparse_adam_step_fast
from vings_core.mapping.ply import ply_property_names
from vings_core.mapping.storage import PassiveStore, active_split, owner_distances
from vings_core.types import CameraModel, Keyframe


def _cam(w=64, h=40, f=50.0):
    return CameraModel(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2)


def _kf(stamp, T_wc, depth, cam, image=None, var=None):
    d = torch.as_tensor(depth, dtype=torch.float32)
    img = torch.full((cam.height, cam.width, 3), 0.5) if image is None else torch.as_tensor(image, dtype=torch.float32)
    return Keyframe(stamp_ns=stamp, image=img, T_wc=torch.as_tensor(T_wc), depth=d,
                    inv_depth_var=torch.zeros_like(d) if var is None else torch.as_tensor(var, dtype=torch.float32),
                    valid=d > 0, camera=cam)


def _random_map(n, sh_degree=0, seed=0, owners=(1, 2, 3)):
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    gm = GaussianMap.create(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g),
                            torch.randn(n, 2, generator=g) - 3, torch.randn(n, generator=g),
                            torch.randn(n, k, 3, generator=g),
                            torch.tensor(owners)[torch.randint(len(owners), (n,), generator=g)])
    for name, t in gm.tensors().items():  # non-trivial optimiser / score state too
        if t.dtype == torch.float32 and name not in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            t.copy_(torch.rand(t.shape, generator=g))
    gm.adam_step.copy_(torch.randint(0, 50, (n,), generator=g, dtype=torch.int32))
    gm.stable.copy_(torch.rand(n, generator=g) > 0.5)
    return gm


def _canon(gm: GaussianMap) -> GaussianMap:
    """Rows in a canonical order (lexicographic on the centre, then the opacity)."""
    m = gm.means.numpy()
    order = np.lexsort((gm.opacity_logits.numpy(), m[:, 2], m[:, 1], m[:, 0]))
    return gm.index(torch.from_numpy(order))


def _assert_maps_equal(a: GaussianMap, b: GaussianMap):
    ta, tb = a.tensors(), b.tensors()
    assert ta.keys() == tb.keys()
    for k in ta:
        assert ta[k].dtype == tb[k].dtype, k
        assert torch.equal(ta[k], tb[k]), k


# ----------------------------------------------------------------------------- score manager


def test_window_slots_give_sum_max_and_argmax_id():
    n, K = 4, 3
    wc, we, idscore = torch.zeros(n, K), torch.zeros(n, K), torch.zeros(n)
    kid = torch.full((n,), 7, dtype=torch.int64)
    S.record_render(wc, we, kid, idscore, 0, torch.tensor([1.0, 0.0, 5.0, 2.0]), torch.tensor([0.1, 0.0, 0.9, 0.3]), 100)
    S.record_render(wc, we, kid, idscore, 1, torch.tensor([3.0, 0.0, 1.0, 2.0]), torch.tensor([0.5, 0.0, 0.2, 0.1]), 200)
    # a second render of keyframe 200 replaces (not adds to) its slot
    S.record_render(wc, we, kid, idscore, 1, torch.tensor([3.0, 0.0, 1.0, 2.0]), torch.tensor([0.5, 0.0, 0.2, 0.1]), 200)
    s_c, s_e = S.window_scores(wc, we)
    assert torch.allclose(s_c, torch.tensor([4.0, 0.0, 6.0, 4.0]))
    assert torch.allclose(s_e, torch.tensor([0.5, 0.0, 0.9, 0.3]))
    # ID(g): keyframe with the highest single-render contribution; untouched -> unchanged; ties keep the first
    assert kid.tolist() == [200, 7, 100, 100]
    # per view: the window sum over the slots that see the Gaussian (a Gaussian seen once with 5 px
    # outranks one seen twice with 2 px each, unlike the sum)
    assert torch.allclose(S.per_view_contribution(wc), torch.tensor([2.0, 0.0, 3.0, 2.0]))
    assert torch.allclose(S.per_view_contribution(torch.tensor([[5.0, 0.0], [2.0, 2.0]])), torch.tensor([5.0, 2.0]))
    # a faint touch by other keyframes (below 0.1 x the best view) is not a view: it must not turn
    # a Gaussian one keyframe sees well (3.0, kept at 1.6) into a prunable one (0.76 if counted)
    faint = torch.tensor([[3.0, 0.01, 0.01, 0.01]])
    assert torch.allclose(S.per_view_contribution(faint), torch.tensor([3.0]))
    assert torch.allclose(S.per_view_contribution(faint, view_floor=0.0), torch.tensor([3.03 / 4]))
    # keyframe 100 leaves the window: its scores go
    S.clear_slot(wc, we, 0)
    s_c, s_e = S.window_scores(wc, we)
    assert torch.allclose(s_c, torch.tensor([3.0, 0.0, 1.0, 2.0]))
    assert torch.allclose(s_e, torch.tensor([0.5, 0.0, 0.2, 0.1]))


def test_error_density_is_the_mean_error_under_a_gaussian():
    # window contributions c_t and errors e_t = sum L(u) alpha T of 3 Gaussians over 2 slots
    wc = torch.tensor([[2.0, 2.0], [1.0, 0.0], [0.0, 0.0]])
    we = torch.tensor([[0.2, 0.6], [0.5, 0.0], [0.0, 0.0]])
    assert torch.allclose(S.error_density(wc, we), torch.tensor([0.2, 0.5, 0.0]))
    assert S.error_density(torch.zeros(2, 0), torch.zeros(2, 0)).tolist() == [0.0, 0.0]


def test_status_and_storage_transitions():
    stable = torch.tensor([False, False, True, True, False, False])
    s_c = torch.tensor([0.0, 5.0, 0.0, 3.0, 0.2, 0.0])
    s_e = torch.tensor([0.0, 0.1, 0.9, 0.1, 0.0, 0.0])
    judged = torch.tensor([True, True, True, True, True, False])
    to_stable, to_unstable = S.status_control(stable, s_c, s_e, judged, sc_status=1e-4, se_status=0.5)
    assert to_stable.tolist() == [True, False, False, False, False, False]   # unseen -> frozen
    assert to_unstable.tolist() == [False, False, True, False, False, False]  # stable and wrong -> retrain
    prune = S.storage_control(stable, s_c, judged, sc_storage=0.5, sc_status=1e-4)
    # unstable, judged, seen but contributing little (#4); unseen #0 is frozen instead, the newborn #5
    # and stable ones are kept
    assert prune.tolist() == [False, False, False, False, True, False]
    # a Gaussian whose best view (ID(g)) has left the window is not judged by the window's sum
    owned = torch.tensor([True, True, True, True, False, True])
    assert not S.storage_control(stable, s_c, judged, 0.5, 1e-4, owned).any()
    # a Gaussian where the render is still wrong is spared (the detail being fitted)
    assert not S.storage_control(stable, s_c, judged, 0.5, 1e-4, spared=torch.tensor([False] * 4 + [True, False])).any()
    wc, we, since = s_c[:, None].repeat(1, 2), s_e[:, None].repeat(1, 2), torch.zeros(6, dtype=torch.int64)
    S.reset_scores(wc, we, since, to_unstable, 123)
    assert (wc[2] == 0).all() and (we[2] == 0).all() and since[2] == 123 and since[0] == 0 and wc[1, 0] == 5.0
    assert S.scored_long_enough(since, 125, 5).tolist() == [True, True, False, True, True, True]


def test_score_manager_in_mapper_freezes_and_prunes(room_small):
    cam, frames = room_small
    cfg = MapperConfig(points_per_keyframe=1500, delta_status=20, delta_storage=10, min_score_age=5,
                       sc_storage=5.0, window_size=2, iters_per_keyframe=10, sample_ratio=1.0)
    m = Mapper(cfg)
    for i in (0, 1, 6, 7):
        m.add_keyframe(frames[i])
        m.train()
    c = m.counters
    assert c["pruned"] > 0
    assert c["to_stable"] > 0                     # Gaussians no longer seen by the window froze
    # frozen Gaussians keep their ID(g) among the added keyframes
    assert set(torch.unique(m.gm.kf_id).tolist()) <= {frames[i].stamp_ns for i in (0, 1, 6, 7)}
    assert m.gm.stable.any()


def test_storage_control_spares_gaussians_where_the_render_is_wrong(room_small, monkeypatch):
    # prune_spare_high_error: the mapper passes storage control the Gaussians whose window error per
    # contribution exceeds the window keyframes' mean L1, and none of them is pruned
    cam, frames = room_small
    seen = []
    orig = S.storage_control

    def spy(*args, **kw):
        out = orig(*args, **kw)
        spared = args[6] if len(args) > 6 else kw.get("spared")
        seen.append((spared, orig(*args[:6]), out))
        return out
    monkeypatch.setattr(S, "storage_control", spy)
    pruned = {}
    for spare in (False, True):
        seen.clear()
        cfg = MapperConfig(points_per_keyframe=1500, delta_status=20, delta_storage=10, min_score_age=5,
                           sc_storage=5.0, window_size=2, iters_per_keyframe=10, sample_ratio=1.0,
                           prune_spare_high_error=spare)
        m = Mapper(cfg)
        for i in (0, 1, 2):
            m.add_keyframe(frames[i])
            m.train()
        pruned[spare] = m.counters["pruned"]
        if spare:
            assert seen and all(sp is not None for sp, _, _ in seen)
            assert any(bool((sp & base).any()) for sp, base, _ in seen)   # some would have been pruned
            assert all(not bool((sp & out).any()) for sp, _, out in seen)  # none of them is
        else:
            assert all(sp is None for sp, _, _ in seen)
    assert 0 < pruned[True] < pruned[False]


# ----------------------------------------------------------------------------- sparse Adam


def test_sparse_adam_matches_torch_adam_and_leaves_other_rows():
    g = torch.Generator().manual_seed(1)
    n = 50
    p0 = torch.randn(n, 3, generator=g)
    rows = torch.tensor([1, 4, 9, 30])
    grads = [torch.randn(n, 3, generator=g) for _ in range(5)]
    for fast in (False, True):
        p, m, v = p0.clone(), torch.zeros(n, 3), torch.zeros(n, 3)
        step = torch.zeros(n, dtype=torch.int32)
        for gr in grads:
            step[rows] += 1
            if fast:
                sparse_adam_step_fast(p, gr, m, v, step, rows, np.full(3, 0.01))
            else:
                sparse_adam_step(p, gr, m, v, step, rows, 0.01)
        ref = reference_adam_rows(p0[rows], [gr[rows] for gr in grads], lr=0.01, eps=1e-15)
        assert torch.allclose(p[rows], ref, atol=1e-6), fast
        others = torch.ones(n, dtype=torch.bool)
        others[rows] = False
        assert torch.equal(p[others], p0[others])            # bit-identical
        assert torch.equal(m[others], torch.zeros_like(m[others]))
        assert int(step[others].sum()) == 0


def test_mapper_training_never_touches_stable_rows(room_small):
    cam, frames = room_small
    m = Mapper(MapperConfig(points_per_keyframe=1500, score_manager=False, sample_ratio=1.0))
    m.add_keyframe(frames[0])
    m.train(2)
    m.gm.stable[::2] = True
    before = m.gm.clone()
    m.train(3)
    st = before.stable
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh", "m_means", "v_sh", "adam_step"):
        assert torch.equal(getattr(m.gm, name)[st], getattr(before, name)[st]), name
    assert not torch.equal(m.gm.means[~st], before.means[~st])


# ----------------------------------------------------------------------------- initialisation


def test_backprojection_of_a_slanted_plane():
    cam = _cam(80, 60, 60.0)
    # plane through (0, 0, 2) with normal n (camera frame): n . p = n . p0
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    p0 = np.array([0.0, 0.0, 2.0])
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
    depth = (n @ p0) / (rays @ n)
    T_wc = np_pose(np_se3_exp(np.array([0.0, 0.0, 0.0, 0.1, 0.2, -0.3]))[:3, :3], [1.0, 2.0, 3.0])
    kf = _kf(5, T_wc, depth, cam)
    nc = depth_normals(kf.depth, cam)
    inner = nc[2:-2, 2:-2].reshape(-1, 3).double()
    assert torch.allclose(inner, torch.as_tensor(n).expand_as(inner), atol=1e-4)   # faces the camera
    rc = sample_pixels(torch.ones(cam.height, cam.width, dtype=torch.bool)[2:-2, 2:-2].clone(), 200,
                       torch.Generator().manual_seed(0)) + 2
    gm = gaussians_from_pixels(kf, rc, 0, 0.7, 1.0, 0.3, 6.0, normals_cam=nc)
    # centres lie on the plane (in the camera frame) and reproject to their pixels
    pc = (gm.means.double() - torch.tensor(T_wc[:3, 3])) @ torch.tensor(T_wc[:3, :3])
    assert torch.allclose(pc @ torch.tensor(n), torch.full((len(pc),), float(n @ p0), dtype=torch.float64), atol=1e-5)
    uv = pc[:, :2] / pc[:, 2:] * cam.fx + torch.tensor([cam.cx, cam.cy])
    assert torch.allclose(uv, rc[:, [1, 0]].double(), atol=1e-3)
    # surfel normal (third rotation column) = plane normal in the world
    nw = quat_to_rotmat(gm.quats.double())[:, :, 2]
    assert torch.allclose(nw, torch.tensor(T_wc[:3, :3] @ n).expand_as(nw), atol=1e-4)
    # scale ~ nearest-neighbour spacing, inside the pixel-footprint clamp; ID(g) = stamp
    s = gm.scales()
    assert (s[:, 0] == s[:, 1]).all()
    foot = pc[:, 2] / cam.fx
    assert (s[:, 0].double() >= 0.3 * foot - 1e-6).all() and (s[:, 0].double() <= 6.0 * foot + 1e-6).all()
    assert (gm.kf_id == 5).all()
    assert torch.allclose(gm.opacities(), torch.full((len(gm),), 0.7))
    assert torch.allclose(gm.rgb(), torch.full((len(gm), 3), 0.5), atol=1e-6)


def test_frame_from_normals_right_handed():
    n = torch.nn.functional.normalize(torch.randn(100, 3, dtype=torch.float64), dim=-1)
    R = frame_from_normals(n)
    assert torch.allclose(R.transpose(1, 2) @ R, torch.eye(3, dtype=torch.float64).expand(100, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(100, dtype=torch.float64))
    assert torch.allclose(R[:, :, 2], n)


def test_usable_mask_and_number_to_add():
    cam = _cam(8, 4)
    d = torch.full((4, 8), 2.0)
    d[0, 0] = 0
    d[0, 1] = 100.0
    var = torch.zeros_like(d)
    var[1, 1] = (0.2 / 2.0) ** 2            # sigma_d / d = sqrt(var) * d = 0.2
    kf = _kf(1, np.eye(4), d, cam, var=var)
    mk = usable_depth_mask(kf, max_depth=40.0, max_rel_std=0.05)
    assert mk.sum() == 29 and not mk[0, 0] and not mk[0, 1] and not mk[1, 1]
    low = torch.zeros(4, 8, dtype=torch.bool)
    low[:2] = True
    assert num_to_add(low, 1000) == 500


def test_empty_mask_separates_sky_from_uncertain_depth():
    """Only pixels known to be empty get the accumulation loss: no surface with a certain inverse
    depth (ground-truth sky) or depth beyond max_depth; front-end pixels dropped for uncertainty are
    unknown (their surface may be mapped from other keyframes)."""
    cam = _cam(8, 4)
    d = torch.full((4, 8), 2.0)
    var = torch.zeros_like(d)
    d[0, 0] = 0                      # ground-truth sky: no surface, variance 0
    d[0, 1] = 0                      # front end: no depth, large inverse-depth variance (std 0.3 1/m)
    var[0, 1] = 0.09
    d[0, 2] = 0                      # no surface, inverse depth 0 +- 0.01 1/m: beyond 40 m at 1 sigma
    var[0, 2] = 1e-4
    kf = _kf(1, np.eye(4), d, cam, var=var)
    kf.valid[0, 3] = False           # depth given but marked invalid, within range: unknown
    d2 = d.clone()
    d2[1, 0] = 100.0                 # excessive depth
    kf2 = _kf(2, np.eye(4), d2, cam, var=var)
    kf2.valid[1, 0] = False
    e = empty_mask(kf, max_depth=40.0)
    assert e[0, 0] and not e[0, 1] and e[0, 2] and not e[0, 3] and int(e.sum()) == 2
    e2 = empty_mask(kf2, max_depth=40.0)
    assert e2[1, 0] and int(e2.sum()) == 3
    kf2.valid[1, 0] = True           # excessive depth marked valid (ground truth): still empty
    assert bool(empty_mask(kf2, max_depth=40.0)[1, 0])


def test_far_valid_pixels_are_not_seeded_at_a_nearer_depth():
    """A keyframe whose right half is a valid surface at 60 m (beyond max_depth 40 m): no Gaussian
    may be put there at a depth interpolated from the near half."""
    cam = _cam(64, 40)
    d = torch.full((40, 64), 5.0)
    d[:, 32:] = 60.0
    img = torch.rand(40, 64, 3, generator=torch.Generator().manual_seed(0))
    m = Mapper(MapperConfig(points_per_keyframe=2000, iters_per_keyframe=1, max_depth=40.0))
    m.add_keyframe(_kf(1, np.eye(4), d, cam, image=img))
    x = m.gm.means[:, 0] / m.gm.means[:, 2] * cam.fx + cam.cx     # column of each centre
    assert len(m.gm) > 0 and int((x > 33).sum()) == 0


def test_mapper_refuses_a_device_it_cannot_score_on():
    with pytest.raises(ConfigError, match="CPU"):
        Mapper(MapperConfig(), device="meta")


def test_fill_depth_keeps_known_pixels_and_interpolates_holes():
    H, W = 40, 64
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    plane = 2.0 + 0.01 * u + 0.02 * v                    # a smooth slanted surface
    known = torch.ones(H, W, dtype=torch.bool)
    known[10:30, 20:44] = False                          # a textureless patch the front end dropped
    known[0:3, 0:3] = False
    d = torch.where(known, plane, torch.zeros(()))
    f = fill_depth(d, known)
    assert torch.equal(f[known], plane[known])
    assert float((f[~known] - plane[~known]).abs().max()) < 0.15      # within 5 % of ~3 m
    assert float(f[~known].min()) >= float(plane[known].min()) and float(f[~known].max()) <= float(plane.max())
    c = fill_depth(torch.where(known, torch.full((H, W), 3.0), torch.zeros(())), known)
    assert torch.allclose(c, torch.full((H, W), 3.0))
    assert torch.equal(fill_depth(d, torch.zeros_like(known)), torch.zeros(H, W))


# ----------------------------------------------------------------------------- losses


def test_ssim_separable_matches_reference_and_is_one_for_equal_images():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(30, 40, 3, generator=g)
    b = (a + 0.1 * torch.rand(30, 40, 3, generator=g)).clamp(0, 1)
    assert torch.allclose(ssim_map(a, b), ssim_reference(a, b), atol=1e-5)
    assert torch.allclose(ssim_map(a, a), torch.ones(30, 40), atol=1e-5)


def test_fast_ssim_and_blur_match_the_convolution_version_with_gradients():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(37, 53, 3, generator=g)
    b = (a + 0.2 * torch.rand(37, 53, 3, generator=g)).clamp(0, 1)
    w = torch.rand(37, 53, generator=g)
    a1 = a.clone().requires_grad_(True)
    a2 = a.clone().requires_grad_(True)
    s1 = ssim_reference(a1, b)
    s2 = ssim_map_fast(a2, b, ssim_target_stats(b))
    assert torch.allclose(s1, s2, atol=1e-5)
    (s1 * w).sum().backward()
    (s2 * w).sum().backward()
    assert torch.allclose(a1.grad, a2.grad, atol=1e-5)
    # the blur is self-adjoint: <blur(x), y> = <x, blur(y)>, and its gradient is the blur
    win = torch.tensor([0.1, 0.2, 0.4, 0.2, 0.1])
    x = torch.rand(2, 9, 13, generator=g, dtype=torch.float32).requires_grad_(True)
    y = torch.rand(2, 9, 13, generator=g)
    fx = sep_blur(x, win)
    ref = torch.nn.functional.conv2d(torch.nn.functional.conv2d(
        x.detach()[:, None], win.reshape(1, 1, 1, 5), padding=(0, 2)), win.reshape(1, 1, 5, 1), padding=(2, 0))[:, 0]
    assert torch.allclose(fx, ref, atol=1e-6)
    assert float((fx.detach() * y).sum()) == pytest.approx(float((x.detach() * sep_blur(y, win)).sum()), rel=1e-5)
    (fx * y).sum().backward()
    assert torch.allclose(x.grad, sep_blur(y, win), atol=1e-6)


def test_depth_normal_and_accumulation_losses():
    cam = _cam(32, 24, 30.0)
    d = torch.full((24, 32), 2.0)
    n, ok = normals_from_depth(d, cam)
    assert torch.allclose(n[ok], torch.tensor([0.0, 0.0, -1.0]).expand(int(ok.sum()), 3), atol=1e-6)
    assert not ok[0].any() and not ok[:, -1].any()
    valid = torch.ones_like(d, dtype=torch.bool)
    assert float(depth_loss(d * 1.1, d, torch.ones_like(d), valid)) == pytest.approx(0.1, rel=1e-5)
    w = torch.full_like(d, 0.5)
    assert float(depth_loss(d * 1.1, d, w, valid)) == pytest.approx(0.05, rel=1e-5)
    # a masked pixel with infinite (or NaN) ground truth does not make the loss NaN
    g2 = d.clone()
    g2[0, 0], g2[0, 1] = float("inf"), float("nan")
    v2 = valid.clone()
    v2[0, :2] = False
    assert float(depth_loss(d * 1.1, g2, torch.ones_like(d), v2)) == pytest.approx(0.1, rel=1e-5)
    # infinite inverse-depth variance (no depth, depth 0) gives weight 0, never NaN
    from vings_core.mapping.losses import depth_weight
    wd = depth_weight(torch.tensor([0.0, 2.0, 2.0]), torch.tensor([float("inf"), float("inf"), 0.0]), 0.02)
    assert torch.equal(wd, torch.tensor([0.0, 0.0, 1.0]))
    a = torch.full_like(d, 0.3)
    m = torch.zeros_like(valid)
    assert float(accumulation_loss(a, m)) == 0.0
    m[:5] = True
    assert float(accumulation_loss(a, m)) == pytest.approx(0.3)


# ----------------------------------------------------------------------------- storage tiers


def test_active_split_tau_and_cap():
    dist = torch.tensor([0.5, 10.0, 1.0, 3.0, 0.5, 2.0])
    keep = active_split(dist, tau=5.0, max_active=10)
    assert keep.tolist() == [True, False, True, True, True, True]
    keep = active_split(dist, tau=5.0, max_active=3)
    assert keep.tolist() == [True, False, True, False, True, False]


def test_owner_distances_lookup():
    stamps = np.array([10, 20, 30])
    pos = np.array([[0, 0, 0], [3, 4, 0], [10, 0, 0]], float)
    d = owner_distances(torch.tensor([20, 10, 30, 99]), stamps, pos, np.zeros(3))
    assert d.tolist() == [5.0, 0.0, 10.0, 0.0]   # unknown owners stay (distance 0)


def test_passive_store_round_trip_is_bit_exact_through_disk(tmp_path):
    gm = _random_map(300, sh_degree=1)
    store = PassiveStore(memory_budget_bytes=1000, spill_dir=str(tmp_path / "spill"))
    poses = {1: np.eye(4), 2: np.eye(4), 3: np.eye(4)}
    store.put(gm.index(torch.arange(0, 150)), poses)
    store.put(gm.index(torch.arange(150, 300)), poses)
    assert store.num_spilled_chunks == 2 and store.memory_bytes == 0
    assert len(list((tmp_path / "spill").rglob("*.npz"))) == 2
    assert store.num_gaussians == 300
    # take owner 2 only: the rest stays
    got2 = store.take(lambda o: o == 2, poses)
    assert (got2.kf_id == 2).all() and len(got2) == int((gm.kf_id == 2).sum())
    rest = store.take(lambda o: np.ones(len(o), bool), poses)
    assert store.num_gaussians == 0
    back = GaussianMap.concat([got2, rest])
    _assert_maps_equal(_canon(back), _canon(gm))
    store.close()
    assert not list((tmp_path / "spill").rglob("*.npz"))


def test_stores_sharing_a_spill_dir_and_a_lost_chunk_file(tmp_path):
    from vings_core.errors import ConfigError
    gm = _random_map(300, sh_degree=1)
    poses = {1: np.eye(4), 2: np.eye(4), 3: np.eye(4)}
    a = PassiveStore(memory_budget_bytes=0, spill_dir=str(tmp_path / "spill"))
    b = PassiveStore(memory_budget_bytes=0, spill_dir=str(tmp_path / "spill"))
    a.put(gm.index(torch.arange(0, 100)), poses)
    b.put(gm.index(torch.arange(100, 200)), poses)
    a.put(gm.index(torch.arange(200, 300)), poses)
    assert len(a.all(poses)) == 200 and len(b.all(poses)) == 100   # no file shared
    b.close()                                   # removes b's files only
    assert len(a.all(poses)) == 200
    # one of a's chunk files disappears: reported, those Gaussians dropped, the rest still loads
    a.chunks[0].path.unlink()
    rest = a.take(lambda o: np.ones(len(o), bool), poses)
    assert len(rest) == 100 and a.lost_total == 100 and a.num_gaussians == 0
    a.close()
    f = tmp_path / "afile"
    f.write_text("x")
    with pytest.raises(ConfigError, match="mapping.spill_dir"):
        PassiveStore(memory_budget_bytes=0, spill_dir=str(f))


def _break_spill_folder(folder) -> Path:
    """Make every later write into a SpillFolder fail for real (its folder replaced by a file);
    returns the folder path, to restore it with :func:`_mend_spill_folder`."""
    d = folder.path("x").parent
    shutil.rmtree(d)
    d.write_text("not a folder")
    return d


def _mend_spill_folder(d: Path) -> None:
    d.unlink()
    d.mkdir()


def test_passive_store_failed_spill_keeps_the_chunk_in_memory(tmp_path, caplog):
    """A spill that cannot be written (disk full, folder removed) keeps the chunk in memory, warned;
    ``put`` does not raise, so the caller's move of those Gaussians out of the active set completes
    (raising there left them both active and passive: duplicated)."""
    gm = _random_map(200)
    poses = {1: np.eye(4), 2: np.eye(4), 3: np.eye(4)}
    store = PassiveStore(memory_budget_bytes=0, spill_dir=str(tmp_path / "spill"))
    d = _break_spill_folder(store._folder)
    with caplog.at_level("WARNING"):
        store.put(gm.index(torch.arange(0, 100)), poses)
    assert "cannot spill" in caplog.text
    assert store.num_gaussians == 100 and store.num_spilled_chunks == 0 and store.memory_bytes > 0
    _mend_spill_folder(d)
    store.put(gm.index(torch.arange(100, 200)), poses)       # the disk is back: both spill
    assert store.num_spilled_chunks == 2 and store.memory_bytes == 0
    _assert_maps_equal(_canon(store.all(poses)), _canon(gm))
    store.close()


def test_a_spill_folder_that_cannot_be_made_keeps_records_in_memory(tmp_path, monkeypatch, caplog):
    """The private temporary folder is made on the first spill: a temp dir that is gone or full
    keeps the chunk / record in memory (warned), as a failed write does."""
    import tempfile
    from vings_core.mapping.history import HistoryStore, compact_keyframe
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "gone"))
    store = PassiveStore(memory_budget_bytes=0)
    hist = HistoryStore(0)
    with caplog.at_level("WARNING"):
        store.put(_random_map(50), {1: np.eye(4), 2: np.eye(4), 3: np.eye(4)})
        hist.put(7, compact_keyframe(_kf(7, np.eye(4), torch.full((24, 32), 2.0), _cam(32, 24))))
    assert caplog.text.count("cannot create a spill folder") == 2
    assert store.num_gaussians == 50 and store.memory_bytes > 0 and hist.get(7) is not None


def test_damaged_checkpoint_is_an_input_error(tmp_path):
    from vings_core.errors import InputError
    for name, data in (("empty.ckpt", b""), ("trunc.ckpt", b"PK\x03\x04garbage")):
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(InputError, match="not a VINGS map checkpoint"):
            Mapper.load_checkpoint(p)


def test_passive_gaussians_follow_pose_changes_of_their_keyframe():
    gm = _random_map(50, owners=(1, 2))
    store = PassiveStore(memory_budget_bytes=10**9)
    poses = {1: np.eye(4), 2: np.eye(4)}
    store.put(gm, poses)
    D = np_se3_exp(np.array([0.5, -0.2, 0.1, 0.05, 0.02, -0.1]))
    new_poses = {1: np.eye(4), 2: D}
    back = store.take(lambda o: np.ones(len(o), bool), new_poses)
    m2 = gm.kf_id == 2
    b2 = back.kf_id == 2
    exp = gm.means[m2].double() @ torch.tensor(D[:3, :3]).T + torch.tensor(D[:3, 3])
    assert torch.allclose(back.means[b2].double(), exp, atol=1e-5)
    assert torch.equal(back.means[~b2], gm.means[~m2])      # owner 1 unchanged: bit-exact
    R_old = quat_to_rotmat(gm.quats[m2].double())
    R_new = quat_to_rotmat(back.quats[b2].double())
    assert torch.allclose(R_new, torch.tensor(D[:3, :3]) @ R_old, atol=1e-5)


def test_mapper_tiers_keep_active_under_cap_and_bring_gaussians_back(room_small, tmp_path):
    cam, frames = room_small
    cfg = MapperConfig(points_per_keyframe=800, delta_k=1, tau=0.05, max_active=1500, passive_memory_mb=0.01,
                       spill_dir=str(tmp_path / "sp"), score_manager=False, iters_per_keyframe=1, sample_ratio=1.0)
    m = Mapper(cfg)
    for i in (0, 2, 4):
        m.add_keyframe(frames[i])
        m.train()
        assert m.num_active <= cfg.max_active
    assert m.num_passive > 0 and m.passive.spilled_total > 0
    total = m.num_gaussians
    before = m.all_gaussians()
    # coming back to the first keyframe brings its Gaussians back (nothing lost)
    m.update_tiers(frames[0].T_wc.numpy())
    assert m.num_gaussians == total
    assert (m.gm.kf_id == frames[0].stamp_ns).any()
    after = m.all_gaussians()
    ta, tb = _canon(before).tensors(), _canon(after).tensors()
    for k in ta:   # window scores of returning Gaussians restart by design; everything else is bit-exact
        if k not in ("win_c", "win_e", "score_since"):
            assert torch.equal(ta[k], tb[k]), k
    m.close()


# ----------------------------------------------------------------------------- map files


def test_ply_header_and_fields_read_back(tmp_path):
    gm = _random_map(20, sh_degree=1)
    from vings_core.mapping import write_ply
    p = tmp_path / "map.ply"
    write_ply(p, gm)
    head = p.read_bytes()[:2000].split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in head and "element vertex 20" in head
    d = read_ply(p)
    assert list(d) == ply_property_names(1)
    assert len([k for k in d if k.startswith("f_rest_")]) == 9
    assert np.array_equal(d["x"], gm.means[:, 0].numpy())
    assert np.array_equal(d["opacity"], gm.opacity_logits.numpy())
    assert np.array_equal(d["scale_0"], gm.log_scales[:, 0].numpy())
    assert (d["scale_2"] < np.minimum(d["scale_0"], d["scale_1"]) - 6).all()   # flat third axis
    q = gm.quats / gm.quats.norm(dim=-1, keepdim=True)
    assert np.allclose(np.stack([d["rot_0"], d["rot_1"], d["rot_2"], d["rot_3"]], 1), q[:, [3, 0, 1, 2]].numpy(),
                       atol=1e-6)
    # f_rest channel-major: f_rest_0..2 = band 1..3 of R
    assert np.array_equal(d["f_rest_0"], gm.sh[:, 1, 0].numpy()) and np.array_equal(d["f_rest_3"], gm.sh[:, 1, 1].numpy())
    assert np.allclose(np.stack([d["nx"], d["ny"], d["nz"]], 1), gm.normals().numpy(), atol=1e-6)


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_empty_map_writes_a_valid_ply(tmp_path, sh_degree):
    # a run whose front end never initialised ends with no Gaussians: still a loadable file
    from vings_core.mapping import write_ply
    gm = _random_map(5, sh_degree=sh_degree)
    empty = gm.index(torch.zeros(0, dtype=torch.long))
    assert len(empty) == 0
    p = tmp_path / "map.ply"
    write_ply(p, empty)
    assert b"element vertex 0" in p.read_bytes()
    d = read_ply(p)
    assert list(d) == ply_property_names(sh_degree) and all(len(v) == 0 for v in d.values())


def test_checkpoint_round_trip_is_bit_exact(room_small, tmp_path):
    cam, frames = room_small
    cfg = MapperConfig(points_per_keyframe=800, delta_k=2, tau=0.05, max_active=100000, iters_per_keyframe=3,
                       sample_ratio=1.0, delta_storage=4, delta_status=8, min_score_age=2, refine_gn_decay=True)
    m = Mapper(cfg)
    for i in (0, 2, 4):
        m.add_keyframe(frames[i])
        m.train()
    m.refine_poses(2)
    assert m.num_passive > 0
    p1, p2 = tmp_path / "a.npz", tmp_path / "b.npz"
    m.save_checkpoint(p1)
    m2 = Mapper.load_checkpoint(p1)
    _assert_maps_equal(m.gm, m2.gm)
    _assert_maps_equal(m.all_gaussians(), m2.all_gaussians())
    assert m2.keyframe_poses().keys() == m.keyframe_poses().keys()
    for s, T in m.keyframe_poses().items():
        assert np.array_equal(T, m2.keyframe_poses()[s])
    assert [k.stamp_ns for k in m2.window] == [k.stamp_ns for k in m.window]
    assert m2.render_count == m.render_count and m2.cfg == m.cfg
    assert m.refiner.gn_steps and m2.refiner.gn_steps == m.refiner.gn_steps      # refinement's step counts
    m2.save_checkpoint(p2)
    a, b = np.load(p1), np.load(p2)
    assert sorted(a.files) == sorted(b.files)
    for k in a.files:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k
    # identical renders, and resumed training follows the same path
    r1 = m.render(frames[2].T_wc.numpy(), cam)
    r2 = m2.render(frames[2].T_wc.numpy(), cam)
    assert np.array_equal(r1["color"], r2["color"])
    m.train(2)
    m2.train(2)
    _assert_maps_equal(m.gm, m2.gm)


def _passive_mapper(room_small, **kw):
    """Three keyframes with a small tau, so earlier keyframes' Gaussians go passive."""
    cam, frames = room_small
    cfg = MapperConfig(points_per_keyframe=800, delta_k=1, tau=0.05, iters_per_keyframe=2, sample_ratio=1.0,
                       score_manager=False, history_ratio=0.0, **kw)
    m = Mapper(cfg)
    for i in (0, 2, 4):
        m.add_keyframe(frames[i])
        m.train()
    assert m.num_passive > 0
    return m, frames


def test_checkpoint_resume_is_exact_with_a_pending_passive_pose_change(room_small, tmp_path):
    """A pose change of a keyframe whose Gaussians are passive is applied to them when they
    return; a checkpoint taken in between must resume with exactly the same map afterwards (saving
    them already moved would round the next change differently)."""
    m, frames = _passive_mapper(room_small)
    s0 = frames[0].stamp_ns
    assert s0 in m.passive.owners().tolist()
    T0 = m.keyframe_poses()[s0]
    m.set_keyframe_poses({s0: T0 @ np_se3_exp(np.array([0.01, 0, 0, 0, 0.02, 0]))})   # pending
    m.save_checkpoint(tmp_path / "c.npz")
    m2 = Mapper.load_checkpoint(tmp_path / "c.npz")
    _assert_maps_equal(m.all_gaussians(), m2.all_gaussians())
    T1 = m.keyframe_poses()[s0]
    for mm in (m, m2):
        mm.set_keyframe_poses({s0: T1 @ np_se3_exp(np.array([0.0, 0.01, 0, 0.03, 0, 0]))})
    _assert_maps_equal(m.all_gaussians(), m2.all_gaussians())
    for mm in (m, m2):
        mm.update_tiers(T1)
    _assert_maps_equal(m.gm, m2.gm)


@pytest.mark.parametrize("second", ["set_poses", "single_refine"])
def test_a_pending_passive_move_survives_a_later_change_that_moves_nothing(room_small, second):
    """A keyframe moved with its Gaussians while they are passive (loop closure) owes them that
    move; a later pose change that moves no Gaussians (``move_gaussians=False``, ``single``
    refinement) must keep that debt, not overwrite it (they came back unmoved)."""
    m, frames = _passive_mapper(room_small, refine_mode="single")
    # a keyframe with passive Gaussians that the refinement may move (active ones in view, not the
    # fixed first keyframe)
    window = [kf.stamp_ns for kf in m.window]
    s0 = next(s for s in m.passive.owners().tolist() if s in window and s != m.state.order[0])
    T0 = m.keyframe_poses()[s0]
    m.set_keyframe_poses({s0: T0 @ np_se3_exp(np.array([0.05, -0.02, 0.03, 0.1, -0.2, 0.15]))})
    owed = m.passive.all(m.state.poses)                 # where they belong now
    unmoved = m.passive.all({})
    sel = owed.kf_id == s0
    assert (owed.means[sel] - unmoved.means[sel]).abs().max() > 0.01
    if second == "set_poses":
        T1 = m.keyframe_poses()[s0]
        m.set_keyframe_poses({s0: T1 @ np_se3_exp(np.array([0.0, 0.04, 0.0, 0.2, 0.1, 0.0]))},
                             move_gaussians=False)
    else:
        P = m.keyframe_poses()
        m.refine_poses(20, mode="single")
        assert not np.array_equal(P[s0], m.keyframe_poses()[s0])
    got = m.passive.all(m.state.poses)
    for k in ("means", "quats"):
        assert torch.allclose(got.tensors()[k], owed.tensors()[k], atol=2e-6), k


def test_single_refinement_leaves_passive_gaussians_in_place(room_small):
    """``single`` moves only cameras: Gaussians of a refined keyframe stay put, active or passive
    (its passive ones must not follow the pose change when they come back)."""
    m, frames = _passive_mapper(room_small, refine_mode="single")
    before_a = m.gm.clone()
    before_p = m.passive.all(m.state.poses)
    P0 = m.keyframe_poses()
    m.refine_poses(20, mode="single")
    moved = [s for s, T in m.keyframe_poses().items() if not np.array_equal(T, P0[s])]
    assert set(moved) & set(before_p.kf_id.tolist())       # a refined keyframe owns passive Gaussians
    _assert_maps_equal(before_a, m.gm)
    _assert_maps_equal(before_p, m.passive.all(m.state.poses))


def test_apply_rigid_rotates_the_quaternion_adam_moment():
    """After ``q -> qR q`` the first moment must be the gradient of the same loss with respect to
    the new quaternions (autograd through the inverse map)."""
    from vings_core.mapping.gaussians import quat_multiply
    gm = _random_map(20)
    q = gm.quats.double().clone().requires_grad_(True)
    c = torch.randn(20, 4, generator=torch.Generator().manual_seed(5), dtype=torch.float64)

    def f(qq):
        return (torch.sin(qq) * c).sum()
    f(q).backward()
    gm.m_quats.copy_(q.grad.float())
    T = np_se3_exp(np.array([0.1, -0.2, 0.3, 0.4, -0.2, 0.3]))
    gm.apply_rigid(torch.from_numpy(T))
    from vings_core.geometry import rotmat_to_quat
    qR = rotmat_to_quat(torch.from_numpy(T[:3, :3]))
    qR_inv = qR * torch.tensor([-1.0, -1.0, -1.0, 1.0], dtype=torch.float64)
    q_new = gm.quats.double().clone().requires_grad_(True)
    f(quat_multiply(qR_inv.expand(20, 4), q_new)).backward()
    assert torch.allclose(gm.m_quats.double(), q_new.grad, atol=1e-5)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rigid_motion_carries_view_dependent_colour(degree):
    """Moving the map and the camera by the same rigid motion (loop correction, multi-pose
    refinement, a passive Gaussian returning under a changed owner pose) leaves the image as it was:
    the SH bands >= 1 turn with their Gaussian (exact rotation matrices, orthogonal)."""
    from vings_core.render import rasterize_2dgs
    from vings_core.render.sh import eval_sh, sh_rotation
    g = torch.Generator().manual_seed(0)
    K = (degree + 1) ** 2
    R = quat_to_rotmat(torch.nn.functional.normalize(torch.randn(4, 4, generator=g, dtype=torch.float64), dim=1))
    D = sh_rotation(R, degree)
    assert torch.allclose(D @ D.transpose(1, 2), torch.eye(K - 1, dtype=torch.float64).expand(4, -1, -1), atol=1e-12)
    c = torch.randn(4, K, 3, generator=g, dtype=torch.float64)
    d = torch.randn(4, 3, generator=g, dtype=torch.float64)
    moved = torch.cat([c[:, :1], D @ c[:, 1:]], 1)
    assert torch.allclose(eval_sh(degree, moved, d), eval_sh(degree, c, (R.transpose(1, 2) @ d[:, :, None])[:, :, 0]),
                          atol=1e-12)
    cam = CameraModel(width=48, height=32, fx=40.0, fy=40.0, cx=23.5, cy=15.5)
    n = 300
    means = torch.rand(n, 3, generator=g) * torch.tensor([2.0, 1.4, 0.5]) + torch.tensor([-1.0, -0.7, 2.0])
    q = torch.zeros(n, 4)
    q[:, 3] = 1
    sh = torch.zeros(n, K, 3)
    sh[:, 0] = 0.3 * torch.randn(n, 3, generator=g)
    sh[:, 1:] = 0.8 * torch.randn(n, K - 1, 3, generator=g)
    gm = GaussianMap.create(means, q, torch.full((n, 2), math.log(0.08)), torch.full((n,), 2.0), sh, 1)
    gm.m_sh.copy_(torch.randn(n, K, 3, generator=g))

    def render(m, T_wc):
        T_cw = torch.from_numpy(np.linalg.inv(T_wc)).float()
        return rasterize_2dgs(m.means, m.quats, m.scales(), m.opacities(), m.sh, T_cw, cam, sh_degree=degree).color
    G = np_se3_exp(np.array([0.3, -0.1, 0.2, 0.0, 0.9, 0.2]))
    gm2 = gm.clone()
    gm2.apply_rigid(torch.from_numpy(G))
    assert float((render(gm, np.eye(4)) - render(gm2, G)).abs().max()) < 1e-4
    Dg = sh_rotation(torch.from_numpy(G[:3, :3])[None], degree)[0].float()
    assert torch.allclose(gm2.m_sh[:, 1:], Dg @ gm.m_sh[:, 1:], atol=1e-5)      # Adam moment turns too
    assert torch.equal(gm2.sh[:, 0], gm.sh[:, 0])


def test_ply_leaves_out_non_finite_splats(tmp_path):
    from vings_core.mapping import write_ply
    gm = _random_map(30)
    gm.means[3, 0] = float("nan")
    gm.log_scales[7, 1] = float("inf")
    gm.quats[11] = 0.0
    assert write_ply(tmp_path / "m.ply", gm) == 27
    v = read_ply(tmp_path / "m.ply")
    assert len(v["x"]) == 27 and all(np.isfinite(a).all() for a in v.values())


def test_damaged_or_foreign_checkpoint_entries_are_input_errors_naming_the_file(tmp_path, room_small):
    """Entries of an .npz are read lazily: damage inside one, a meta without a field, a plain
    .npy file, or a config whose SH degree differs from the stored map must all be one InputError
    naming the file (the mapper node's resume reports VingsErrors, not tracebacks)."""
    import json
    import zipfile
    cam, frames = room_small
    m = Mapper(MapperConfig(points_per_keyframe=300, iters_per_keyframe=1, sample_ratio=1.0))
    m.add_keyframe(frames[0])
    m.train()
    good = tmp_path / "good.npz"
    m.save_checkpoint(good)
    raw = good.read_bytes()
    info = zipfile.ZipFile(good).getinfo("active/means.npy")
    off = info.header_offset + 30 + len(info.filename) + len(info.extra) + 200
    flipped = bytearray(raw)
    flipped[off] ^= 0xFF
    (tmp_path / "flip.npz").write_bytes(bytes(flipped))
    with np.load(good) as z:
        entries = {k: z[k] for k in z.files}
    meta = json.loads(bytes(entries["meta"]).decode())
    del meta["config"]
    np.savez(tmp_path / "noconfig.npz", **{**entries, "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)})
    np.save(tmp_path / "plain.npy", np.zeros(3))
    for name in ("flip.npz", "noconfig.npz", "plain.npy"):
        with pytest.raises(InputError, match=f"{name}: not a VINGS map checkpoint"):
            Mapper.load_checkpoint(tmp_path / name)
    with pytest.raises(InputError, match="good.npz: checkpoint holds SH of degree 0, the config 1"):
        Mapper.load_checkpoint(good, MapperConfig(points_per_keyframe=300, sh_degree=1))
    assert len(Mapper.load_checkpoint(good).gm) == len(m.gm)


def test_bad_checkpoint_and_bad_keyframes_give_clear_errors(tmp_path, room_small):
    cam, frames = room_small
    with pytest.raises(InputError, match="not found"):
        Mapper.load_checkpoint(tmp_path / "nope.npz")
    (tmp_path / "bad.npz").write_bytes(b"garbage")
    with pytest.raises(InputError, match="not a VINGS map checkpoint"):
        Mapper.load_checkpoint(tmp_path / "bad.npz")
    m = Mapper(MapperConfig(points_per_keyframe=100))
    m.add_keyframe(frames[0])
    with pytest.raises(InputError, match="already added"):
        m.add_keyframe(frames[0])
    other = _kf(frames[1].stamp_ns, frames[1].T_wc, torch.ones(20, 30), _cam(30, 20))
    with pytest.raises(InputError, match="camera model differs"):
        m.add_keyframe(other)
    bad = _kf(frames[2].stamp_ns, np.full((4, 4), np.nan), frames[2].depth, cam)
    with pytest.raises(InputError, match="non-finite"):
        m.add_keyframe(bad)
    with pytest.raises(InputError, match="unknown keyframe"):
        m.set_keyframe_poses({12345: np.eye(4)})


def test_a_late_keyframe_is_mapped_in_stamp_order(tmp_path, room_small):
    """A keyframe older than the newest one (sent again after a mapper restart) is added to the
    training window; the keyframe list stays in stamp order, also through a checkpoint."""
    cam, frames = room_small
    m = Mapper(MapperConfig(points_per_keyframe=200))
    m.add_keyframe(frames[0])
    m.add_keyframe(frames[2])
    info = m.add_keyframe(frames[1])
    assert info["stamp_ns"] == frames[1].stamp_ns
    assert list(m.keyframe_poses()) == [frames[i].stamp_ns for i in range(3)]
    assert frames[1].stamp_ns in [kf.stamp_ns for kf in m.state.window]
    m.save_checkpoint(tmp_path / "late.npz")
    assert list(Mapper.load_checkpoint(tmp_path / "late.npz").keyframe_poses()) == [f.stamp_ns for f in frames[:3]]


def test_bad_keyframe_content_is_refused_before_any_change(room_small):
    """Images outside [0, 1] (8-bit, 0..255), non-finite pixels, mis-shaped depth / variance /
    validity, negative variance: clear errors, nothing of the keyframe kept (it can be re-sent
    corrected), and a rejected first keyframe does not fix the camera model."""
    from dataclasses import replace
    cam, frames = room_small
    f = frames[0]
    H, W = cam.height, cam.width
    nan_img = f.image.clone()
    nan_img[3, 4, 1] = float("nan")
    wide = torch.zeros(H, W, 2)
    bad = [(replace(f, image=(f.image * 255).round().to(torch.uint8)), "dtype torch.uint8"),
           (replace(f, image=f.image * 255), r"values must lie in \[0, 1\]"),
           (replace(f, image=nan_img), "non-finite"),
           (replace(f, depth=torch.stack([f.depth, f.depth], -1)), "depth must have shape"),
           (replace(f, inv_depth_var=wide), "inv_depth_var must have shape"),
           (replace(f, valid=wide > 0), "valid must have shape"),
           (replace(f, inv_depth_var=torch.full((H, W), -1.0)), "negative")]
    m = Mapper(MapperConfig(points_per_keyframe=100))
    other_cam = _kf(f.stamp_ns, f.T_wc, torch.full((20, 30), 2.0), _cam(30, 20))
    other_cam = replace(other_cam, depth=torch.full((20, 30), float("nan")))
    with pytest.raises(InputError, match="non-finite"):
        m.add_keyframe(other_cam)
    for kf, msg in bad:
        with pytest.raises(InputError, match=msg):
            m.add_keyframe(kf)
        assert len(m.window) == 0 and m.num_gaussians == 0 and m.keyframe_poses() == {}
    info = m.add_keyframe(f)                       # the corrected keyframe, same stamp, same camera
    assert info["added"] == m.num_gaussians > 0
    m.train(2)


def test_reported_additions_are_the_gaussians_added():
    """More Gaussians asked for than there are pixels: one per pixel, and that is what is reported."""
    cam = _cam(16, 12, 15.0)
    m = Mapper(MapperConfig(points_per_keyframe=20000))
    info = m.add_keyframe(_kf(1, np.eye(4), torch.full((12, 16), 2.0), cam))
    assert info["added"] == m.num_gaussians == m.counters["added"] == 16 * 12


def test_set_keyframe_poses_moves_owned_gaussians_and_render_sees_passive(room_small):
    cam, frames = room_small
    m = Mapper(MapperConfig(points_per_keyframe=800, iters_per_keyframe=2, sample_ratio=1.0, tau=0.05, delta_k=1))
    for f in frames[:3]:
        m.add_keyframe(f)
        m.train()
    s0 = frames[0].stamp_ns
    allg = m.all_gaussians()
    own = allg.kf_id == s0
    assert own.any() and m.num_passive > 0
    D = np_se3_exp(np.array([0.1, 0.0, -0.05, 0.0, 0.02, 0.0]))
    m.set_keyframe_poses({s0: D @ frames[0].T_wc.numpy()})
    moved = m.all_gaussians()
    exp = allg.means[own].double() @ torch.tensor(D[:3, :3]).T + torch.tensor(D[:3, 3])
    got = moved.means[moved.kf_id == s0].double()
    assert torch.allclose(_canon_rows(got), _canon_rows(exp), atol=1e-5)
    others = moved.kf_id != s0
    assert torch.equal(_canon_rows(moved.means[others]), _canon_rows(allg.means[~own]))
    # rendering at the first keyframe includes its (passive) Gaussians; the active set alone is emptier
    T0 = m.keyframe_poses()[s0]
    full = m.render(T0, cam)
    act = m.render(T0, cam, include_passive=False)
    assert full["alpha"].mean() > act["alpha"].mean() + 0.02


def _canon_rows(x: torch.Tensor) -> torch.Tensor:
    a = x.numpy()
    return x[torch.from_numpy(np.lexsort(a.T[::-1].copy()))]


def test_config_from_params_file(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 7\n      refine_mode: single\n")
    cfg = load_section(MapperConfig, "mapping", p)
    assert cfg.iters_per_keyframe == 7 and cfg.refine_mode == "single"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      refine_mode: both\n")
    with pytest.raises(ConfigError, match="refine_mode"):
        load_section(MapperConfig, "mapping", p)


# ----------------------------------------------------------------------------- mapping behaviour


def test_mapping_fits_keyframes_and_deletes_floaters(room_small):
    cam, frames = room_small
    m = Mapper(MapperConfig(points_per_keyframe=2500, iters_per_keyframe=30, sample_ratio=1.0))
    m.add_keyframe(frames[0])
    st0 = m.train(1)
    st = m.train()
    assert st["psnr"] > st0["psnr"] + 2
    # a big dark floater half-way to the wall in front of keyframe 1 is deleted when it arrives
    kf = frames[1]
    T = kf.T_wc.numpy()
    p = T[:3, :3] @ np.array([0.0, 0.0, float(kf.depth[20, 32]) * 0.5]) + T[:3, 3]
    fl = GaussianMap.create(torch.from_numpy(p[None].astype(np.float32)), torch.tensor([[0.0, 0, 0, 1]]),
                            torch.full((1, 2), math.log(0.05)), torch.tensor([5.0]), torch.full((1, 1, 3), -1.5),
                            kf_id=frames[0].stamp_ns)
    # and a splat whose parameters went non-finite is removed too (never rendered or trained again)
    bad = GaussianMap.create(torch.tensor([[float("nan"), 0.0, 1.0]]), torch.tensor([[0.0, 0, 0, 1]]),
                             torch.full((1, 2), math.log(0.05)), torch.tensor([0.0]), torch.zeros((1, 1, 3)),
                             kf_id=frames[0].stamp_ns)
    m.gm = GaussianMap.concat([m.gm, fl, bad])
    n = len(m.gm)
    info = m.add_keyframe(kf)
    assert info["deleted"] >= 2 and info["delete_rules"]["non_finite"] == 1
    assert torch.isfinite(m.gm.means).all()
    assert not (torch.isclose(m.gm.means, fl.means).all(1)).any()
    assert len(m.gm) == n - info["deleted"] + info["added"]
    r = m.render(kf.T_wc.numpy(), cam)
    assert r["color"].shape == (cam.height, cam.width, 3) and r["depth"].dtype == np.float32
    assert np.isfinite(r["depth"]).all() and (r["alpha"] <= 1.0 + 1e-6).all()


def test_new_keyframe_deletes_wrong_coloured_and_oversized_splats(room_small):
    """Deletion rules (b) and (c): a splat on the observed surface whose colour stays wrong over a
    3x3 neighbourhood, and a seen splat whose projected radius exceeds the diagonal fraction, are
    removed when a keyframe sees them (and counted under their rule); the trained map around them
    is not."""
    cam, frames = room_small
    m = Mapper(MapperConfig(points_per_keyframe=2500, iters_per_keyframe=30, sample_ratio=1.0))
    m.add_keyframe(frames[0])
    m.train()
    kf = frames[1]
    T = kf.T_wc.numpy()

    def on_ray(u, v, scale):        # world point at pixel (u, v), depth scale x observed depth
        d = float(kf.depth[v, u]) * scale
        return T[:3, :3] @ np.array([(u - cam.cx) / cam.fx * d, (v - cam.cy) / cam.fy * d, d]) + T[:3, 3]

    q_cam = torch.tensor([[*np_rotmat_to_quat(T[:3, :3])]], dtype=torch.float32)   # facing the camera
    # (b) on the surface (5 % in front of it, inside the 15 % band), magenta, opaque, ~5 px wide
    d_w = float(kf.depth[20, 32])
    wrong = GaussianMap.create(torch.tensor(on_ray(32, 20, 0.95)[None], dtype=torch.float32), q_cam,
                               torch.full((1, 2), math.log(2.5 * d_w / cam.fx)), torch.tensor([6.0]),
                               torch.tensor([[[2.0, -1.5, 2.0]]]), kf_id=frames[0].stamp_ns)
    # (c) a splat covering most of the view (radius far above 0.15 x diagonal), faint
    big = GaussianMap.create(torch.tensor(on_ray(12, 30, 0.9)[None], dtype=torch.float32), q_cam,
                             torch.full((1, 2), math.log(0.5 * d_w)), torch.tensor([-3.0]),
                             torch.zeros((1, 1, 3)), kf_id=frames[0].stamp_ns)
    m.gm = GaussianMap.concat([m.gm, wrong, big])
    info = m.add_keyframe(kf)
    rules = info["delete_rules"]
    assert rules["wrong_colour"] >= 1 and rules["too_big"] >= 1, rules
    for g in (wrong, big):
        assert not torch.isclose(m.gm.means, g.means).all(1).any()
    assert info["deleted"] < 0.05 * (len(m.gm) + info["deleted"] - info["added"])   # not the map


def test_unknown_depth_is_seeded_and_not_forced_empty(room_small):
    """Front-end style keyframe: a band of pixels without depth (dropped as uncertain: depth 0, large
    inverse-depth variance). With fill_unknown_depth the band is covered and rendered; without it
    the band stays (nearly) empty. Neither run applies the accumulation loss there."""
    cam, frames = room_small
    kf = frames[0]
    d = kf.depth.clone()
    var = torch.zeros_like(d)
    d[:, 20:44] = 0
    var[:, 20:44] = 0.09
    fe_kf = Keyframe(stamp_ns=kf.stamp_ns, image=kf.image, T_wc=kf.T_wc, depth=d, inv_depth_var=var, valid=d > 0,
                     camera=cam)
    cov = {}
    for fill in (True, False):
        m = Mapper(MapperConfig(points_per_keyframe=2500, iters_per_keyframe=30, sample_ratio=1.0,
                                fill_unknown_depth=fill))
        m.add_keyframe(fe_kf)
        m.train()
        r = m.render(kf.T_wc.numpy(), cam)
        cov[fill] = float(r["alpha"][:, 24:40].mean())
        if fill:
            err = np.abs(r["depth"][:, 24:40] - kf.depth[:, 24:40].numpy()) / kf.depth[:, 24:40].numpy()
            assert np.median(err) < 0.1
    assert cov[True] > 0.8 and cov[False] < 0.5


def _pose_err(T, T_gt):
    dt = np.linalg.norm(T[:3, 3] - T_gt[:3, 3])
    return dt, float(rotation_angle_deg(T[:3, :3].T @ T_gt[:3, :3]))


@pytest.fixture(scope="module")
def room_two_views():
    """Two 128x80 room views 0.3 s apart (pose refinement needs more pixels than room_small)."""
    sim = pytest.importorskip("vings_core.sim")
    scene = sim.make_scene("room", seed=0)
    cam = sim.default_camera(128, 80)
    Ts = scene.T_wc(np.array([0.0, 0.3]))
    out = []
    for i, T in enumerate(Ts):
        rgb, d, _ = sim.render_view(scene, cam, T)
        out.append(_kf(1_000_000_000 + i * 300_000_000, T, d, cam, image=rgb.astype(np.float32) / 255.0))
    return cam, out


PERTURB = np.array([0.02, -0.015, 0.01, 0.01, -0.008, 0.006])   # ~3.5 cm / 0.8 deg at the camera


def _scaled(f, cam, scale: float):
    """Keyframe ``f`` in a world ``scale`` times larger (pose translation and depth)."""
    T = f.T_wc.numpy().copy()
    T[:3, 3] *= scale
    return _kf(f.stamp_ns, T, f.depth.numpy() * scale, cam, image=f.image)


@pytest.mark.parametrize("solver", ["gn", "adam"])
@pytest.mark.parametrize("scale", [1.0, 6.0])
def test_single_pose_refinement_corrects_a_pose_against_a_correct_map(room_two_views, scale, solver):
    """At scale 6 the same scene and perturbation are 6x larger (a monocular map has no metric
    scale): translation steps follow the median keyframe depth, so the correction is as good."""
    cam, (f0, f1) = room_two_views
    f0, f1 = _scaled(f0, cam, scale), _scaled(f1, cam, scale)
    m = Mapper(MapperConfig(points_per_keyframe=6000, iters_per_keyframe=20, sample_ratio=1.0,
                            refine_lr_trans_rel=1.5e-3, refine_lr_rot=2e-3, refine_solver=solver))
    for f in (f0, f1):
        m.add_keyframe(f)
        m.train()
    T_gt = f1.T_wc.numpy().copy()
    T_bad = np_se3_exp(PERTURB * np.array([scale] * 3 + [1.0] * 3)) @ T_gt
    m.set_keyframe_poses({f1.stamp_ns: T_bad}, move_gaussians=False)   # map right, pose wrong
    e0 = _pose_err(T_bad, T_gt)
    poses = m.refine_poses(40, mode="single")
    e1 = _pose_err(poses[f1.stamp_ns], T_gt)
    assert e1[0] < 0.7 * e0[0] and e1[1] < 0.7 * e0[1], (e0, e1)
    assert np.array_equal(poses[f0.stamp_ns], f0.T_wc.numpy())          # gauge: the first is fixed


@pytest.mark.parametrize("sh_degree,solver", [(0, "gn"), (1, "gn"), (0, "adam")])
def test_multi_pose_refinement_corrects_a_keyframe_and_its_gaussians(room_two_views, sh_degree, solver):
    cam, (f0, f1) = room_two_views
    m = Mapper(MapperConfig(points_per_keyframe=6000, iters_per_keyframe=20, sample_ratio=1.0,
                            refine_lr_trans_rel=1.5e-3, refine_lr_rot=2e-3, sh_degree=sh_degree,
                            refine_solver=solver))
    m.add_keyframe(f0)
    m.train()
    T_gt = f1.T_wc.numpy().copy()
    T_bad = np_se3_exp(PERTURB) @ T_gt
    # the keyframe arrives with a wrong pose: its Gaussians are back-projected with it
    m.add_keyframe(_kf(f1.stamp_ns, T_bad, f1.depth, cam, image=f1.image))
    own = m.gm.kf_id == f1.stamp_ns
    before = m.gm.means[own].clone()
    e0 = _pose_err(T_bad, T_gt)
    poses = m.refine_poses(40, mode="multi")
    e1 = _pose_err(poses[f1.stamp_ns], T_gt)
    assert e1[0] < 0.85 * e0[0] and e1[1] < 0.65 * e0[1], (e0, e1)
    # its Gaussians moved rigidly with it: T_new T_bad^-1 applied to their centres
    D = poses[f1.stamp_ns] @ np.linalg.inv(T_bad)
    own = m.gm.kf_id == f1.stamp_ns
    exp = before.double() @ torch.tensor(D[:3, :3]).T + torch.tensor(D[:3, 3])
    assert torch.allclose(m.gm.means[own].double(), exp, atol=1e-4)


def test_multi_pose_refinement_is_reproducible(room_two_views):
    """Two runs give bit-identical poses and Gaussians (--sync runs and benchmarks rely on it; the
    backward of ``Wd[inv]`` summed in a thread-dependent order)."""
    cam, (f0, f1) = room_two_views

    def run(junk):
        _ = [torch.empty(1000 + 37 * k) for k in range(junk)]   # a different allocation history
        m = Mapper(MapperConfig(points_per_keyframe=4000, iters_per_keyframe=10, sample_ratio=1.0))
        m.add_keyframe(f0)
        m.train()
        m.add_keyframe(_kf(f1.stamp_ns, np_se3_exp(PERTURB) @ f1.T_wc.numpy(), f1.depth, cam,
                           image=f1.image))
        m.train()
        return m.refine_poses(20, mode="multi"), m.gm.means.clone()

    (p1, g1), (p2, g2) = run(0), run(5)
    assert all(np.array_equal(p1[s], p2[s]) for s in p1)
    assert torch.equal(g1, g2)


def test_pose_refinement_needs_enough_contribution(room_two_views):
    """refine_min_pixels gates the update: a keyframe whose Gaussians contribute less than it to
    the render (here: any, with an impossible threshold) keeps its pose and its Gaussians; with the
    default it is corrected (previous test)."""
    cam, (f0, f1) = room_two_views
    m = Mapper(MapperConfig(points_per_keyframe=6000, iters_per_keyframe=20, sample_ratio=1.0,
                            refine_min_pixels=1e9))
    m.add_keyframe(f0)
    m.train()
    T_bad = np_se3_exp(PERTURB) @ f1.T_wc.numpy()
    m.add_keyframe(_kf(f1.stamp_ns, T_bad, f1.depth, cam, image=f1.image))
    before = m.gm.means.clone()
    poses = m.refine_poses(10, mode="multi")
    assert np.array_equal(poses[f1.stamp_ns], T_bad)
    assert torch.equal(m.gm.means, before)


@pytest.fixture(scope="module")
def room_small():
    """Eight 64x40 views of the synthetic room with ground-truth depth, as Keyframes."""
    sim = pytest.importorskip("vings_core.sim")
    scene = sim.make_scene("room", seed=0)
    cam = sim.default_camera(64, 40)
    t = np.arange(0, 12) / 20.0
    Ts = scene.T_wc(t)
    frames = []
    for i in range(0, 12, 2):
        rgb, d, _ = sim.render_view(scene, cam, Ts[i])
        frames.append(_kf(1_000_000_000 + i * 50_000_000, Ts[i], d, cam, image=rgb.astype(np.float32) / 255.0))
    # two more looking the opposite way (frames[6], frames[7]): they see none of frames[0]'s surfaces
    for j, yaw in enumerate((math.pi, math.pi + 0.15)):
        c, s_ = math.cos(yaw), math.sin(yaw)
        T = Ts[10] @ np_pose(np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]]), np.zeros(3))
        rgb, d, _ = sim.render_view(scene, cam, T)
        frames.append(_kf(2_000_000_000 + j * 50_000_000, T, d, cam, image=rgb.astype(np.float32) / 255.0))
    return cam, frames


def test_se3_exp_has_finite_gradient_at_zero():
    # pose refinement differentiates geometry.se3_exp at a zero tangent (its deltas start there)
    from vings_core.geometry import se3_exp, skew
    xi = torch.randn(20, 6, dtype=torch.float64)
    xi[0] = 0
    xi[1, 3:] = 1e-6
    twist = torch.zeros(20, 4, 4, dtype=torch.float64)     # [[phi^, rho], [0, 0]]
    twist[:, :3, :3] = skew(xi[:, 3:])
    twist[:, :3, 3] = xi[:, :3]
    assert torch.allclose(se3_exp(xi), torch.linalg.matrix_exp(twist), atol=1e-12)
    x = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    p = torch.tensor([0.3, -0.2, 1.5], dtype=torch.float64)
    (se3_exp(x)[:3, :3] @ p).sum().backward()
    # d/dphi of (R p) at 0 is -[p]x; summed over rows: (1,1,1) . (-[p]x) = p x (1,1,1)
    assert torch.isfinite(x.grad).all()
    assert torch.allclose(x.grad[3:], torch.linalg.cross(p, torch.ones(3, dtype=torch.float64)))


def test_history_keyframe_with_far_depth_keeps_the_loss_finite():
    """Depth beyond float16's range (ground-truth sky at 1e5 m) in a keyframe that left the window:
    history training reports a finite loss (before: inf / inf = NaN in the depth term)."""
    cam = _cam(48, 32, 40.0)
    d = torch.full((32, 48), 2.0)
    d[:8] = 1.0e5
    img = torch.rand(32, 48, 3, generator=torch.Generator().manual_seed(0)) * 0.6 + 0.2
    m = Mapper(MapperConfig(points_per_keyframe=400, window_size=1, history_ratio=0.9, score_manager=False))
    m.add_keyframe(_kf(1, np.eye(4), d, cam, image=img))
    m.train(2)
    T = np.eye(4)
    T[0, 3] = 0.02
    m.add_keyframe(_kf(2, T, d, cam, image=img))
    assert torch.isfinite(m.state.history.get(1)["depth"].float()).all()
    t = m.train(20)
    assert math.isfinite(t["loss"]) and math.isfinite(t["depth"])


def test_multi_refinement_leaves_a_keyframe_that_sees_only_its_own_gaussians(room_two_views):
    """In multi mode a keyframe's own Gaussians move with its camera, so they cannot constrain its
    pose: a keyframe looking away from every other keyframe's map (here: turned by 180 deg) is not
    moved (before: its round-off gradient, normalised by Adam, took full-size steps, ~0.4 deg)."""
    from vings_core.geometry import np_pose
    sim = pytest.importorskip("vings_core.sim")
    cam, (f0, f1) = room_two_views
    scene = sim.make_scene("room", seed=0)
    c, s_ = -1.0, 0.0
    T1 = f1.T_wc.numpy() @ np_pose(np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]]), np.zeros(3))
    rgb, d, _ = sim.render_view(scene, cam, T1)
    away = _kf(f1.stamp_ns, T1, d, cam, image=rgb.astype(np.float32) / 255.0)
    m = Mapper(MapperConfig(points_per_keyframe=3000, iters_per_keyframe=5, sample_ratio=1.0))
    for f in (f0, away):
        m.add_keyframe(f)
        m.train()
    out = m.state.rasterize(m.gm, torch.from_numpy(np.linalg.inv(T1)).float(), cam)
    foreign = m.gm.kf_id != away.stamp_ns
    assert float(out.contribution[foreign].sum()) < m.cfg.refine_min_pixels      # the set-up
    P0 = m.keyframe_poses()
    P = m.refine_poses(20, mode="multi")
    assert all(np.array_equal(P[s], P0[s]) for s in P)


def test_set_keyframe_poses_is_all_or_nothing(room_small):
    cam, frames = room_small
    m = Mapper(MapperConfig(points_per_keyframe=300, iters_per_keyframe=2))
    for f in frames[:2]:
        m.add_keyframe(f)
    s0, s1 = frames[0].stamp_ns, frames[1].stamp_ns
    P, means = m.keyframe_poses(), m.gm.means.clone()
    good = P[s0] @ np_se3_exp(np.array([0.05, 0, 0, 0, 0.02, 0]))
    bad = P[s1].copy()
    bad[:3, :3] *= 1.5
    with pytest.raises(InputError, match="not a rigid pose"):
        m.set_keyframe_poses({s0: good, s1: bad})
    assert np.array_equal(m.keyframe_poses()[s0], P[s0]) and torch.equal(m.gm.means, means)
    m.set_keyframe_poses({s0: good})             # the retry moves the pose and its Gaussians
    own = m.gm.kf_id == s0
    assert not torch.equal(m.gm.means[own], means[own])


def test_non_finite_gaussian_does_not_freeze_its_owner_in_refinement(room_two_views):
    cam, (f0, f1) = room_two_views
    m = Mapper(MapperConfig(points_per_keyframe=3000, iters_per_keyframe=5, sample_ratio=1.0,
                            refine_fix_first=False))
    for f in (f0, f1):
        m.add_keyframe(f)
        m.train()
    k = int((m.gm.kf_id == f0.stamp_ns).nonzero()[0, 0])
    m.gm.means[k] = float("nan")
    P0 = m.keyframe_poses()
    P = m.refine_poses(6, mode="multi")
    assert not np.array_equal(P[f0.stamp_ns], P0[f0.stamp_ns])
    assert all(np.isfinite(P[s]).all() for s in P)


def test_history_spilled_to_disk_trains_and_checkpoints_exactly_as_in_memory(room_small, tmp_path):
    """history_memory_mb bounds the memory of keyframes that left the window: beyond it records go to
    disk and come back when sampled. Spilling changes nothing: same map, same checkpoint arrays."""
    cam, frames = room_small
    maps = []
    for mb in (1000.0, 0.02):   # 0.02 MB holds less than one 64x40 record (23 kB)
        cfg = MapperConfig(points_per_keyframe=400, window_size=1, history_ratio=0.6, iters_per_keyframe=4,
                           history_memory_mb=mb, spill_dir=str(tmp_path / "spill"))
        m = Mapper(cfg)
        for i in range(0, 8, 2):
            m.add_keyframe(frames[i])
            m.train()
        maps.append(m)
    big, small = maps
    assert len(small.state.history) == 3 and small.state.history.num_spilled >= 2
    assert small.state.history.memory_bytes <= 2 * 64 * 40 * 9 and small.state.history.loaded_total > 0
    assert big.state.history.num_spilled == 0
    _assert_maps_equal(big.gm, small.gm)
    for m, name in ((big, "big.npz"), (small, "small.npz")):
        m.save_checkpoint(tmp_path / name)
    a, b = np.load(tmp_path / "big.npz"), np.load(tmp_path / "small.npz")
    assert sorted(a.files) == sorted(b.files) and len(a["hist/stamps"]) == 3
    for k in a.files:
        if k != "meta":   # the config inside differs (the budget)
            assert np.array_equal(a[k], b[k]), k
    # saving read the spilled records without bringing them back into memory
    assert small.state.history.memory_bytes <= 2 * 64 * 40 * 8
    back = Mapper.load_checkpoint(tmp_path / "small.npz")
    assert back.state.history.stamps() == big.state.history.stamps()
    for s in big.state.history.stamps():
        r1, r2 = big.state.history.get(s), back.state.history.get(s)
        assert r1["index"] == r2["index"] and all(torch.equal(r1[k], r2[k]) for k in ("image", "depth", "valid"))
    spill = list((tmp_path / "spill").glob("vings_history_*/*.npz"))
    assert spill
    # (checkpoints of older layout versions, history stacked per field: test_mapping_checkpoint.py)
    for m in (small, back, big):
        m.close()
    assert not any((tmp_path / "spill").glob("vings_history_*/*.npz"))


def test_history_store_lost_spill_file_is_reported_and_dropped(tmp_path, caplog):
    from vings_core.mapping.history import HistoryStore, compact_keyframe
    cam = _cam(32, 24)
    store = HistoryStore(0, str(tmp_path))        # budget 0: everything but the last read spills
    recs = {}
    for s in (10, 20, 30):
        kf = _kf(s, np.eye(4), torch.full((24, 32), 2.0 + s), cam,
                 image=torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(s)))
        recs[s] = compact_keyframe(kf)
        store.put(s, recs[s])
    assert store.num_spilled == 3 and store.memory_bytes == 0 and store.stamps() == [10, 20, 30]
    for s in (20, 10):
        got = store.get(s)
        assert all(torch.equal(got[k], recs[s][k]) for k in ("image", "depth", "inv_depth_var", "valid"))
        assert got["index"] == recs[s]["index"]
    next(tmp_path.glob("vings_history_*/kf_30.npz")).write_bytes(b"not an npz")
    with caplog.at_level("ERROR"):
        assert store.get(30) is None
    assert "history keyframe 30" in caplog.text and "damaged" in caplog.text
    assert 30 not in store and store.stamps() == [10, 20] and store.lost_total == 1
    store.close()
    assert not list(tmp_path.glob("vings_history_*"))


def test_history_store_failed_spill_keeps_the_record_in_memory(tmp_path, caplog):
    from vings_core.mapping.history import HistoryStore, compact_keyframe
    cam = _cam(32, 24)
    store = HistoryStore(0, str(tmp_path))
    rec = compact_keyframe(_kf(7, np.eye(4), torch.full((24, 32), 2.0), cam))
    d = _break_spill_folder(store._folder)     # a real failing write (disk full, folder removed)
    with caplog.at_level("WARNING"):
        store.put(7, rec)
    assert "cannot spill" in caplog.text and store.num_spilled == 0
    assert store.memory_bytes == 32 * 24 * 9 and torch.equal(store.get(7)["image"], rec["image"])
    _mend_spill_folder(d)
    store.put(8, rec)          # the disk is back: both spill now
    assert store.num_spilled == 2 and store.memory_bytes == 0
    assert torch.equal(store.get(7)["depth"], rec["depth"])
    store.close()
