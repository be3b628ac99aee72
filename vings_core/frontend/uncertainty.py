"""Marginal inverse-depth covariance from the dense-BA information matrix (paper: "Depth
Uncertainty Estimation").

With the block system ``[[B, E], [E^T, C]]`` (poses, depths; ``C`` diagonal) and the reduced pose
Hessian ``S = B - E C^-1 E^T = L L^T`` (gauge-fixed poses removed), the marginal covariance of every
inverse depth is the diagonal of

    Sigma_d = C^-1 + C^-1 E^T S^-1 E C^-1 = C^-1 + (L^-1 E C^-1)^T (L^-1 E C^-1),

computed for all pixels at once: one triangular solve with ``MP`` right-hand sides and a column-wise
sum of squares. Units follow the weights: with information in 1/px^2 the result is in (inverse depth)^2.
"""
from __future__ import annotations

import torch

from .ba import NormalEquations, ReducedSystem, dense_matrix, jittered_cholesky, schur_reduce
from ..profiling import profiled

DT = torch.float64


def marginal_inv_depth_var(rs: ReducedSystem, jitter: float = 1e-9) -> torch.Tensor:
    """Diagonal of ``Sigma_d`` (``(MP,)``) from a reduced system built without LM damping.

    ``jitter`` (relative to the mean diagonal of ``S``) is added before the Cholesky factorisation
    so a nearly singular gauge direction does not break it.
    """
    if rs.S.shape[0] == 0:
        return rs.Cinv.clone()
    L = jittered_cholesky(rs.S, jitter)
    G = torch.linalg.solve_triangular(L, rs.Ef * rs.Cinv, upper=False)   # (6F, MP)
    return rs.Cinv + (G * G).sum(0)


@profiled("tracking", "depth uncertainty")
def window_inv_depth_var(ne: NormalEquations, free: torch.Tensor, eps_c: float = 1e-9) -> torch.Tensor:
    """``(M, P)`` marginal inverse-depth variances of a BA window whose free poses are ``free``;
    ``inf`` for depths no residual observes (``C = 0``: the solve's regulariser ``eps_c`` would
    otherwise pass for a real, if large, variance, e.g. in the upsampler's median)."""
    M, P = ne.C.shape
    rs = schur_reduce(ne, free, lam=0.0, eps_c=eps_c)
    var = marginal_inv_depth_var(rs).reshape(M, P)
    return torch.where(ne.C > 0, var, torch.full_like(var, float("inf")))


def marginal_inv_depth_var_dense(ne: NormalEquations, free: torch.Tensor,
                                 eps_c: float = 1e-9) -> torch.Tensor:
    """Reference: the depth block diagonal of the inverse of the full (gauge-fixed) Hessian."""
    M, P = ne.C.shape
    Hfull, _ = dense_matrix(ne)
    keep = torch.cat([torch.cat([torch.arange(6) + 6 * int(m) for m in free]) if len(free) else
                      torch.zeros(0, dtype=torch.long), 6 * M + torch.arange(M * P)])
    H = Hfull[keep][:, keep].clone()
    nP = 6 * len(free)
    H[nP:, nP:] += torch.eye(M * P, dtype=DT) * eps_c
    return torch.diagonal(torch.linalg.inv(H))[nP:].reshape(M, P)
