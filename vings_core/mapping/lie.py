"""SE(3) exponential built by concatenation (no in-place writes into a buffer), for the pose
refinement's autograd graph; values and gradients equal ``vings_core.geometry.se3_exp`` (both use
:func:`vings_core.geometry.so3_coeffs`, finite at zero).
"""
from __future__ import annotations

import torch

from ..geometry import skew, so3_coeffs


def se3_exp_safe(xi: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` tangent ``[rho, phi]`` -> ``(..., 4, 4)``, differentiable everywhere."""
    rho, phi = xi[..., :3], xi[..., 3:]
    A, B, C = so3_coeffs((phi * phi).sum(-1))
    K = skew(phi)
    K2 = K @ K
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(K.shape)
    R = eye + A[..., None, None] * K + B[..., None, None] * K2
    J = eye + B[..., None, None] * K + C[..., None, None] * K2
    t = (J @ rho[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)
