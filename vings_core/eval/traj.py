"""Trajectory accuracy: association, ATE after Sim(3)/SE(3) alignment, RPE over path lengths.

Both trajectories are cam0 ``T_wc`` (camera-to-world) with int-nanosecond stamps. Ground truth given
for the body must be mapped to cam0 by the caller (``Source.gt_camera_trajectory()``).

Conventions (see docs/evaluation.md):

* **Association**: for every estimate stamp the ground truth (GT) is *interpolated* (SLERP on
  rotation, linear on position) when the stamp lies between two GT samples at most
  ``2 * max_dt_ns`` apart (so the nearer one is within ``max_dt_ns``; exact matches are a special
  case); otherwise the nearest GT sample within ``max_dt_ns`` is used, each GT sample at most once.
* **ATE**: RMSE of position differences after aligning the estimate onto the GT with Umeyama,
  with scale (Sim(3), the monocular convention) and without (SE(3)).
* **RPE**: evo's ``RPE`` with ``delta`` in metres of GT path, ``all_pairs=True`` and pairs chosen on
  the GT (``pairs_from_reference=True``), relative tolerance 10 %. The estimate's scale is first
  corrected with the Sim(3) scale (``rpe_correct_scale``; rigid alignment does not change relative
  poses). Reported KITTI-style per segment length ``L``: ``trans_pct = 100 * mean(|t_err|) / L`` and
  ``rot_deg_per_m = mean(angle_err_deg) / L``, plus the average over all pairs of all lengths.
"""
from __future__ import annotations

import logging
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError
from ..geometry import check_rigid_pose, np_so3_exp, np_so3_log
from ..types import Trajectory
from .align import apply_sim3, umeyama

log = logging.getLogger("vings.eval")

DEFAULT_MAX_DT_NS = 10_000_000  # 10 ms
SHORT_LENGTHS_M = (5.0, 10.0, 25.0, 50.0)
KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
ROOM_LENGTHS_M = (1.0, 2.0)
RPE_REL_TOL = 0.1


# ----------------------------------------------------------------------------------- association


def _check_sorted(traj: Trajectory, name: str) -> Trajectory:
    if len(traj) == 0:
        raise InputError(f"{name} trajectory is empty")
    st = traj.stamps_ns
    if np.any(np.diff(st) <= 0):
        order = np.argsort(st, kind="stable")
        st = st[order]
        if np.any(np.diff(st) == 0):
            raise InputError(f"{name} trajectory has duplicated time stamps")
        traj = Trajectory(st, traj.poses[order])
    if not np.all(np.isfinite(traj.poses)):
        raise InputError(f"{name} trajectory contains non-finite poses")
    bad = np.linalg.det(traj.poses[:, :3, :3]) < 0
    if bad.any():
        raise InputError(f"{name} trajectory has {int(bad.sum())} reflections (rotation blocks with "
                         f"determinant -1, a left-handed frame), e.g. at stamp {int(traj.stamps_ns[bad][0])} ns")
    # e.g. KITTI poses printed with few digits: projected onto SO(3)
    return Trajectory(traj.stamps_ns, check_rigid_pose(traj.poses, f"{name} trajectory", tol=1e-3,
                                                       error=InputError, project=True))


