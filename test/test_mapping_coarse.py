"""Coarse training iterations (mapping.coarse_fraction): the coarse keyframe against a plain loop
reference, its intrinsics against a full-resolution render, and training with them."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vings_core.mapping import Mapper, MapperConfig
from vings_core.mapping.training import coarse_keyframe
from vings_core.types import CameraModel, Keyframe

from test_mapping import room_small  # noqa: F401  (fixture)


def _coarse_reference(kf: Keyframe, f: int):
    """Block by block, pixel by pixel."""
    H, W = kf.camera.height // f, kf.camera.width // f
    img = np.zeros((H, W, 3), np.float32)
    depth = np.zeros((H, W), np.float32)
    var = np.zeros((H, W), np.float32)
    valid = np.zeros((H, W), bool)
    for i in range(H):
        for j in range(W):
            blk = (slice(i * f, (i + 1) * f), slice(j * f, (j + 1) * f))
            img[i, j] = kf.image[blk].reshape(-1, 3).mean(0).numpy()
            d = kf.depth[blk].numpy()
            ok = kf.valid[blk].numpy() & (d > 0)
            valid[i, j] = ok.all()
            depth[i, j] = d.mean() if ok.all() else 0.0
            var[i, j] = kf.inv_depth_var[blk].max()
    return img, depth, var, valid


@pytest.mark.parametrize("f,H,W", [(2, 7, 9), (3, 9, 12)])
def test_coarse_keyframe_matches_the_loop_reference(f, H, W):
    g = torch.Generator().manual_seed(f)
    cam = CameraModel(W, H, 20.0, 21.0, (W - 1) / 2, (H - 1) / 2)
    depth = torch.rand(H, W, generator=g) + 0.5
    depth[1, 1] = 0.0
    valid = torch.rand(H, W, generator=g) > 0.1
    kf = Keyframe(5, torch.rand(H, W, 3, generator=g), torch.eye(4, dtype=torch.float64), depth,
                  torch.rand(H, W, generator=g), valid, cam, index=3)
    c = coarse_keyframe(kf, f)
    img, d, v, ok = _coarse_reference(kf, f)
    assert (c.camera.width, c.camera.height) == (W // f, H // f) and c.stamp_ns == 5 and c.index == 3
    assert np.allclose(c.image.numpy(), img, atol=1e-6) and np.allclose(c.depth.numpy(), d, atol=1e-6)
    assert np.array_equal(c.inv_depth_var.numpy(), v) and np.array_equal(c.valid.numpy(), ok)
    # OpenCV pixel centres: full-resolution pixel x lies at coarse (x + 0.5) / f - 0.5
    X = np.array([0.3, -0.2, 2.0])
    u_full = cam.fx * X[0] / X[2] + cam.cx
    u_c = c.camera.fx * X[0] / X[2] + c.camera.cx
    assert u_c == pytest.approx((u_full + 0.5) / f - 0.5)


def test_a_splat_renders_where_the_coarse_intrinsics_project_it():
    """One small opaque splat: the alpha centroid of its coarse render is its full-resolution
    centroid mapped by (x + 0.5) / f - 0.5 (the coarse camera keeps OpenCV pixel centres)."""
    from vings_core.render import rasterize_2dgs
    cam = CameraModel(96, 64, 80.0, 80.0, 47.3, 30.8)
    kf = Keyframe(1, torch.zeros(64, 96, 3), torch.eye(4, dtype=torch.float64), torch.ones(64, 96),
                  torch.zeros(64, 96), torch.ones(64, 96, dtype=torch.bool), cam)
    c = coarse_keyframe(kf, 2).camera

    def centroid(camera):
        out = rasterize_2dgs(torch.tensor([[0.13, -0.07, 2.0]]), torch.tensor([[0.0, 0, 0, 1]]),
                             torch.full((1, 2), 0.05), torch.tensor([0.99]), torch.ones(1, 3),
                             torch.eye(4), camera)
        a = out.alpha.detach().numpy().astype(np.float64)
        ys, xs = np.mgrid[0:a.shape[0], 0:a.shape[1]]
        return (a * xs).sum() / a.sum(), (a * ys).sum() / a.sum()
    xf, yf = centroid(cam)
    xc, yc = centroid(c)
    assert xc == pytest.approx((xf + 0.5) / 2 - 0.5, abs=0.05)
    assert yc == pytest.approx((yf + 0.5) / 2 - 0.5, abs=0.05)


def test_training_with_coarse_iterations_fits_the_keyframe(room_small):
    cam, frames = room_small
    m = Mapper(MapperConfig(points_per_keyframe=2500, iters_per_keyframe=30, sample_ratio=1.0,
                            coarse_fraction=0.6))
    m.add_keyframe(frames[0])
    before = m.render(frames[0].T_wc.numpy(), cam)["color"]
    m.train()
    after = m.render(frames[0].T_wc.numpy(), cam)["color"]
    img = frames[0].image.numpy()

    def psnr(x):
        return -10 * np.log10(((np.clip(x, 0, 1) - img) ** 2).mean())
    assert psnr(after) > psnr(before) + 1.5
    assert m.state.render_count == 30
