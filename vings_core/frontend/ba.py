"""Dense bundle adjustment over SE(3) poses and per-pixel inverse depths (paper: "Dense BA & Vision
Factor"), vectorised in torch, float64.

Variables: ``M`` window poses ``T_cw`` (left-perturbed, tangent ``[rho, phi]``, see
:mod:`.projective`) and ``M x P`` inverse depths (``P`` BA grid pixels per keyframe). Observations:
edges ``(i, j)`` carrying a flow target ``u*_ij`` and an information weight ``w_ij`` (1/px^2) per
pixel of ``i``. The Gauss-Newton system has the block form

    [ B   E ] [dxi]   [v]
    [ E^T C ] [dd ] = [z]

``B (6M x 6M)`` pose blocks, ``E (6M x MP)`` pose-depth coupling, ``C`` diagonal. Depths are
eliminated with the Schur complement ``S = B - E C^-1 E^T``, ``y = v - E C^-1 z``; the reduced pose
system is solved by Cholesky and depths are back-substituted ``dd = C^-1 (z - E^T dxi)``.
Levenberg-Marquardt damping scales the diagonals of ``B`` and ``C`` by ``1 + lambda``; robust
(Huber/Cauchy) weights are applied by iteratively re-weighted least squares.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import torch

from ..geometry import se3_exp
from .projective import Intrinsics, adjoint, edge_residuals, linearize_edges, relative_poses
from ..profiling import profiled

DT = torch.float64


# ------------------------------------------------------------------------------------ robust


def robust_weight(rn: torch.Tensor, loss: str, delta: float) -> torch.Tensor:
    """IRLS weight ``psi(|r|) / |r|`` for residual norms ``rn`` (px)."""
    if loss == "huber":
        return torch.where(rn <= delta, torch.ones_like(rn), delta / rn.clamp_min(1e-12))
    if loss == "cauchy":
        return 1.0 / (1.0 + (rn / delta) ** 2)
    return torch.ones_like(rn)


def robust_cost(rn: torch.Tensor, loss: str, delta: float) -> torch.Tensor:
    """``rho(|r|)`` with ``rho(x) ~ x^2 / 2`` near 0 (so IRLS weights are ``rho'(x) / x``)."""
    if loss == "huber":
        return torch.where(rn <= delta, 0.5 * rn * rn, delta * (rn - 0.5 * delta))
    if loss == "cauchy":
        return 0.5 * delta * delta * torch.log1p((rn / delta) ** 2)
    return 0.5 * rn * rn


def observation_cost(r: torch.Tensor, valid: torch.Tensor, weight: torch.Tensor, loss: str,
                     delta: float) -> float:
    """Robust cost ``sum w rho(|r|)`` over valid observations: the one cost function of the BA
    (:func:`assemble`'s cost at the linearisation point, :func:`evaluate_cost` for trial points and
    :func:`motion_only`), so LM compares like with like. ``r (E,P,2)``, ``valid, weight (E,P)``."""
    rn = torch.linalg.norm(r, dim=-1)
    return float((weight * valid.to(DT) * robust_cost(rn, loss, delta)).sum())


# ------------------------------------------------------------------------------- assembly


class NormalEquations(NamedTuple):
    """Block normal equations of one linearisation (pose-depth coupling kept per keyframe)."""

    B: torch.Tensor      #: (M, M, 6, 6) pose blocks
    v: torch.Tensor      #: (M, 6) pose gradient (J^T W r)
    E: torch.Tensor      #: (M, M, P, 6): E[m, k, p] couples pose m with inverse depth p of keyframe k
    C: torch.Tensor      #: (M, P) diagonal depth block
    z: torch.Tensor      #: (M, P) depth gradient
    cost: float          #: robust cost at the linearisation point
    W: torch.Tensor      #: (E, P) effective weights used (information x robust x valid)


def finite_targets(target: torch.Tensor, weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(target, weight)`` with non-finite targets (or weights) replaced by 0 at weight 0: a
    weight-0 residual must not turn the cost into ``0 * NaN = NaN`` (which no LM step can lower,
    so BA and tracking would silently stop moving)."""
    bad = ~(torch.isfinite(target).all(-1) & torch.isfinite(weight))
    if not bool(bad.any()):
        return target, weight
    return (torch.where(bad[..., None], torch.zeros((), dtype=target.dtype), target),
            torch.where(bad, torch.zeros((), dtype=weight.dtype), weight))


def _onehot(idx: torch.Tensor, n: int) -> torch.Tensor:
    """``(n, len(idx))`` float64 matrix with ones at ``(idx[k], k)``: ``O @ X`` sums rows of ``X``
    into the slots ``idx``."""
    O = torch.zeros(n, idx.shape[0], dtype=DT)
    O[idx, torch.arange(idx.shape[0])] = 1.0
    return O


def assemble(T_cw: torch.Tensor, d: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
             rays: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, K: Intrinsics,
             loss: str = "huber", delta: float = 2.0) -> NormalEquations:
    """Linearise all edges and scatter the Hessian blocks (paper Eq. "hessian matrix")."""
    M, P = d.shape
    target, weight = finite_targets(target, weight)
    lin = linearize_edges(T_cw, d, ii, jj, rays, target, K, need_ji=False)
    rn = torch.linalg.norm(lin.r, dim=-1)
    cost = observation_cost(lin.r, lin.valid, weight, loss, delta)
    W = weight * lin.valid.to(DT) * robust_weight(rn, loss, delta)
    nE = ii.shape[0]
    # Only J_j is formed: J_i = -J_j Adj(T_ji), so every i-block is an adjoint transform of a
    # j-block (H_ii = A^T H_jj A, H_ij = -A^T H_jj, v_i = -A^T v_j, E_i = -A^T E_j).
    A = adjoint(relative_poses(T_cw, ii, jj))               # (E,6,6)
    At = A.transpose(1, 2)
    Jf = lin.Jj.reshape(nE, P * 2, 6)
    WJ = lin.Jj * W[..., None, None]                        # (E,P,2,6)
    WJf = WJ.reshape(nE, P * 2, 6)
    Hjj = WJf.transpose(1, 2) @ Jf                          # (E,6,6)
    vj = (WJf.transpose(1, 2) @ lin.r.reshape(nE, P * 2, 1))[..., 0]   # (E,6)
    Ej = (WJ * lin.Jd[..., None]).sum(2)                    # (E,P,6)
    Ei = -(Ej @ A)                                          # (E,P,6) = (-A^T E_j^T)^T
    Hij = -(At @ Hjj)
    Hii = -(Hij @ A)
    vi = -(At @ vj[..., None])[..., 0]
    Ce = (W[..., None] * lin.Jd * lin.Jd).sum(-1)           # (E,P)
    ze = (W[..., None] * lin.Jd * lin.r).sum(-1)            # (E,P)

    # scatter-add by one-hot matrix products (much faster than index_add_ on CPU)
    pair = torch.cat([ii * M + ii, ii * M + jj, jj * M + ii, jj * M + jj])
    B = _onehot(pair, M * M) @ torch.cat([Hii, Hij, Hij.transpose(1, 2), Hjj]).reshape(4 * nE, 36)
    v = _onehot(torch.cat([ii, jj]), M) @ torch.cat([vi, vj])
    E = _onehot(torch.cat([ii * M + ii, jj * M + ii]), M * M) @ torch.cat([Ei, Ej]).reshape(2 * nE, P * 6)
    Oi = _onehot(ii, M)
    C = Oi @ Ce
    z = Oi @ ze
    return NormalEquations(B.reshape(M, M, 6, 6), v, E.reshape(M, M, P, 6), C, z, cost, W)


def dense_matrix(ne: NormalEquations) -> tuple[torch.Tensor, torch.Tensor]:
    """The full ``(6M + MP)`` square system ``[[B, E], [E^T, diag C]]`` and right side ``[v, z]``
    (reference for tests; poses first in window order, then depths keyframe-major)."""
    M, _, P, _ = ne.E.shape
    Bd = ne.B.permute(0, 2, 1, 3).reshape(6 * M, 6 * M)
    Ed = ne.E.permute(0, 3, 1, 2).reshape(6 * M, M * P)
    top = torch.cat([Bd, Ed], 1)
    bot = torch.cat([Ed.T, torch.diag(ne.C.reshape(-1))], 1)
    return torch.cat([top, bot], 0), torch.cat([ne.v.reshape(-1), ne.z.reshape(-1)])


# ---------------------------------------------------------------------------------- schur


class ReducedSystem(NamedTuple):
    """Schur complement over the poses ``idx`` (others held fixed)."""

    S: torch.Tensor      #: (6F, 6F) reduced pose Hessian
    y: torch.Tensor      #: (6F,) reduced gradient
    Ef: torch.Tensor     #: (6F, MP) coupling rows of the kept poses
    Cinv: torch.Tensor   #: (MP,) inverse (damped) depth diagonal
    z: torch.Tensor      #: (MP,) depth gradient
    idx: torch.Tensor    #: (F,) kept pose indices (window order)


def schur_reduce(ne: NormalEquations, idx: torch.Tensor, lam: float = 0.0,
                 eps_c: float = 1e-9, eps_b: float = 0.0) -> ReducedSystem:
    """Eliminate all inverse depths; keep poses ``idx``. ``lam`` is LM damping (diagonals of B and
    C times ``1 + lam``); ``eps_c`` a small absolute depth regulariser so unobserved depths (C = 0)
    stay finite; ``eps_b`` is added to the pose diagonal."""
    M, _, P, _ = ne.E.shape
    F = idx.shape[0]
    Bf = ne.B[idx][:, idx].permute(0, 2, 1, 3).reshape(6 * F, 6 * F)
    if lam > 0 or eps_b > 0:
        Bf = Bf + torch.diag(lam * torch.diagonal(Bf) + eps_b)
    Ef = ne.E[idx].permute(0, 3, 1, 2).reshape(6 * F, M * P)
    C = ne.C.reshape(-1) * (1.0 + lam) + eps_c
    Cinv = 1.0 / C
    z = ne.z.reshape(-1)
    EC = Ef * Cinv
    S = Bf - EC @ Ef.T
    S = 0.5 * (S + S.T)
    y = ne.v[idx].reshape(-1) - EC @ z
    return ReducedSystem(S, y, Ef, Cinv, z, idx)


def jittered_cholesky(S: torch.Tensor, jitter: float) -> torch.Tensor:
    """Lower Cholesky factor of ``S + eps I``: ``eps`` starts at ``jitter`` x the mean |diagonal| and
    grows 100x per failed try (6 tries), so a nearly singular gauge direction does not break it."""
    scale = torch.diagonal(S).abs().mean().clamp_min(1e-30)
    eye = torch.eye(S.shape[0], dtype=S.dtype)
    for k in range(6):
        L, info = torch.linalg.cholesky_ex(S + eye * scale * jitter * (100.0 ** k))
        if int(info) == 0:
            break
    return L


def solve_reduced(rs: ReducedSystem, jitter: float = 1e-12) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve ``S dxi = y`` (Cholesky, with a tiny relative jitter if needed) and back-substitute
    ``dd = C^-1 (z - E^T dxi)``. Returns ``(dxi (F,6), dd (MP,))``."""
    if rs.S.shape[0] == 0:
        return torch.zeros(0, 6, dtype=DT), rs.Cinv * rs.z
    L = jittered_cholesky(rs.S, jitter)
    dxi = torch.cholesky_solve(rs.y[:, None], L)[:, 0]
    dd = rs.Cinv * (rs.z - rs.Ef.T @ dxi)
    return dxi.reshape(-1, 6), dd


# ------------------------------------------------------------------------------------- LM


@dataclass
class BAResult:
    T_cw: torch.Tensor
    d: torch.Tensor
    cost0: float
    cost: float
    iters: int
    accepted: int
    lam: float
    ne: Optional[NormalEquations] = None       #: linearisation at the final estimate
    history: list = field(default_factory=list)
    fixed: Optional[torch.Tensor] = None       #: (M,) bool: the poses held fixed (the gauge)


def evaluate_cost(T_cw, d, ii, jj, rays, target, weight, K, loss, delta) -> float:
    """Robust cost at ``(T_cw, d)``: the same residuals, validity test (:func:`edge_residuals`) and
    cost (:func:`observation_cost`) as :func:`assemble`, so a trial point's cost is comparable
    with the cost of the linearisation point."""
    r, valid = edge_residuals(T_cw, d, ii, jj, rays, target, K)
    return observation_cost(r, valid, weight, loss, delta)


GAUGE_MIN_BASELINE_FRAC = 0.03
"""See :func:`gauge_mask`: a fixed pose must have at least this fraction of the window's largest
baseline to the oldest pose to count as fixing the monocular scale. Small on purpose: with the two
oldest poses held, the marginal depth std grows by ~10 % at 0.03 and ~50 % at 0.01 over the best
gauge (4x at 0.003, meaningless at 0); in the synthetic room/street benchmarks the two oldest
window poses always had >= 0.05 of the largest baseline, so normal operation is unchanged."""


def gauge_mask(T_cw: torch.Tensor, n_fixed: int,
               min_baseline_frac: float = GAUGE_MIN_BASELINE_FRAC) -> torch.Tensor:
    """``(M,)`` bool: the window poses held fixed to remove the gauge (rigid motion and, with two
    or more fixed poses, the monocular scale). ``T_cw (M,4,4)`` in window order (oldest first).

    Normally the ``n_fixed`` oldest poses. Scale is only fixed if some fixed pose has a baseline to
    the oldest one: when none of poses ``1..n_fixed-1`` has a baseline (camera centre distance) of
    at least ``min_baseline_frac`` x the window's largest baseline to the oldest pose (the camera
    panned in place: keyframes are triggered by flow, which rotation alone produces), the youngest
    of them is replaced by the *oldest* pose that has. If no pose has a baseline at all (pure
    rotation everywhere) the ``n_fixed`` oldest poses are kept. ``n_fixed >= M`` fixes all."""
    M = T_cw.shape[0]
    fixed = torch.zeros(M, dtype=torch.bool)
    n = max(0, min(int(n_fixed), M))
    fixed[:n] = True
    if n < 2 or n >= M:
        return fixed
    R, t = T_cw[:, :3, :3], T_cw[:, :3, 3]
    c = -(R.transpose(1, 2) @ t[..., None])[..., 0]          # camera centres
    base = torch.linalg.norm(c - c[:1], dim=-1)                # baseline to the oldest pose
    bmax = float(base[1:].max())
    if not (bmax > 1e-9):                                       # no baseline anywhere (or NaN)
        return fixed
    ok = base >= min_baseline_frac * bmax
    ok[0] = False
    if bool(ok[1:n].any()):
        return fixed
    fixed[n - 1] = False
    fixed[int(torch.nonzero(ok)[0, 0])] = True
    return fixed


def apply_update(T_cw: torch.Tensor, d: torch.Tensor, idx: torch.Tensor, dxi: torch.Tensor,
                 dd: torch.Tensor, d_lo: torch.Tensor, d_hi: torch.Tensor):
    T = T_cw.clone()
    if idx.numel():
        T[idx] = se3_exp(dxi) @ T_cw[idx]
    dn = torch.minimum(torch.maximum(d + dd.reshape(d.shape), d_lo), d_hi)
    return T, dn


@profiled("tracking", "window BA")
def bundle_adjust(T_cw: torch.Tensor, d: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                  rays: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, K: Intrinsics,
                  n_fixed: int = 1, iters: int = 6, loss: str = "huber", delta: float = 2.0,
                  lam: float = 1e-4, d_bounds: tuple[float, float] = (1e-6, 1e6),
                  fixed_mask: Optional[torch.Tensor] = None, tol: float = 1e-6) -> BAResult:
    """Levenberg-Marquardt dense BA. Poses ``0..n_fixed-1`` (or ``fixed_mask``) stay fixed.

    ``T_cw (M,4,4)``, ``d (M,P)`` inverse depths, ``target (E,P,2)`` flow targets in ``j``,
    ``weight (E,P)`` information (1/px^2). ``d_bounds`` clamps inverse depths. Returns the refined
    estimate, costs and the linearisation at the final point.
    """
    T_cw = T_cw.to(DT)
    d = d.to(DT)
    target, weight = finite_targets(target, weight)
    M = T_cw.shape[0]
    fixed = torch.zeros(M, dtype=torch.bool)
    fixed[:n_fixed] = True
    if fixed_mask is not None:
        fixed |= fixed_mask
    idx = torch.nonzero(~fixed)[:, 0]
    d_lo = torch.full_like(d, d_bounds[0])
    d_hi = torch.full_like(d, d_bounds[1])
    ne = assemble(T_cw, d, ii, jj, rays, target, weight, K, loss, delta)
    # trial points are compared with the current point's cost computed the same way (the two
    # agree exactly: assemble and evaluate_cost share edge_residuals and observation_cost)
    cost0 = cost = evaluate_cost(T_cw, d, ii, jj, rays, target, weight, K, loss, delta)
    accepted = 0
    hist = [cost]
    it = 0
    for it in range(1, iters + 1):
        rs = schur_reduce(ne, idx, lam=lam)
        dxi, dd = solve_reduced(rs)
        if not (torch.isfinite(dxi).all() and torch.isfinite(dd).all()):
            lam *= 10
            continue
        T_new, d_new = apply_update(T_cw, d, idx, dxi, dd, d_lo, d_hi)
        new_cost = evaluate_cost(T_new, d_new, ii, jj, rays, target, weight, K, loss, delta)
        if new_cost < cost:
            rel = (cost - new_cost) / max(cost, 1e-30)
            T_cw, d, cost = T_new, d_new, new_cost
            accepted += 1
            lam = max(lam / 5.0, 1e-7)
            ne = assemble(T_cw, d, ii, jj, rays, target, weight, K, loss, delta)
            hist.append(cost)
            if rel < tol:
                break
        else:
            lam = min(lam * 8.0, 1e4)
    return BAResult(T_cw, d, cost0, cost, it, accepted, lam, ne, hist, fixed)


def triangulate_grid(T_cw: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor, rays: torch.Tensor,
                     target: torch.Tensor, weight: torch.Tensor, K: Intrinsics,
                     candidates: torch.Tensor, loss: str = "huber", delta: float = 2.0) -> torch.Tensor:
    """Per-pixel inverse depth by exhaustive 1-D search with poses fixed: for every keyframe pixel,
    the candidate (``(C,)`` inverse depths) with the smallest robust reprojection cost over its
    outgoing edges. A safe starting point for Gauss-Newton when nothing is known (two-view
    initialisation); vectorised over candidates, edges and pixels. Returns ``(M, P)``."""
    M = T_cw.shape[0]
    P = rays.shape[0]
    nC = candidates.shape[0]
    cost = torch.zeros(nC, M, P, dtype=DT)
    for c in range(nC):              # C ~ 48 small batched evaluations (not a loop over pixels)
        d = torch.full((M, P), float(candidates[c]), dtype=DT)
        r, valid = edge_residuals(T_cw, d, ii, jj, rays, target, K)     # the BA's validity test
        rn = torch.linalg.norm(r, dim=-1)
        pen = torch.where(valid, robust_cost(rn, loss, delta), torch.full_like(rn, 1e6))
        cost[c] = _onehot(ii, M) @ (weight * pen)
    best = candidates.to(DT)[cost.argmin(0)]               # (M,P)
    seen = (_onehot(ii, M) @ weight) > 0
    for m in range(M):                                       # unobserved pixels: keyframe median
        if seen[m].any():
            best[m, ~seen[m]] = best[m, seen[m]].median()
    return best


# ---------------------------------------------------------------- reduced pose system export


@dataclass
class PoseSystem:
    """Schur-reduced visual pose system of one BA window, for a linear (Hessian) factor.

    Energy: ``E(x) = 1/2 x^T H x - x^T v`` (+ const), ``x = [xi_0; ...; xi_{M-1}]`` stacked in
    window order (``stamps_ns``, oldest first). ``xi_k`` (6) is the left perturbation of the
    world-to-camera pose ``T_{c_k w} <- exp(xi_k) T_{c_k w}``, order ``[rho (m), phi (rad)]`` (the
    paper's :math:`\\xi_w^{c_k}`); equivalently a right perturbation ``T_wc <- T_wc exp(-xi)`` of
    the camera pose. Linearised at ``T_cw`` (the poses after BA); units: information in
    1/px^2 x (px / tangent)^2. Depths are eliminated; no gauge is fixed (H has a 7-dim null space
    in monocular mode: rigid motion and scale). Use :meth:`to_gtsam_ordering` for GTSAM's Pose3.
    """

    stamps_ns: list
    T_cw: torch.Tensor   #: (M,4,4) linearisation points
    H: torch.Tensor      #: (6M,6M)
    v: torch.Tensor      #: (6M,)

    def to_gtsam_ordering(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(G, g)`` for GTSAM ``Pose3`` values of the camera poses ``T_wc`` with GTSAM's right
        perturbation ``T_wc <- T_wc Exp([phi, rho])``: per block ``delta_gtsam = -P xi`` where ``P``
        swaps ``[rho, phi] -> [phi, rho]``. GTSAM's HessianFactor error ``1/2 x^T G x - x^T g``."""
        M = len(self.stamps_ns)
        perm = torch.tensor([3, 4, 5, 0, 1, 2])
        full = torch.cat([perm + 6 * k for k in range(M)])
        G = self.H[full][:, full]
        g = -self.v[full]
        return G, g


@profiled("tracking", "pose system")
def reduced_pose_system(ne: NormalEquations, T_cw: torch.Tensor, stamps_ns: list,
                        eps_c: float = 1e-9) -> PoseSystem:
    """Schur complement of the linearisation ``ne`` over all window poses (no damping)."""
    M = T_cw.shape[0]
    rs = schur_reduce(ne, torch.arange(M), lam=0.0, eps_c=eps_c)
    return PoseSystem(list(stamps_ns), T_cw.clone(), rs.S, rs.y)


# --------------------------------------------------------------------------- motion only


@dataclass
class MotionResult:
    T_cw: torch.Tensor       #: (4,4) refined world-to-camera pose of the frame
    H: torch.Tensor          #: (6,6) information of the left tangent of T_cw
    rms_px: float            #: weighted RMS residual (px)
    inlier_frac: float       #: fraction of weighted observations within the robust width
    cost: float
    iters: int


def depth_inflated_weight(weight: torch.Tensor, Jd: torch.Tensor,
                          d_var: Optional[torch.Tensor]) -> torch.Tensor:
    """Flow information reduced by the depth uncertainty at one linearisation:
    ``1/w <- 1/w + |J_d|^2 var_d`` (``w / (1 + w |J_d|^2 var_d)``); pixels whose depth variance is
    infinite (or NaN: unknown) get weight 0 whatever ``J_d`` (at zero baseline ``J_d = 0`` would
    otherwise give them full weight). ``weight (N,P)``, ``Jd (N,P,2)``, ``d_var (N,P)`` or None."""
    if d_var is None:
        return weight
    var = d_var.to(weight.dtype)
    known = torch.isfinite(var)
    jv = (Jd ** 2).sum(-1) * torch.where(known, var.clamp_min(0.0), torch.zeros_like(var))
    w = weight / (1.0 + weight * jv)
    return torch.where(known & (weight > 0), w, torch.zeros_like(weight))


@profiled("tracking", "motion-only BA")
def motion_only(T_kf: torch.Tensor, d_kf: torch.Tensor, rays: torch.Tensor, target: torch.Tensor,
                weight: torch.Tensor, K: Intrinsics, T_init: torch.Tensor, iters: int = 8,
                loss: str = "huber", delta: float = 2.0,
                d_var: Optional[torch.Tensor] = None) -> MotionResult:
    """Pose-only Gauss-Newton (LM-damped) of one frame against ``N`` keyframes with fixed poses and
    depths. ``T_kf (N,4,4)`` ``T_cw``, ``d_kf (N,P)``, ``target (N,P,2)``, ``weight (N,P)``
    information (1/px^2). ``d_var (N,P)``: optional inverse-depth variances of the keyframes; the
    depth error they cause is added to the flow noise (``1/w <- 1/w + |J_d|^2 var``, re-evaluated
    at every iteration's linearisation point, see :func:`depth_inflated_weight`), so pixels with
    unknown depth do not pull the pose, also when the initial guess has no baseline to the
    keyframe. Within one iteration the current and the trial cost use the same weights."""
    N = T_kf.shape[0]
    target, weight = finite_targets(target, weight)
    weight = weight.to(DT)
    ii = torch.arange(N)
    jj = torch.full((N,), N, dtype=torch.long)
    T = torch.cat([T_kf.to(DT), T_init.to(DT)[None]], 0)
    lam = 1e-4
    dpad = torch.cat([d_kf.to(DT), torch.zeros_like(d_kf[:1], dtype=DT)], 0)
    it = 0
    for it in range(1, iters + 1):
        lin = linearize_edges(T, dpad, ii, jj, rays, target, K, need_ji=False)
        w_it = depth_inflated_weight(weight, lin.Jd, d_var)     # weights of this iteration
        cost = observation_cost(lin.r, lin.valid, w_it, loss, delta)
        rn = torch.linalg.norm(lin.r, dim=-1)
        W = w_it * lin.valid.to(DT) * robust_weight(rn, loss, delta)
        Jj = lin.Jj.reshape(-1, 2, 6)
        Wf = W.reshape(-1)
        WJ = Jj * Wf[:, None, None]
        H = torch.einsum("nki,nkj->ij", WJ, Jj)
        g = torch.einsum("nki,nk->i", WJ, lin.r.reshape(-1, 2))
        Hd = H + torch.diag(lam * torch.diagonal(H) + 1e-9)
        try:
            dxi = torch.linalg.solve(Hd, g)
        except RuntimeError:
            break
        Tn = T.clone()
        Tn[N] = se3_exp(dxi) @ T[N]
        new_cost = evaluate_cost(Tn, dpad, ii, jj, rays, target, w_it, K, loss, delta)
        if new_cost <= cost:
            T = Tn
            lam = max(lam / 5, 1e-7)
            if float(dxi.norm()) < 1e-7:
                break
        else:
            lam *= 8
            if lam > 1e4:
                break
    lin = linearize_edges(T, dpad, ii, jj, rays, target, K, need_ji=False)
    w_fin = depth_inflated_weight(weight, lin.Jd, d_var)
    cost = observation_cost(lin.r, lin.valid, w_fin, loss, delta)
    rn = torch.linalg.norm(lin.r, dim=-1)
    Wv = w_fin * lin.valid.to(DT)
    sw = float(Wv.sum())
    rms = float(torch.sqrt((Wv * rn * rn).sum() / max(sw, 1e-12))) if sw > 0 else float("inf")
    inl = float((Wv * (rn <= delta).to(DT)).sum() / max(sw, 1e-12)) if sw > 0 else 0.0
    W = Wv * robust_weight(rn, loss, delta)
    Jj = lin.Jj.reshape(-1, 2, 6)
    H = torch.einsum("nki,nkj->ij", Jj * W.reshape(-1)[:, None, None], Jj)
    return MotionResult(T[N], H, rms, inl, cost, it)
