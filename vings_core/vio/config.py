"""Visual-inertial fusion configuration: section ``vio`` of the params YAML."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import Enum


class ViState(str, Enum):
    """Visual-inertial state of the front end."""

    VISUAL_ONLY = "visual-only"
    INITIALISING = "initialising"
    VISUAL_INERTIAL = "visual-inertial"
    STANDSTILL = "standstill"        #: the latest frame was posed at zero velocity (IMU and images still)
    IMU_ONLY = "imu-only"            #: the latest frame was posed by IMU propagation (vision outage)


@dataclass
class ViConfig:
    """Units: seconds, metres, radians; IMU noise in EuRoC/Kalibr continuous-time units."""

    enabled: bool = True                  #: fuse the IMU when the source has one and a known T_bc
    # ---- IMU noise: 0 = take the calibration's value (sensor.yaml / imu.yaml)
    gyro_noise_density: float = 0.0       #: rad/s/sqrt(Hz)
    gyro_random_walk: float = 0.0         #: rad/s^2/sqrt(Hz)
    accel_noise_density: float = 0.0      #: m/s^2/sqrt(Hz)
    accel_random_walk: float = 0.0        #: m/s^3/sqrt(Hz)
    noise_inflation: float = 1.0          #: factor on the noise densities (unmodelled vibration)
    td_s: float = 0.0                     #: camera-IMU time offset: t_imu = t_cam + td_s
    max_imu_gap_s: float = 0.1            #: a longer gap between IMU readings within a keyframe
                                          #: interval drops the fusion back to visual-only
    # ---- initialisation (visual-inertial alignment)
    init_min_keyframes: int = 6           #: keyframes of the segment the alignment needs
    init_max_keyframes: int = 15          #: at most the newest this many
    init_min_span_s: float = 1.0          #: their time span
    init_min_excitation: float = 0.25     #: std of the mean specific force (m/s^2), VINS-Mono's test
    align_g_tol: float = 0.1              #: relative error of |g| the unrefined alignment may have
    align_max_residual: float = 0.1       #: RMS residual (m, m/s) above which it is refused
    align_max_scale_std: float = 0.02     #: relative std of the scale above which it is refused
    # ---- smoother
    visual_weight: float = 1.0            #: factor on the dense BA's information
    smoother_iters: int = 5               #: Levenberg-Marquardt iterations per keyframe
    prior_rot_sigma: float = 1e-3         #: prior of the first state: rotation (rad)
    prior_pos_sigma: float = 1e-3         #: ... position (m)
    prior_vel_sigma: float = 0.1          #: ... velocity (m/s)
    prior_acc_bias_sigma: float = 0.1     #: ... accelerometer bias (m/s^2)
    prior_gyro_bias_sigma: float = 0.01   #: ... gyroscope bias (rad/s)
    # ---- standstill (zero-velocity test; see vio/standstill.py)
    zupt_window_s: float = 1.0            #: IMU window the test looks at (s)
    zupt_block_s: float = 0.25            #: block length whose means are compared (s)
    zupt_gyro_tol: float = 0.02           #: largest block deviation of the gyro mean (rad/s)
    zupt_acc_tol: float = 0.2             #: largest block deviation of the specific force (m/s^2)
    # ---- vision outage
    outage_max_s: float = 2.0             #: longest IMU-only propagation without visual tracking (s)
    reacquire_sigmas: float = 5.0         #: a re-acquired position further from the IMU-propagated one
    reacquire_floor_m: float = 0.1        #: than this many position stds plus this floor is refused
    # ---- online camera-IMU time offset (see vio/time_offset.py)
    estimate_td: bool = True              #: estimate td online from rotations
    td_window_s: float = 5.0              #: tracked frames the estimate uses (s, newest)
    td_pair_s: float = 0.5                #: frames compared are this far apart (s)
    td_max_abs_s: float = 0.05            #: largest correction accepted (s)
    td_max_std_s: float = 0.002           #: largest standard deviation accepted (s)
    td_every_keyframes: int = 5           #: re-estimate every this many keyframes

    def validate(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{f.name} must be a finite number, got {v}")
        for name in ("gyro_noise_density", "gyro_random_walk", "accel_noise_density",
                     "accel_random_walk", "init_min_span_s", "init_min_excitation"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("noise_inflation", "max_imu_gap_s", "align_g_tol", "align_max_residual", "align_max_scale_std",
                     "visual_weight", "prior_rot_sigma", "prior_pos_sigma", "prior_vel_sigma",
                     "prior_acc_bias_sigma", "prior_gyro_bias_sigma", "zupt_window_s", "zupt_block_s",
                     "zupt_gyro_tol", "zupt_acc_tol", "reacquire_sigmas", "reacquire_floor_m",
                     "td_window_s", "td_pair_s", "td_max_abs_s",
                     "td_max_std_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.init_min_keyframes < 3:
            raise ValueError(f"init_min_keyframes must be >= 3, got {self.init_min_keyframes}")
        if self.init_max_keyframes < self.init_min_keyframes:
            raise ValueError("init_max_keyframes must be >= init_min_keyframes")
        if self.smoother_iters < 1:
            raise ValueError(f"smoother_iters must be >= 1, got {self.smoother_iters}")
        if self.outage_max_s < 0:
            raise ValueError(f"outage_max_s must be >= 0, got {self.outage_max_s}")
        if self.zupt_block_s * 2 > self.zupt_window_s:
            raise ValueError("zupt_window_s must hold at least two zupt_block_s blocks")
        if self.td_every_keyframes < 1:
            raise ValueError(f"td_every_keyframes must be >= 1, got {self.td_every_keyframes}")
        if abs(self.td_s) > 1.0:
            raise ValueError(f"td_s must be within +-1 s, got {self.td_s}")
