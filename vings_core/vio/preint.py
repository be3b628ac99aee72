"""IMU pre-integration between two times (Forster et al. 2017, on-manifold pre-integration), in
numpy as the obvious reference and as GTSAM's ``PreintegratedCombinedMeasurements`` for the factor
graph. Both integrate the same piecewise-constant signal: each reading holds from its stamp to the
next (zero-order hold), and the interval ``[t0, t1]`` is cut at ``t0`` and ``t1``.

Model (world gravity ``g_w``, body rotation ``R_i`` at ``t0``, biases held fixed)::

    R_j = R_i dR          v_j = v_i + g_w dt + R_i dv          p_j = p_i + v_i dt + 1/2 g_w dt^2 + R_i dp

Units: seconds, metres, radians; ``stamps`` in integer nanoseconds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError


def _exp_np(phi: np.ndarray) -> np.ndarray:
    """SO(3) exponential (Rodrigues)."""
    th = float(np.linalg.norm(phi))
    K = hat(phi)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th ** 2 * K @ K


def so3_log_np(R: np.ndarray) -> np.ndarray:
    """SO(3) logarithm (rotation vector, rad); accurate near 0 and near pi."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-6:
        return 0.5 * w
    if np.pi - th < 1e-4:
        # near pi: the axis from the symmetric part (w vanishes there)
        B = (R + np.eye(3)) / 2.0
        k = int(np.argmax(np.diag(B)))
        axis = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
        axis *= np.sign(axis @ w) if abs(axis @ w) > 0 else 1.0
        return th * axis / np.linalg.norm(axis)
    return th / (2.0 * np.sin(th)) * w


