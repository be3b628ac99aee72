"""Loop-closure pose graph over keyframe poses (GTSAM Levenberg-Marquardt).

Conventions (see :mod:`vings_core.geometry`):

* A keyframe pose is ``T_wc`` (4x4 rigid, camera to world, metres). A similarity
  ``S = [[s R, t], [0, 1]]`` maps points as ``x -> s R x + t``; a keyframe's similarity ``S_wc``
  says where its camera centre (``t``) and orientation (``R``) lie and how its content scales (``s``).
* The result moves keyframe ``k`` by the world-frame increment ``C_k = S_new S_old^-1``
  (``S_old = T_old``, rigid): the pose exchange applies it as
  ``T_new = geometry.sim3_apply_to_pose(C_k, T_old)`` (centre mapped as a point, rotation turned by
  ``R``, content scaled by ``s``), see :mod:`vings_core.exchange`.

GTSAM conventions (verified on the gtsam 4.3.0 wheel, tested in ``test/test_loop_pose_graph.py``):

* ``gtsam.Similarity3(R, t, s)`` maps points as ``transformFrom(p) = s (R p + t)`` and its
  ``matrix()`` is ``[[R, t], [0, 1/s]]`` (a projective multiple of ours). Ours ``[[s R, t], [0, 1]]``
  is ``Similarity3(R, t / s, s)``; ``compose`` and ``inverse`` agree with the matrix products.
* The Similarity3 tangent order is ``[omega (3, rad), u (3, translation), lambda = log s]``;
  Pose3's is ``[omega (3, rad), v (3, m)]``. Both charts are ``Local(a, b) = Logmap(a^-1 b)``.
  A ``BetweenFactor`` with measurement ``Z`` between ``X_i`` and ``X_j`` has the error
  ``Logmap(Z^-1 X_i^-1 X_j)``: a right perturbation expressed in ``j``'s (measured) frame; a
  translation error there is in ``j``'s units (``i``'s units over ``Z``'s scale). The 6x6 / 7x7
  matrices of ``odometry_info`` are information matrices on that tangent, in that order.
"""
from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, field
from typing import Optional

import gtsam
import numpy as np

from ..errors import InputError
from ..geometry import (check_sim3, np_project_rotation, rigid_deviation, rotation_angle_deg, sim3, sim3_inverse,
                        sim3_scale)

__all__ = ["GraphMode", "LoopEdge", "PoseGraphResult", "optimize_pose_graph", "sim3_to_gtsam", "sim3_from_gtsam"]

_FIXED_SIGMA = 1e-6   # prior on the fixed node (rad, m, log-scale); the result is re-anchored exactly anyway


class GraphMode(str, enum.Enum):
    """Which group the nodes live in."""

    SIM3 = "sim3"   #: scale unobservable (visual-only): 7-DoF nodes
    SE3 = "se3"     #: metric (visual-inertial): 6-DoF nodes

    def __str__(self) -> str:
        return self.value


@dataclass
class LoopEdge:
    """A loop measurement between two keyframes (stamps in ns).

    ``T_on``: 4x4 similarity ``S_older^-1 S_newer``, the pose of ``newer`` in ``older``'s camera
    frame; its scale is the size of one of ``newer``'s units in ``older``'s units (1 in SE3).
    ``sigma_rot`` (rad), ``sigma_pos`` (in ``older``'s units), ``sigma_scale`` (log-scale, SIM3 only)."""

    older: int
    newer: int
    T_on: np.ndarray
    sigma_rot: float
    sigma_pos: float
    sigma_scale: float = 0.05


@dataclass
class PoseGraphResult:
    """``poses[stamp]``: new ``S_wc`` ``[[s R, t], [0, 1]]`` (``s = 1`` in SE3); ``increments[stamp]``:
    ``C = S_new S_old^-1`` (the fixed node's is the identity). ``error_before`` / ``error_after``:
    GTSAM graph error (``0.5 sum |whitened residual|^2``, Huber loss on loop edges). ``loop_residuals``:
    per loop edge after optimisation, ``rot_deg`` (deg), ``pos`` (position of ``newer`` in ``older``'s
    frame vs the measurement, ``older``'s units), ``scale`` (``log(s_achieved / s_measured)``),
    ``whitened`` (Mahalanobis norm) and ``weight`` (Huber weight, 1 = inlier)."""

    poses: dict[int, np.ndarray]
    increments: dict[int, np.ndarray]
    error_before: float
    error_after: float
    loop_residuals: list[dict] = field(default_factory=list)
    iterations: int = 0
    seconds: float = 0.0


