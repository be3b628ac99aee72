"""Mapper.apply_increments: world-frame Sim(3) corrections of keyframes move their poses and their
Gaussians (active, passive in memory and spilled to disk); a rigid one is set_keyframe_poses. Also
the refinement policies as Enums."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vings_core.config import load_section
from vings_core.errors import ConfigError, InputError
from vings_core.geometry import np_se3_exp, quat_to_rotmat, sim3, sim3_apply_to_pose
from vings_core.mapping import GaussianMap, Mapper, MapperConfig, RefineMode, RefineSolver
from vings_core.types import CameraModel, Keyframe

CAM = CameraModel(width=40, height=30, fx=36.0, fy=36.0, cx=19.5, cy=14.5)
STAMPS = (1_000, 2_000, 3_000, 4_000)
PARAM_AND_MOMENTS = ("means", "quats", "log_scales", "opacity_logits", "sh", "kf_id", "m_means", "m_quats", "m_sh")


def _keyframe(stamp: int, x: float) -> Keyframe:
    g = torch.Generator().manual_seed(stamp)
    u = torch.arange(CAM.width, dtype=torch.float32)[None, :].expand(CAM.height, CAM.width)
    d = 2.0 + 0.3 * u / CAM.width
    img = (0.5 + 0.3 * torch.sin(u[..., None] / 3.0 + torch.arange(3)) * torch.rand(1, 1, 3, generator=g)).clamp(0, 1)
    T = np.eye(4)
    T[0, 3] = x
    return Keyframe(stamp_ns=stamp, image=img.contiguous(), T_wc=torch.from_numpy(T), depth=d.contiguous(),
                    inv_depth_var=torch.zeros_like(d), valid=d > 0, camera=CAM)


def _random_map(n: int, seed: int, owners, k: int) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    gm = GaussianMap.create(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g),
                            torch.randn(n, 2, generator=g) - 3, torch.randn(n, generator=g),
                            torch.randn(n, k, 3, generator=g),
                            torch.tensor(owners)[torch.randint(len(owners), (n,), generator=g)], window=3)
    gm.m_means.copy_(torch.randn(n, 3, generator=g))
    return gm


def _mapper(tmp_path, sh_degree: int = 1) -> Mapper:
    """Four keyframes (window of three), and passive Gaussians of keyframes 1 and 2, one chunk kept
    in memory and one spilled to disk, with a rigid move still pending for keyframe 1's."""
    m = Mapper(MapperConfig(points_per_keyframe=300, iters_per_keyframe=3, sample_ratio=1.0, window_size=3,
                            sh_degree=sh_degree, passive_memory_mb=0.05, spill_dir=str(tmp_path / "spill")))
    for i, s in enumerate(STAMPS):
        m.add_keyframe(_keyframe(s, 0.04 * i))
        m.train()
    k = (sh_degree + 1) ** 2
    m.passive.put(_random_map(400, 0, (1_000, 2_000), k), m.state.poses)
    m.passive.put(_random_map(100, 1, (2_000, 3_000), k), m.state.poses)
    assert m.passive.num_spilled_chunks == 1 and len(m.passive.chunks) == 2
    m.set_keyframe_poses({1_000: m.keyframe_poses()[1_000] @ np_se3_exp(np.array([0.02, 0, 0.01, 0, 0.03, 0]))})
    return m


def _C(s: float) -> np.ndarray:
    R = np_se3_exp(np.array([0, 0, 0, 0.1, -0.2, 0.05]))[:3, :3]
    return sim3(R, np.array([0.3, -0.1, 0.2]), s)


def _close(a: GaussianMap, b: GaussianMap, atol: float, fields=None) -> None:
    for k, t in a.tensors().items():
        if fields is not None and k not in fields:
            continue
        u = getattr(b, k)
        assert t.dtype == u.dtype, k
        assert (torch.equal(t, u) if not t.dtype.is_floating_point else torch.allclose(t, u, atol=atol, rtol=0)), k


def test_a_rigid_increment_is_set_keyframe_poses(tmp_path):
    a, b = _mapper(tmp_path / "a"), _mapper(tmp_path / "b")
    C = _C(1.0)
    moved = (1_000, 3_000, 4_000)
    n = a.apply_increments({**{s: C for s in moved}, 99: C})          # an unknown stamp is ignored
    assert n == 3
    b.set_keyframe_poses({s: C @ b.keyframe_poses()[s] for s in moved})
    for s, T in b.keyframe_poses().items():
        assert np.allclose(a.keyframe_poses()[s], T, atol=1e-9, rtol=0), s
    assert [k.T_wc.numpy().tolist() for k in a.window] == [a.keyframe_poses()[k.stamp_ns].tolist() for k in a.window]
    _close(a.gm, b.gm, 1e-9)
    _close(a.all_gaussians(), b.all_gaussians(), 1e-9)
    for m in (a, b):                                       # passive ones come back moved alike
        m.update_tiers(np.eye(4))
    _close(a.gm, b.gm, 1e-9)
    assert a.apply_increments({2_000: np.eye(4)}) == 0 and a.apply_increments({}) == 0
    a.close()
    b.close()


