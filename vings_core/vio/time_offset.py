"""Online estimate of the camera-IMU time offset ``td`` (``t_imu = t_cam + td``) from rotations.

The visual trajectory gives the body's relative rotation ``dR_vis`` between consecutive tracked
frames ``i, j`` (camera clock); the gyroscope integrated over ``[t_i + d, t_j + d]`` (``d``: the
correction to the offset in use) at bias ``b_g`` gives ``dR_imu(d, b_g)``. Rotations carry no scale,
so this works before the metric alignment. The residual ``r = Log(dR_vis^T dR_imu)`` is, to first
order (right perturbations)::

    r(d, b_g) = r_0 + J_bg (b_g - b_g0) + (w_j - dR_imu^T w_i) (d - d_0)

with ``w_i``, ``w_j`` the bias-corrected rates at the interval's ends: moving both ends later by
``d`` removes ``w_i d`` at the start and adds ``w_j d`` at the end. Gauss-Newton on ``(b_g, d)``
re-integrates at each step. The offset is observable only while the body rotates; the test
``min_rate`` (RMS angular rate, rad/s) refuses it otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..geometry import np_so3_exp, np_so3_log
from .preint import ImuArrays


@dataclass
class TdEstimate:
    """``delta_s``: correction to add to the offset in use (s); ``std_s`` its standard deviation
    (least squares); ``gyro_bias`` (rad/s); ``rms_rad``: residual RMS; ``pairs`` used; ``rate``:
    RMS angular rate (rad/s); ``ok`` and ``why`` (in words when refused)."""

    delta_s: float
    std_s: float
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rms_rad: float = float("nan")
    pairs: int = 0
    rate: float = 0.0
    ok: bool = False
    why: str = ""


class GyroAttitude:
    """Gyro-integrated attitude over a stretch of readings (each held from its stamp to the next:
    pass :func:`.preint.centred` readings), queried at any time: ``Q(t)`` (the
    rotation from the first reading's body frame to the body at ``t``) and ``S(t)``, the running
    sum of ``Q dt`` that gives the first-order bias Jacobian of a relative rotation (``J_R_bg`` of
    ``Q(t0)^T Q(t1)`` is about ``-Q(t1)^T (S(t1) - S(t0))``, the right Jacobians taken as I)."""

    def __init__(self, imu: ImuArrays, t0_ns: int, t1_ns: int, bg: np.ndarray):
        st = imu.stamps_ns
        i0 = max(int(np.searchsorted(st, t0_ns, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(st, t1_ns, side="right")), len(st))
        self.t = st[i0:i1]
        self.w = imu.gyro[i0:i1] - bg
        dt = np.diff(self.t) * 1e-9
        inc = np_so3_exp(self.w[:-1] * dt[:, None])
        Q = np.empty((len(self.t), 3, 3))
        Q[0] = np.eye(3)
        for k in range(len(dt)):                 # a few hundred 3x3 products
            Q[k + 1] = Q[k] @ inc[k]
        self.Q = Q
        self.S = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(Q[1:] * dt[:, None, None], axis=0)])

    def at(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Q(t)``, ``S(t)`` (``(M, 3, 3)``) and the bias-corrected rate ``w(t)`` (``(M, 3)``)
        holding at camera-clock times ``t_ns``."""
        k = np.clip(np.searchsorted(self.t, t_ns, side="right") - 1, 0, len(self.t) - 1)
        tau = (np.asarray(t_ns) - self.t[k]) * 1e-9
        Qt = self.Q[k] @ np_so3_exp(self.w[k] * tau[:, None])
        return Qt, self.S[k] + Qt * tau[:, None, None], self.w[k]


def estimate_td(imu: ImuArrays, stamps_ns: Sequence[int], R_wb: Sequence[np.ndarray],
                bg0: np.ndarray | None = None, pair_s: float = 0.5, max_abs_s: float = 0.05,
                min_rate: float = 0.1, max_std_s: float = 1e-3, iters: int = 6,
                min_pairs: int = 10, pairs: tuple[np.ndarray, np.ndarray] | None = None) -> TdEstimate:
    """Offset correction from body rotations ``R_wb`` (3x3, world from body) at camera-clock
    ``stamps_ns`` and the IMU ``imu`` on the camera clock of the offset in use, its stamps centred
    (:func:`.preint.centred`; see module docs). The rotations compared are ``pairs`` (index arrays
    ``(i, j)``, ``t_i < t_j``; only the relative rotation of each pair is used, so each pair may
    have its own world frame), by default each frame with the first one at least ``pair_s`` later
    (a longer interval makes the rates at its ends differ more, which is what the offset is seen
    through; ``stamps_ns`` increasing). Refused (``ok`` False) with too few pairs, too little
    rotation, a correction beyond ``max_abs_s``, or a standard deviation above ``max_std_s``."""
    st = np.asarray(stamps_ns, np.int64)
    R = np.asarray(R_wb, np.float64).reshape(-1, 3, 3)
    bg = np.zeros(3) if bg0 is None else np.asarray(bg0, np.float64).copy()
    margin = int(2 * max_abs_s * 1e9) + 1
    if pairs is None:
        j = np.searchsorted(st, st + int(pair_s * 1e9), side="left")
        i = np.flatnonzero(j < len(st))
        j = j[i]
    else:
        i, j = (np.asarray(a, np.int64) for a in pairs)
    if len(imu.stamps_ns):
        lo, hi = imu.stamps_ns[0] + margin, imu.stamps_ns[-1] - margin
        inside = (st[i] >= lo) & (st[j] <= hi)
        i, j = i[inside], j[inside]
    else:
        i, j = i[:0], j[:0]
    if len(i) < min_pairs:
        return TdEstimate(0.0, float("inf"), bg, pairs=len(i),
                          why=f"{len(i)} frame pairs with IMU around them (need {min_pairs})")
    dR_vis = R[i].transpose(0, 2, 1) @ R[j]
    ang = np_so3_log(dR_vis)
    rate = float(np.sqrt(np.mean(np.sum(ang ** 2, 1) / ((st[j] - st[i]) * 1e-9) ** 2)))
    if rate < min_rate:
        return TdEstimate(0.0, float("inf"), bg, pairs=len(i), rate=rate,
                          why=f"RMS angular rate {rate:.3f} rad/s below {min_rate:g}: the offset is "
                              f"not observable")
    d = 0.0
    t_lo, t_hi = int(st[i].min()), int(st[j].max())
    for _ in range(iters):
        dn = int(round(d * 1e9))
        att = GyroAttitude(imu, t_lo + dn - margin, t_hi + dn + margin, bg)
        Qi, Si, wi = att.at(st[i] + dn)
        Qj, Sj, wj = att.at(st[j] + dn)
        dR = Qi.transpose(0, 2, 1) @ Qj
        r = np_so3_log(dR_vis.transpose(0, 2, 1) @ dR)
        J_bg = -Qj.transpose(0, 2, 1) @ (Sj - Si)
        J_d = wj - np.einsum("nji,nj->ni", dR, wi)          # w_j - dR^T w_i
        A = np.concatenate([J_bg, J_d[:, :, None]], axis=2).reshape(-1, 4)
        rr = r.reshape(-1)
        H = A.T @ A
        try:
            step = -np.linalg.solve(H, A.T @ rr)
        except np.linalg.LinAlgError:
            return TdEstimate(0.0, float("inf"), bg, pairs=len(i), rate=rate,
                              why="singular system (no rotation about enough axes)")
        bg, d = bg + step[:3], d + float(step[3])
        if abs(d) > 2 * max_abs_s or abs(step[3]) < 1e-6:
            break
    rms = float(np.sqrt(np.mean(rr ** 2)))
    sigma2 = float(rr @ rr) / max(len(rr) - 4, 1)
    try:
        std = float(np.sqrt(sigma2 * np.linalg.inv(H)[3, 3]))
    except np.linalg.LinAlgError:
        std = float("inf")
    out = TdEstimate(d, std, bg, rms, len(i), rate, True, "")
    if not abs(d) <= max_abs_s:
        out.ok, out.why = False, f"correction {1e3 * d:.1f} ms beyond +-{1e3 * max_abs_s:g} ms"
    elif not std <= max_std_s:
        out.ok, out.why = False, f"standard deviation {1e3 * std:.2f} ms above {1e3 * max_std_s:g} ms"
    return out
