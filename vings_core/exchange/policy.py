"""Write-back gates: which increments the keeper accepts."""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from ..geometry import np_pose_inverse, np_se3_log, sim3_apply_to_pose


def correction_consistency(pose_system, pose_of: Callable[[int], np.ndarray],
                           corrections: dict[int, np.ndarray], confidence: float = 0.99
                           ) -> tuple[dict[int, np.ndarray], Optional[float], Optional[float]]:
    """Which increments the keeper's visual evidence allows.

    The increments of keyframes in the keeper's BA window form a joint perturbation ``x`` of the
    window poses (left tangent of ``T_cw``); its cost under the Schur-reduced pose information ``H``
    of the last window BA (``pose_system``, :class:`~vings_core.frontend.ba.PoseSystem`, 1/px^2
    units: flow residuals over their sigma) is ``q = x^T H x``, chi-square with ``rank(H_xx)`` (at
    most ``6 n``) degrees of freedom if the increments were within the keeper's noise. ``x`` is the
    deviation of the moved poses (``pose_of(stamp)`` moved by the increment) from the BA's
    linearisation point, not just this increment: increments accepted since the last BA count too,
    so a series of small ones cannot walk away from the visual evidence. They are accepted together
    iff ``q <= chi2.ppf(confidence, dof)``. Keyframes outside the window are never accepted.
    Returns ``(accepted, q, limit)``; ``q``/``limit`` are None when no keyframe was in the window."""
    from scipy.stats import chi2

    if pose_system is None:
        return {}, None, None
    idx = {int(s): i for i, s in enumerate(pose_system.stamps_ns)}
    inwin = {s: C for s, C in corrections.items() if s in idx}
    if not inwin:
        return {}, None, None
    H = pose_system.H.detach().cpu().numpy().astype(np.float64)
    T_lin = pose_system.T_cw.detach().cpu().numpy().astype(np.float64)
    x = np.zeros(H.shape[0])
    rows = []
    for s, C in inwin.items():
        i = idx[s]
        T_wc_new = sim3_apply_to_pose(C, pose_of(s))
        # T_cw_new = exp(xi) T_cw_lin  ->  xi = log(T_cw_new T_cw_lin^-1)
        x[6 * i:6 * i + 6] = np_se3_log(np_pose_inverse(T_wc_new) @ np_pose_inverse(T_lin[i]))
        rows.extend(range(6 * i, 6 * i + 6))
    q = float(x @ H @ x)
    ev = np.linalg.eigvalsh(H[np.ix_(rows, rows)])
    dof = int((ev > 1e-9 * max(float(ev.max()), 1e-300)).sum())
    if dof == 0:            # the window's BA constrains none of these poses: nothing to check against
        return {}, None, None
    limit = float(chi2.ppf(confidence, dof))
    return (dict(inwin) if q <= limit else {}), q, limit
