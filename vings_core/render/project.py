"""Per-Gaussian set-up of the 2DGS rasterizer in torch (vectorised, differentiable by autograd).

A 2DGS surfel has centre ``p`` (world, m), rotation ``R`` (world, from the quaternion) whose first
two columns are the tangent axes ``t_u, t_v`` and whose third column is the normal, and scales
``s_u, s_v`` (m). A point of the splat at local coordinates ``(u, v)`` (in units of the scales) is
``p + u s_u t_u + v s_v t_v``. In the camera (``T_cw``: world -> camera, pinhole ``K``) its
homogeneous pixel is ``M @ [u, v, 1]`` with the 3x3 *ray-splat transform*

    M = K @ [R_cw t_u s_u | R_cw t_v s_v | R_cw p + t_cw].

Row 2 of ``M`` gives the camera z of a splat point, ``M[2, 2]`` is the centre depth and
``M[:2, 2] / M[2, 2]`` the projected centre (pixels). The kernels only see ``M``, the opacity, the
colour and the camera-frame normal, so every geometric gradient reaches means / quats / scales /
pose through this module by torch autograd.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..geometry import quat_to_rotmat

NPARAM = 16  # packed per-Gaussian record: M (9, row-major), opacity, rgb (3), normal (3)


@dataclass
class Projected:
    """Camera-dependent per-Gaussian quantities (all ``(N, ...)``, differentiable)."""

    M: torch.Tensor         # (N, 3, 3) ray-splat transform, pixels
    normals: torch.Tensor   # (N, 3) unit normal, camera frame, facing the camera
    means_c: torch.Tensor   # (N, 3) centres in the camera frame (m)


def project_surfels(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                    T_cw: torch.Tensor, fx: float, fy: float, cx: float, cy: float) -> Projected:
    """Ray-splat transforms ``M`` and camera-frame normals of ``N`` surfels.

    ``means (N,3)`` world m, ``quats (N,4)`` xyzw (normalised here), ``scales (N,2)`` m,
    ``T_cw (4,4)`` world->camera. The normal is flipped to face the camera (``n . p_c <= 0``) as in
    2DGS; the sign flip is treated as a constant by autograd.
    """
    R_cw, t_cw = T_cw[:3, :3], T_cw[:3, 3]
    p_c = means @ R_cw.T + t_cw
    Rc = torch.matmul(R_cw, quat_to_rotmat(quats))          # (N, 3, 3) surfel axes in camera
    tu = Rc[:, :, 0] * scales[:, 0:1]
    tv = Rc[:, :, 1] * scales[:, 1:2]
    n = Rc[:, :, 2]
    A = torch.stack([tu, tv, p_c], dim=-1)                  # (N, 3, 3), columns u, v, centre
    row0 = fx * A[:, 0, :] + cx * A[:, 2, :]
    row1 = fy * A[:, 1, :] + cy * A[:, 2, :]
    M = torch.stack([row0, row1, A[:, 2, :]], dim=1)
    flip = ((n * p_c).sum(-1, keepdim=True) > 0).to(n.dtype)
    n = n * (1.0 - 2.0 * flip)
    return Projected(M=M, normals=n, means_c=p_c)


def pack_params(M: torch.Tensor, opacities: torch.Tensor, colors: torch.Tensor,
                normals: torch.Tensor) -> torch.Tensor:
    """``(N, 16)`` record the kernels read: M row-major, opacity, rgb, normal."""
    return torch.cat([M.reshape(-1, 9), opacities.reshape(-1, 1), colors, normals], dim=1)