def hat(w: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[w]_x`` of a 3-vector."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _right_jacobian(phi: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(phi))
    if th < 1e-8:
        return np.eye(3) - 0.5 * hat(phi)
    K = hat(phi / th)
    return np.eye(3) - (1 - np.cos(th)) / th * K + (th - np.sin(th)) / th * K @ K


@dataclass
class ImuArrays:
    """An IMU stream as arrays: ``stamps_ns`` (N,) int64 increasing, ``gyro`` (N, 3) rad/s,
    ``accel`` (N, 3) m/s^2 (gravity included), body frame."""

    stamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    @classmethod
    def from_samples(cls, samples) -> "ImuArrays":
        """From a list of :class:`~vings_core.types.ImuSample`."""
        st = np.array([s.stamp_ns for s in samples], np.int64)
        g = np.array([s.gyro for s in samples], np.float64).reshape(-1, 3)
        a = np.array([s.accel for s in samples], np.float64).reshape(-1, 3)
        return cls(st, g, a)


def centred(imu: ImuArrays) -> ImuArrays:
    """``imu`` with its stamps moved back by half the median reading period. Readings are
    instantaneous samples; integrating each one from its stamp to the next (zero-order hold)
    would delay the integrated motion by half a period (2.5 ms at 200 Hz), which shows as a bias of
    the estimated camera-IMU offset. With the shift each reading holds over the half periods
    around its stamp."""
    if len(imu.stamps_ns) < 2:
        return imu
    half = int(np.median(np.diff(imu.stamps_ns[-400:]))) // 2
    return ImuArrays(imu.stamps_ns - half, imu.gyro, imu.accel)


def hold_intervals(imu: ImuArrays, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The zero-order-hold pieces of ``[t0_ns, t1_ns]``: durations ``dt`` (K,) s and the gyro and
    accel readings ``(K, 3)`` that hold over them. Raises :class:`InputError` when no reading is at
    or before ``t0_ns`` or ``t1_ns <= t0_ns``."""
    if t1_ns <= t0_ns:
        raise InputError(f"IMU pre-integration: interval [{t0_ns}, {t1_ns}] ns is empty")
    st = imu.stamps_ns
    first = int(np.searchsorted(st, t0_ns, side="right")) - 1
    if first < 0:
        raise InputError(f"IMU pre-integration: no IMU reading at or before {t0_ns} ns (first at "
                         f"{int(st[0]) if len(st) else 'none'})")
    last = int(np.searchsorted(st, t1_ns, side="left"))          # readings strictly before t1
    idx = np.arange(first, last)
    edges = np.concatenate([[t0_ns], st[first + 1:last], [t1_ns]]).astype(np.int64)
    dt = np.diff(edges) * 1e-9
    return dt, imu.gyro[idx], imu.accel[idx]


@dataclass
class Preintegrated:
    """Pre-integrated IMU between two times, at the biases ``bg``, ``ba``, with first-order bias
    Jacobians (``J_R_bg``: right-perturbation of ``dR`` per unit gyro bias)."""

    dt: float
    dR: np.ndarray
    dv: np.ndarray
    dp: np.ndarray
    J_R_bg: np.ndarray
    J_v_bg: np.ndarray
    J_p_bg: np.ndarray
    J_v_ba: np.ndarray
    J_p_ba: np.ndarray
    bg: np.ndarray
    ba: np.ndarray

    def corrected(self, bg: np.ndarray, ba: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(dR, dv, dp)`` at other biases, to first order."""
        dbg, dba = np.asarray(bg) - self.bg, np.asarray(ba) - self.ba
        dR = self.dR @ _exp_np(self.J_R_bg @ dbg)
        dv = self.dv + self.J_v_bg @ dbg + self.J_v_ba @ dba
        dp = self.dp + self.J_p_bg @ dbg + self.J_p_ba @ dba
        return dR, dv, dp


def preintegrate(imu: ImuArrays, t0_ns: int, t1_ns: int, bg=None, ba=None) -> Preintegrated:
    """Reference pre-integration over ``[t0_ns, t1_ns]`` (loop over the readings: a few hundred per
    keyframe interval)."""
    bg = np.zeros(3) if bg is None else np.asarray(bg, np.float64)
    ba = np.zeros(3) if ba is None else np.asarray(ba, np.float64)
    dts, gyro, accel = hold_intervals(imu, t0_ns, t1_ns)
    dR, dv, dp = np.eye(3), np.zeros(3), np.zeros(3)
    JRg, Jvg, Jpg, Jva, Jpa = (np.zeros((3, 3)) for _ in range(5))
    for dt, w, a in zip(dts, gyro, accel):
        w, a = w - bg, a - ba
        phi = w * dt
        Exp = _exp_np(phi)
        A = dR @ hat(a)
        # Jacobians first (they use dR, dv at the start of the step)
        Jpg = Jpg + Jvg * dt - 0.5 * A @ JRg * dt * dt
        Jpa = Jpa + Jva * dt - 0.5 * dR * dt * dt
        Jvg = Jvg - A @ JRg * dt
        Jva = Jva - dR * dt
        JRg = Exp.T @ JRg - _right_jacobian(phi) * dt
        dp = dp + dv * dt + 0.5 * dR @ a * dt * dt
        dv = dv + dR @ a * dt
        dR = dR @ Exp
    return Preintegrated(float(dts.sum()), dR, dv, dp, JRg, Jvg, Jpg, Jva, Jpa, bg, ba)


def predict(pre: Preintegrated, R_i: np.ndarray, p_i: np.ndarray, v_i: np.ndarray,
            g_w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(R_j, p_j, v_j)`` from the state at ``t0`` and the pre-integrated readings."""
    dt = pre.dt
    return (R_i @ pre.dR, p_i + v_i * dt + 0.5 * g_w * dt * dt + R_i @ pre.dp,
            v_i + g_w * dt + R_i @ pre.dv)


def gtsam_preintegrate(imu: ImuArrays, t0_ns: int, t1_ns: int, params, bias=None):
    """The same interval as GTSAM ``PreintegratedCombinedMeasurements`` (for ``CombinedImuFactor``);
    ``params`` from :func:`gtsam_params`, ``bias`` a ``gtsam.imuBias.ConstantBias`` (default 0)."""
    import gtsam
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias or gtsam.imuBias.ConstantBias())
    dts, gyro, accel = hold_intervals(imu, t0_ns, t1_ns)
    for dt, w, a in zip(dts, gyro, accel):
        if dt > 0:
            pim.integrateMeasurement(a, w, float(dt))
    return pim


@dataclass
class ImuNoiseConfig:
    """Continuous-time IMU noise (EuRoC/Kalibr units): ``*_noise_density`` in rad/s/sqrt(Hz) and
    m/s^2/sqrt(Hz), ``*_random_walk`` in rad/s^2/sqrt(Hz) and m/s^3/sqrt(Hz); ``gravity`` m/s^2."""

    gyro_noise_density: float = 1.6968e-4
    gyro_random_walk: float = 1.9393e-5
    accel_noise_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-3
    gravity: float = 9.81
    integration_sigma: float = 1e-4       #: integration noise (m/s^2/sqrt(Hz)), GTSAM's term


def gtsam_params(noise: ImuNoiseConfig):
    """``gtsam.PreintegrationCombinedParams`` for a z-up world (gravity ``[0, 0, -g]``)."""
    import gtsam
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(noise.gravity)
    I3 = np.eye(3)
    p.setGyroscopeCovariance(noise.gyro_noise_density ** 2 * I3)
    p.setAccelerometerCovariance(noise.accel_noise_density ** 2 * I3)
    p.setBiasOmegaCovariance(noise.gyro_random_walk ** 2 * I3)
    p.setBiasAccCovariance(noise.accel_random_walk ** 2 * I3)
    p.setIntegrationCovariance(noise.integration_sigma ** 2 * I3)
    return p
