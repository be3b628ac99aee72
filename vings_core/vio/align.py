"""Visual-inertial alignment (Qin et al., VINS-Mono, section V-B): gyroscope bias, velocities,
gravity and metric scale from an up-to-scale visual keyframe trajectory and the IMU pre-integrated
between its keyframes; gravity refined on its sphere (``|g|`` fixed, two tangent degrees of
freedom). The accelerometer bias is taken as zero here (it is barely observable over a few seconds)
and left to the smoother.

Visual poses are camera-to-world ``T_wc`` in the visual world ``w`` with positions ``p = p_metric /
s``; ``T_bc`` is metric. With ``p_b = s p_c + R_wc p_cb`` (``p_cb``: the body origin in the camera
frame), for consecutive keyframes ``i, j`` (interval ``dt``)::

    s (p_cj - p_ci) - v_i dt - 1/2 g dt^2 = R_bi dp_ij - (R_wcj - R_wci) p_cb
    v_j - v_i - g dt                        = R_bi dv_ij

a linear system in ``[v_0 .. v_n, g, s]`` (world frame, metric).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .preint import Preintegrated, so3_log_np


@dataclass
class Alignment:
    """Result of :func:`align`. ``ok`` false: refused (``why`` says why), never to be applied.

    ``scale``: metric metres per visual unit; ``g_w``: gravity in the visual world (m/s^2);
    ``bg``: gyroscope bias (rad/s); ``velocities``: ``(n, 3)`` metric body velocities in the visual
    world's axes; ``residual_rms``: RMS of the linear system's residual (m and m/s);
    ``scale_std``: the scale's standard deviation relative to the scale, from the least-squares
    covariance (residual variance times ``(A^T A)^-1``): large when the motion leaves the scale
    unobservable (constant velocity); ``C``: 4x4 similarity to the metric gravity-aligned frame
    (z up), ``x -> s R x`` on visual world points."""

    ok: bool
    why: str
    scale: float = float("nan")
    g_w: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    bg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocities: Optional[np.ndarray] = None
    residual_rms: float = float("nan")
    scale_std: float = float("nan")
    C: Optional[np.ndarray] = None


def excitation(pres: Sequence[Preintegrated]) -> float:
    """Standard deviation (m/s^2) of the mean specific force ``dv/dt`` of the intervals: VINS-Mono's
    test that the motion excites the accelerometer enough for scale and gravity to be observable."""
    a = np.array([p.dv / p.dt for p in pres if p.dt > 0])
    if len(a) < 2:
        return 0.0
    return float(np.sqrt(((a - a.mean(0)) ** 2).sum(1).mean()))


def solve_gyro_bias(R_wb: Sequence[np.ndarray], pres: Sequence[Preintegrated]) -> np.ndarray:
    """Gyroscope bias correction (rad/s) that best explains the visual relative rotations
    (first order, least squares), added to the biases the ``pres`` were integrated at."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for k, pre in enumerate(pres):
        r = so3_log_np(pre.dR.T @ R_wb[k].T @ R_wb[k + 1])
        A += pre.J_R_bg.T @ pre.J_R_bg
        b += pre.J_R_bg.T @ r
    return pres[0].bg + np.linalg.solve(A + 1e-12 * np.eye(3), b)


def _tangent_basis(g: np.ndarray) -> np.ndarray:
    a = g / np.linalg.norm(g)
    tmp = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 0, 1.0])
    b1 = np.cross(a, tmp)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(a, b1)], 1)


def _linear_system(T_wc, T_bc, pres, g_fixed=None, B=None):
    """Rows of the alignment system; unknowns ``[v (3n), g (3) or w (2), s]``."""
    n = len(T_wc)
    p_cb = np.linalg.inv(T_bc)[:3, 3]
    R_cb = np.linalg.inv(T_bc)[:3, :3]
    ng = 3 if g_fixed is None else 2
    N = 3 * n + ng + 1
    rows, rhs = [], []
    for k, pre in enumerate(pres):
        i, j = k, k + 1
        dt = pre.dt
        R_bi = T_wc[i][:3, :3] @ R_cb
        # position row block
        A = np.zeros((3, N))
        A[:, 3 * i:3 * i + 3] = -dt * np.eye(3)
        A[:, -1] = T_wc[j][:3, 3] - T_wc[i][:3, 3]
        r = R_bi @ pre.dp - (T_wc[j][:3, :3] - T_wc[i][:3, :3]) @ p_cb
        if g_fixed is None:
            A[:, 3 * n:3 * n + 3] = -0.5 * dt * dt * np.eye(3)
        else:
            A[:, 3 * n:3 * n + 2] = -0.5 * dt * dt * B
            r = r + 0.5 * dt * dt * g_fixed
        rows.append(A)
        rhs.append(r)
        # velocity row block
        A = np.zeros((3, N))
        A[:, 3 * i:3 * i + 3] = -np.eye(3)
        A[:, 3 * j:3 * j + 3] = np.eye(3)
        r = R_bi @ pre.dv
        if g_fixed is None:
            A[:, 3 * n:3 * n + 3] = -dt * np.eye(3)
        else:
            A[:, 3 * n:3 * n + 2] = -dt * B
            r = r + dt * g_fixed
        rows.append(A)
        rhs.append(r)
    return np.vstack(rows), np.concatenate(rhs)


