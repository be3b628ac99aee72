"""SE(3) exponential whose gradient is finite at zero.

``vings_core.geometry.se3_exp`` selects a Taylor branch with ``torch.where`` but still evaluates
``sqrt(theta^2)`` at 0, whose derivative is infinite, so autograd returns NaN for the rotation part
of a zero tangent (exactly where pose refinement starts). This version feeds the non-Taylor branch a
safe argument ("double where"); values equal ``geometry.se3_exp``.
"""
from __future__ import annotations

import torch

from ..geometry import skew


def so3_coeffs_safe(theta2: torch.Tensor):
    """``A = sin t / t``, ``B = (1 - cos t) / t^2``, ``C = (t - sin t) / t^3``, smooth at 0."""
    small = theta2 < 1e-8
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    A = torch.where(small, 1 - theta2 / 6, torch.sin(t) / t)
    B = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(t)) / t2)
    C = torch.where(small, 1.0 / 6 - theta2 / 120, (t - torch.sin(t)) / (t2 * t))
    return A, B, C


def se3_exp_safe(xi: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` tangent ``[rho, phi]`` -> ``(..., 4, 4)``, differentiable everywhere."""
    rho, phi = xi[..., :3], xi[..., 3:]
    A, B, C = so3_coeffs_safe((phi * phi).sum(-1))
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
