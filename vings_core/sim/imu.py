"""IMU synthesis from a trajectory's analytic derivatives.

Body frame = IMU frame. Noise-free readings at time t:

* gyro  = angular velocity of the body expressed in the body frame (rad/s),
* accel = ``R_wb^T (a_w - g_w)`` with ``g_w = (0, 0, -9.81)`` (specific force, m/s^2; +9.81 on z at
  rest, level).

Noise (EuRoC / ADIS16448-like, continuous-time densities): white noise of density ``sigma`` is
sampled as ``sigma / sqrt(dt)`` per reading; biases follow a random walk
``b_{k+1} = b_k + sigma_rw * sqrt(dt) * N(0, I)`` starting from a small random initial bias. All
randomness comes from a seeded ``numpy.random.Generator``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np

from .trajectory import Motion

GRAVITY = 9.81
G_WORLD = np.array([0.0, 0.0, -GRAVITY])


@dataclass
class ImuNoise:
    """Continuous-time IMU noise parameters (EuRoC units) and initial-bias spread.

    ``gyro_noise_density`` rad/s/sqrt(Hz), ``gyro_random_walk`` rad/s^2/sqrt(Hz),
    ``accel_noise_density`` m/s^2/sqrt(Hz), ``accel_random_walk`` m/s^3/sqrt(Hz);
    ``gyro_bias_std`` rad/s and ``accel_bias_std`` m/s^2: std of the initial biases.
    """

    gyro_noise_density: float = 1.6968e-4
    gyro_random_walk: float = 1.9393e-5
    accel_noise_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-3
    gyro_bias_std: float = 2.0e-3
    accel_bias_std: float = 2.0e-2

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ImuData:
    """IMU readings at times ``t`` (N,) s: ``gyro``/``accel`` (N, 3) as measured (with noise and
    bias), ``bias_gyro``/``bias_accel`` (N, 3) the true biases, ``gyro_true``/``accel_true`` the
    noise-free values."""

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    gyro_true: np.ndarray
    accel_true: np.ndarray


def imu_truth(motion: Motion, t) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free ``(gyro (N, 3) rad/s, accel (N, 3) m/s^2)`` of ``motion`` at times ``t`` (s)."""
    s = motion.sample(np.atleast_1d(np.asarray(t, np.float64)))
    accel = np.einsum("nji,nj->ni", s.R, s.a - G_WORLD)
    return s.w.copy(), accel


def simulate_imu(motion: Motion, t, noise: Optional[ImuNoise] = None,
                 rng: Optional[np.random.Generator] = None) -> ImuData:
    """IMU readings of ``motion`` at evenly spaced times ``t`` (s). ``noise=None``: exact readings,
    zero biases. Otherwise ``rng`` (required) draws the initial biases, the bias random walk and the
    white noise."""
    t = np.atleast_1d(np.asarray(t, np.float64))
    gyro_t, accel_t = imu_truth(motion, t)
    n = len(t)
    if noise is None:
        z = np.zeros((n, 3))
        return ImuData(t, gyro_t.copy(), accel_t.copy(), z, z.copy(), gyro_t, accel_t)
    if rng is None:
        raise ValueError("simulate_imu: a seeded rng is required when noise is on")
    if n > 1:
        dts = np.diff(t)
        dt = float(np.median(dts))
        if dt <= 0 or np.abs(dts - dt).max() > 1e-6 * dt + 1e-12:
            raise ValueError("simulate_imu: sample times must be evenly spaced and increasing")
    else:
        dt = 0.005
    bg0 = rng.normal(0.0, noise.gyro_bias_std, 3)
    ba0 = rng.normal(0.0, noise.accel_bias_std, 3)
    steps_g = rng.normal(0.0, noise.gyro_random_walk * np.sqrt(dt), (n, 3))
    steps_a = rng.normal(0.0, noise.accel_random_walk * np.sqrt(dt), (n, 3))
    steps_g[0] = 0.0
    steps_a[0] = 0.0
    bg = bg0 + np.cumsum(steps_g, axis=0)
    ba = ba0 + np.cumsum(steps_a, axis=0)
    wg = rng.normal(0.0, noise.gyro_noise_density / np.sqrt(dt), (n, 3))
    wa = rng.normal(0.0, noise.accel_noise_density / np.sqrt(dt), (n, 3))
    return ImuData(t, gyro_t + bg + wg, accel_t + ba + wa, bg, ba, gyro_t, accel_t)
