"""Gauss-Newton steps for single-to-multi pose refinement (dense direct alignment on a render).

A render of keyframe ``r`` is linearised in the motion of its content relative to the camera:
a pixel ``u`` whose content sits at ``X(u)`` (camera-``r`` frame, m, from the rendered expected
depth) and moves by the small twist ``delta = (v, w)`` (``X -> X + v + w x X``) changes colour by
``-grad I(u) . d pi/dX . [I | -[X]x] delta`` and relative depth by that shift of the depth image
plus the point's own ``z`` motion. Which twist a pixel's content undergoes follows ID(g): with
``T_k <- T_k exp(xi_k)`` (camera-frame deltas, ``[rho, phi]`` order) and owner ``k``'s Gaussians
moving with their keyframe, content of owner ``k`` moves in camera ``r`` by
``Ad(T_r^-1 T_k) xi_k - xi_r``; content of ``r`` itself moves with the camera (no motion), content
of owners held still moves by ``-xi_r``. Per pixel the owners blend with their share of the
rendered alpha (``w_k(u)``, from renders of owner indicator colours).

Pure functions; the mapper (:meth:`Mapper.refine_poses`) renders and calls them.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..geometry import skew
from ..types import CameraModel


def se3_adjoint(T: torch.Tensor) -> torch.Tensor:
    """``(..., 4, 4)`` pose -> ``(..., 6, 6)`` adjoint for twists ``[rho, phi]``:
    ``exp(Ad(T) xi) = T exp(xi) T^-1``."""
    R = T[..., :3, :3]
    A = torch.zeros(T.shape[:-2] + (6, 6), dtype=T.dtype)
    A[..., :3, :3] = R
    A[..., :3, 3:] = skew(T[..., :3, 3]) @ R
    A[..., 3:, 3:] = R
    return A


def blur_image(x: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """``(H, W)`` or ``(H, W, C)`` -> Gaussian blur of std ``sigma_px`` pixels (replicate edges);
    ``sigma_px <= 0`` returns ``x``."""
    if sigma_px <= 0:
        return x
    r = max(1, int(round(3 * sigma_px)))
    g = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype) / sigma_px) ** 2)
    g = g / g.sum()
    img = x[None, None] if x.ndim == 2 else x.permute(2, 0, 1)[:, None]
    img = F.pad(img, (r, r, r, r), mode="replicate")
    img = F.conv2d(F.conv2d(img, g.view(1, 1, 1, -1)), g.view(1, 1, -1, 1))
    return img[0, 0] if x.ndim == 2 else img[:, 0].permute(1, 2, 0)


def image_gradient(x: torch.Tensor) -> torch.Tensor:
    """``(H, W, C)`` -> ``(H, W, C, 2)`` central differences ``(d/du, d/dv)`` per pixel (one-sided
    at the border)."""
    gu = torch.zeros_like(x)
    gv = torch.zeros_like(x)
    gu[:, 1:-1] = 0.5 * (x[:, 2:] - x[:, :-2])
    gu[:, 0], gu[:, -1] = x[:, 1] - x[:, 0], x[:, -1] - x[:, -2]
    gv[1:-1] = 0.5 * (x[2:] - x[:-2])
    gv[0], gv[-1] = x[1] - x[0], x[-1] - x[-2]
    return torch.stack([gu, gv], -1)


def point_jacobians(u: torch.Tensor, v: torch.Tensor, z: torch.Tensor,
                    camera: CameraModel) -> tuple[torch.Tensor, torch.Tensor]:
    """For pixels ``(u, v)`` (``(P,)``, px) whose content lies at depth ``z`` (m, camera frame):
    ``d(u, v)/d delta`` ``(P, 2, 6)`` and ``dz/d delta`` ``(P, 6)`` of the motion
    ``X -> X + v + w x X`` (closed form of ``d pi/dX [I | -[X]x]``)."""
    z = z.clamp_min(1e-6)
    x = (u - camera.cx) / camera.fx * z
    y = (v - camera.cy) / camera.fy * z
    iz = 1.0 / z
    xz, yz = x * iz, y * iz
    o = torch.zeros_like(z)
    ju = camera.fx * torch.stack([iz, o, -xz * iz, -xz * yz, 1 + xz * xz, -yz], -1)
    jv = camera.fy * torch.stack([o, iz, -yz * iz, -(1 + yz * yz), xz * yz, xz], -1)
    jz = torch.stack([o, o, torch.ones_like(z), y, -x, o], -1)
    return torch.stack([ju, jv], 1), jz


@dataclass
class GNTerms:
    """One render's normal-equation pieces in the content twist ``delta`` (camera-``r`` frame):
    per used pixel ``Q = J^T Omega J`` ``(P, 6, 6)``, ``q = J^T Omega r`` ``(P, 6)``, the pixels'
    flat indices ``(P,)`` and the robust cost ``sum rho(r)`` (float)."""

    Q: torch.Tensor
    q: torch.Tensor
    pix: torch.Tensor
    cost: float


def pixel_terms(color: torch.Tensor, exp_depth: torch.Tensor, alpha: torch.Tensor, target: torch.Tensor,
                target_depth: torch.Tensor, depth_weight: torch.Tensor, depth_ok: torch.Tensor,
                camera: CameraModel, sigma_rgb: float, sigma_depth_rel: float, huber: float,
                blur_px: float, stride: int = 1) -> GNTerms:
    """Gauss-Newton terms of the residuals ``render - keyframe`` of one render.

    Colour ``(H, W, 3)`` in [0, 1] (noise ``sigma_rgb``) on pixels with ``alpha > 0.5``; relative
    depth ``(D_hat/alpha - d)/d`` (noise ``sigma_depth_rel / sqrt(depth_weight)``) where also
    ``depth_ok``. Both images are blurred by ``blur_px`` (wider convergence basin); the gradient is
    the mean of the render's and the keyframe's (efficient second-order minimisation). Huber
    weights at ``huber`` noise stds (iteratively re-weighted least squares). ``stride``: only
    pixels on that grid are used (gradients still from the full images)."""
    f64 = torch.float64
    col = blur_image(color.detach().to(f64), blur_px)
    tgt = blur_image(target.to(f64), blur_px)
    ed = exp_depth.detach().to(f64)
    a = alpha.detach().to(f64)
    used = (a > 0.5) & torch.isfinite(ed) & (ed > 0)
    if stride > 1:
        grid = torch.zeros_like(used)
        grid[::stride, ::stride] = True
        used &= grid
    idx = used.reshape(-1).nonzero()[:, 0]
    # gradients: the mean of the render's and the keyframe's (ESM), at the used pixels only
    g = 0.5 * (image_gradient(col) + image_gradient(tgt)).reshape(-1, 3, 2)[idx]      # (P, 3, 2)
    # the depth image is not blurred (edges would mix foreground and background depths)
    gd = image_gradient(ed[..., None]).reshape(-1, 2)[idx]                           # (P, 2)
    W = color.shape[1]
    z = ed.reshape(-1)[idx]
    Ju, Jz = point_jacobians((idx % W).to(f64), (idx // W).to(f64), z, camera)
    # small batched matmuls are slow on the CPU: the 2-term products written out
    Jc = -(g[..., 0:1] * Ju[:, None, 0] + g[..., 1:2] * Ju[:, None, 1]) / sigma_rgb  # (P, 3, 6)
    rc = (col - tgt).reshape(-1, 3)[idx] / sigma_rgb                                # (P, 3)
    d = target_depth.to(f64).reshape(-1)[idx]
    dok = (depth_ok.reshape(-1)[idx] & (d > 0)).to(f64)
    wd = depth_weight.to(f64).reshape(-1)[idx].clamp_min(0) * dok
    sd = sigma_depth_rel / wd.clamp_min(1e-12).sqrt()
    inv_d = 1.0 / torch.where(d > 0, d, torch.ones_like(d))
    Jd = (Jz - gd[:, 0:1] * Ju[:, 0] - gd[:, 1:2] * Ju[:, 1]) * (dok * inv_d / sd)[:, None]
    rd = (z - d) * inv_d / sd * dok
    J = torch.cat([Jc, Jd[:, None]], 1)                                    # (P, 4, 6)
    r = torch.cat([rc, rd[:, None]], 1)                                    # (P, 4)
    ar = r.abs()
    w = torch.where(ar <= huber, torch.ones_like(ar), huber / ar.clamp_min(1e-12))
    cost = torch.where(ar <= huber, 0.5 * r ** 2, huber * (ar - 0.5 * huber)).sum()
    Jw = J * w[..., None]
    Q = (Jw[:, :, :, None] * J[:, :, None, :]).sum(1)
    q = (Jw * r[..., None]).sum(1)
    return GNTerms(Q=Q, q=q, pix=idx, cost=float(cost))


def owner_system(terms: GNTerms, coeff: torch.Tensor, adj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normal equations ``H xi = -b`` in the owners' camera-frame deltas ``xi`` ``(V*6,)``.

    ``coeff`` ``(P, V)``: per used pixel, how each owner's delta enters the content twist
    (``delta(u) = sum_k coeff[u, k] adj[k] xi_k``); ``adj`` ``(V, 6, 6)``."""
    V = coeff.shape[1]
    M = torch.einsum("pk,pl,pij->klij", coeff, coeff, terms.Q)            # (V, V, 6, 6)
    m = torch.einsum("pk,pi->ki", coeff, terms.q)                         # (V, 6)
    H = adj.transpose(1, 2)[:, None] @ M @ adj[None]                      # A_k^T M_kl A_l
    b = (adj.transpose(1, 2) @ m[:, :, None])[:, :, 0]
    return H.permute(0, 2, 1, 3).reshape(V * 6, V * 6), b.reshape(V * 6)


