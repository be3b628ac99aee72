"""The dense BA's Schur-reduced pose system as a linear factor on body poses in GTSAM.

The front end exports the system ``E(x) = 1/2 x^T G x - x^T g`` over the window's camera poses
(:meth:`~vings_core.frontend.ba.PoseSystem.to_gtsam_ordering`: GTSAM's right perturbation of
``T_wc``, tangent order ``[phi (rad), rho (m)]``). The smoother's states are body poses ``T_wb``
with ``T_wc = T_wb T_bc``; a right perturbation of the body pose moves the camera by

    T_wb Exp(d_b) T_bc = T_wc Exp(Ad(T_cb) d_b)       so  d_c = J d_b,  J = Ad(T_bc^-1)

and the factor on body poses is ``G_b = J^T G J``, ``g_b = J^T g`` per block (``J`` is the same for
every pose). GTSAM's Python wheel has no N-key ``HessianFactor`` constructor: the factor is the sum
of 1- and 2-key ``HessianFactor`` blocks of a ``GaussianFactorGraph``, joined by
``HessianFactor(graph)`` and wrapped in a ``LinearContainerFactor`` at the body poses it was
linearised at. Its constant term is ``g^T G^+ g`` so the error is >= 0 (LM stops at once on a graph
whose error is 0).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np


def adjoint_gtsam(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of the pose ``T`` in GTSAM's tangent order ``[phi, rho]``:
    ``T Exp(x) T^-1 = Exp(Ad(T) x)``."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    return A


def camera_to_body_system(G: np.ndarray, g: np.ndarray, T_bc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(G_b, g_b)`` on body-pose perturbations from ``(G, g)`` on camera-pose perturbations (both
    GTSAM right perturbations, ``[phi, rho]`` per pose, ``M`` poses stacked)."""
    M = G.shape[0] // 6
    J1 = adjoint_gtsam(np.linalg.inv(T_bc))
    J = np.kron(np.eye(M), J1)
    return J.T @ G @ J, J.T @ g


def hessian_factor(G: np.ndarray, g: np.ndarray, keys: Sequence[int]):
    """One GTSAM ``HessianFactor`` on ``keys`` (6-dof each) with error
    ``1/2 x^T G x - x^T g + 1/2 g^T G^+ g`` (its minimum is 0), built from 1- and 2-key blocks."""
    import gtsam
    M = len(keys)
    if G.shape != (6 * M, 6 * M) or g.shape != (6 * M,):
        raise ValueError(f"visual factor: G {G.shape} / g {g.shape} do not fit {M} poses")
    gfg = gtsam.GaussianFactorGraph()
    B = lambda i, j: np.ascontiguousarray(G[6 * i:6 * i + 6, 6 * j:6 * j + 6])   # noqa: E731
    gb = lambda i: np.ascontiguousarray(g[6 * i:6 * i + 6])                       # noqa: E731
    c = float(g @ np.linalg.lstsq(G, g, rcond=None)[0])
    if M == 1:
        return gtsam.HessianFactor(keys[0], B(0, 0), gb(0), c)
    for i in range(M):
        for j in range(i + 1, M):
            # diagonal blocks and gradients spread over the pairs each pose takes part in
            share = 1.0 / (M - 1)
            gfg.add(gtsam.HessianFactor(keys[i], keys[j], B(i, i) * share, B(i, j), gb(i) * share,
                                        B(j, j) * share, gb(j) * share, c / (M * (M - 1) / 2)))
    return gtsam.HessianFactor(gfg)


def visual_factor(G_cam: np.ndarray, g_cam: np.ndarray, T_bc: np.ndarray, keys: Sequence[int],
                  T_wb: Sequence[np.ndarray]):
    """``LinearContainerFactor`` on the body poses ``keys`` (``gtsam.Pose3`` values), linearised at
    ``T_wb`` (the body poses of the BA's linearisation point: ``T_wc T_bc^-1``)."""
    import gtsam
    Gb, gb = camera_to_body_system(G_cam, g_cam, T_bc)
    lin = gtsam.Values()
    for k, T in zip(keys, T_wb):
        lin.insert(k, gtsam.Pose3(np.asarray(T, np.float64)))
    return gtsam.LinearContainerFactor(hessian_factor(Gb, gb, keys), lin)
