"""Sliding-window visual-inertial smoother in GTSAM (the paper's "Visual Inertial Factor Graph").

States per keyframe ``k`` (GTSAM keys ``x k``, ``v k``, ``b k``): body pose ``T_wb`` (``Pose3``),
velocity ``v`` (m/s, world) and IMU biases (``imuBias.ConstantBias``: accelerometer m/s^2, gyro
rad/s). Factors:

* ``CombinedImuFactor`` between consecutive keyframes (pre-integration from :mod:`.preint`, bias
  random walk included);
* the dense BA's Schur-reduced pose system on the window's body poses (:mod:`.visual_factor`),
  replaced after every window BA;
* linear priors: the initial one on the first state (pose, velocity, biases) and those left by
  marginalisation.

Marginalisation of the oldest state: the factors that touch it (priors, its IMU factor, the visual
information of the edges incident to its keyframe, given by the caller) are linearised at the
current estimate and the state is eliminated (``eliminatePartialSequential``); what remains is kept
as ``LinearContainerFactor`` at that linearisation point (first-estimate Jacobians: the prior does
not move with later estimates, which keeps the window consistent).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from .visual_factor import visual_factor


def _keys(i: int) -> tuple[int, int, int]:
    import gtsam
    return gtsam.symbol("x", i), gtsam.symbol("v", i), gtsam.symbol("b", i)


@dataclass
class NavEstimate:
    """One keyframe's state: ``T_wb`` (4x4 body-to-world), ``v`` (m/s, world), ``ba`` (m/s^2),
    ``bg`` (rad/s)."""

    stamp_ns: int
    T_wb: np.ndarray
    v: np.ndarray
    ba: np.ndarray
    bg: np.ndarray


@dataclass
class _Tracked:
    """A nonlinear factor and the state indices it touches (GTSAM KeySets are not iterated: they
    crashed in the Python wheel)."""

    factor: object
    states: tuple[int, ...]


class WindowSmoother:
    """Keyframe states oldest first; ``T_bc`` camera-to-body; ``params`` GTSAM
    ``PreintegrationCombinedParams`` (:func:`.preint.gtsam_params`)."""

    def __init__(self, params, T_bc: np.ndarray):
        self.params = params
        self.T_bc = np.asarray(T_bc, np.float64)
        self.states: list[int] = []               # state indices, oldest first
        self.stamps: dict[int, int] = {}          # state index -> stamp (ns)
        self._index: dict[int, int] = {}          # stamp -> state index
        self._next = 0
        self.imu: list[_Tracked] = []
        self.priors: list[_Tracked] = []
        self.visual: Optional[_Tracked] = None
        self.values = None

    # ---------------------------------------------------------------------------- building

    def _new_state(self, stamp_ns: int, T_wb: np.ndarray, v: np.ndarray, ba, bg) -> int:
        import gtsam
        i = self._next
        self._next += 1
        x, vk, b = _keys(i)
        self.values.insert(x, gtsam.Pose3(np.asarray(T_wb, np.float64)))
        self.values.insert(vk, np.asarray(v, np.float64))
        self.values.insert(b, gtsam.imuBias.ConstantBias(np.asarray(ba, np.float64), np.asarray(bg, np.float64)))
        self.states.append(i)
        self.stamps[i] = int(stamp_ns)
        self._index[int(stamp_ns)] = i
        return i

    def start(self, first: NavEstimate, pose_sigma: Sequence[float], vel_sigma: float,
              acc_bias_sigma: float, gyro_bias_sigma: float) -> None:
        """The first state with its prior (``pose_sigma``: 6 std, GTSAM order ``[rot rad, pos m]``)."""
        import gtsam
        self.values = gtsam.Values()
        self.states, self.stamps, self._index = [], {}, {}
        self.imu, self.priors, self.visual = [], [], None
        i = self._new_state(first.stamp_ns, first.T_wb, first.v, first.ba, first.bg)
        x, vk, b = _keys(i)
        Diag = gtsam.noiseModel.Diagonal.Sigmas
        self.priors += [
            _Tracked(gtsam.PriorFactorPose3(x, gtsam.Pose3(first.T_wb), Diag(np.asarray(pose_sigma, float))), (i,)),
            _Tracked(gtsam.PriorFactorVector(vk, np.asarray(first.v, float), gtsam.noiseModel.Isotropic.Sigma(3, vel_sigma)), (i,)),
            _Tracked(gtsam.PriorFactorConstantBias(
                b, gtsam.imuBias.ConstantBias(np.asarray(first.ba, float), np.asarray(first.bg, float)),
                Diag(np.r_[[acc_bias_sigma] * 3, [gyro_bias_sigma] * 3])), (i,))]

    def add(self, stamp_ns: int, pim, T_wb_guess: Optional[np.ndarray] = None) -> int:
        """A new keyframe state joined to the newest one by the pre-integration ``pim``; its initial
        value is the IMU prediction, or ``T_wb_guess`` for the pose when given."""
        import gtsam
        j = self.states[-1]
        xi, vi, bi = _keys(j)
        prev = gtsam.NavState(self.values.atPose3(xi), self.values.atVector(vi))
        bias = self.values.atConstantBias(bi)
        pred = pim.predict(prev, bias)
        T = pred.pose().matrix() if T_wb_guess is None else np.asarray(T_wb_guess, float)
        k = self._new_state(stamp_ns, T, pred.velocity(), bias.accelerometer(), bias.gyroscope())
        xk, vk, bk = _keys(k)
        self.imu.append(_Tracked(gtsam.CombinedImuFactor(xi, vi, xk, vk, bi, bk, pim), (j, k)))
        return k

    def set_visual(self, G_cam: np.ndarray, g_cam: np.ndarray, stamps: Sequence[int],
                   T_wc_lin: Sequence[np.ndarray]) -> None:
        """Replace the visual factor by the window BA's pose system over keyframes ``stamps`` (GTSAM
        order, see :meth:`~vings_core.frontend.ba.PoseSystem.to_gtsam_ordering`), linearised at the
        camera poses ``T_wc_lin``. Keyframes without a state are left out (their rows and columns
        are dropped, i.e. their poses held at the linearisation point)."""
        self.visual = self._visual_factor(G_cam, g_cam, stamps, T_wc_lin)

    def _visual_factor(self, G, g, stamps, T_wc_lin) -> Optional[_Tracked]:
        keep = [n for n, s in enumerate(stamps) if int(s) in self._index]
        if len(keep) < 2:
            return None
        idx = np.concatenate([np.arange(6 * n, 6 * n + 6) for n in keep])
        states = tuple(self._index[int(stamps[n])] for n in keep)
        T_cb = np.linalg.inv(self.T_bc)
        f = visual_factor(G[np.ix_(idx, idx)], g[idx], self.T_bc,
                          [_keys(i)[0] for i in states], [T_wc_lin[n] @ T_cb for n in keep])
        return _Tracked(f, states)

    # -------------------------------------------------------------------------- solving

    def graph(self):
        import gtsam
        g = gtsam.NonlinearFactorGraph()
        for t in self.priors + self.imu + ([self.visual] if self.visual is not None else []):
            g.add(t.factor)
        return g

    def optimize(self, iters: int = 5) -> float:
        """Levenberg-Marquardt from the current values; returns the final graph error."""
        import gtsam
        p = gtsam.LevenbergMarquardtParams()
        p.setMaxIterations(int(iters))
        p.setErrorTol(float("-inf"))      # a graph of linear factors at its constant would not move
        opt = gtsam.LevenbergMarquardtOptimizer(self.graph(), self.values, p)
        self.values = opt.optimize()
        return float(self.graph().error(self.values))

    def marginalize_oldest(self, incident: Optional[tuple] = None) -> None:
        """Eliminate the oldest state. ``incident``: ``(G_cam, g_cam, stamps, T_wc_lin)``, the pose
        system of the visual edges incident to its keyframe (kept in the prior); ``None``: its visual
        information is dropped."""
        import gtsam
        if len(self.states) < 2:
            return
        old = self.states[0]
        touching = [t for t in self.priors + self.imu if old in t.states]
        if incident is not None:
            f = self._visual_factor(*incident)
            if f is not None and old in f.states:
                touching.append(f)
        nl = gtsam.NonlinearFactorGraph()
        for t in touching:
            nl.add(t.factor)
        lin = nl.linearize(self.values)
        ordering = gtsam.Ordering()
        for k in _keys(old):
            ordering.push_back(k)
        _, rest = lin.eliminatePartialSequential(ordering)
        others = sorted({s for t in touching for s in t.states} - {old})
        keep_vals = gtsam.Values()
        for s in others:
            x, vk, b = _keys(s)
            keep_vals.insert(x, self.values.atPose3(x))
            keep_vals.insert(vk, self.values.atVector(vk))
            keep_vals.insert(b, self.values.atConstantBias(b))
        new_priors = []
        for n in range(rest.size()):
            fac = rest.at(n)
            if fac is None:
                continue
            new_priors.append(_Tracked(gtsam.LinearContainerFactor(fac, keep_vals), tuple(others)))
        self.priors = [t for t in self.priors if old not in t.states] + new_priors
        self.imu = [t for t in self.imu if old not in t.states]
        if self.visual is not None and old in self.visual.states:
            self.visual = None               # re-set by the next window BA
        self.states.pop(0)
        self._index.pop(self.stamps.pop(old))
        for k in _keys(old):
            self.values.erase(k)

    def move(self, increments: dict[int, np.ndarray]) -> int:
        """Move states by rigid world-frame increments ``{stamp: C}`` (4x4; a loop correction): the
        body pose becomes ``C T_wb``, the velocity ``R_C v``; biases stay. The priors (the first
        state's and those left by marginalisation) were linearised at the old states: they are
        replaced by one prior on the oldest state at its moved value, with its marginal covariance
        before the move (velocity block rotated by ``R_C``; the information the window's own
        factors give that state is counted twice, once per correction). The IMU and visual factors
        are relative and move with the states. Returns how many states moved."""
        import gtsam
        hit = [i for i in self.states if self.stamps[i] in increments]
        if not hit:
            return 0
        first = self.states[0]
        x0, v0, b0 = _keys(first)
        try:
            m = gtsam.Marginals(self.graph(), self.values)
            P = [np.array(m.marginalCovariance(k)) for k in (x0, v0, b0)]
        except RuntimeError:
            P = None
        for i in hit:
            C = np.asarray(increments[self.stamps[i]], np.float64)
            x, vk, _ = _keys(i)
            self.values.update(x, gtsam.Pose3(C @ self.values.atPose3(x).matrix()))
            self.values.update(vk, C[:3, :3] @ np.asarray(self.values.atVector(vk)))
        C0 = np.asarray(increments.get(self.stamps[first], np.eye(4)), np.float64)
        if P is None:
            P = [np.eye(6) * 1e-6, np.eye(3) * 1e-2, np.eye(6) * 1e-4]
        Pv = C0[:3, :3] @ P[1] @ C0[:3, :3].T
        Cov = gtsam.noiseModel.Gaussian.Covariance
        self.priors = [
            _Tracked(gtsam.PriorFactorPose3(x0, self.values.atPose3(x0), Cov(0.5 * (P[0] + P[0].T))), (first,)),
            _Tracked(gtsam.PriorFactorVector(v0, np.asarray(self.values.atVector(v0)), Cov(0.5 * (Pv + Pv.T))), (first,)),
            _Tracked(gtsam.PriorFactorConstantBias(b0, self.values.atConstantBias(b0), Cov(0.5 * (P[2] + P[2].T))),
                     (first,))]
        return len(hit)

    # --------------------------------------------------------------------------- reading

    def estimate(self, stamp_ns: int) -> NavEstimate:
        i = self._index[int(stamp_ns)]
        x, vk, b = _keys(i)
        bias = self.values.atConstantBias(b)
        return NavEstimate(int(stamp_ns), self.values.atPose3(x).matrix(), np.array(self.values.atVector(vk)),
                           np.array(bias.accelerometer()), np.array(bias.gyroscope()))

    def latest(self) -> NavEstimate:
        return self.estimate(self.stamps[self.states[-1]])

    def window_stamps(self) -> list[int]:
        return [self.stamps[i] for i in self.states]

    def velocity_bias_covariance(self, stamp_ns: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Marginal covariances of a state's velocity (3x3, world, (m/s)^2) and biases (6x6,
        ``[acc, gyro]``); ``None`` when the graph is singular."""
        import gtsam
        _, vk, bk = _keys(self._index[int(stamp_ns)])
        try:
            m = gtsam.Marginals(self.graph(), self.values)
            return np.array(m.marginalCovariance(vk)), np.array(m.marginalCovariance(bk))
        except RuntimeError:
            return None