def damped_step(H: torch.Tensor, b: torch.Tensor, free: torch.Tensor, damping: float,
                max_trans: float, max_rot: float) -> torch.Tensor:
    """Levenberg-Marquardt step ``(V, 6)`` of the free owners (``free`` ``(V,)`` bool; held ones get
    0): ``(H + damping diag H + eps I) xi = -b`` (``eps`` 1e-9 of the largest diagonal entry),
    shrunk as a whole so no owner's translation exceeds ``max_trans`` (m) nor its rotation
    ``max_rot`` (rad) (trust region)."""
    V = free.numel()
    step = torch.zeros(V, 6, dtype=H.dtype)
    cols = free.repeat_interleave(6)
    if not bool(cols.any()):
        return step
    Hf = H[cols][:, cols]
    bf = b[cols]
    dg = torch.diagonal(Hf)
    eps = 1e-9 * float(dg.max().clamp_min(1e-30))
    A = Hf + torch.diag(damping * dg + eps)
    try:
        x = -torch.linalg.solve(A, bf)
    except RuntimeError:          # singular: nothing observed
        return step
    if not bool(torch.isfinite(x).all()):
        return step
    step[free] = x.view(-1, 6)
    lim = max(float(step[:, :3].norm(dim=1).max()) / max_trans, float(step[:, 3:].norm(dim=1).max()) / max_rot)
    if lim > 1.0:
        step = step / lim
    return step
