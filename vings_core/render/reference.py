"""Slow, obvious pure-torch reference of the 2DGS rasterizer (autograd for every gradient).

It states the same image model as the numba kernels in a different way, so the two check each
other: the pixel ray ``r = K^-1 (x, y, 1)`` is intersected with the surfel plane in the camera
frame (``X = r (n . p_c) / (n . r)``), and the hit point is expressed in the splat's tangent axes
(``X - p_c = u s_u t_u + v s_v t_v``), instead of the homogeneous-plane algebra on ``M`` of the kernels.
Compositing is dense: every Gaussian x every pixel, with cumulative products. With ``tile_cull``
the pixels are processed per 16x16 tile, each with the Gaussians whose (torch-computed,
conservative) screen box touches it; the result is identical, only faster and lighter. Only for
small scenes and tests; the benchmark times it at 10k Gaussians.
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from ..geometry import quat_to_rotmat
from ..types import CameraModel
from .kernels import ALPHA_MAX, ALPHA_MIN, DIST_FAR, DIST_NEAR, T_MIN, TILE
from .sh import sh_to_color


def _composite(xy: torch.Tensor, p_c: torch.Tensor, Rc: torch.Tensor, scales: torch.Tensor,
               opac: torch.Tensor, rgb: torch.Tensor, normals: torch.Tensor, cam: CameraModel,
               bg: torch.Tensor, near: float, far: float, loss: Optional[torch.Tensor]):
    """Render pixels ``xy (P, 2)`` from Gaussians given in the camera frame. Returns per-pixel
    ``(rgb (P,3), depth, normal (P,3), alpha, dist, count)`` and per-Gaussian
    ``(contribution, touched, error)`` in the input order."""
    N = p_c.shape[0]
    P = xy.shape[0]
    dt = p_c.dtype
    if N == 0:
        z = torch.zeros(P, dtype=dt)
        return (bg.expand(P, 3).clone(), z, torch.zeros(P, 3, dtype=dt), z, z, z,
                torch.zeros(0, dtype=dt), torch.zeros(0, dtype=dt), torch.zeros(0, dtype=dt))
    order = torch.argsort(p_c[:, 2].detach(), stable=True)
    p_c, Rc, scales, opac, rgb, normals = (a[order] for a in (p_c, Rc, scales, opac, rgb, normals))
    rays = torch.stack([(xy[:, 0] - cam.cx) / cam.fx, (xy[:, 1] - cam.cy) / cam.fy,
                        torch.ones(P, dtype=dt)], -1)                         # (P, 3)
    # the splat plane is spanned by its scaled tangent axes a, b (orthonormal frame times scales,
    # unless T_cw itself carries a non-rigid perturbation, as in a raw T_cw gradient)
    a = Rc[:, :, 0] * scales[:, 0:1]
    b = Rc[:, :, 1] * scales[:, 1:2]
    n_plane = torch.linalg.cross(a, b)                                        # (N, 3)
    denom = n_plane @ rays.T                                                  # (N, P)
    ok = denom != 0
    denom_s = torch.where(ok, denom, torch.ones_like(denom))
    t_hit = (n_plane * p_c).sum(-1, keepdim=True) / denom_s                   # (N, P) = hit z
    X = t_hit[..., None] * rays[None]                                         # (N, P, 3)
    d = X - p_c[:, None, :]
    # splat coordinates: d = u a + v b, solved through the 2x2 normal equations
    gaa, gab, gbb = (a * a).sum(-1, keepdim=True), (a * b).sum(-1, keepdim=True), (b * b).sum(-1, keepdim=True)
    da, db = (d * a[:, None, :]).sum(-1), (d * b[:, None, :]).sum(-1)
    det = gaa * gbb - gab * gab
    u = (gbb * da - gab * db) / det
    v = (gaa * db - gab * da) / det
    rho3 = u * u + v * v
    # centres at or behind the near plane are culled below; a safe z keeps their (unused) screen
    # position finite, else 0 * inf would put NaN into the gradients
    zc = torch.where(p_c[:, 2] > near, p_c[:, 2], torch.ones_like(p_c[:, 2]))
    mx = cam.fx * p_c[:, 0] / zc + cam.cx
    my = cam.fy * p_c[:, 1] / zc + cam.cy
    rho2 = 2.0 * ((xy[None, :, 0] - mx[:, None]) ** 2 + (xy[None, :, 1] - my[:, None]) ** 2)
    use3 = ok & (t_hit > near) & (rho3 < rho2)
    rho = torch.where(use3, rho3, rho2)
    depth = torch.where(use3, t_hit, p_c[:, 2:3].expand(N, P))
    alpha = torch.clamp(opac[:, None] * torch.exp(-0.5 * rho), max=ALPHA_MAX)
    visible = ((p_c[:, 2] > near) & (p_c[:, 2] < far))[:, None]
    alpha = torch.where(visible & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        include = torch.cumprod(1.0 - alpha, dim=0) >= T_MIN   # monotone: a prefix per pixel
    alpha = alpha * include
    trans = torch.cumprod(1.0 - alpha, dim=0)
    T_before = torch.cat([torch.ones(1, P, dtype=dt), trans[:-1]], 0)
    w = alpha * T_before                                                      # (N, P)
    T_final = trans[-1]
    out_rgb = w.T @ rgb + T_final[:, None] * bg
    out_depth = (w * depth).sum(0)
    out_normal = w.T @ normals
    out_alpha = 1.0 - T_final
    # where nothing is composited the depth may be 0 (a centre in the camera plane): 0 * inf = NaN
    depth_m = torch.where(w > 0, depth, torch.ones_like(depth))
    m = DIST_FAR / (DIST_FAR - DIST_NEAR) * (1.0 - DIST_NEAR / depth_m)
    wm, wm2 = w * m, w * m * m
    d1_prev = torch.cumsum(wm, 0) - wm
    d2_prev = torch.cumsum(wm2, 0) - wm2
    out_dist = (w * (m * m * (1.0 - T_before) + d2_prev - 2.0 * m * d1_prev)).sum(0)
    touched_mask = (alpha > 0).to(dt)
    count = touched_mask.sum(0)
    inv = torch.empty_like(order)
    inv[order] = torch.arange(N)
    contrib = w.sum(1)[inv]
    touched = touched_mask.sum(1)[inv]
    err = (w * loss[None, :]).sum(1)[inv] if loss is not None else torch.zeros(N, dtype=dt)
    return out_rgb, out_depth, out_normal, out_alpha, out_dist, count, contrib, touched, err


def _screen_boxes(p_c: torch.Tensor, Rc: torch.Tensor, scales: torch.Tensor, opac: torch.Tensor,
                  cam: CameraModel) -> torch.Tensor:
    """Conservative ``(N, 4)`` pixel boxes ``(x0, x1, y0, y1)`` (float) outside which a Gaussian
    has alpha < 1/255: the box of the projected cut-off ellipse (dual conic) united with the
    low-pass disc, padded by one pixel; the whole image when the ellipse reaches the camera plane."""
    with torch.no_grad():
        K = torch.tensor(cam.K, dtype=p_c.dtype)
        A = torch.stack([Rc[:, :, 0] * scales[:, 0:1], Rc[:, :, 1] * scales[:, 1:2], p_c], -1)
        M = K @ A
        lk = torch.log(opac.clamp_min(1e-30) * 255.0).clamp_min(0)
        k2 = 2 * lk
        Dm = M @ torch.diag_embed(torch.stack([k2, k2, -torch.ones_like(k2)], -1)) @ M.transpose(1, 2)
        d22 = Dm[:, 2, 2]
        d22s = torch.where(d22 < 0, d22, -torch.ones_like(d22))
        ecx, ecy = Dm[:, 0, 2] / d22s, Dm[:, 1, 2] / d22s
        hx = (ecx ** 2 - Dm[:, 0, 0] / d22s).clamp_min(0).sqrt()
        hy = (ecy ** 2 - Dm[:, 1, 1] / d22s).clamp_min(0).sqrt()
        mx, my = M[:, 0, 2] / M[:, 2, 2], M[:, 1, 2] / M[:, 2, 2]
        rl = lk.sqrt()
        box = torch.stack([torch.minimum(ecx - hx, mx - rl), torch.maximum(ecx + hx, mx + rl),
                           torch.minimum(ecy - hy, my - rl), torch.maximum(ecy + hy, my + rl)], -1)
        full = torch.tensor([-1.0, cam.width + 1.0, -1.0, cam.height + 1.0], dtype=p_c.dtype)
        box = torch.where((d22 < 0)[:, None], box, full)
        return box + torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=p_c.dtype)


def render_reference(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                     opacities: torch.Tensor, colors: torch.Tensor, T_cw: torch.Tensor,
                     camera: CameraModel, *, sh_degree: Optional[int] = None,
                     pose_delta: Optional[torch.Tensor] = None,
                     background: Optional[torch.Tensor] = None, loss_map: Optional[torch.Tensor] = None,
                     near: float = 0.01, far: float = 1e3, tile_cull: bool = False) -> dict:
    """Render like :func:`vings_core.render.rasterize_2dgs`, densely and with torch autograd.

    Same arguments and conventions. Returns a dict with ``color (H,W,3)``, ``depth``, ``normal
    (H,W,3)``, ``alpha``, ``distortion``, ``n_contrib`` (per-pixel count) and per-Gaussian
    ``contribution``, ``pixels_touched``, ``error``.
    """
    from .rasterize import _prepare
    means, quats, scales, opacities, colors, T_cw, pose_delta = _prepare(
        means, quats, scales, opacities, colors, T_cw, camera, sh_degree, pose_delta, near, far)
    dt = means.dtype
    H, W = camera.height, camera.width
    T = torch.as_tensor(T_cw, dtype=torch.float64)
    if pose_delta is not None:
        from .rasterize import apply_pose_delta
        T = apply_pose_delta(pose_delta, T)
    T = T.to(dt)
    R_cw, t_cw = T[:3, :3], T[:3, 3]
    p_c = means @ R_cw.T + t_cw
    Rc = torch.matmul(R_cw, quat_to_rotmat(quats))
    if sh_degree is not None:
        cam_center = -R_cw.T @ t_cw
        rgb = sh_to_color(sh_degree, colors, means - cam_center)
    else:
        rgb = colors
    n = Rc[:, :, 2]
    n = torch.where(((n * p_c).sum(-1, keepdim=True) > 0).detach(), -n, n)
    bg = torch.zeros(3, dtype=dt) if background is None else torch.as_tensor(background).to(dt)
    loss = None if loss_map is None else torch.as_tensor(loss_map).to(dt).reshape(-1)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dt), torch.arange(W, dtype=dt), indexing="ij")
    xy = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
    if not tile_cull:
        rgb_o, dep, nrm, alp, dist, cnt, contrib, touched, err = _composite(
            xy, p_c, Rc, scales, opacities, rgb, n, camera, bg, near, far, loss)
    else:
        box = _screen_boxes(p_c, Rc, scales, opacities, camera)
        parts = []
        N = means.shape[0]
        contrib = torch.zeros(N, dtype=dt)
        touched = torch.zeros(N, dtype=dt)
        err = torch.zeros(N, dtype=dt)
        pix_index = []
        for ty in range(math.ceil(H / TILE)):
            for tx in range(math.ceil(W / TILE)):
                x0, y0 = tx * TILE, ty * TILE
                x1, y1 = min(x0 + TILE, W) - 1, min(y0 + TILE, H) - 1
                idx = torch.nonzero((box[:, 0] <= x1) & (box[:, 1] >= x0) & (box[:, 2] <= y1)
                                    & (box[:, 3] >= y0))[:, 0]
                pid = (torch.arange(y0, y1 + 1)[:, None] * W + torch.arange(x0, x1 + 1)[None]).reshape(-1)
                r = _composite(xy[pid], p_c[idx], Rc[idx], scales[idx], opacities[idx], rgb[idx],
                               n[idx], camera, bg, near, far, None if loss is None else loss[pid])
                parts.append(r[:6])
                pix_index.append(pid)
                contrib = contrib.index_add(0, idx, r[6])
                touched = touched.index_add(0, idx, r[7])
                err = err.index_add(0, idx, r[8])
        pid = torch.cat(pix_index)
        inv = torch.empty_like(pid)
        inv[pid] = torch.arange(pid.numel())
        rgb_o, dep, nrm, alp, dist, cnt = (torch.cat([p[k] for p in parts], 0)[inv] for k in range(6))
    return {
        "color": rgb_o.reshape(H, W, 3), "depth": dep.reshape(H, W), "normal": nrm.reshape(H, W, 3),
        "alpha": alp.reshape(H, W), "distortion": dist.reshape(H, W),
        "n_contrib": cnt.reshape(H, W), "contribution": contrib, "pixels_touched": touched,
        "error": err,
    }
