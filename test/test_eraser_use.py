"""How the dynamic mask is used: the mapper adds no Gaussians and computes no loss in masked
pixels, erases what a moving object left, keeps the mask through the coarse copy, the history and
checkpoints; the front end gives masked grid points weight 0 in the dense BA."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vings_core.frontend import Frontend, FrontendConfig
from vings_core.frontend.synthetic import make_box_scene, orbit_trajectory, render_box
from vings_core.mapping import Mapper, MapperConfig
from vings_core.mapping.history import compact_keyframe, expand_keyframe
from vings_core.mapping.training import coarse_keyframe
from vings_core.types import CameraModel, Frame, Keyframe

CAM = CameraModel(width=48, height=32, fx=40.0, fy=40.0, cx=23.5, cy=15.5)


def _kf(stamp: int, x: float = 0.0, seed: int = 0, dynamic=None, depth: float = 2.0) -> Keyframe:
    g = torch.Generator().manual_seed(seed)
    d = depth + 0.05 * torch.rand((CAM.height, CAM.width), generator=g)
    T = np.eye(4)
    T[0, 3] = x
    return Keyframe(stamp_ns=stamp, image=torch.rand((CAM.height, CAM.width, 3), generator=g),
                    T_wc=torch.from_numpy(T), depth=d, inv_depth_var=torch.full_like(d, 1e-4),
                    valid=torch.ones_like(d, dtype=torch.bool), camera=CAM, dynamic=dynamic)


def _mask() -> torch.Tensor:
    m = torch.zeros(CAM.height, CAM.width, dtype=torch.bool)
    m[8:24, 12:36] = True
    return m


def _pixels(m: Mapper, stamp: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (u, v) of each Gaussian owned by keyframe ``stamp``, projected into it."""
    T_cw = np.linalg.inv(m.keyframe_poses()[stamp])
    own = (m.gm.kf_id == stamp).numpy()
    p = m.gm.means.numpy()[own].astype(np.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]
    return (np.round(CAM.fx * p[:, 0] / p[:, 2] + CAM.cx).astype(int),
            np.round(CAM.fy * p[:, 1] / p[:, 2] + CAM.cy).astype(int))


def _mapper(**kw) -> Mapper:
    kw = {"window_size": 4, **kw}
    return Mapper(MapperConfig(points_per_keyframe=2000, iters_per_keyframe=2, sample_ratio=1.0, **kw))


def test_no_gaussians_are_added_in_dynamic_pixels():
    m = _mapper()
    m.add_keyframe(_kf(1_000, dynamic=_mask()))
    u, v = _pixels(m, 1_000)
    assert len(u) > 500
    inside = (u >= 12) & (u < 36) & (v >= 8) & (v < 24)
    assert not inside.any()


def test_dynamic_pixels_are_left_out_of_every_loss():
    m = _mapper()
    m.add_keyframe(_kf(1_000))
    kf = m.state.window[0]
    mask = _mask()
    other = kf.image.clone()
    other[mask] = 1.0 - other[mask]                         # what the object shows: anything
    a = torch.tensor(0.0)
    terms: list = []
    for img in (kf.image, other):
        k = Keyframe(stamp_ns=2_000 + len(terms), image=img, T_wc=kf.T_wc, depth=kf.depth.clone(),
                     inv_depth_var=kf.inv_depth_var, valid=kf.valid, camera=CAM, dynamic=mask)
        out = m.state.rasterize(m.gm, torch.from_numpy(np.linalg.inv(k.T_wc.numpy())), CAM, sample_ratio=1.0)
        t: dict = {}
        k.depth[mask] = 50.0                                 # and its depth: anything too
        loss = m.trainer.losses(out, k, t)
        terms.append((float(loss), t["l1_map"]))
    assert terms[0][0] == pytest.approx(terms[1][0], rel=1e-6)
    assert float(terms[1][1][mask].abs().max()) == 0.0
    del a


