"""Map growth and pruning when a keyframe arrives (paper "2D Gaussian Map"): the keyframe is
checked, the map is rendered from it, Gaussians that conflict with its observation are deleted and
new ones are added from its depth where the render's accumulation is low.

Frames: ``T_wc`` camera-to-world; Gaussians in the world frame (m). Vectorised over Gaussians and
pixels.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Optional

import torch

from ..errors import InputError
from ..geometry import check_rigid_pose, pose_inverse
from ..types import CameraModel, Keyframe
from ..util import log
from .gaussians import GaussianMap
from .init import (depth_normals, empty_mask, fill_depth, gaussians_from_pixels, num_to_add, sample_pixels,
                   static_mask, usable_depth_mask)
from .losses import l1_map
from .state import MapState
from ..profiling import profiled


def check_keyframe(kf: Keyframe, known: dict[int, object], camera: Optional[CameraModel]) -> None:
    """Raise :class:`InputError` unless ``kf`` can be added: a new stamp (not in ``known``; an older
    stamp than the newest known is fine: a keyframe sent again after a mapper restart), an
    undistorted camera equal to ``camera`` (the first keyframe's; None before it), float RGB in
    [0, 1], depth / variance / validity of the image's size, finite depth, non-negative variance
    and a rigid ``T_wc``."""
    if not isinstance(kf, Keyframe):
        raise InputError(f"add_keyframe: expected a Keyframe, got {type(kf).__name__}")
    if int(kf.stamp_ns) in known:
        raise InputError(f"add_keyframe: keyframe {kf.stamp_ns} was already added")
    what = f"add_keyframe {kf.stamp_ns}"
    if kf.camera.is_distorted:
        raise InputError(f"{what}: camera has lens distortion; undistort first")
    if camera is not None and kf.camera != camera:
        c, f = kf.camera, camera
        raise InputError(f"{what}: camera model differs from the first keyframe's ({c.width}x{c.height} "
                         f"fx {c.fx:g} fy {c.fy:g} cx {c.cx:g} cy {c.cy:g} vs {f.width}x{f.height} "
                         f"fx {f.fx:g} fy {f.fy:g} cx {f.cx:g} cy {f.cy:g})")
    img = kf.image
    if img.ndim != 3 or img.shape[2] < 3:
        raise InputError(f"{what}: image must be (H, W, 3), got {tuple(img.shape)}")
    if not img.dtype.is_floating_point:
        raise InputError(f"{what}: image must be float RGB in [0, 1], got dtype {img.dtype} "
                         f"(8-bit images: divide by 255)")
    if not bool(torch.isfinite(img).all()):
        raise InputError(f"{what}: image has non-finite values")
    lo, hi = float(img.min()), float(img.max())
    if lo < -1e-3 or hi > 1.0 + 1e-3:
        raise InputError(f"{what}: image values must lie in [0, 1], got [{lo:g}, {hi:g}]")
    H, W = kf.camera.height, kf.camera.width
    for name in ("depth", "inv_depth_var", "valid"):
        t = getattr(kf, name)
        if tuple(t.shape) != (H, W):
            raise InputError(f"{what}: {name} must have shape ({H}, {W}), got {tuple(t.shape)}")
    check_rigid_pose(kf.T_wc, f"keyframe {kf.stamp_ns} T_wc", tol=1e-2, project=True)
    if not bool(torch.isfinite(kf.depth).all()):
        raise InputError(f"{what}: depth has non-finite values (use 0 for invalid)")
    var = kf.inv_depth_var
    if bool(torch.isnan(var).any()) or bool((var < 0).any()):
        raise InputError(f"{what}: inv_depth_var has NaN or negative values (use inf for unknown)")


@torch.no_grad()
@profiled("mapping", "densify")
def densify(st: MapState, kf: Keyframe) -> dict:
    """Delete the Gaussians that conflict with keyframe ``kf`` (:func:`conflicts`) and add new
    ones from its depth where the render's accumulated opacity is low (or the observed surface
    lies clearly in front of the rendered one). Updates ``st.gm``, the keyframe's loss map and the
    counters; returns ``added``, ``deleted``, ``low_fraction`` and the deletions per rule."""
    cfg = st.cfg
    cam = kf.camera
    T_cw = pose_inverse(kf.T_wc)
    usable = usable_depth_mask(kf, cfg.max_depth, cfg.max_depth_rel_std)
    if not bool(usable.any()):
        log.warning("keyframe %d: no pixel has usable depth (missing, or too uncertain: e.g. too "
                    "little parallax yet); no Gaussians from it", int(kf.stamp_ns))
    depth = kf.depth
    # pixels that may seed Gaussians: usable depth, and (fill_unknown_depth) pixels whose depth is
    # unknown (dropped as uncertain, not known empty) at depth interpolated from the usable ones
    seed, seed_depth = usable, depth
    if cfg.fill_unknown_depth and bool(usable.any()):
        unknown = ~usable & ~empty_mask(kf, cfg.max_depth) & static_mask(kf)
        if bool(unknown.any()):
            seed = usable | unknown
            seed_depth = fill_depth(depth, usable)
    n_del = 0
    rules: dict = {}
    if len(st.gm):
        out = st.rasterize(st.gm, T_cw, cam)
        l1 = l1_map(out.color, kf.image)
        # the error map that drives sampling and scores leaves the dynamic pixels out
        st.loss_maps[kf.stamp_ns] = torch.where(static_mask(kf), l1, 0.0).to(torch.float32)
        exp_d = out.depth / out.alpha.clamp_min(1e-10)
        dmask, rules = conflicts(st, out, l1, exp_d, kf, usable, T_cw)
        n_del = int(dmask.sum())
        if n_del:
            st.gm = st.gm.remove(dmask)
            out = st.rasterize(st.gm, T_cw, cam)
        alpha = out.alpha
        exp_d = out.depth / alpha.clamp_min(1e-10)
        # low accumulation, or the observed surface lies clearly in front of what is rendered
        behind = usable & (alpha > cfg.add_alpha_threshold) & (exp_d > depth * (1 + cfg.delete_depth_rel))
        low = seed & ((alpha < cfg.add_alpha_threshold) | behind)
    else:
        low = seed
    n_add = num_to_add(low, cfg.points_per_keyframe)
    if n_add > 0:
        rc = sample_pixels(low, n_add, st.rng)
        src = kf if seed_depth is depth else replace(kf, depth=seed_depth)
        new = gaussians_from_pixels(src, rc, cfg.sh_degree, cfg.init_opacity, cfg.init_scale_factor,
                                    cfg.min_scale_px, cfg.max_scale_px, score_since=st.render_count,
                                    normals_cam=depth_normals(seed_depth, cam), window=cfg.window_size)
        st.gm = GaussianMap.concat([st.gm, new.to(st.device)])
        n_add = len(rc)                  # at most one per low pixel
    st.counters["added"] += n_add
    st.counters["deleted"] += n_del
    return {"added": n_add, "deleted": n_del, "low_fraction": float(low.float().mean()), "delete_rules": dict(rules)}


def conflicts(st: MapState, out, l1: torch.Tensor, exp_d: torch.Tensor, kf: Keyframe, usable: torch.Tensor,
              T_cw: torch.Tensor) -> tuple[torch.Tensor, dict[str, int]]:
    """Gaussians of ``st.gm`` to delete for a new keyframe: ``(N,)`` bool and the count per rule.

    Each centre is projected into the keyframe. Inside the frustum a Gaussian is removed when
    (a) it floats in front of the observed surface: its depth ``z < D_min (1 - delete_depth_rel)``,
    ``D_min`` the nearest observed depth in the 5x5 neighbourhood of its pixel (so splats on an
    object's silhouette are not taken for floaters), while the render there is in front of the
    observed surface by the same margin; or (b) it lies on the observed surface
    (``|z - D| < delete_depth_rel D``) and the RGB error stays above ``delete_rgb`` over the whole
    3x3 neighbourhood (a persistent error, not a one-pixel misalignment at an edge); or (c) it is
    seen (contribution > 0) with a projected radius above ``delete_max_radius_frac`` x diagonal.
    Gaussians with non-finite parameters are removed too.
    """
    cfg = st.cfg
    gm = st.gm
    cam = kf.camera
    H, W = cam.height, cam.width
    R = T_cw[:3, :3].to(torch.float32)
    t = T_cw[:3, 3].to(torch.float32)
    pc = gm.means @ R.T + t
    finite = gm.finite_rows()
    pc = torch.where(finite[:, None], pc, torch.zeros((), dtype=pc.dtype))
    z = pc[:, 2]
    front = z > 1e-3
    u = torch.round(pc[:, 0] / z.clamp_min(1e-6) * cam.fx + cam.cx)
    v = torch.round(pc[:, 1] / z.clamp_min(1e-6) * cam.fy + cam.cy)
    inside = front & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    ui = u.clamp(0, W - 1).long()
    vi = v.clamp(0, H - 1).long()
    D = kf.depth
    Dinf = torch.where(usable, D, torch.full_like(D, float("inf")))
    Dmin = -torch.nn.functional.max_pool2d(-Dinf[None, None], 5, stride=1, padding=2)[0, 0]
    l1min = -torch.nn.functional.max_pool2d(-l1[None, None], 3, stride=1, padding=1)[0, 0]
    ok = inside & usable[vi, ui]
    rel = cfg.delete_depth_rel
    Dg = D[vi, ui]
    render_in_front = exp_d[vi, ui] < Dg * (1 - rel)
    floater = ok & (z < Dmin[vi, ui] * (1 - rel)) & render_in_front
    on_surface = ok & ((z - Dg).abs() < rel * Dg) & (l1min[vi, ui] > cfg.delete_rgb)
    # only splats whose centre projects into the image and that are actually seen: Gaussians beside
    # or behind the camera plane have huge clipped screen boxes but are not in this view
    too_big = inside & (out.contribution.to(st.device) > 0) & \
        (out.radii.to(st.device) > cfg.delete_max_radius_frac * math.hypot(W, H))
    rules = {"floater": int(floater.sum()), "wrong_colour": int(on_surface.sum()), "too_big": int(too_big.sum()),
             "non_finite": int((~finite).sum())}
    return floater | on_surface | too_big | ~finite, rules