# ------------------------------------------------------------------------------ conversions


def sim3_to_gtsam(S: np.ndarray) -> gtsam.Similarity3:
    """Our ``[[s R, t], [0, 1]]`` (``x -> s R x + t``) as ``gtsam.Similarity3(R, t / s, s)``."""
    return _nodes(np.asarray(S, np.float64)[None], True)[0]


def sim3_from_gtsam(g: gtsam.Similarity3) -> np.ndarray:
    """``gtsam.Similarity3`` (``p -> s (R p + t)``) as our 4x4 ``[[s R, s t], [0, 1]]``."""
    s = float(g.scale())
    return sim3(g.rotation().matrix(), s * np.asarray(g.translation(), np.float64), s)


# ------------------------------------------------------------------------------ the graph


def _rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of ``(..., 4, 4)`` rigid transforms (numpy, batched)."""
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def _check_poses(stamps: list[int], mats: list) -> np.ndarray:
    """Stack ``T_wc`` into ``(N, 4, 4)`` float64, rotations off SO(3) by more than 1e-9 re-projected;
    InputError naming the stamp of a non-finite or non-rigid (deviation > 1e-5) pose."""
    try:
        P = np.array([np.asarray(T, np.float64) for T in mats])
    except (ValueError, TypeError):
        P = None
    if P is None or P.shape[1:] != (4, 4):
        raise InputError("pose graph: every keyframe pose must be a 4x4 matrix")
    finite = np.isfinite(P).all(axis=(1, 2))
    if not finite.all():
        raise InputError(f"pose graph: keyframe {stamps[int(np.argmin(finite))]}: pose has non-finite entries")
    dev = rigid_deviation(P)
    bad = np.flatnonzero(~(dev <= 1e-5))
    if bad.size:
        raise InputError(f"pose graph: keyframe {stamps[bad[0]]}: not a finite rigid 4x4 pose "
                         f"(deviation {dev[bad[0]]:.2g})")
    fix = dev > 1e-9                     # round-off of composed increments: project back onto SO(3)
    if fix.any():
        P[fix, :3, :3] = np_project_rotation(P[fix, :3, :3])
    return P


def _sigmas(mode: GraphMode, rot: float, pos: float, scale: float) -> np.ndarray:
    sig = [rot] * 3 + [pos] * 3 + ([scale] if mode is GraphMode.SIM3 else [])
    return np.asarray(sig, np.float64)


def _check_positive(what: str, x: float) -> float:
    x = float(x)
    if not (math.isfinite(x) and x > 0):
        raise InputError(f"{what}: must be a finite number > 0, got {x}")
    return x


def _check_info(M: np.ndarray, dim: int, what: str) -> np.ndarray:
    M = np.asarray(M, np.float64)
    if M.shape != (dim, dim) or not np.isfinite(M).all():
        raise InputError(f"{what}: expected a finite {dim}x{dim} information matrix, got shape {M.shape}")
    M = 0.5 * (M + M.T)
    if np.linalg.eigvalsh(M).min() <= 0:
        raise InputError(f"{what}: information matrix is not positive definite")
    return M


def _nodes(M: np.ndarray, sim: bool) -> list:
    """``(N, 4, 4)`` similarities (rigid if not ``sim``) as gtsam Similarity3 / Pose3 values."""
    if not sim:
        return [gtsam.Pose3(m) for m in M]
    s = np.cbrt(np.linalg.det(M[:, :3, :3]))
    R, t = M[:, :3, :3] / s[:, None, None], M[:, :3, 3] / s[:, None]
    return [gtsam.Similarity3(gtsam.Rot3(R[i]), t[i], float(s[i])) for i in range(len(M))]


def _lm(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iters: int) -> tuple[gtsam.Values, int]:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iters))
    # tighter relative tolerances only buy round-off-level LM retries; near a zero error (consistent
    # measurements) the absolute one lets LM converge quadratically down to ~1e-20
    params.setRelativeErrorTol(1e-7)
    params.setAbsoluteErrorTol(1e-12)
    # errorTol (default 0, STACK.md) only stops LM at a zero error: every factor's error is >= 0 here,
    # and a zero error is the optimum
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    return opt.optimize(), int(opt.iterations())


def optimize_pose_graph(poses: dict[int, np.ndarray], loops: list[LoopEdge], mode: GraphMode | str, *,
                        odo_sigma_rot: float = 0.01, odo_sigma_pos_rel: float = 0.02,
                        odo_sigma_pos_min: float = 0.005, odo_sigma_scale: float = 0.01,
                        robust_k: Optional[float] = 1.345,
                        odometry_info: Optional[dict[tuple[int, int], np.ndarray]] = None,
                        fixed: Optional[int] = None, max_iters: int = 100) -> PoseGraphResult:
    """Correct keyframe poses ``{stamp: T_wc}`` (4x4 rigid, m) with loop edges (Levenberg-Marquardt).

    Nodes: every stamp, sorted (keyframe order). Odometry edges join consecutive keyframes with the
    current relative pose ``T_i^-1 T_j`` (scale 1), sigmas ``odo_sigma_rot`` (rad),
    ``max(odo_sigma_pos_rel |t_ij|, odo_sigma_pos_min)`` (m) and ``odo_sigma_scale`` (log-scale,
    SIM3), or ``odometry_info[(i, j)]`` (an information matrix on GTSAM's tangent, module docstring;
    only for consecutive stamps ``i < j``). Loop edges get a Huber kernel (``robust_k``, in whitened
    units; None or inf: plain Gaussian). The ``fixed`` node (default: the oldest) holds still: a
    tight prior, and the result is re-anchored on it exactly (every edge is invariant to that gauge
    move).

    Solve: LM from the current poses on the graph without kernels, then, if a loop edge ends
    outside Huber's quadratic zone, LM with the kernels from that solution (at most ``max_iters``
    iterations each). Started from the current poses, Huber-LM stalls when the drift is large: a
    true loop's residual is then hundreds of sigmas, its weight tiny, and the long chain's
    nonlinearity rejects every step (1000 keyframes, 1 rad / 1.5x scale drift: stopped at the
    start, while the kernel-free LM converged in 6 iterations).

    Raises :class:`InputError` for bad input (fewer than 2 poses, unknown stamps, non-finite or
    non-rigid matrices, bad sigmas)."""
    t0 = time.perf_counter()
    try:
        mode = GraphMode(mode)
    except ValueError:
        raise InputError(f"pose graph: unknown mode {mode!r} (expected 'sim3' or 'se3')") from None
    if len(poses) < 2:
        raise InputError(f"pose graph: needs at least 2 keyframe poses, got {len(poses)}")
    stamps = sorted(int(s) for s in poses)
    index = {s: i for i, s in enumerate(stamps)}
    P = _check_poses(stamps, [poses[s] for s in stamps])
    fixed = stamps[0] if fixed is None else int(fixed)
    if fixed not in index:
        raise InputError(f"pose graph: fixed keyframe {fixed} is not among the poses")
    for name, v in (("odo_sigma_rot", odo_sigma_rot), ("odo_sigma_pos_rel", odo_sigma_pos_rel),
                    ("odo_sigma_pos_min", odo_sigma_pos_min), ("odo_sigma_scale", odo_sigma_scale)):
        _check_positive(f"pose graph: {name}", v)
    huber = None
    if robust_k is not None and math.isfinite(float(robust_k)):
        huber = gtsam.noiseModel.mEstimator.Huber.Create(_check_positive("pose graph: robust_k", robust_k))
    sim = mode is GraphMode.SIM3
    dim = 7 if sim else 6
    Between = gtsam.BetweenFactorSimilarity3 if sim else gtsam.BetweenFactorPose3
    Prior = gtsam.PriorFactorSimilarity3 if sim else gtsam.PriorFactorPose3
    Diagonal, Gaussian = gtsam.noiseModel.Diagonal.Sigmas, gtsam.noiseModel.Gaussian.Information

    infos: dict[tuple[int, int], np.ndarray] = {}
    for (a, b), M in (odometry_info or {}).items():
        a, b = int(a), int(b)
        if a not in index or b not in index or index[b] != index[a] + 1:
            raise InputError(f"pose graph: odometry_info pair ({a}, {b}) is not two consecutive keyframe stamps "
                             f"(older, newer)")
        infos[(a, b)] = _check_info(M, dim, f"pose graph: odometry_info ({a}, {b})")

    # loop edges first: all input checks before any graph work
    loop_meta = []   # (edge, node indices, measured similarity, Gaussian noise)
    for n, e in enumerate(loops):
        what = f"pose graph: loop edge {n} ({e.older} -> {e.newer})"
        if int(e.older) not in index or int(e.newer) not in index:
            raise InputError(f"{what}: names a keyframe stamp that is not among the poses")
        if int(e.older) == int(e.newer):
            raise InputError(f"{what}: joins a keyframe to itself")
        Zl = check_sim3(e.T_on, f"{what}: T_on", tol=1e-5)
        s = sim3_scale(Zl)
        if not sim and abs(s - 1.0) > 1e-6:
            raise InputError(f"{what}: T_on has scale {s:.6g}, but an SE3 graph needs a rigid loop measurement")
        if not sim:
            Zl[:3, :3] = np_project_rotation(Zl[:3, :3])
        # the error's translation lies in newer's measured frame: older's units over the scale
        sig = _sigmas(mode, _check_positive(f"{what}: sigma_rot", e.sigma_rot),
                      _check_positive(f"{what}: sigma_pos", e.sigma_pos) / s,
                      _check_positive(f"{what}: sigma_scale", e.sigma_scale) if sim else 1.0)
        loop_meta.append((e, (index[int(e.older)], index[int(e.newer)]), Zl, Diagonal(sig)))

    N = len(stamps)
    values = gtsam.Values()
    for i, v in enumerate(_nodes(P, sim)):
        values.insert(i, v)
    chain = gtsam.NonlinearFactorGraph()
    chain.add(Prior(index[fixed], _nodes(P[index[fixed]][None], sim)[0], Diagonal(np.full(dim, _FIXED_SIGMA))))
    Z = _rigid_inverse(P[:-1]) @ P[1:]                     # odometry T_i^-1 T_j, (N-1, 4, 4)
    sig_pos = np.maximum(odo_sigma_pos_rel * np.linalg.norm(Z[:, :3, 3], axis=1), odo_sigma_pos_min)
    for i, z in enumerate(_nodes(Z, sim)):
        key = (stamps[i], stamps[i + 1])
        noise = (Gaussian(infos[key]) if key in infos
                 else Diagonal(_sigmas(mode, odo_sigma_rot, float(sig_pos[i]), odo_sigma_scale)))
        chain.add(Between(i, i + 1, z, noise))
    plain, robust = gtsam.NonlinearFactorGraph(chain), gtsam.NonlinearFactorGraph(chain)
    measured = _nodes(np.array([m[2] for m in loop_meta]).reshape(-1, 4, 4), sim)
    loop_factors = []                                       # without kernel: residuals, the first solve
    for (e, (a, b), Zl, gauss), z in zip(loop_meta, measured):
        loop_factors.append(Between(a, b, z, gauss))
        plain.add(loop_factors[-1])
        robust.add(Between(a, b, z, gauss if huber is None else gtsam.noiseModel.Robust.Create(huber, gauss)))

    def whitened(vals: gtsam.Values) -> list[float]:
        return [float(np.sqrt(m[3].squaredMahalanobisDistance(f.unwhitenedError(vals))))
                for m, f in zip(loop_meta, loop_factors)]

    error_before = float(robust.error(values))
    result, iterations = _lm(plain, values, max_iters)
    if huber is not None and any(r > float(robust_k) for r in whitened(result)):
        result, more = _lm(robust, result, max_iters)
        iterations += more

    if sim:
        S = np.stack([sim3_from_gtsam(result.atSimilarity3(i)) for i in range(N)])
    else:
        S = np.stack([result.atPose3(i).matrix() for i in range(N)])
    # re-anchor on the fixed node exactly: a global similarity, to which every between factor (all
    # but the prior, satisfied to solver precision anyway) is invariant; S and C stay similarities
    f = index[fixed]
    S = P[f] @ np.linalg.inv(S[f]) @ S
    S[f] = P[f]
    C = S @ _rigid_inverse(P)
    C[f] = np.eye(4)
    residuals = []
    for (e, (a, b), Zl, _), r in zip(loop_meta, whitened(result)):
        X = sim3_inverse(S[a]) @ S[b]
        sz, sx = sim3_scale(Zl), sim3_scale(X)
        residuals.append(dict(
            older=int(e.older), newer=int(e.newer),
            rot_deg=float(rotation_angle_deg((X[:3, :3] / sx) @ (Zl[:3, :3] / sz).T)),
            pos=float(np.linalg.norm(X[:3, 3] - Zl[:3, 3])), scale=float(np.log(sx / sz)), whitened=r,
            weight=1.0 if huber is None else float(huber.weight(r))))
    return PoseGraphResult(poses={s: S[i] for i, s in enumerate(stamps)},
                           increments={s: C[i] for i, s in enumerate(stamps)}, error_before=error_before,
                           error_after=float(robust.error(result)), loop_residuals=residuals,
                           iterations=iterations, seconds=time.perf_counter() - t0)
