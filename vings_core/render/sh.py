"""Real spherical harmonics (degree 0-3) for view-dependent Gaussian colour, in torch.

Same basis, sign convention and constants as 3DGS/gsplat, so SH coefficients trained elsewhere
render the same here: ``colour = max(SH(dir) + 0.5, 0)`` where ``dir`` is the unit vector from the
camera centre to the Gaussian centre, in the world frame.
"""
from __future__ import annotations

import math

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree`` (0-3): ``(degree + 1) ** 2``."""
    return (degree + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    """Inverse of :func:`num_sh_bases`; raises ``ValueError`` when ``k`` is not a square <= 16."""
    d = int(round(math.sqrt(k))) - 1
    if (d + 1) ** 2 != k or not 0 <= d <= 3:
        raise ValueError(f"{k} SH coefficients per channel is not (degree+1)^2 for degree 0-3")
    return d


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient that renders ``rgb`` (values in [0, 1]) at every view direction."""
    return (rgb - 0.5) / SH_C0


def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH ``(N, K, C)`` (``K >= (degree+1)^2``) at directions ``(N, 3)`` -> ``(N, C)``.

    ``dirs`` need not be normalised. Raw value, without the ``+0.5`` offset and clamp (see
    :func:`sh_to_color`).
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    res = SH_C0 * sh[:, 0]
    if degree == 0:
        return res
    d = dirs / torch.linalg.norm(dirs, dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    res = res - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if degree == 1:
        return res
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    res = (res + SH_C2[0] * xy * sh[:, 4] + SH_C2[1] * yz * sh[:, 5]
           + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6] + SH_C2[3] * xz * sh[:, 7]
           + SH_C2[4] * (xx - yy) * sh[:, 8])
    if degree == 2:
        return res
    return (res + SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9] + SH_C3[1] * xy * z * sh[:, 10]
            + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
            + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
            + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
            + SH_C3[5] * z * (xx - yy) * sh[:, 14] + SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15])


def sh_to_color(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colour ``max(SH(dirs) + 0.5, 0)`` as in 3DGS/gsplat, ``(N, K, 3) -> (N, 3)``."""
    return torch.clamp_min(eval_sh(degree, sh, dirs) + 0.5, 0.0)


def _basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """``(N, K)`` values of the K basis functions at ``dirs (N, 3)`` (the renderer's own basis)."""
    k = num_sh_bases(degree)
    eye = torch.eye(k, dtype=dirs.dtype, device=dirs.device).expand(dirs.shape[0], k, k)
    return eval_sh(degree, eye, dirs)


_PROBE_DIRS: dict = {}


def sh_rotation(R: torch.Tensor, degree: int) -> torch.Tensor:
    """Matrices ``(M, K-1, K-1)`` that carry the SH bands 1..degree along a rotation ``R (M, 3, 3)``.

    For a Gaussian rotated by ``R`` (world frame), ``sh'[1:] = D @ sh[1:]`` gives the colour it
    showed before from the matching direction: ``SH'(d) = SH(R^T d)`` (the DC band is invariant).
    Bands do not mix and the basis is orthonormal, so ``D`` is orthogonal (block diagonal); it is
    found exactly as the least-squares map between the basis evaluated at fixed probe directions
    and at the rotated ones. Differentiable in ``R`` (float64 recommended).
    """
    if not 1 <= degree <= 3:
        raise ValueError(f"sh_rotation: degree must be 1..3, got {degree}")
    key = (degree, R.dtype, R.device)
    if key not in _PROBE_DIRS:
        g = torch.Generator().manual_seed(0)
        d = torch.randn(48, 3, generator=g, dtype=torch.float64)
        d = (d / torch.linalg.norm(d, dim=1, keepdim=True)).to(R.dtype).to(R.device)
        A = _basis(degree, d)[:, 1:]
        _PROBE_DIRS[key] = (d, torch.linalg.pinv(A))
    d, A_pinv = _PROBE_DIRS[key]
    M = R.shape[0]
    rd = torch.einsum("mji,nj->mni", R, d)               # R^T d for every rotation, (M, n, 3)
    B = _basis(degree, rd.reshape(-1, 3)).reshape(M, d.shape[0], -1)[:, :, 1:]
    return A_pinv @ B


def rotate_sh(sh: torch.Tensor, R: torch.Tensor, index: torch.Tensor | None = None) -> torch.Tensor:
    """SH coefficients ``(N, K, C)`` carried along rotations (see :func:`sh_rotation`): ``R (3, 3)``
    for all rows, ``(N, 3, 3)`` one per row, or ``(M, 3, 3)`` with ``index (N,)`` naming each row's
    rotation (differentiable in ``R``; the per-row form is not). Degree 0 is returned unchanged."""
    degree = sh_degree_from_bases(sh.shape[1])
    if degree == 0 or sh.shape[0] == 0:
        return sh
    dt = sh.dtype
    R = R.to(torch.float64)
    if R.ndim == 2:
        R, index = R[None], torch.zeros(sh.shape[0], dtype=torch.long, device=sh.device)
    elif index is None:     # one per row: each distinct rotation once
        R, index = torch.unique(R.reshape(-1, 9), dim=0, return_inverse=True)
        R = R.reshape(-1, 3, 3)
    D = sh_rotation(R, degree).to(dt)
    return torch.cat([sh[:, :1], torch.index_select(D, 0, index) @ sh[:, 1:]], 1)
