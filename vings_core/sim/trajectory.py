"""Smooth body trajectories with analytic derivatives (for exact IMU synthesis).

Frames: world z up (gravity -z); body x forward, y left, z up. Orientation is yaw-pitch-roll
``R_wb = Rz(yaw) Ry(pitch) Rx(roll)``. A :class:`Motion` returns, for times ``t`` (s), the body
position, velocity and acceleration in the world and the body angular velocity in the body frame,
all analytic (C2 or smoother), so that the IMU built from them is exactly consistent with the poses.

* :class:`HandheldMotion`: sums of sinusoids (room scene), unbounded in time. :func:`random_handheld`
  wanders around the room; :func:`route_handheld` walks a lap of the room back to its start pose
  (``'return'``) or half a lap from one end of the room to the other (``'oneway'``).
* :class:`DriveMotion`: a car-like motion along a route of straights and 90-degree turns on a street
  grid. Turn heading follows a quintic smooth step (curvature C1), speed follows quintic smooth
  ramps (slow down before turns, speed up after), so position is C3. A closed route returns exactly
  (to quadrature precision, ~1e-9 m) to its start with the same velocity.
* :class:`RetraceMotion`: a closed route driven on into a second pass over the same lanes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np


@dataclass
class MotionSample:
    """Body state at times ``t`` (N,): ``p``, ``v``, ``a`` (N, 3) world (m, m/s, m/s^2); ``R`` (N, 3, 3)
    ``R_wb``; ``w`` (N, 3) angular velocity of the body in the body frame (rad/s)."""

    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    R: np.ndarray
    w: np.ndarray

    def T_wb(self) -> np.ndarray:
        """(N, 4, 4) body-to-world poses."""
        T = np.zeros((len(self.t), 4, 4))
        T[:, :3, :3] = self.R
        T[:, :3, 3] = self.p
        T[:, 3, 3] = 1.0
        return T


def euler_zyx(yaw, pitch, roll) -> np.ndarray:
    """(N, 3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty(np.shape(yaw) + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def euler_zyx_body_rates(pitch, roll, dyaw, dpitch, droll) -> np.ndarray:
    """(N, 3) body angular velocity ``vee(R^T dR/dt)`` of ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    return np.stack([droll - dyaw * sp,
                     dpitch * cr + dyaw * cp * sr,
                     -dpitch * sr + dyaw * cp * cr], axis=-1)


class Motion:
    """A body trajectory; ``duration`` (s) is None when unbounded."""

    duration: Optional[float] = None

    def sample(self, t) -> MotionSample:  # pragma: no cover - interface
        raise NotImplementedError

    def T_wb(self, t) -> np.ndarray:
        return self.sample(np.atleast_1d(np.asarray(t, np.float64))).T_wb()

    def route_clock(self, t) -> tuple["Motion", np.ndarray]:
        """The motion this one plays and its clock at times ``t`` (s): wrappers that only re-time
        another motion (:class:`TimeScaledMotion`, :class:`SlowStartMotion`,
        :class:`RetraceMotion`) pass the question on to it; any other motion is its own."""
        return self, np.atleast_1d(np.asarray(t, np.float64))


# ------------------------------------------------------------------------------ sinusoid sums


@dataclass
class SineSum:
    """``c + sum_k A_k sin(w_k t + phi_k)`` with exact derivatives."""

    c: float
    A: np.ndarray
    w: np.ndarray
    phi: np.ndarray

    def __call__(self, t, order: int = 0) -> np.ndarray:
        t = np.asarray(t, np.float64)[..., None]
        arg = self.w * t + self.phi
        if order == 0:
            return self.c + (self.A * np.sin(arg)).sum(-1)
        if order == 1:
            return (self.A * self.w * np.cos(arg)).sum(-1)
        if order == 2:
            return (-self.A * self.w ** 2 * np.sin(arg)).sum(-1)
        raise ValueError(order)


@dataclass
class SmoothStep:
    """``c + delta * S((t - t0) / tau)`` with ``S`` the quintic smooth step (0 before ``t0``, 1 after
    ``t0 + tau``; ``t0``, ``tau`` in s), with exact derivatives (zero outside the step, C2)."""

    c: float
    delta: float
    t0: float
    tau: float

    def __call__(self, t, order: int = 0) -> np.ndarray:
        u = np.clip((np.asarray(t, np.float64) - self.t0) / self.tau, 0.0, 1.0)
        if order == 0:
            return self.c + self.delta * _S(u)
        if order == 1:
            return self.delta * _S1(u) / self.tau
        if order == 2:
            return self.delta * _S2(u) / self.tau ** 2
        raise ValueError(order)


@dataclass
class SignalSum:
    """The sum of signals (:class:`SineSum`, :class:`SmoothStep`, ...: ``f(t, order)``), with exact
    derivatives."""

    terms: tuple

    def __call__(self, t, order: int = 0) -> np.ndarray:
        return sum(f(t, order) for f in self.terms)


class HandheldMotion(Motion):
    """Handheld motion: position and yaw/pitch/roll are sums of sinusoids plus a slow yaw drift.

    ``x, y, z, yaw, pitch, roll`` are :class:`SineSum` (or any signal ``f(t, order)`` with exact
    derivatives, e.g. :class:`SignalSum`: m, rad); ``yaw_rate`` (rad/s) adds ``yaw_rate * t`` so the
    camera looks all around the room over time.
    """

    def __init__(self, x: SineSum, y: SineSum, z: SineSum, yaw: SineSum, pitch: SineSum,
                 roll: SineSum, yaw_rate: float = 0.0):
        self.x, self.y, self.z = x, y, z
        self.yaw, self.pitch, self.roll = yaw, pitch, roll
        self.yaw_rate = float(yaw_rate)
        self.duration = None

    def sample(self, t) -> MotionSample:
        t = np.atleast_1d(np.asarray(t, np.float64))
        p = np.stack([self.x(t), self.y(t), self.z(t)], -1)
        v = np.stack([self.x(t, 1), self.y(t, 1), self.z(t, 1)], -1)
        a = np.stack([self.x(t, 2), self.y(t, 2), self.z(t, 2)], -1)
        yaw = self.yaw(t) + self.yaw_rate * t
        pitch, roll = self.pitch(t), self.roll(t)
        R = euler_zyx(yaw, pitch, roll)
        w = euler_zyx_body_rates(pitch, roll, self.yaw(t, 1) + self.yaw_rate, self.pitch(t, 1),
                                 self.roll(t, 1))
        return MotionSample(t, p, v, a, R, w)


def random_handheld(rng: np.random.Generator, center, half_range, z_mean: float,
                    speed: float = 0.9) -> HandheldMotion:
    """A handheld motion bounded to ``center +- half_range`` (x, y) and ``z_mean +- 0.2`` m.

    Mean translational speed is roughly ``speed`` m/s; yaw sweeps slowly around with a sway.
    """
    hx, hy = half_range

    def ss(c, amps, freqs):
        amps = np.asarray(amps, np.float64)
        return SineSum(float(c), amps, np.asarray(freqs, np.float64) * rng.uniform(0.9, 1.1, len(amps)),
                       rng.uniform(0, 2 * np.pi, len(amps)))

    k = speed / 0.9
    x = ss(center[0], [0.8 * hx, 0.2 * hx, 0.02], [0.42 * k, 1.05 * k, 2.9])
    y = ss(center[1], [0.8 * hy, 0.2 * hy, 0.02], [0.55 * k, 1.3 * k, 3.4])
    z = ss(z_mean, [0.12, 0.05, 0.01], [0.8 * k, 1.7 * k, 3.1])
    yaw = ss(rng.uniform(-np.pi, np.pi), [0.6, 0.15, 0.01], [0.35, 0.9, 3.7])
    pitch = ss(-0.08, [0.14, 0.05, 0.006], [0.5, 1.2, 4.1])
    roll = ss(0.0, [0.07, 0.03, 0.006], [0.6, 1.4, 3.9])
    return HandheldMotion(x, y, z, yaw, pitch, roll, yaw_rate=rng.choice([-1.0, 1.0]) * 0.3)


ROOM_ROUTES = ("handheld", "return", "oneway")
ROUTE_MIN_DURATION_S = 5.0          # shortest return / oneway walk (s)


def _whole_period_freqs(freqs: np.ndarray, period: float) -> np.ndarray:
    """``freqs`` (rad/s) rounded to the nearest whole multiples (at least one) of ``2 pi / period``
    (``period`` in s), so that sinusoids of them repeat exactly after ``period``."""
    base = 2 * np.pi / period
    return np.maximum(np.round(np.asarray(freqs, np.float64) / base), 1.0) * base


def route_handheld(rng: np.random.Generator, kind: str, duration: float, center, half_range,
                   z_mean: float) -> HandheldMotion:
    """A handheld walk through the room that lasts ``duration`` s, bounded like
    :func:`random_handheld` (body within ``center +- half_range`` in x/y, m; ``z_mean +- 0.2`` m),
    with a handheld sway of position, yaw, pitch and roll on top (the same for both kinds).

    * ``'return'``: one lap of the ellipse centred at ``center`` that fills ``half_range`` less the
      sway, from a random point in a random direction, at a constant angular rate, looking along
      the walk (yaw = the angle around the centre plus 90 degrees, within a few degrees of the
      ellipse's tangent). Every sway frequency is a whole multiple of ``2 pi / duration``, so at
      ``t = duration`` the pose (and velocity, acceleration, angular rate) equals the one at
      ``t = 0``: the last frames re-see what the first frames saw, which the middle of the lap
      looks away from.
    * ``'oneway'``: starts at one end of the room's long (x) axis, on the centre line, looking at
      that end's wall; turns around (yaw by 180 degrees, either way, between 20 % and 50 % of
      ``duration``) and walks to the other end, x changing monotonically (a quintic smooth step
      over the whole ``duration``; the sway aside). The first 20 % of the frames look at one end of
      the room, the last 50 % at the other, and never back.

    At ``duration`` = 15 s the mean speed is about 0.6 m/s (return) and 0.5 m/s (oneway), the
    room's :func:`random_handheld` about 0.8 m/s; the walk's share falls as ``duration`` grows.
    """
    if kind not in ("return", "oneway"):
        raise ValueError(f"route kind must be 'return' or 'oneway', got {kind!r}")
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"route duration must be > 0 s, got {duration}")
    hx, hy = half_range
    T = float(duration)

    def ss(c, amps, freqs):
        amps = np.asarray(amps, np.float64)
        w = _whole_period_freqs(np.asarray(freqs, np.float64) * rng.uniform(0.9, 1.1, len(amps)), T)
        return SineSum(float(c), amps, w, rng.uniform(0, 2 * np.pi, len(amps)))

    amp_x, amp_y = [0.28, 0.07, 0.012], [0.2, 0.06, 0.012]          # sway (m)
    a, b = hx - sum(amp_x), hy - sum(amp_y)                          # room left for the walk (m)
    direction = float(rng.choice([-1.0, 1.0]))     # return: +1 counter-clockwise; oneway: turn left
    sway_x = ss(0.0, amp_x, [1.7, 3.8, 6.5])
    sway_y = ss(0.0, amp_y, [2.0, 4.3, 7.0])
    z = ss(z_mean, [0.1, 0.04, 0.012], [0.8, 2.3, 6.5])
    pitch = ss(-0.08, [0.12, 0.04, 0.006], [0.5, 1.2, 4.1])
    roll = ss(0.0, [0.06, 0.03, 0.006], [0.6, 1.4, 3.9])
    yaw_sway = ss(0.0, [0.1, 0.04, 0.01], [0.7, 1.9, 3.7])
    if kind == "return":
        phi0 = float(rng.uniform(0, 2 * np.pi))
        w_walk = direction * 2 * np.pi / T           # rad/s around the centre
        # (a cos(phi), b sin(phi)), phi = phi0 + w_walk t, written as sines
        walk_x = SineSum(float(center[0]), np.array([a]), np.array([w_walk]), np.array([phi0 + np.pi / 2]))
        walk_y = SineSum(float(center[1]), np.array([b]), np.array([w_walk]), np.array([phi0]))
        x, y = SignalSum((walk_x, sway_x)), SignalSum((walk_y, sway_y))
        yaw = SineSum(phi0 + direction * np.pi / 2, yaw_sway.A, yaw_sway.w, yaw_sway.phi)
        return HandheldMotion(x, y, z, yaw, pitch, roll, yaw_rate=w_walk)
    end = float(rng.choice([-1.0, 1.0]))             # the end of the room it starts at
    x = SignalSum((SmoothStep(float(center[0]) + end * a, -2 * end * a, 0.0, T), sway_x))
    y = SineSum(float(center[1]), sway_y.A, sway_y.w, sway_y.phi)           # on the centre line
    look0 = 0.0 if end > 0 else np.pi                  # at the start wall
    yaw = SignalSum((SmoothStep(look0, direction * np.pi, 0.2 * T, 0.3 * T), yaw_sway))
    return HandheldMotion(x, y, z, yaw, pitch, roll)


# ------------------------------------------------------------------------------ driving

# quintic smooth step and its integral/derivatives on [0, 1]
def _S(u):
    return u ** 3 * (10 - 15 * u + 6 * u * u)


def _S1(u):
    return 30 * u * u * (1 - u) ** 2


def _S2(u):
    return 60 * u * (1 - u) * (1 - 2 * u)


def _Sint(u):
    return u ** 4 * (2.5 - 3 * u + u * u)


_GL_X, _GL_W = np.polynomial.legendre.leggauss(32)


def turn_displacement(length: float, dtheta: float, u) -> np.ndarray:
    """(N, 2) position, in the turn's entry frame (x forward, y left), after a fraction ``u`` (N,) of a
    turn of arc length ``length`` whose heading goes 0 -> dtheta as ``dtheta * S(u)``.
    32-point Gauss-Legendre per query (the integrand is an entire function: error ~1e-15)."""
    u = np.atleast_1d(np.asarray(u, np.float64))
    x = 0.5 * u[:, None] * (_GL_X[None, :] + 1.0)            # nodes on [0, u]
    th = dtheta * _S(x)
    wts = 0.5 * u[:, None] * _GL_W[None, :] * length
    return np.stack([(wts * np.cos(th)).sum(1), (wts * np.sin(th)).sum(1)], -1)


@dataclass
class _Piece:
    kind: str            # "straight" | "turn"
    s0: float            # arc length at its start (m)
    length: float
    p0: np.ndarray       # (2,) start position
    theta0: float        # heading at start
    dtheta: float = 0.0  # turn angle (turns)


@dataclass
class _Phase:
    t0: float
    s0: float
    v0: float
    v1: float
    tau: float           # duration (s)


class DriveMotion(Motion):
    """Planar car motion on a route of straights and smooth 90-degree turns, with a speed profile of
    quintic ramps, small suspension bounce (height, pitch, roll) and yaw = heading.

    Built by :func:`plan_drive`. ``height``: body height above the road (m). ``closed``: the
    route ends where and as it starts (a loop). ``route_length`` (m) and ``route_end_s`` (s) are the
    whole planned route, which goes on past ``total_length`` / ``duration`` when an open route is
    cut (:func:`plan_drive`).
    """

    def __init__(self, pieces: list[_Piece], phases: list[_Phase], height: float,
                 bounce: tuple[SineSum, SineSum, SineSum], closed: bool = False):
        self.pieces = pieces
        self.phases = phases
        self.height = float(height)
        self.zb, self.pitchb, self.rollb = bounce
        self.closed = bool(closed)
        self.total_length = pieces[-1].s0 + pieces[-1].length
        self.route_length = self.total_length
        last = phases[-1]
        self.duration = last.t0 + last.tau
        self.route_end_s = self.duration
        self._ps0 = np.array([p.s0 for p in pieces])
        self._ph_t0 = np.array([p.t0 for p in phases])

    # -- speed profile (t -> s, ds/dt, d2s/dt2)
    def arc(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, np.float64))
        i = np.clip(np.searchsorted(self._ph_t0, t, side="right") - 1, 0, len(self.phases) - 1)
        t0 = self._ph_t0[i]
        s0 = np.array([p.s0 for p in self.phases])[i]
        v0 = np.array([p.v0 for p in self.phases])[i]
        v1 = np.array([p.v1 for p in self.phases])[i]
        tau = np.array([p.tau for p in self.phases])[i]
        dt = t - t0
        u = np.clip(dt / tau, 0.0, 1.0)
        dv = v1 - v0
        beyond = dt - u * tau                    # extrapolate at constant end speed
        s = s0 + v0 * u * tau + dv * tau * _Sint(u) + v1 * beyond
        v = v0 + dv * _S(u)
        a = np.where((dt >= 0) & (dt <= tau), dv * _S1(u) / tau, 0.0)
        return s, v, a

    # -- geometry (s -> position, heading, curvature)
    def geometry(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = np.atleast_1d(np.asarray(s, np.float64))
        j = np.clip(np.searchsorted(self._ps0, s, side="right") - 1, 0, len(self.pieces) - 1)
        pos = np.empty((len(s), 2))
        th = np.empty(len(s))
        kap = np.zeros(len(s))
        for k in np.unique(j):
            m = j == k
            pc = self.pieces[k]
            ds = s[m] - pc.s0
            c, sn = np.cos(pc.theta0), np.sin(pc.theta0)
            if pc.kind == "straight":
                pos[m] = pc.p0 + ds[:, None] * np.array([c, sn])
                th[m] = pc.theta0
            else:
                u = np.clip(ds / pc.length, 0.0, 1.0)
                d = turn_displacement(pc.length, pc.dtheta, u)
                pos[m] = pc.p0 + d[:, :1] * np.array([c, sn]) + d[:, 1:] * np.array([-sn, c])
                th[m] = pc.theta0 + pc.dtheta * _S(u)
                kap[m] = pc.dtheta * _S1(u) / pc.length
        return pos, th, kap

    def sample(self, t) -> MotionSample:
        t = np.atleast_1d(np.asarray(t, np.float64))
        s, sd, sdd = self.arc(t)
        pos, th, kap = self.geometry(s)
        c, sn = np.cos(th), np.sin(th)
        tan = np.stack([c, sn], -1)
        nor = np.stack([-sn, c], -1)
        z = self.height + self.zb(t)
        p = np.concatenate([pos, z[:, None]], -1)
        v = np.concatenate([sd[:, None] * tan, self.zb(t, 1)[:, None]], -1)
        a2 = sdd[:, None] * tan + (sd * sd * kap)[:, None] * nor
        a = np.concatenate([a2, self.zb(t, 2)[:, None]], -1)
        pitch, roll = self.pitchb(t), self.rollb(t)
        R = euler_zyx(th, pitch, roll)
        w = euler_zyx_body_rates(pitch, roll, kap * sd, self.pitchb(t, 1), self.rollb(t, 1))
        return MotionSample(t, p, v, a, R, w)


def _turn_offsets(length: float, dtheta: float) -> tuple[float, float]:
    """Distances (d_in, d_out) from the turn's start/end to the corner where its entry and exit
    lines meet."""
    D = turn_displacement(length, dtheta, np.array([1.0]))[0]
    e_out = np.array([np.cos(dtheta), np.sin(dtheta)])
    # D = d_in * (1, 0) + d_out * e_out
    d_out = D[1] / e_out[1]
    d_in = D[0] - d_out * e_out[0]
    return float(d_in), float(d_out)


def plan_drive(corners: np.ndarray, closed: bool, rng: np.random.Generator, *,
               turn_length: float = 22.0, v_turn: float = 5.5, v_cruise=(8.5, 11.5),
               ramp_length: float = 20.0, height: float = 1.58, start_fraction: float = 0.5,
               total_length: Optional[float] = None) -> DriveMotion:
    """A :class:`DriveMotion` through rectilinear ``corners`` (K, 2) (lane positions of the 90-degree
    turns, plus the route's start and end for open routes).

    Closed routes start (and end) at ``start_fraction`` of the first leg, at cruise speed, and
    return to exactly the same state. Open routes are cut at ``total_length`` (m) if given.
    ``rng`` draws each leg's cruise speed (m/s, in ``v_cruise``), then the suspension bounce.
    """
    legs = _route_legs(corners, closed, turn_length, ramp_length)
    v_c = [float(rng.uniform(*v_cruise)) for _ in legs]
    if closed:
        legs, v_c = _start_inside_first_leg(legs, v_c, start_fraction, ramp_length)
    pieces, phases = _pieces_and_phases(legs, v_c, closed, turn_length, v_turn, ramp_length)
    duration = phases[-1].t0 + phases[-1].tau
    motion = DriveMotion(pieces, phases, height, _bounce(rng, duration if closed else None), closed)
    if total_length is not None and total_length < motion.total_length:
        # cut an open route: keep phases up to the time the length is reached
        tt = _time_at_length(motion, total_length)
        motion.duration = tt
        motion.total_length = float(total_length)
    return motion


class _Leg(NamedTuple):
    """The straight part of a route segment: start ``p0`` (2,) m, ``heading`` (rad), ``length`` (m)
    and the angle (rad) of the turn that follows it (None when none does)."""

    p0: np.ndarray
    heading: float
    length: float
    turn_after: Optional[float]


def _route_segments(corners: np.ndarray, closed: bool
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Route points (a closed route repeats its first corner at the end), segment vectors (m),
    lengths (m) and headings (rad) of the segments between ``corners`` (K, 2)."""
    corners = np.asarray(corners, np.float64)
    if closed:
        pts = np.vstack([corners, corners[:1]])
    else:
        pts = corners
    dirs = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(dirs, axis=1)
    if np.any(seg_len < 1e-9):
        raise ValueError("route has repeated corners")
    heads = np.arctan2(dirs[:, 1], dirs[:, 0])
    return pts, dirs, seg_len, heads


def _turn_angles(heads: np.ndarray, closed: bool) -> list[float]:
    """Turn angle (+-pi/2 rad) at the end of each segment of headings ``heads``, towards the next
    (every segment's when ``closed``, else all but the last)."""
    nseg = len(heads)
    turns = []
    for i in range(nseg if closed else nseg - 1):
        d = (heads[(i + 1) % nseg] - heads[i] + np.pi) % (2 * np.pi) - np.pi
        if abs(abs(d) - np.pi / 2) > 1e-6:
            raise ValueError("route corners must be 90-degree turns")
        turns.append(float(np.sign(d) * np.pi / 2))
    return turns


def _route_legs(corners: np.ndarray, closed: bool, turn_length: float, ramp_length: float) -> list[_Leg]:
    """The straight legs of the route through ``corners``: each segment less the turns (of arc
    length ``turn_length``, m) at its ends; too short for them (and, between two turns, for two
    speed ramps of ``ramp_length`` m) is an error."""
    pts, dirs, seg_len, heads = _route_segments(corners, closed)
    nseg = len(dirs)
    turns = _turn_angles(heads, closed)
    offs = {+1: _turn_offsets(turn_length, np.pi / 2), -1: _turn_offsets(turn_length, -np.pi / 2)}
    legs = []
    for i in range(nseg):
        e = dirs[i] / seg_len[i]
        before = turns[i - 1] if (closed or i > 0) else None
        after = turns[i] if (closed or i < nseg - 1) else None
        a0 = offs[int(np.sign(before))][1] if before is not None else 0.0
        a1 = offs[int(np.sign(after))][0] if after is not None else 0.0
        L = seg_len[i] - a0 - a1
        if L < 2 * ramp_length - 1e-9 and (before is not None and after is not None):
            raise ValueError(f"route leg {i} too short ({seg_len[i]:.1f} m) for turns and ramps")
        if L < 0:
            raise ValueError(f"route leg {i} too short ({seg_len[i]:.1f} m)")
        legs.append(_Leg(pts[i] + a0 * e, heads[i], L, after))
    return legs


def _start_inside_first_leg(legs: list[_Leg], v_c: list[float], start_fraction: float,
                            ramp_length: float) -> tuple[list[_Leg], list[float]]:
    """A closed route's legs and cruise speeds split at ``start_fraction`` of leg 0 (kept
    ``ramp_length`` m from its ends), so the route starts and ends at the same place and speed."""
    p0, h0, L0, turn0 = legs[0]
    cut = start_fraction * L0
    cut = float(np.clip(cut, ramp_length, L0 - ramp_length)) if L0 >= 2 * ramp_length else 0.5 * L0
    e0 = np.array([np.cos(h0), np.sin(h0)])
    first = _Leg(p0 + cut * e0, h0, L0 - cut, turn0)
    last = _Leg(p0, h0, cut, None)
    return [first] + legs[1:] + [last], v_c + [v_c[0]]


class _SpeedProfile:
    """Phases of constant or quintically ramped speed, appended end to end from t = 0 s, s = 0 m."""

    def __init__(self) -> None:
        self.phases: list[_Phase] = []
        self.t = 0.0
        self.s = 0.0

    def add(self, v0: float, v1: float, dist: float) -> None:
        """A phase from speed ``v0`` to ``v1`` (m/s) over ``dist`` m."""
        tau = 2.0 * dist / (v0 + v1)
        self.phases.append(_Phase(t0=self.t, s0=self.s, v0=v0, v1=v1, tau=tau))
        self.s += dist
        self.t += tau


def _leg_ramps(length: float, v_now: float, vc: float, ramp_down: bool, ramp_length: float
               ) -> tuple[float, float]:
    """Lengths (m) of a leg's ramp from ``v_now`` to its cruise speed ``vc`` (none when they are
    equal) and of its ramp down before a turn (``ramp_down``), shrunk together to fit ``length``."""
    ramp_in = ramp_length if abs(v_now - vc) > 1e-9 else 0.0
    ramp_out = ramp_length if ramp_down else 0.0
    if ramp_in + ramp_out > length + 1e-9:
        scale = length / (ramp_in + ramp_out)
        ramp_in *= scale
        ramp_out *= scale
    return ramp_in, ramp_out


def _pieces_and_phases(legs: list[_Leg], v_c: list[float], closed: bool, turn_length: float,
                       v_turn: float, ramp_length: float) -> tuple[list[_Piece], list[_Phase]]:
    """The route's pieces (each leg, then its turn) and speed phases: on each leg, from the
    current speed ramp to its cruise speed ``v_c``, and down to ``v_turn`` (m/s) before a turn,
    which is driven at constant speed."""
    pieces: list[_Piece] = []
    profile = _SpeedProfile()
    s = 0.0
    v_now = v_c[0]
    for li, (p_start, head, L, turn_after) in enumerate(legs):
        pieces.append(_Piece("straight", s, L, np.asarray(p_start, np.float64), float(head)))
        vc = v_c[li]
        has_turn = turn_after is not None
        ramp_down = has_turn and not (closed and li == len(legs) - 1)
        ramp_in, ramp_out = _leg_ramps(L, v_now, vc, ramp_down, ramp_length)
        if ramp_in > 0:
            profile.add(v_now, vc, ramp_in)
        cruise = L - ramp_in - ramp_out
        if cruise > 1e-12:
            profile.add(vc, vc, cruise)
        if ramp_out > 0:
            profile.add(vc, v_turn, ramp_out)
            v_now = v_turn
        else:
            v_now = vc
        s += L
        if has_turn:
            p_end = np.asarray(p_start) + L * np.array([np.cos(head), np.sin(head)])
            pieces.append(_Piece("turn", s, turn_length, p_end, float(head), turn_after))
            profile.add(v_now, v_now, turn_length)
            s += turn_length
    return pieces, profile.phases


class TimeScaledMotion(Motion):
    """``base`` played at a slightly different rate: pose(t) = base.pose(scale * t). Derivatives
    stay exact (v * scale, a * scale^2, w * scale). Used to make a closed route's duration a whole
    number of camera and IMU periods so the last frame lands exactly on the start."""

    def __init__(self, base: Motion, scale: float):
        self.base = base
        self.scale = float(scale)
        self.duration = None if base.duration is None else base.duration / self.scale
        self.total_length = getattr(base, "total_length", None)
        base_period = getattr(base, "period", None)
        self.period = None if base_period is None else base_period / self.scale

    def sample(self, t) -> MotionSample:
        t = np.atleast_1d(np.asarray(t, np.float64))
        s = self.base.sample(self.scale * t)
        k = self.scale
        return MotionSample(t, s.p, s.v * k, s.a * k * k, s.R, s.w * k)

    def route_clock(self, t) -> tuple[Motion, np.ndarray]:
        return self.base.route_clock(self.scale * np.atleast_1d(np.asarray(t, np.float64)))


class SlowStartMotion(Motion):
    """``base`` started from rest: over the first ``ramp_s`` seconds its clock runs at the rate
    ``g'(t / ramp_s)`` (a quintic smooth step from 0 to 1), so speed, acceleration and angular
    rate grow smoothly from zero (zero at ``t = 0``) to ``base``'s own at ``ramp_s``, which then plays
    on ``ramp_s / 2`` seconds behind. Derivatives by the chain rule: ``v = v_b tau'``,
    ``a = a_b tau'^2 + v_b tau''``, ``w = w_b tau'``."""

    def __init__(self, base: Motion, ramp_s: float):
        if not (np.isfinite(ramp_s) and ramp_s > 0):
            raise ValueError(f"ramp_s must be > 0 s, got {ramp_s}")
        self.base = base
        self.ramp_s = float(ramp_s)
        self.duration = None if base.duration is None else base.duration + 0.5 * self.ramp_s
        self.total_length = getattr(base, "total_length", None)

    def time_of(self, tau: float) -> float:
        """The time ``t`` (s) at which the base clock reads ``tau`` (s, >= 0): the inverse of
        :meth:`warp` (bisection inside the ramp)."""
        T = self.ramp_s
        if tau >= 0.5 * T:
            return float(tau + 0.5 * T)
        lo, hi = 0.0, T
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            if self.warp(mid)[0][0] < tau:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def warp(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``tau(t)``, ``tau'(t)``, ``tau''(t)`` (base time and its derivatives)."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        T = self.ramp_s
        u = np.clip(t / T, 0.0, 1.0)
        ramp = t < T
        tau = np.where(ramp, T * (2.5 * u ** 4 - 3 * u ** 5 + u ** 6), t - 0.5 * T)
        d1 = np.where(ramp, 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5, 1.0)
        d2 = np.where(ramp, (30 * u ** 2 - 60 * u ** 3 + 30 * u ** 4) / T, 0.0)
        return tau, d1, d2

    def sample(self, t) -> MotionSample:
        t = np.atleast_1d(np.asarray(t, np.float64))
        tau, d1, d2 = self.warp(t)
        s = self.base.sample(tau)
        return MotionSample(t, s.p, s.v * d1[:, None], s.a * (d1 ** 2)[:, None] + s.v * d2[:, None], s.R,
                            s.w * d1[:, None])

    def route_clock(self, t) -> tuple[Motion, np.ndarray]:
        return self.base.route_clock(self.warp(t)[0])


class RetraceMotion(Motion):
    """A closed route driven on into a second pass: ``base`` (a closed :class:`DriveMotion`) played
    at ``t mod period`` (``period = base.duration``, s) until ``fraction`` (0-1] of the route's
    length has been driven a second time, over the same lanes in the same direction.

    A closed route's state at its end equals its start (position, velocity, acceleration, attitude,
    angular rate: it starts and ends cruising on a straight, and the suspension bounce's frequencies
    are whole multiples of 1 / period), so the motion stays smooth across ``t = period`` and the IMU
    built from it stays exact. The pose at ``t + period`` is the pose at ``t``.
    ``total_length`` (m) is the whole drive, ``loop_length`` (m) one lap.
    """

    def __init__(self, base: DriveMotion, fraction: float):
        if not (np.isfinite(fraction) and 0.0 < fraction <= 1.0):
            raise ValueError(f"retrace fraction must be in (0, 1], got {fraction}")
        self.base = base
        self.fraction = float(fraction)
        self.period = float(base.duration)
        self.loop_length = float(base.total_length)
        extra = self.period if fraction >= 1.0 else _time_at_length(base, fraction * self.loop_length)
        self.duration = self.period + extra
        self.total_length = self.loop_length * (1.0 + self.fraction)

    def sample(self, t) -> MotionSample:
        t = np.atleast_1d(np.asarray(t, np.float64))
        s = self.base.sample(np.mod(t, self.period))
        return MotionSample(t, s.p, s.v, s.a, s.R, s.w)

    def route_clock(self, t) -> tuple[Motion, np.ndarray]:
        return self.base.route_clock(np.mod(np.atleast_1d(np.asarray(t, np.float64)), self.period))


def _time_at_length(m: DriveMotion, length: float) -> float:
    lo, hi = 0.0, m.duration
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if m.arc(mid)[0][0] < length:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-10:
            break
    return 0.5 * (lo + hi)


def _bounce(rng: np.random.Generator, period: Optional[float] = None
            ) -> tuple[SineSum, SineSum, SineSum]:
    """Small suspension motion: height +-1.5 cm, pitch and roll +-0.4 deg, 1-3 Hz. With ``period``
    (s) every frequency is a whole multiple of 1/period, so the motion repeats exactly (loops)."""
    def ss(amps, freqs):
        freqs = np.asarray(freqs, np.float64) * rng.uniform(0.9, 1.1, len(freqs))
        if period is not None:
            freqs = np.maximum(np.round(freqs * period), 1.0) / period
        return SineSum(0.0, np.asarray(amps, np.float64), 2 * np.pi * freqs,
                       rng.uniform(0, 2 * np.pi, len(amps)))
    return (ss([0.01, 0.005], [1.3, 2.7]), ss([0.005, 0.002], [1.1, 2.3]),
            ss([0.004, 0.002], [0.9, 2.9]))
