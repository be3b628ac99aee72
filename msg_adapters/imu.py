"""``sensor_msgs/Imu`` <-> :class:`vings_core.types.ImuSample` (body frame, SI units).

No orientation is estimated, so ``orientation_covariance[0] = -1`` (the sensor_msgs convention for
"not provided"). Angular velocity / linear acceleration covariances are optional diagonal variances;
:func:`imu_variances` derives the per-sample (discrete-time) ones from a calibration's continuous
noise densities: ``sigma_d^2 = sigma_c^2 * rate``.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from geometry_msgs.msg import Vector3
from sensor_msgs.msg import Imu

from vings_core.errors import InputError
from vings_core.types import Calibration, ImuSample

from .stamps import header_ns, make_header


def imu_variances(calib: Calibration) -> tuple[float, float]:
    """Discrete-time per-axis variances ``(gyro (rad/s)^2, accel (m/s^2)^2)`` of one sample."""
    rate = float(calib.imu_rate_hz)
    return calib.gyro_noise_density ** 2 * rate, calib.accel_noise_density ** 2 * rate


def imu_sample_to_msg(sample: ImuSample, frame_id: str, gyro_var: Optional[float] = None,
                      accel_var: Optional[float] = None, where: str = "imu") -> Imu:
    """ImuSample -> Imu with the exact stamp; variances (if given) on the covariance diagonals."""
    g = np.asarray(sample.gyro, dtype=np.float64).reshape(3)
    a = np.asarray(sample.accel, dtype=np.float64).reshape(3)
    msg = Imu(header=make_header(sample.stamp_ns, frame_id, where),
              angular_velocity=Vector3(x=float(g[0]), y=float(g[1]), z=float(g[2])),
              linear_acceleration=Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2])))
    oc = np.zeros(9)
    oc[0] = -1.0
    msg.orientation_covariance = oc
    if gyro_var is not None:
        msg.angular_velocity_covariance = np.diag([float(gyro_var)] * 3).reshape(-1)
    if accel_var is not None:
        msg.linear_acceleration_covariance = np.diag([float(accel_var)] * 3).reshape(-1)
    return msg


def msg_to_imu_sample(msg: Imu, where: str = "imu") -> ImuSample:
    """Imu -> ImuSample (orientation ignored). Non-finite readings, a reading marked "not provided"
    (``covariance[0] = -1``, sensor_msgs convention) and a non-finite covariance raise InputError."""
    for field in ("angular_velocity_covariance", "linear_acceleration_covariance"):
        cov = np.asarray(getattr(msg, field), dtype=np.float64)
        if cov.size and cov[0] == -1:
            raise InputError(f"{where}.{field}[0] = -1: the sensor does not provide "
                             f"{field[:-len('_covariance')]}; the front end needs both gyro and "
                             f"accelerometer readings")
        if not np.all(np.isfinite(cov)):
            raise InputError(f"{where}.{field} is not finite: {cov.tolist()}")
    av, la = msg.angular_velocity, msg.linear_acceleration
    g = np.array([av.x, av.y, av.z], dtype=np.float64)
    a = np.array([la.x, la.y, la.z], dtype=np.float64)
    if not np.all(np.isfinite(g)):
        raise InputError(f"{where}: angular_velocity is not finite: {g.tolist()}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{where}: linear_acceleration is not finite: {a.tolist()}")
    return ImuSample(stamp_ns=header_ns(msg.header, f"{where}.header"), gyro=g, accel=a)


__all__ = ["imu_variances", "imu_sample_to_msg", "msg_to_imu_sample"]
