"""Standstill (zero-velocity) test on the IMU, attitude from the accelerometer, and the unit check
of an accelerometer at rest.

A platform at rest may still vibrate (a multicopter on the ground with its rotors running shakes
the accelerometer by about 1 m/s^2 per reading), so the test is on short block means, not on single
readings: the window ``[t - window_s, t]`` is cut into blocks of ``block_s``; the IMU is still when
every block's mean gyro and mean specific force stay within ``gyro_tol`` (rad/s) and ``acc_tol``
(m/s^2) of the window's means. The gyro's mean is then its bias, and the accelerometer's mean the
reaction to gravity (plus its bias): ``a = R_wb^T (-g_w)`` with ``g_w = (0, 0, -g)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .preint import ImuArrays


@dataclass
class StillTest:
    """Result of :func:`imu_still`: ``still``; the window's mean gyro (rad/s) and specific force
    (m/s^2, body frame); the largest block deviations; ``why`` (in words) when not still."""

    still: bool
    gyro_mean: np.ndarray
    acc_mean: np.ndarray
    gyro_dev: float
    acc_dev: float
    why: str = ""


def imu_still(imu: ImuArrays, t_ns: int, window_s: float, block_s: float, gyro_tol: float,
              acc_tol: float) -> Optional[StillTest]:
    """Zero-velocity test on the readings in ``[t_ns - window_s, t_ns]`` (see module docs);
    ``None`` when fewer than two blocks of readings cover the window."""
    st = imu.stamps_ns
    t0 = int(t_ns - window_s * 1e9)
    i0, i1 = int(np.searchsorted(st, t0, side="left")), int(np.searchsorted(st, t_ns, side="right"))
    if i1 - i0 < 4 or (st[i1 - 1] - st[i0]) * 1e-9 < 0.75 * window_s:
        return None
    # blocks counted back from the newest reading; a partial oldest block is left out
    blk = ((st[i1 - 1] - st[i0:i1]) // int(block_s * 1e9)).astype(np.int64)
    n_blk = int(blk.max()) + 1
    counts = np.bincount(blk, minlength=n_blk).astype(np.float64)
    ok = counts >= 0.5 * counts.max()
    if ok.sum() < 2:
        return None
    g, a = imu.gyro[i0:i1], imu.accel[i0:i1]
    gb = np.stack([np.bincount(blk, g[:, k], n_blk) for k in range(3)], 1)[ok] / counts[ok, None]
    ab = np.stack([np.bincount(blk, a[:, k], n_blk) for k in range(3)], 1)[ok] / counts[ok, None]
    gm, am = g.mean(0), a.mean(0)
    gdev = float(np.abs(gb - gm).max())
    adev = float(np.abs(ab - am).max())
    why = ""
    if gdev > gyro_tol:
        why = f"gyro varies by {gdev:.3f} rad/s (> {gyro_tol:g})"
    elif adev > acc_tol:
        why = f"specific force varies by {adev:.3f} m/s^2 (> {acc_tol:g})"
    return StillTest(not why, gm, am, gdev, adev, why)


def attitude_from_gravity(acc_mean: np.ndarray) -> np.ndarray:
    """``R_wb`` (3x3) whose world z axis is opposite to gravity, from the mean specific force at
    rest (body frame): roll and pitch from the accelerometer; yaw is unobservable and set so that
    the body x axis projects onto the world x-z plane (yaw 0)."""
    z_b = np.asarray(acc_mean, np.float64) / np.linalg.norm(acc_mean)    # world z in the body frame
    x_ref = np.array([1.0, 0.0, 0.0]) if abs(z_b[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x_b = x_ref - (x_ref @ z_b) * z_b
    x_b /= np.linalg.norm(x_b)
    y_b = np.cross(z_b, x_b)
    return np.stack([x_b, y_b, z_b], 0)          # rows: world axes in the body frame = R_wb


def units_problem(acc_norm: float, gravity: float, tol: float = 0.1) -> Optional[str]:
    """Why an accelerometer reading ``acc_norm`` at rest is not REP-145 (m/s^2 with gravity
    included), or ``None`` when it is (within ``tol``, relative, of ``gravity``)."""
    if abs(acc_norm - gravity) <= tol * gravity:
        return None
    if abs(acc_norm - 1.0) <= tol:
        return (f"the accelerometer reads |a| = {acc_norm:.3f} at rest: the stream is in g, not "
                f"m/s^2 (REP-145); scale it by {gravity:g}")
    if acc_norm < 0.2 * gravity:
        return (f"the accelerometer reads |a| = {acc_norm:.3f} m/s^2 at rest: gravity was removed "
                f"from the stream; REP-145 wants the specific force with gravity included")
    return (f"the accelerometer reads |a| = {acc_norm:.3f} m/s^2 at rest, not {gravity:g} m/s^2 "
            f"(REP-145 units with gravity included)")
