"""The dynamic eraser's parts: proposals, the re-render and motion cues against their references,
the stage on synthetic keyframes, and the learned-segmenter plug-in."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vings_core.errors import ConfigError
from vings_core.eraser import (Cue, DynamicEraser, EraserConfig, LossTerms, ProposalMethod, make_segmenter,
                               motion_residual, rerender_loss, segment_weight_free)
from vings_core.eraser.mask_io import encode_mask_png, mono8_to_mask, read_mask_png
from vings_core.eraser.motion import moving_proposals, moving_proposals_reference
from vings_core.eraser.score import dynamic_proposals, dynamic_proposals_reference
from vings_core.types import CameraModel, Keyframe

H, W = 96, 128
CAM = CameraModel(W, H, 100.0, 100.0, W / 2 - 0.5, H / 2 - 0.5)


def _texture(seed: int, h: int = H, w: int = W) -> np.ndarray:
    """Smooth random RGB texture in [0, 1] (trackable by optical flow)."""
    import cv2
    rng = np.random.default_rng(seed)
    small = rng.random((h // 4 + 2, w // 4 + 2, 3)).astype(np.float32)
    big = cv2.resize(small, (w + 8, h + 8), interpolation=cv2.INTER_CUBIC)[4:4 + h, 4:4 + w]
    return np.clip(big, 0, 1)


def _keyframe(image: np.ndarray, T_wc=None, stamp: int = 1_000_000_000, var=None) -> Keyframe:
    d = torch.full((H, W), 2.0)
    return Keyframe(stamp_ns=stamp, image=torch.from_numpy(image.astype(np.float32)),
                    T_wc=torch.from_numpy(np.eye(4) if T_wc is None else T_wc), depth=d,
                    inv_depth_var=torch.full((H, W), 1e-3) if var is None else torch.from_numpy(var),
                    valid=torch.ones(H, W, dtype=torch.bool), camera=CAM)


def test_vectorised_rules_match_their_references():
    rng = np.random.default_rng(0)
    cfg = EraserConfig(min_proposal_px=5, loss_threshold=0.02)
    for trial in range(5):
        labels = rng.integers(0, 40, (H, W)).astype(np.int32)
        labels[:20, :30] = 40 + trial                       # one large proposal
        loss = (rng.random((H, W)) ** 3).astype(np.float32) * 0.2
        loss[:20, :30] += 0.3 * (trial % 2)
        covered = rng.random((H, W)) > 0.2
        fast, info = dynamic_proposals(labels, loss, covered, cfg)
        assert np.array_equal(fast, dynamic_proposals_reference(labels, loss, covered, cfg))
        assert info["judged"] > 0
        assert fast[40 + trial] == (trial % 2 == 1)       # the large proposal: dynamic when its loss is raised
        from vings_core.eraser.motion import MotionResidual
        moving = rng.random((H, W)) > 0.6
        moving[:20, :30] = trial % 2 == 1
        res = MotionResidual(np.zeros((H, W), np.float32), np.ones((H, W), np.float32),
                             rng.random((H, W)) > 0.3, moving, np.zeros((H, W), bool))
        res.moving &= res.reliable
        assert np.array_equal(moving_proposals(labels, res, 5, 0.5, 0.3),
                              moving_proposals_reference(labels, res, 5, 0.5, 0.3))


def test_rerender_loss_terms_and_coverage():
    img = _texture(1)
    covered = np.ones((H, W), bool)
    covered[:, :10] = False
    assert np.allclose(rerender_loss(img, img, None, covered, LossTerms.L1), 0)
    bad = img.copy()
    bad[40:60, 40:80] = 1 - bad[40:60, 40:80]
    var = np.full((H, W), 1e-3, np.float32)
    var[40:50] = 1e-2                                                 # uncertain rows weigh more
    l1 = rerender_loss(bad, img, None, covered, LossTerms.L1)
    sl1 = rerender_loss(bad, img, None, covered, LossTerms.SSIM_L1)
    full = rerender_loss(bad, img, var, covered, LossTerms.SSIM_L1_SIGMA, sigma_clip=10.0)
    assert l1[:, :10].max() == 0 and full[:, :10].max() == 0          # uncovered pixels do not count
    assert l1[45, 60] > 0.1 and 0 < sl1[45, 60] <= l1[45, 60]
    assert full[45, 60] == pytest.approx(10.0 * sl1[45, 60], rel=1e-5)  # relative Sigma 10 there (clipped)
    assert full[55, 60] == pytest.approx(sl1[55, 60], rel=1e-5)         # relative Sigma 1 at the median
    with pytest.raises(ValueError, match="inverse-depth variance"):
        rerender_loss(bad, img, None, covered, LossTerms.SSIM_L1_SIGMA)


def test_proposals_cover_the_image_and_follow_edges():
    img = _texture(2) * 0.2
    img[30:70, 50:100] = [0.9, 0.2, 0.1]                 # a uniform block on a dark texture
    for method in (ProposalMethod.FELZENSZWALB, ProposalMethod.SLIC):
        lab = segment_weight_free(img, EraserConfig(proposals=method, slic_segments=40))
        assert lab.shape == (H, W) and lab.dtype == np.int32 and lab.min() == 0
        assert len(np.unique(lab)) == lab.max() + 1
        inside = lab[35:65, 55:95]
        # the block's interior is covered by proposals that barely leak outside it
        inside_share = {k: (lab == k)[30:70, 50:100].sum() / (lab == k).sum() for k in np.unique(inside)}
        # the block's interior lies in proposals that are mostly inside it (SLIC's compact cells leak)
        good = np.isin(inside, [k for k, f in inside_share.items() if f > 0.6])
        assert good.mean() > (0.95 if method == ProposalMethod.FELZENSZWALB else 0.7), method


def _camera_move(tx: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = tx
    return T


def _plane_views(dx: int, dy: int = 0):
    """Two views of a fronto-parallel textured plane at 2 m, the camera moving 0.1 m right (the
    texture shifts 5 px left), with a patch that moves by itself ``(dx, dy)`` px."""
    big = _texture(3, H, W + 40)
    a = big[:, 20:20 + W].copy()
    b = big[:, 25:25 + W].copy()             # x_b = x_a - 5: induced flow -5 px
    patch = _texture(4, 24, 30)
    a[40:64, 50:80] = patch
    b[40 + dy:64 + dy, 50 - 5 + dx:80 - 5 + dx] = patch
    return a, b


@pytest.mark.parametrize("with_depth", [True, False])
def test_motion_residual_finds_the_object_that_moves_by_itself(with_depth):
    a, b = _plane_views(6)
    T_prev, T_cur = np.eye(4), _camera_move(0.1)
    depth = np.full((H, W), 2.0) if with_depth else None
    res = motion_residual(b, a, T_cur, T_prev, CAM, depth, motion_px=1.5, motion_rel=0.15, fb_check_px=1.0)
    obj = np.zeros((H, W), bool)
    obj[44:60, 56:70] = True                 # the object's interior in the current view (shifted +1 px)
    rest = np.ones((H, W), bool)
    rest[30:74, 35:95] = False
    rest[:, :8] = rest[:, -8:] = False
    rest[:8] = rest[-8:] = False
    assert res.reliable[rest].mean() > 0.8
    assert res.moving[rest].mean() < 0.02
    assert res.residual[rest & res.reliable].mean() < 0.5
    if with_depth:
        assert res.reliable[obj].mean() > 0.6 and res.with_depth[obj].all()
        assert res.moving[obj & res.reliable].mean() > 0.95
    else:
        # motion along the epipolar line (here: horizontal, the camera's own direction) is invisible
        # without depth: the epipolar distance stays small
        assert not res.with_depth.any() and res.moving[obj].mean() < 0.2


def test_the_stage_masks_an_object_the_map_does_not_have():
    background = _texture(5) * 0.5
    img = background.copy()
    img[20:50, 30:70] = 0.5 + 0.5 * _texture(6)[20:50, 30:70]     # an object, brighter than the scene
    er = DynamicEraser(EraserConfig(cue=Cue.RERENDER, felz_min_size=10, ablation=True))
    res = er.process(_keyframe(img), {"color": background, "depth": np.full((H, W), 2.0, np.float32),
                                      "alpha": np.ones((H, W), np.float32)})
    truth = np.zeros((H, W), bool)
    truth[20:50, 30:70] = True
    iou = (res.mask & truth).sum() / (res.mask | truth).sum()
    assert iou > 0.7, iou
    assert res.mask[~truth].mean() < 0.05
    assert set(res.variants) == {"l1", "ssim_l1", "ssim_l1_sigma", "motion", "combined"}
    assert np.array_equal(res.variants["combined"], res.mask)        # no motion cue on a first keyframe
    # without a map nothing is judged by the re-render cue: no mask
    er2 = DynamicEraser(EraserConfig(cue=Cue.RERENDER))
    assert not er2.process(_keyframe(img), None).mask.any()


def test_the_stage_masks_a_moving_object_the_map_does_not_cover():
    a, b = _plane_views(0, 5)                # across the epipolar lines: seen without depth
    er = DynamicEraser(EraserConfig(cue=Cue.BOTH, felz_min_size=10))
    no_map = {"color": np.zeros((H, W, 3), np.float32), "depth": np.zeros((H, W), np.float32),
              "alpha": np.zeros((H, W), np.float32)}
    er.process(_keyframe(a, np.eye(4), stamp=1_000_000_000), no_map)
    plane = {"color": b, "depth": np.full((H, W), 2.0, np.float32), "alpha": np.ones((H, W), np.float32)}
    plane["alpha"][30:74, 35:95] = 0.0                    # the map does not cover the object's area
    plane["depth"][30:74, 35:95] = 0.0
    res = er.process(_keyframe(b, _camera_move(0.1), stamp=1_100_000_000), plane)
    assert res.dynamic_motion >= 1
    obj = np.zeros((H, W), bool)
    obj[45:69, 45:75] = True
    assert (res.mask & obj).sum() / obj.sum() > 0.5
    assert res.mask[~obj].mean() < 0.05


def test_a_mask_over_the_whole_view_is_not_trusted():
    img = _texture(7)
    er = DynamicEraser(EraserConfig(cue=Cue.RERENDER, gamma=0.0, loss_threshold=0.0, percentile=1.0))
    res = er.process(_keyframe(img), {"color": 1 - img, "depth": np.ones((H, W), np.float32),
                                      "alpha": np.ones((H, W), np.float32)})
    assert not res.mask.any() and "max_masked_fraction" in res.note


class _Halves(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:      # (1, 3, H, W) -> (1, 2, H, W) logits
        left = (torch.arange(x.shape[-1]) < x.shape[-1] // 2).to(x.dtype).expand(x.shape[-2], -1)
        return torch.stack([left - 0.5, 0.5 - left])[None] + 0 * x[:, :2]


def test_a_learned_segmenter_from_a_local_file(tmp_path):
    path = tmp_path / "seg.pt"
    torch.jit.script(_Halves()).save(str(path))
    seg = make_segmenter(EraserConfig(proposals=ProposalMethod.MODEL, model_path=str(path)))
    lab = seg(_texture(8))
    assert lab.shape == (H, W) and len(np.unique(lab)) == 2
    assert (lab[:, : W // 2] == lab[0, 0]).all() and (lab[:, W // 2:] != lab[0, 0]).all()
    with pytest.raises(ConfigError, match="no such file"):
        make_segmenter(EraserConfig(proposals=ProposalMethod.MODEL, model_path=str(tmp_path / "none.pt")))
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(ConfigError, match="not a loadable TorchScript"):
        make_segmenter(EraserConfig(proposals=ProposalMethod.MODEL, model_path=str(tmp_path / "junk.pt")))
    with pytest.raises(ValueError, match="model_path"):
        EraserConfig(proposals=ProposalMethod.MODEL).validate()


def test_mask_png_roundtrip(tmp_path):
    m = np.zeros((H, W), bool)
    m[10:20, 5:50] = True
    p = tmp_path / "kf_1.png"
    p.write_bytes(encode_mask_png(m))
    assert np.array_equal(read_mask_png(p), m)
    with pytest.raises(ValueError, match="mono8"):
        mono8_to_mask(np.zeros((H, W, 3), np.uint8))


def test_the_opencv_ssim_matches_the_mapper_reference_inside():
    from vings_core.eraser.score import ssim_map_cv
    from vings_core.mapping.losses import ssim_reference
    a = _texture(9)
    b = np.clip(a + 0.1 * _texture(10) - 0.05, 0, 1)
    ref = ssim_reference(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    fast = ssim_map_cv(a, b)
    # the same away from the borders (padding differs there)
    assert np.abs(fast[6:-6, 6:-6] - ref[6:-6, 6:-6]).max() < 1e-4


def test_a_still_camera_sees_an_object_move_without_depth():
    a = _texture(11)
    b = a.copy()
    patch = _texture(12, 24, 30)
    a[40:64, 50:80] = patch
    b[44:68, 54:84] = patch                  # the object moves 4 px down and right; the camera does not
    res = motion_residual(b, a, np.eye(4), np.eye(4), CAM, None, 1.5, 0.5, 1.0)
    obj = np.zeros((H, W), bool)
    obj[48:64, 58:80] = True
    assert res.moving[obj & res.reliable].mean() > 0.9
    rest = np.ones((H, W), bool)
    rest[30:78, 40:94] = False
    assert res.moving[rest].mean() < 0.01


def test_the_flow_does_not_veto_an_object_it_cannot_see_move():
    """A car ahead holding its distance under forward motion: zero flow, along its epipolar line,
    where the camera's translation hardly moves the pixels. The re-render cue's detection stands."""
    from vings_core.eraser.motion import MotionResidual, static_proposals
    labels = np.zeros((H, W), np.int32)
    labels[40:60, 50:80] = 1
    ok = np.ones((H, W), bool)
    no_motion = MotionResidual(np.zeros((H, W), np.float32), np.zeros((H, W), np.float32), ok,
                               np.zeros((H, W), bool), ok, np.zeros((H, W), bool))
    assert not static_proposals(labels, no_motion, 0.3, 0.1).any()
    seen = MotionResidual(no_motion.residual, no_motion.ratio, ok, no_motion.moving, ok, ok)
    assert static_proposals(labels, seen, 0.3, 0.1).all()


def test_float_label_maps_from_a_model_are_labels():
    from vings_core.eraser.proposals import model_output_labels
    y = np.zeros((1, 1, H, W), np.float32)
    y[..., :, W // 2:] = 1.0
    y[..., H // 2:, :] += 2.0
    lab = model_output_labels(y, H, W)
    assert len(np.unique(lab)) == 4
    with pytest.raises(ConfigError, match="integer labels"):
        model_output_labels(y + 0.5 * np.random.default_rng(0).random(y.shape).astype(np.float32), H, W)


def test_motion_residual_tolerates_depth_error_where_the_map_is_seen_at_a_grazing_angle():
    """The map's depth is off by a factor 2 everywhere (the plane rendered at 4 m instead of 2 m):
    along the epipolar line the static plane then seems to move. Where the map's normal says the
    surface is seen at a grazing angle, that depth is not trusted as much (the tolerance along
    the line grows as 1 / |cos|); where it faces the camera, the same error still counts."""
    a, b = _plane_views(0)
    T_prev, T_cur = np.eye(4), _camera_move(0.1)
    wrong = np.full((H, W), 4.0)
    plain = motion_residual(b, a, T_cur, T_prev, CAM, wrong, 1.5, 0.15, 1.0, refine=False)
    rest = np.zeros((H, W), bool)
    rest[10:-10, 10:-10] = True
    assert plain.moving[rest & plain.reliable].mean() > 0.9
    grazing = np.zeros((H, W, 3), np.float32)
    grazing[..., 0] = 1.0                     # normals across the rays: cos ~ 0 (clamped to 0.2)
    g = motion_residual(b, a, T_cur, T_prev, CAM, wrong, 1.5, 0.15, 1.0, refine=False, normal=grazing,
                        grazing_cos_min=0.2)
    assert g.moving[rest & g.reliable].mean() < 0.02
    frontal = np.zeros((H, W, 3), np.float32)
    frontal[..., 2] = -1.0                    # facing the camera: cos = 1, nothing changes
    f = motion_residual(b, a, T_cur, T_prev, CAM, wrong, 1.5, 0.15, 1.0, refine=False, normal=frontal,
                        grazing_cos_min=0.2)
    assert np.array_equal(f.moving, plain.moving)