def _angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles (deg) of ``(N, 3, 3)`` rotations via the log map (accurate near 0)."""
    return np.degrees(np.linalg.norm(np_so3_log(R), axis=-1))


def interpolate_poses(traj: Trajectory, stamps_ns: np.ndarray) -> np.ndarray:
    """Poses of ``traj`` at ``stamps_ns`` (each within the trajectory's span): rotation by SLERP
    (geodesic on SO(3)), position linearly. Returns ``(M, 4, 4)`` float64."""
    st = np.asarray(stamps_ns, dtype=np.int64)
    g = traj.stamps_ns
    if len(st) and (st.min() < g[0] or st.max() > g[-1]):
        raise ValueError("interpolate_poses: stamps outside the trajectory's span")
    i1 = np.clip(np.searchsorted(g, st, side="left"), 0, len(g) - 1)
    i0 = np.where(g[i1] == st, i1, np.maximum(i1 - 1, 0))
    span = (g[i1] - g[i0]).astype(np.float64)
    alpha = np.where(span > 0, (st - g[i0]).astype(np.float64) / np.where(span > 0, span, 1.0), 0.0)
    P0, P1 = traj.poses[i0], traj.poses[i1]
    R0, R1 = P0[:, :3, :3], P1[:, :3, :3]
    out = np.zeros((len(st), 4, 4))
    out[:, 3, 3] = 1.0
    if len(st):
        dphi = np_so3_log(np.swapaxes(R0, 1, 2) @ R1)
        out[:, :3, :3] = R0 @ np_so3_exp(alpha[:, None] * dphi)
    out[:, :3, 3] = (1 - alpha)[:, None] * P0[:, :3, 3] + alpha[:, None] * P1[:, :3, 3]
    return out


def _span_str(st: np.ndarray) -> str:
    return f"[{st[0] * 1e-9:.3f}, {st[-1] * 1e-9:.3f}] s"


def associate_indices(est: Trajectory, gt: Trajectory, max_dt_ns: int = DEFAULT_MAX_DT_NS,
                      interpolate: bool = True) -> dict:
    """Match estimate stamps to ground truth (see the module doc). Both must be sorted.

    Returns a dict: ``est_idx`` (M,) indices into ``est``; ``gt_poses`` (M, 4, 4);
    ``gt_stamps_ns`` (M,) (the estimate's stamp where interpolated, else the GT sample's);
    ``dt_ns`` (M,) distance to the nearest GT sample; ``interpolated`` (M,) bool.
    """
    if max_dt_ns < 0:
        raise InputError(f"max_dt must be >= 0, got {max_dt_ns} ns")
    e, g = est.stamps_ns, gt.stamps_ns
    if e[-1] < g[0] - max_dt_ns or e[0] > g[-1] + max_dt_ns:
        raise InputError(f"no overlap in time: estimate spans {_span_str(e)}, ground truth spans "
                         f"{_span_str(g)} (same clock and units?)")
    n = len(g)
    i1 = np.searchsorted(g, e, side="left")  # first GT stamp >= e
    i0 = i1 - 1
    has1, has0 = i1 < n, i0 >= 0
    g1 = g[np.minimum(i1, n - 1)]
    g0 = g[np.maximum(i0, 0)]
    big = np.iinfo(np.int64).max
    d1 = np.where(has1, g1 - e, big)
    d0 = np.where(has0, e - g0, big)
    exact = has1 & (d1 == 0)
    near_is1 = d1 <= d0
    near_idx = np.where(near_is1, i1, i0)
    near_dt = np.where(near_is1, d1, d0)
    interp = np.zeros(len(e), dtype=bool)
    if interpolate:
        interp = has0 & has1 & ~exact & ((g1 - g0) <= 2 * max_dt_ns)
    nearest = ~interp & (near_dt <= max_dt_ns)
    # one GT sample per nearest match: keep the estimate closest to it
    ne = np.nonzero(nearest)[0]
    if len(ne):
        order = np.lexsort((near_dt[ne], near_idx[ne]))
        ne_sorted = ne[order]
        first = np.ones(len(ne_sorted), dtype=bool)
        first[1:] = near_idx[ne_sorted][1:] != near_idx[ne_sorted][:-1]
        keep = np.zeros(len(e), dtype=bool)
        keep[ne_sorted[first]] = True
        nearest &= keep
    sel = interp | nearest
    est_idx = np.nonzero(sel)[0]
    gt_poses = np.empty((len(est_idx), 4, 4))
    gt_stamps = np.empty(len(est_idx), dtype=np.int64)
    is_int = interp[est_idx]
    if is_int.any():
        ii = est_idx[is_int]
        gt_poses[is_int] = interpolate_poses(gt, e[ii])
        gt_stamps[is_int] = e[ii]
    if (~is_int).any():
        jj = near_idx[est_idx[~is_int]]
        gt_poses[~is_int] = gt.poses[jj]
        gt_stamps[~is_int] = g[jj]
    return {"est_idx": est_idx, "gt_poses": gt_poses, "gt_stamps_ns": gt_stamps,
            "dt_ns": near_dt[est_idx], "interpolated": is_int}


def associate(est: Trajectory, gt: Trajectory, max_dt_ns: int = DEFAULT_MAX_DT_NS,
              interpolate: bool = True, min_matches: int = 3) -> tuple[Trajectory, Trajectory]:
    """Pair estimate poses with ground truth; returns ``(est_sub, gt_sub)`` of equal length.

    ``est_sub`` keeps the matched estimate poses; ``gt_sub`` holds the GT pose at each (its stamp
    is the estimate's where interpolated, the GT sample's otherwise). Raises :class:`InputError`
    on no time overlap or fewer than ``min_matches`` matches.
    """
    est = _check_sorted(est, "estimated")
    gt = _check_sorted(gt, "ground-truth")
    a = associate_indices(est, gt, max_dt_ns, interpolate)
    _require_matches(len(a["est_idx"]), min_matches, est, gt, max_dt_ns)
    return (Trajectory(est.stamps_ns[a["est_idx"]], est.poses[a["est_idx"]]),
            Trajectory(a["gt_stamps_ns"], a["gt_poses"]))


#: below this fraction of the estimate's poses inside the ground truth's time span matched, the
#: two files almost surely use different time bases (e.g. frame index vs seconds) or rates
MIN_MATCH_FRACTION = 0.5


def _require_matches(m: int, min_matches: int, est: Trajectory, gt: Trajectory, max_dt_ns: int) -> None:
    if m < min_matches:
        raise InputError(f"too few matched poses: {m} of {len(est)} estimate poses have ground truth "
                         f"within {max_dt_ns * 1e-6:g} ms (need >= {min_matches}; estimate spans "
                         f"{_span_str(est.stamps_ns)}, ground truth {_span_str(gt.stamps_ns)}; "
                         "try a larger --max-dt-ms)")
    st, gs = est.stamps_ns, gt.stamps_ns
    inside = int(np.count_nonzero((st >= gs[0] - max_dt_ns) & (st <= gs[-1] + max_dt_ns)))
    gt_inside = int(np.count_nonzero((gs >= st[0] - max_dt_ns) & (gs <= st[-1] + max_dt_ns)))
    possible = min(inside, gt_inside)   # each GT sample matches one estimate pose at most
    if m < MIN_MATCH_FRACTION * possible:
        raise InputError(f"only {m} of the {inside} estimate poses inside the ground truth's time span "
                         f"have ground truth within {max_dt_ns * 1e-6:g} ms: the two trajectories "
                         f"most likely use different time bases or units (estimate spans "
                         f"{_span_str(est.stamps_ns)} with {len(est)} poses, ground truth "
                         f"{_span_str(gt.stamps_ns)} with {len(gt)}); an ATE over a few coincidental "
                         "matches would be meaningless")


# ------------------------------------------------------------------------------------------ ATE


def _stats(err: np.ndarray) -> dict:
    return {"rmse_m": float(np.sqrt(np.mean(err ** 2))), "mean_m": float(np.mean(err)),
            "median_m": float(np.median(err)), "max_m": float(np.max(err))}


def ate(est: Trajectory, gt: Trajectory, mode: str = "sim3") -> dict:
    """Absolute trajectory error of associated trajectories (same length, row i <-> row i).

    ``mode``: ``"sim3"`` (Umeyama with scale) or ``"se3"`` (rigid). Returns ``rmse_m``, ``mean_m``,
    ``median_m``, ``max_m`` (position errors in GT metres after alignment), ``scale``, ``rotation``
    (3x3 list), ``translation`` (3 list) of the alignment ``p_gt ~= s R p_est + t``, and ``n``.
    """
    if mode not in ("sim3", "se3"):
        raise ValueError(f"ate mode must be 'sim3' or 'se3', got {mode!r}")
    if len(est) != len(gt):
        raise InputError(f"ATE needs associated trajectories of equal length, got {len(est)} and "
                         f"{len(gt)} (call associate() first)")
    s, R, t = umeyama(est.positions, gt.positions, with_scale=(mode == "sim3"))
    aligned = s * est.positions @ R.T + t
    err = np.linalg.norm(aligned - gt.positions, axis=1)
    out = _stats(err)
    out.update(scale=float(s), rotation=R.tolist(), translation=t.tolist(), n=int(len(err)))
    return out


# ------------------------------------------------------------------------------------------ RPE


def default_rpe_lengths(path_length_m: float) -> list[float]:
    """Segment lengths (m) that fit a path: only lengths <= half the GT path length, from
    KITTI's 100..800 m when 100 m fits, else 5/10/25/50 m, else 1/2 m (room-scale clips).
    Empty when even 1 m does not fit."""
    half = 0.5 * float(path_length_m)
    for cands in (KITTI_LENGTHS_M, SHORT_LENGTHS_M, ROOM_LENGTHS_M):
        fit = [L for L in cands if L <= half]
        if fit:
            return fit
    return []


def _length_key(L: float) -> str:
    return f"{L:g}"


def rpe(est: Trajectory, gt: Trajectory, lengths_m: Optional[Sequence[float]] = None,
        correct_scale: bool = True, rel_tol: float = RPE_REL_TOL) -> Optional[dict]:
    """Relative pose error with evo over GT path lengths (see the module doc).

    ``est``/``gt`` are associated (row i <-> row i). ``lengths_m`` None picks
    :func:`default_rpe_lengths` of the GT path length. Returns None when no length fits or no
    pairs are found, else::

        {"lengths_m": [...], "pairs": int, "trans_pct": float, "rot_deg_per_m": float,
         "scale_corrected": bool,
         "per_length": {"5": {"pairs", "trans_pct", "rot_deg_per_m", "trans_mean_m",
                              "trans_rmse_m", "rot_mean_deg"}, ...}}
    """
    from evo.core import metrics
    from evo.core.filters import FilterException
    from evo.core.trajectory import PoseTrajectory3D

    if len(est) != len(gt):
        raise InputError(f"RPE needs associated trajectories of equal length, got {len(est)} and {len(gt)}")
    if len(est) < 2:
        return None
    if lengths_m is None:
        lengths_m = default_rpe_lengths(gt.path_length())
    lengths_m = sorted({float(L) for L in lengths_m})     # a length given twice counts once
    if any(L <= 0 for L in lengths_m):
        raise InputError(f"RPE segment lengths must be positive, got {lengths_m}")
    if not lengths_m:
        return None
    P = est.poses
    if correct_scale:
        s, R, t = umeyama(est.positions, gt.positions, with_scale=True)
        P = apply_sim3(P, s, R, t)
    ts = est.stamps_ns.astype(np.float64) * 1e-9
    ref = PoseTrajectory3D(poses_se3=list(gt.poses), timestamps=ts)
    tra = PoseTrajectory3D(poses_se3=list(P), timestamps=ts)
    per, all_t, all_r = {}, [], []
    for L in lengths_m:
        m = metrics.RPE(metrics.PoseRelation.translation_part, delta=L, delta_unit=metrics.Unit.meters,
                        rel_delta_tol=rel_tol, all_pairs=True, pairs_from_reference=True)
        try:
            m.process_data((ref, tra))
        except FilterException:
            log.info("RPE: no pose pairs %g m apart (+-%g%%); length skipped", L, rel_tol * 100)
            continue
        terr = np.asarray(m.error, dtype=np.float64)
        rerr = _angle_deg(np.stack(m.E)[:, :3, :3])
        if len(terr) == 0:
            continue
        per[_length_key(L)] = {
            "pairs": int(len(terr)),
            "trans_pct": float(100.0 * terr.mean() / L),
            "rot_deg_per_m": float(rerr.mean() / L),
            "trans_mean_m": float(terr.mean()),
            "trans_rmse_m": float(np.sqrt(np.mean(terr ** 2))),
            "rot_mean_deg": float(rerr.mean()),
        }
        all_t.append(terr / L)
        all_r.append(rerr / L)
    if not per:
        return None
    at, ar = np.concatenate(all_t), np.concatenate(all_r)
    return {"lengths_m": [float(k) for k in per], "pairs": int(len(at)),
            "trans_pct": float(100.0 * at.mean()), "rot_deg_per_m": float(ar.mean()),
            "scale_corrected": bool(correct_scale), "per_length": per}


# ----------------------------------------------------------------------------------- everything


def evaluate_trajectory(est: Trajectory, gt: Trajectory, max_dt_ns: int = DEFAULT_MAX_DT_NS,
                        rpe_lengths_m: Optional[Sequence[float]] = None, interpolate: bool = True,
                        rpe_correct_scale: bool = True) -> dict:
    """Full trajectory evaluation of an estimate against cam0 ground truth.

    Returns a JSON-ready dict with ``ate_sim3_m``, ``ate_se3_m`` (RMSE, m), ``sim3_scale``,
    ``rpe`` (see :func:`rpe`; None when no segment length fits), ``matched_poses``,
    ``path_length_m`` (GT path over the matched poses), and details: ``estimate_poses``,
    ``gt_poses``, ``interpolated_poses``, ``max_match_dt_ms``, ``duration_s``, ``ate_sim3`` /
    ``ate_se3`` (rmse/mean/median/max), ``sim3_alignment`` (scale, rotation, translation).
    """
    est = _check_sorted(est, "estimated")
    gt = _check_sorted(gt, "ground-truth")
    a = associate_indices(est, gt, int(max_dt_ns), interpolate)
    _require_matches(len(a["est_idx"]), 3, est, gt, int(max_dt_ns))
    est_sub = Trajectory(est.stamps_ns[a["est_idx"]], est.poses[a["est_idx"]])
    gt_sub = Trajectory(a["gt_stamps_ns"], a["gt_poses"])
    a_sim = ate(est_sub, gt_sub, "sim3")
    a_se = ate(est_sub, gt_sub, "se3")
    r = rpe(est_sub, gt_sub, rpe_lengths_m, correct_scale=rpe_correct_scale)
    st = est_sub.stamps_ns
    return {
        "ate_sim3_m": a_sim["rmse_m"],
        "ate_se3_m": a_se["rmse_m"],
        "sim3_scale": a_sim["scale"],
        "rpe": r,
        "matched_poses": int(len(est_sub)),
        "path_length_m": float(gt_sub.path_length()),
        "estimate_poses": int(len(est)),
        "gt_poses": int(len(gt)),
        "interpolated_poses": int(a["interpolated"].sum()),
        "max_match_dt_ms": float(a["dt_ns"].max() * 1e-6),
        "duration_s": float((st[-1] - st[0]) * 1e-9),
        "ate_sim3": {k: a_sim[k] for k in ("rmse_m", "mean_m", "median_m", "max_m")},
        "ate_se3": {k: a_se[k] for k in ("rmse_m", "mean_m", "median_m", "max_m")},
        "sim3_alignment": {"scale": a_sim["scale"], "rotation": a_sim["rotation"],
                           "translation": a_sim["translation"]},
    }