@pytest.mark.parametrize("s", [1.7, 0.6])
def test_a_scaled_increment_moves_poses_and_gaussians_by_the_similarity(tmp_path, s):
    m = _mapper(tmp_path)
    C = _C(s)
    R, t = C[:3, :3] / s, C[:3, 3]
    moved = (1_000, 3_000)
    P0 = m.keyframe_poses()
    before = m.all_gaussians().clone()
    assert m.apply_increments({q: C for q in moved}) == 2
    P1 = m.keyframe_poses()
    for q in STAMPS:
        assert np.array_equal(P1[q], sim3_apply_to_pose(C, P0[q]) if q in moved else P0[q]), q
    after = m.all_gaussians()
    own = torch.isin(before.kf_id, torch.tensor(moved))
    assert torch.equal(after.kf_id, before.kf_id) and int(own.sum()) > 100 and int((~own).sum()) > 100
    for k, v in before.index(~own).tensors().items():              # other keyframes' Gaussians stay
        assert torch.equal(after.index(~own).tensors()[k], v), k
    b, a = before.index(own), after.index(own)
    mu = b.means.double() @ torch.from_numpy(s * R).T + torch.from_numpy(t)
    assert torch.allclose(a.means.double(), mu, atol=2e-5 * s, rtol=0)
    rot = torch.from_numpy(R) @ quat_to_rotmat(b.quats.double() / b.quats.double().norm(dim=1, keepdim=True))
    assert torch.allclose(quat_to_rotmat(a.quats.double() / a.quats.double().norm(dim=1, keepdim=True)), rot, atol=1e-5)
    assert torch.allclose(a.log_scales.double(), b.log_scales.double() + math.log(s), atol=1e-6, rtol=0)
    for k in ("opacity_logits", "win_c", "stable", "adam_step", "v_means"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k
    assert torch.equal(a.sh[:, 0], b.sh[:, 0]) and not torch.equal(a.sh[:, 1:], b.sh[:, 1:])   # colour turns
    # the passive ones come back (from memory and from disk) where all_gaussians() showed them (their
    # scores restart)
    m.update_tiers(np.eye(4))
    assert m.num_passive == 0
    order = torch.argsort(m.gm.means[:, 0] * 1e3 + m.gm.means[:, 1])
    ref = torch.argsort(after.means[:, 0] * 1e3 + after.means[:, 1])
    _close(m.gm.index(order), after.index(ref), 0.0, PARAM_AND_MOMENTS)
    m.close()


def test_a_scaled_map_renders_as_before_from_the_moved_camera(tmp_path):
    """Every keyframe moved by the same similarity: the render from a moved keyframe is the render
    from where it was, with depth times s."""
    m = _mapper(tmp_path, sh_degree=0)
    m.update_tiers(np.eye(4))
    m.passive.close()
    s = 1.5
    T0 = m.keyframe_poses()[4_000]
    r0 = m.render(T0, CAM, include_passive=False)
    m.apply_increments({q: _C(s) for q in STAMPS})
    r1 = m.render(m.keyframe_poses()[4_000], CAM, include_passive=False)
    assert r0["alpha"].mean() > 0.5
    assert np.allclose(r1["color"], r0["color"], atol=2e-4)
    assert np.allclose(r1["alpha"], r0["alpha"], atol=2e-4)
    assert np.allclose(r1["depth"], s * r0["depth"], atol=2e-4 * s, rtol=1e-4)
    m.close()


def test_a_pending_scale_survives_a_checkpoint_and_a_change_that_moves_nothing(tmp_path):
    m = _mapper(tmp_path)
    m.apply_increments({1_000: _C(1.3), 2_000: _C(0.8)})
    owed = m.all_gaussians()
    m.save_checkpoint(tmp_path / "c.npz")
    m2 = Mapper.load_checkpoint(tmp_path / "c.npz")
    assert m2.state.depth_scale == m.state.depth_scale == {1_000: 1.3}     # history keyframe 1 owes its scale
    _close(owed, m2.all_gaussians(), 0.0)
    # a pose change that moves no Gaussians keeps what the passive ones are owed
    for mm in (m, m2):
        T = mm.keyframe_poses()[2_000]
        mm.set_keyframe_poses({2_000: T @ np_se3_exp(np.array([0.0, 0.03, 0, 0.1, 0, 0.05]))}, move_gaussians=False)
        _close(owed, mm.all_gaussians(), 2e-6)
    for mm in (m, m2):
        mm.update_tiers(np.eye(4))
    _close(m.gm, m2.gm, 0.0)
    _close(m.gm.index(m.gm.kf_id == 1_000), owed.index(owed.kf_id == 1_000), 2e-6, ("means", "quats", "log_scales"))
    m.close()
    m2.close()


def test_bad_increments_change_nothing(tmp_path):
    m = _mapper(tmp_path)
    P0, g0 = m.keyframe_poses(), m.all_gaussians().clone()
    shear = np.eye(4)
    shear[0, 1] = 0.3
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    for bad, msg in ((np.full((4, 4), np.nan), "finite 4x4"), (np.eye(3), "finite 4x4"),
                     (mirror, "positive scale"), (shear, "not a similarity")):
        with pytest.raises(InputError, match=r"apply_increments\[2000\]"):
            m.apply_increments({1_000: _C(1.2), 2_000: bad})
        with pytest.raises(InputError, match=msg):
            m.apply_increments({2_000: bad})
    assert all(np.array_equal(T, m.keyframe_poses()[s]) for s, T in P0.items())
    _close(g0, m.all_gaussians(), 0.0)
    m.close()


def test_refinement_policies_are_enums_that_load_from_strings(tmp_path):
    cfg = MapperConfig(refine_mode="single", refine_solver="adam")
    assert cfg.refine_mode is RefineMode.SINGLE and cfg.refine_solver is RefineSolver.ADAM
    assert cfg.refine_mode == "single" and str(cfg.refine_solver) == "adam"
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      refine_mode: none\n      refine_solver: adam\n")
    cfg = load_section(MapperConfig, "mapping", p)
    assert cfg.refine_mode is RefineMode.NONE and cfg.refine_solver is RefineSolver.ADAM
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      refine_solver: lm\n")
    with pytest.raises(ConfigError, match="refine_solver"):
        load_section(MapperConfig, "mapping", p)
    with pytest.raises(ValueError, match="refine_mode must be none|single|multi"):
        MapperConfig(refine_mode="both").validate()
    m = Mapper(MapperConfig(points_per_keyframe=200, iters_per_keyframe=2))
    m.add_keyframe(_keyframe(1_000, 0.0))
    m.add_keyframe(_keyframe(2_000, 0.03))
    m.train()
    with pytest.raises(InputError, match="mode must be none|single|multi"):
        m.refine_poses(2, mode="both")
    P = m.refine_poses(2, mode=RefineMode.NONE)
    assert P == {} or all(np.array_equal(T, m.keyframe_poses()[s]) for s, T in P.items())
    m.refine_poses(2, mode=RefineMode.SINGLE)
    m.refine_poses(2, mode="multi")


def test_a_scaled_increment_scales_the_keyframes_depth_maps(tmp_path):
    """Depth follows the similarity (depth x s, inverse-depth variance / s^2): window keyframes at
    once, history keyframes when training reads them, and across a checkpoint."""
    import dataclasses
    m = _mapper(tmp_path)
    win = {kf.stamp_ns: (kf.depth.clone(), kf.inv_depth_var.clone() + 0.5) for kf in m.state.window}
    for kf in m.state.window:
        kf.inv_depth_var = win[kf.stamp_ns][1].clone()
    hist = STAMPS[0]
    assert hist in m.state.history and hist not in win
    m.apply_increments({hist: _C(1.3), STAMPS[-1]: _C(0.8)})
    kf = m.state.window_keyframe(STAMPS[-1])
    d0, v0 = win[STAMPS[-1]]
    assert torch.allclose(kf.depth, d0 * 0.8) and torch.allclose(kf.inv_depth_var, v0 / 0.64)
    assert torch.equal(m.state.window_keyframe(STAMPS[1]).depth, win[STAMPS[1]][0])   # not moved
    assert m.state.depth_scale == {hist: 1.3}
    m.save_checkpoint(tmp_path / "c.npz")
    m2 = Mapper.load_checkpoint(tmp_path / "c.npz")
    assert m2.state.depth_scale == {hist: 1.3}
    assert torch.equal(m2.state.window_keyframe(STAMPS[-1]).depth, kf.depth)
    from vings_core.mapping.history import expand_keyframe
    stored = m.state.history.peek(hist)
    for mm in (m, m2):
        mm.state.cfg = dataclasses.replace(mm.state.cfg, history_ratio=1.0, tau=1e3)
        h = mm.trainer.history_keyframe()
        assert h is not None and h.stamp_ns == hist
        valid = h.depth > 0
        plain = expand_keyframe(stored, hist, mm.keyframe_poses()[hist], mm.state.camera)
        assert valid.any() and torch.allclose(h.depth[valid], plain.depth[valid] * 1.3)
        mm.close()
