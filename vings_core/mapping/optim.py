"""Sparse Adam: updates only selected rows (unstable Gaussians touched by the render).

Each row keeps its own step count, so bias correction follows the number of updates that row has
received (as gsplat's SparseAdam / Taming-3DGS). Rows outside the mask are not read or written: their
parameters and moments stay bit-identical.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange


def sparse_adam_step(param: torch.Tensor, grad: torch.Tensor, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor,
                     step: torch.Tensor, rows: torch.Tensor, lr: float | torch.Tensor,
                     betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15) -> None:
    """In place Adam update of ``param[rows]``.

    ``param``, ``grad``, ``exp_avg``, ``exp_avg_sq``: (N, ...); ``step`` (N,) int32 per-row step
    counts *already incremented* for ``rows``; ``rows``: int64 indices (unique); ``lr``: scalar or
    (len(rows),) per-row learning rates, or a tensor broadcastable to ``param[rows]`` (e.g.
    ``(1, K, 1)`` per SH band).
    """
    if rows.numel() == 0:
        return
    b1, b2 = betas
    g = grad.index_select(0, rows)
    m = exp_avg.index_select(0, rows).mul_(b1).add_(g, alpha=1 - b1)
    v = exp_avg_sq.index_select(0, rows).mul_(b2).addcmul_(g, g, value=1 - b2)
    t = step.index_select(0, rows).to(param.dtype)
    shape = (-1,) + (1,) * (param.ndim - 1)
    bc1 = (1 - b1 ** t).reshape(shape)
    bc2 = (1 - b2 ** t).reshape(shape)
    lr_t = torch.as_tensor(lr, dtype=param.dtype)
    if lr_t.ndim == 1 and lr_t.numel() == rows.numel():
        lr_t = lr_t.reshape(shape)          # per-row rates; otherwise broadcast as given
    upd = (m / bc1) / ((v / bc2).sqrt() + eps) * lr_t
    param.index_copy_(0, rows, param.index_select(0, rows) - upd)
    exp_avg.index_copy_(0, rows, m)
    exp_avg_sq.index_copy_(0, rows, v)


def reference_adam_rows(param: torch.Tensor, grads: list[torch.Tensor], lr: float,
                        betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15) -> torch.Tensor:
    """Slow reference: plain ``torch.optim.Adam`` run on a copy of ``param`` for the given gradients."""
    p = param.clone().requires_grad_(True)
    opt = torch.optim.Adam([p], lr=lr, betas=betas, eps=eps)
    for g in grads:
        opt.zero_grad()
        p.grad = g.clone()
        opt.step()
    return p.detach()


@njit(parallel=True, cache=True)
def _adam_rows_kernel(p, g, m, v, step, rows, lr, b1, b2, eps):  # pragma: no cover - compiled
    D = p.shape[1]
    for k in prange(rows.shape[0]):
        i = rows[k]
        t = step[i]
        bc1 = 1.0 - b1 ** t
        bc2 = 1.0 - b2 ** t
        for j in range(D):
            gj = np.float64(g[i, j])
            mj = b1 * np.float64(m[i, j]) + (1.0 - b1) * gj
            vj = b2 * np.float64(v[i, j]) + (1.0 - b2) * gj * gj
            m[i, j] = mj
            v[i, j] = vj
            p[i, j] = np.float64(p[i, j]) - lr[j] * (mj / bc1) / (np.sqrt(vj / bc2) + eps)


def sparse_adam_step_fast(param: torch.Tensor, grad: torch.Tensor, exp_avg: torch.Tensor,
                          exp_avg_sq: torch.Tensor, step: torch.Tensor, rows: torch.Tensor,
                          lr_cols: np.ndarray, betas: tuple[float, float] = (0.9, 0.999),
                          eps: float = 1e-15) -> None:
    """Numba version of :func:`sparse_adam_step` (same maths, float64 inside, one pass per row).

    CPU tensors, contiguous, viewed as ``(N, D)``; ``lr_cols`` (D,) learning rate per column of that
    view. Falls back to the torch version for non-CPU tensors.
    """
    if rows.numel() == 0:
        return
    if param.device.type != "cpu":
        lr = torch.as_tensor(lr_cols, dtype=param.dtype, device=param.device).reshape((1,) + param.shape[1:])
        sparse_adam_step(param, grad, exp_avg, exp_avg_sq, step, rows, lr, betas, eps)
        return
    n = param.shape[0]
    views = []
    for t in (param, exp_avg, exp_avg_sq):
        if not t.is_contiguous():
            raise ValueError("sparse_adam_step_fast needs contiguous parameter and moment tensors")
        views.append(t.detach().numpy().reshape(n, -1))
    g = grad.detach().contiguous().numpy().reshape(n, -1)
    lr = np.ascontiguousarray(np.broadcast_to(np.asarray(lr_cols, dtype=np.float64), (views[0].shape[1],)))
    _adam_rows_kernel(views[0], g, views[1], views[2], step.numpy(), rows.numpy().astype(np.int64),
                      lr, float(betas[0]), float(betas[1]), float(eps))
