"""Optimising randomly initialised 2D Gaussians against one synthetic image with the CPU
rasterizer reaches PSNR >= 30 dB, with the full and with the sampled (r = 0.5) backward pass."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vings_core.render import rasterize_2dgs
from vings_core.types import CameraModel


def _sim_image(width: int, height: int) -> torch.Tensor:
    from vings_core.sim import default_camera, make_scene, render_view
    scene = make_scene("room", seed=0)
    rgb, _, _ = render_view(scene, default_camera(width, height), scene.T_wc([1.0])[0])
    return torch.tensor(rgb / 255.0, dtype=torch.float32)


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return -10.0 * math.log10(float(((a - b) ** 2).mean()))


def fit(target: torch.Tensor, n: int, iters: int, ratio: float, seed: int = 0):
    """Adam on means/quats/log-scales/logit-opacities/colours of ``n`` surfels initialised at
    random on the plane z = 2 in front of the camera (random colours, identity-ish rotations);
    L1 + 0.2 L2 photometric loss; the sampled backward keeps each tile's highest-L1 pixels.
    Returns (final PSNR of a full render, stats of the last training render)."""
    torch.manual_seed(seed)
    H, W = target.shape[:2]
    cam = CameraModel(W, H, fx=0.8 * W, fy=0.8 * W, cx=(W - 1) / 2, cy=(H - 1) / 2)
    z = 2.0
    u, v = torch.rand(n) * W, torch.rand(n) * H
    means = torch.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z,
                         torch.full((n,), z)], -1).requires_grad_(True)
    quats = (torch.tensor([[0.0, 0.0, 0.0, 1.0]]) + 0.1 * torch.randn(n, 4)).requires_grad_(True)
    spacing = z / cam.fx * math.sqrt(W * H / n)
    log_s = torch.full((n, 2), math.log(0.7 * spacing)).requires_grad_(True)
    logit_o = torch.full((n,), 1.0).requires_grad_(True)
    col = torch.rand(n, 3).requires_grad_(True)
    opt = torch.optim.Adam([{"params": [means], "lr": 0.05 * spacing},
                            {"params": [quats], "lr": 0.01}, {"params": [log_s], "lr": 0.02},
                            {"params": [logit_o], "lr": 0.05}, {"params": [col], "lr": 0.02}])

    def render(r: float):
        return rasterize_2dgs(means, quats, log_s.exp(), torch.sigmoid(logit_o), col, np.eye(4),
                              cam, sample_ratio=r)

    stats = {}
    for _ in range(iters):
        out = render(ratio)
        err = out.color - target
        if ratio < 1.0:
            out.set_sample_map(err.detach().abs().sum(-1))
        loss = err.abs().mean() + 0.2 * (err ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        stats = out.stats
    with torch.no_grad():
        return _psnr(render(1.0).color, target), stats


@pytest.mark.parametrize("ratio", [1.0, 0.5])
def test_fit_small_sim_image_reaches_30db(ratio):
    target = _sim_image(64, 48)
    psnr, stats = fit(target, n=3000, iters=150, ratio=ratio)
    assert psnr >= 30.0, psnr
    expected = 64 * 48 if ratio == 1.0 else 64 * 48 // 2   # 4x3 full 16x16 tiles, half of each
    assert stats["bwd_pixels"] == expected


@pytest.mark.slow
@pytest.mark.parametrize("ratio", [1.0, 0.5])
def test_fit_larger_sim_image_reaches_30db(ratio):
    target = _sim_image(160, 120)
    psnr, _ = fit(target, n=20000, iters=400, ratio=ratio)
    assert psnr >= 30.0, psnr
