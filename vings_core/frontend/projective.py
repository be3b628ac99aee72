"""Pinhole projection of inverse-depth pixels between keyframes, with analytic Jacobians.

Conventions (all torch, float64 in the BA):

* Poses are world-to-camera ``T_cw`` (4x4), perturbed on the left: ``T_cw <- exp(xi) T_cw`` with
  ``xi = [rho, phi]`` (the paper's :math:`\\xi_w^{c_k}`).
* A BA pixel of keyframe ``i`` is a grid point ``uv`` (working-resolution pixels) with inverse depth
  ``d``. Its homogeneous point is ``X = [x_n, y_n, 1, d]`` with ``x_n = (u - cx) / fx`` etc., so the
  point in camera ``j`` is ``q / d`` with ``q = R_ji [x_n, y_n, 1] + t_ji d`` (``T_ji = T_j T_i^-1``).
  Working with ``q`` keeps points at infinity (``d = 0``) finite.
* The residual of an observation is ``r = u* - pi(q)`` (target minus prediction, pixels).
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from ..geometry import pose_inverse, skew


class Intrinsics(NamedTuple):
    fx: float
    fy: float
    cx: float
    cy: float


def grid_points(width: int, height: int, stride: int = 8, dtype=torch.float64):
    """The BA grid: centres of ``stride`` x ``stride`` blocks of a ``width`` x ``height`` image.

    Returns ``(h, w, uv)``: grid size and ``(h*w, 2)`` pixel coordinates (working resolution,
    row-major), ``uv = stride * index + (stride - 1) / 2``. Pixels right/below the last whole block
    are not covered.
    """
    h, w = height // stride, width // stride
    ys, xs = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    off = (stride - 1) / 2.0
    uv = torch.stack([xs * stride + off, ys * stride + off], -1).reshape(-1, 2)
    return h, w, uv


def normalized_rays(uv: torch.Tensor, K: Intrinsics) -> torch.Tensor:
    """``(..., 2)`` pixels -> ``(..., 3)`` rays ``[x_n, y_n, 1]``."""
    x = (uv[..., 0] - K.cx) / K.fx
    y = (uv[..., 1] - K.cy) / K.fy
    return torch.stack([x, y, torch.ones_like(x)], -1)


def relative_poses(T_cw: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor) -> torch.Tensor:
    """``T_ji = T_j T_i^-1`` for edges ``(ii, jj)``: ``(E, 4, 4)``."""
    return T_cw[jj] @ pose_inverse(T_cw[ii])


def transform_h(T_ji: torch.Tensor, rays: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``q = R_ji ray + t_ji d``. ``T_ji (E,4,4)``, ``rays (P,3)`` or ``(E,P,3)``, ``d (E,P)``."""
    R = T_ji[:, :3, :3]
    t = T_ji[:, None, :3, 3]
    return torch.matmul(rays, R.transpose(-1, -2)) + t * d[..., None]


def project(q: torch.Tensor, K: Intrinsics, min_z: float = 1e-6) -> torch.Tensor:
    """``(..., 3) -> (..., 2)`` pinhole projection (z clamped to ``min_z`` to stay finite)."""
    z = q[..., 2].clamp_min(min_z)
    return torch.stack([K.fx * q[..., 0] / z + K.cx, K.fy * q[..., 1] / z + K.cy], -1)