def test_set_dynamic_mask_erases_what_recent_keyframes_left_inside_it():
    m = _mapper(erase_owner_keyframes=1)
    m.add_keyframe(_kf(1_000, 0.0, seed=1))
    m.add_keyframe(_kf(2_000, 0.0, seed=2, depth=1.0))      # something in front of the first surface
    n1, n2 = int((m.gm.kf_id == 1_000).sum()), int((m.gm.kf_id == 2_000).sum())
    assert n1 > 500 and n2 > 500
    m.add_keyframe(_kf(3_000, 0.0, seed=3, depth=1.0))
    erased = m.set_dynamic_mask(3_000, _mask().numpy())
    assert erased > 0 and m.counters["erased_dynamic"] == erased
    # only keyframe 2 000's (the latest before) and 3 000's own Gaussians inside the mask went
    assert int((m.gm.kf_id == 1_000).sum()) == n1
    assert int((m.gm.kf_id == 2_000).sum()) < n2
    u, v = _pixels(m, 3_000)
    assert not ((u >= 12) & (u < 36) & (v >= 8) & (v < 24)).any()
    assert m.state.window[-1].dynamic is not None
    assert m.set_dynamic_mask(99, _mask().numpy()) == 0          # unknown keyframe: ignored
    # what lies behind the object's observed surface stays (the static map it hides)
    m2 = _mapper(erase_owner_keyframes=2)
    m2.add_keyframe(_kf(1_000, 0.0, seed=1, depth=4.0))
    m2.add_keyframe(_kf(2_000, 0.0, seed=2, depth=1.0))
    far = int((m2.gm.kf_id == 1_000).sum())
    m2.set_dynamic_mask(2_000, _mask().numpy())
    assert int((m2.gm.kf_id == 1_000).sum()) == far and int((m2.gm.kf_id == 2_000).sum()) > 0
    with pytest.raises(ValueError, match="shape"):
        m.set_dynamic_mask(3_000, np.zeros((3, 3), bool))


def test_the_mask_survives_the_coarse_copy_the_history_and_a_checkpoint(tmp_path):
    kf = _kf(1_000, dynamic=_mask())
    c = coarse_keyframe(kf, 2)
    assert c.dynamic.shape == (16, 24) and bool(c.dynamic[4:12, 6:18].all()) and int(c.dynamic.sum()) == 8 * 12
    back = expand_keyframe(compact_keyframe(kf), 1_000, kf.T_wc.numpy(), CAM)
    assert torch.equal(back.dynamic, kf.dynamic)
    assert expand_keyframe(compact_keyframe(_kf(2_000)), 2_000, np.eye(4), CAM).dynamic is None
    m = _mapper(history_ratio=0.5, window_size=1)
    for i in range(3):
        m.add_keyframe(_kf(1_000 * (i + 1), 0.02 * i, seed=i, dynamic=_mask() if i != 1 else None))
    m.save_checkpoint(tmp_path / "c.npz")
    m2 = Mapper.load_checkpoint(tmp_path / "c.npz")
    assert [k.stamp_ns for k in m2.window] == [k.stamp_ns for k in m.window]
    for a, b in zip(m.window, m2.window):
        assert (a.dynamic is None) == (b.dynamic is None) and (a.dynamic is None or torch.equal(a.dynamic, b.dynamic))
    for s in m.state.history.stamps():
        assert torch.equal(m.state.history.get(s)["dynamic"], m2.state.history.get(s)["dynamic"])


STEP_NS = 50_000_000
FCAM = CameraModel(160, 120, 110.0, 110.0, 79.5, 59.5)


def test_the_front_end_gives_masked_grid_points_weight_zero():
    scene = make_box_scene(seed=1)
    frames = [Frame(1_000_000_000 + k * STEP_NS, render_box(scene, FCAM, T)[0], FCAM)
              for k, T in enumerate(orbit_trajectory(36, radius=1.5, arc=1.6))]
    fe = Frontend(FrontendConfig(keyframe_flow_lr_px=1.2), FCAM)
    for f in frames[:20]:
        fe.process(f)
    win = fe.win
    assert len(win.keyframes) >= 2
    stamps = [k.stamp for k in win.keyframes]
    _, _, _, w0 = win.edge_tensors(stamps)
    mask = np.zeros((FCAM.height, FCAM.width), bool)
    mask[:, : FCAM.width // 2] = True
    k = win.keyframes[-1]
    fe.post_dynamic_mask(k.stamp, mask)
    fe.post_dynamic_mask(1, mask)                               # a keyframe no longer in the window
    fe.process(frames[20])
    assert fe.stats["dynamic_masks"] == 1 and fe.stats["dynamic_masks_late"] == 1
    assert k.static is not None and k.static.min() == 0 and k.static.max() == 1
    stamps = [x.stamp for x in win.keyframes]
    ii, jj, tg, w = win.edge_tensors(stamps)
    pos = stamps.index(k.stamp)
    left = torch.from_numpy(fe.uv_np[:, 0] < FCAM.width // 2)
    src = ii == pos
    assert bool(src.any()) and float(w[src][:, left].abs().max()) == 0.0
    # observations landing on the mask in keyframe k get weight 0 too
    dst = jj == pos
    lands = tg[dst][..., 0] < FCAM.width // 2 - 1
    assert float(w[dst][lands].abs().max()) == 0.0
    assert float(w.sum()) > 0
    del w0