def gravity_alignment(g_w: np.ndarray) -> np.ndarray:
    """Smallest rotation taking the direction of ``g_w`` to ``-z`` (REP-103: z up)."""
    a = g_w / np.linalg.norm(g_w)
    b = np.array([0.0, 0.0, -1.0])
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:                     # opposite: turn about x
        return np.diag([1.0, -1.0, -1.0])
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1 + c)


def align(T_wc: Sequence[np.ndarray], T_bc: np.ndarray, pres: Sequence[Preintegrated],
          gravity: float = 9.81, g_tol: float = 0.1, max_residual: float = 0.05,
          refine_iters: int = 4, max_scale_std: float = 0.02) -> Alignment:
    """Align ``n`` visual keyframe poses ``T_wc`` (consecutive, up to scale) with the ``n - 1``
    pre-integrations between them. Refused (``ok`` false) when the scale is not positive, the
    unrefined gravity norm is off by more than ``g_tol`` (relative), the residual RMS after
    refinement exceeds ``max_residual`` (m, m/s), or the scale's relative standard deviation
    exceeds ``max_scale_std``. ``pres`` are re-used at the estimated gyro bias to first order."""
    n = len(T_wc)
    if n < 3 or len(pres) != n - 1:
        return Alignment(False, f"need >= 3 keyframes and one pre-integration per interval "
                                f"(got {n} and {len(pres)})")
    R_cb = np.linalg.inv(T_bc)[:3, :3]
    R_wb = [T[:3, :3] @ R_cb for T in T_wc]
    bg = solve_gyro_bias(R_wb, pres)
    ba = pres[0].ba
    fixed = []
    for pre in pres:
        dR, dv, dp = pre.corrected(bg, ba)
        fixed.append(Preintegrated(pre.dt, dR, dv, dp, pre.J_R_bg, pre.J_v_bg, pre.J_p_bg,
                                   pre.J_v_ba, pre.J_p_ba, bg, ba))
    A, b = _linear_system(T_wc, T_bc, fixed)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    s, g = float(x[-1]), x[3 * n:3 * n + 3]
    gnorm = float(np.linalg.norm(g))
    if not s > 0:
        return Alignment(False, f"scale {s:.4g} is not positive", scale=s, g_w=g, bg=bg)
    if not abs(gnorm - gravity) <= g_tol * gravity:
        return Alignment(False, f"gravity norm {gnorm:.2f} m/s^2 is far from {gravity:g}", scale=s,
                         g_w=g, bg=bg)
    g = g / gnorm * gravity
    for _ in range(refine_iters):
        B = _tangent_basis(g)
        A, b = _linear_system(T_wc, T_bc, fixed, g_fixed=g, B=B)
        x = np.linalg.lstsq(A, b, rcond=None)[0]
        g = g + B @ x[3 * n:3 * n + 2]
        g = g / np.linalg.norm(g) * gravity
    A, b = _linear_system(T_wc, T_bc, fixed, g_fixed=g, B=_tangent_basis(g))
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    s = float(x[-1])
    r = A @ x - b
    res = float(np.sqrt(np.mean(r ** 2)))
    dof = max(A.shape[0] - A.shape[1], 1)
    try:
        cov_ss = float(np.linalg.inv(A.T @ A)[-1, -1])
    except np.linalg.LinAlgError:
        cov_ss = float("inf")
    s_std = float(np.sqrt(max(r @ r / dof * cov_ss, 0.0))) / abs(s) if s != 0 else float("inf")
    vel = x[:3 * n].reshape(n, 3)
    kw = dict(scale=s, g_w=g, bg=bg, velocities=vel, residual_rms=res, scale_std=s_std)
    if not s > 0:
        return Alignment(False, f"refined scale {s:.4g} is not positive", **kw)
    if not res <= max_residual:
        return Alignment(False, f"residual RMS {res:.3g} above {max_residual:g}", **kw)
    if not s_std <= max_scale_std:
        return Alignment(False, f"scale not observable yet (relative std {s_std:.3f} > "
                                f"{max_scale_std:g}: too little acceleration)", **kw)
    R = gravity_alignment(g)
    C = np.eye(4)
    C[:3, :3] = s * R
    return Alignment(True, "aligned", C=C, **kw)