def adjoint(T: torch.Tensor) -> torch.Tensor:
    """SE(3) adjoint for tangent order ``[rho, phi]``: ``[[R, [t]x R], [0, R]]`` ``(..., 6, 6)``."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    A = torch.zeros(T.shape[:-2] + (6, 6), dtype=T.dtype, device=T.device)
    A[..., :3, :3] = R
    A[..., :3, 3:] = skew(t) @ R
    A[..., 3:, 3:] = R
    return A


class EdgeLinearization(NamedTuple):
    """Residuals and Jacobians of a batch of edges (``E`` edges x ``P`` pixels)."""

    r: torch.Tensor      #: (E, P, 2) residual u* - pi(q) (px)
    Ji: torch.Tensor     #: (E, P, 2, 6) d pi / d xi_i (left perturbation of T_i)
    Jj: torch.Tensor     #: (E, P, 2, 6) d pi / d xi_j
    Jd: torch.Tensor     #: (E, P, 2) d pi / d inverse depth of pixel in i
    valid: torch.Tensor  #: (E, P) bool: point in front of camera j, finite


def project_edges(T_cw: torch.Tensor, d: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                  rays: torch.Tensor, K: Intrinsics) -> tuple[torch.Tensor, torch.Tensor]:
    """Induced flow: where each grid pixel of ``i`` lands in ``j``. Returns ``(uv_j (E,P,2), valid)``.

    A geometric prediction (flow initialisation, edge selection, keyframe distance) with a loose
    validity test; BA costs use :func:`edge_residuals` (the test of :func:`linearize_edges`)."""
    q = transform_h(relative_poses(T_cw, ii, jj), rays, d[ii])
    valid = (q[..., 2] > 1e-6 * torch.clamp(d[ii], min=1e-12)) & (q[..., 2] > 0)
    return project(q, K), valid


MIN_DEPTH_RATIO = 1e-3
"""A BA observation is usable only when the point lies in front of camera ``j`` by more than this
fraction of its depth in ``i`` (``z_j > MIN_DEPTH_RATIO * d_i`` in ``q`` units) and ``d_i > 0``."""


def _edge_projection(T_ji: torch.Tensor, rays: torch.Tensor, di: torch.Tensor, target: torch.Tensor,
                     K: Intrinsics, min_depth_ratio: float):
    """Shared by :func:`edge_residuals` and :func:`linearize_edges` (so the BA's trial cost and its
    linearisation use one validity test and bit-identical residuals): ``(q, xp, yp, iz, r, valid)``;
    ``r`` is 0 where not valid."""
    q = transform_h(T_ji, rays, di)               # (E,P,3)
    X, Y, Z = q[..., 0], q[..., 1], q[..., 2]
    # a point is usable when it lies in front of camera j with positive inverse depth
    valid = (Z > min_depth_ratio * di.abs().clamp_min(1e-12)) & (di > 0) & torch.isfinite(Z)
    Zs = torch.where(valid, Z, torch.ones_like(Z))
    iz = 1.0 / Zs
    xp, yp = X * iz, Y * iz
    r = target - torch.stack([K.fx * xp + K.cx, K.fy * yp + K.cy], -1)
    r = torch.where(valid[..., None], r, torch.zeros_like(r))
    return q, xp, yp, iz, r, valid


def edge_residuals(T_cw: torch.Tensor, d: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                   rays: torch.Tensor, target: torch.Tensor, K: Intrinsics,
                   min_depth_ratio: float = MIN_DEPTH_RATIO) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals ``r = u* - pi(q)`` ``(E,P,2)`` (0 where not valid) and validity ``(E,P)``, exactly
    as :func:`linearize_edges` computes them, without the Jacobians (the BA's cost evaluation)."""
    _, _, _, _, r, valid = _edge_projection(relative_poses(T_cw, ii, jj), rays, d[ii], target, K,
                                            min_depth_ratio)
    return r, valid


def linearize_edges(T_cw: torch.Tensor, d: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                    rays: torch.Tensor, target: torch.Tensor, K: Intrinsics,
                    min_depth_ratio: float = MIN_DEPTH_RATIO,
                    need_ji: bool = True) -> EdgeLinearization:
    """Residuals and analytic Jacobians of ``pi(T_j T_i^-1 X_i(d))`` for all edges at once.

    ``T_cw (M,4,4)``, ``d (M,P)`` inverse depths, ``ii, jj (E,)`` keyframe indices, ``rays (P,3)``,
    ``target (E,P,2)``. With ``q`` as in the module docstring and ``w = d``:
    ``dq/dxi_j = [w I, -[q]x]``, ``dq/dxi_i = -dq/dxi_j Adj(T_ji)``, ``dq/dd = t_ji``; composed with
    ``d pi / d q`` in closed form. ``need_ji=False`` skips ``Ji`` (returned as None): callers can use
    ``Ji = -Jj Adj(T_ji)`` on reduced quantities instead.
    """
    T_ji = relative_poses(T_cw, ii, jj)
    di = d[ii]                                    # (E,P)
    q, xp, yp, iz, r, valid = _edge_projection(T_ji, rays, di, target, K, min_depth_ratio)
    a, b = K.fx * iz, K.fy * iz
    zero = torch.zeros_like(iz)
    ju = torch.stack([a * di, zero, -a * xp * di, -K.fx * xp * yp, K.fx * (1 + xp * xp), -K.fx * yp], -1)
    jv = torch.stack([zero, b * di, -b * yp * di, -K.fy * (1 + yp * yp), K.fy * xp * yp, K.fy * xp], -1)
    Jj = torch.stack([ju, jv], -2)                                  # (E,P,2,6)
    t = T_ji[:, None, :3, 3]                                        # (E,1,3)
    Jd = torch.stack([a * (t[..., 0] - xp * t[..., 2]), b * (t[..., 1] - yp * t[..., 2])], -1)
    Ji = None
    if need_ji:
        nE, P = di.shape
        Ji = -(Jj.reshape(nE, P * 2, 6) @ adjoint(T_ji)).reshape(nE, P, 2, 6)
    return EdgeLinearization(r, Ji, Jj, Jd, valid)
