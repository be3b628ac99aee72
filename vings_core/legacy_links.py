"""TEMPORARY: the two-party pose links used by the nodes until they move to vings_core.exchange.
Deleted once vings_ros/frontend_node.py and mapper_node.py use PoseKeeper / PoseFollower."""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from .exchange.policy import correction_consistency as _cc
from .geometry import np_pose_compose, np_pose_inverse
from .types import Keyframe


def correction_consistency(frontend, corrections, confidence=0.99):
    return _cc(getattr(frontend, "pose_system", None), frontend.pose, corrections, confidence)


class PoseCorrections(dict):
    """``{stamp_ns: C}`` world-frame increments from one mapper refinement, numbered ``batch``
    (increasing; 0 = unnumbered)."""

    def __init__(self, items=(), batch: int = 0) -> None:
        super().__init__(items)
        self.batch = int(batch)


class PoseUpdates(dict):
    """``{stamp_ns: T_wc}`` front-end keyframe poses, with ``ack``: the last correction batch the
    front end had processed (accepted or rejected) when it sent them (None = unknown: every batch)."""

    def __init__(self, items=(), ack: Optional[int] = None) -> None:
        super().__init__(items)
        self.ack = ack


def pose_correction(T_new: np.ndarray, T_old: np.ndarray) -> np.ndarray:
    """World-frame left increment ``C`` with ``T_new = C @ T_old`` (4x4, T_wc convention)."""
    return np.asarray(T_new, np.float64) @ np_pose_inverse(np.asarray(T_old, np.float64))


def _differs(A: np.ndarray, B: np.ndarray, tol: float = 1e-7) -> bool:
    return bool(np.abs(np.asarray(A) - np.asarray(B)).max() > tol)


class MapperPoseLink:
    """Mapper side of the pose exchange.

    ``fe[s]``: the front end's pose of keyframe ``s`` as the mapper last learned it (packet pose,
    then every update), advanced by the corrections the mapper sent. A front-end update ``P`` that
    saw correction batches up to ``ack`` is applied as the increment ``P base^-1`` to the mapper's
    pose, where ``base`` is ``fe[s]`` without the corrections of later batches (still in flight);
    so the mapper's refinement is kept, and a correction the front end rejected is undone.
    :meth:`refine` returns the mapper's refinement as increments for the front end."""

    def __init__(self) -> None:
        self.fe: dict[int, np.ndarray] = {}
        #: updates for keyframes not added yet (the graph: still in the mapper's queue)
        self.pending: dict[int, np.ndarray] = {}
        #: corrections sent and not yet acknowledged: stamp -> [(batch, C), ...] oldest first
        self.in_flight: dict[int, list[tuple[int, np.ndarray]]] = {}
        self.batch = 0

    def resumed(self, poses: dict[int, np.ndarray]) -> None:
        """After loading a checkpoint: take the stored poses as the last exchanged ones."""
        self.fe.update({int(s): np.array(T, np.float64) for s, T in poses.items()})

    def keyframe_added(self, kf: Keyframe) -> None:
        self.fe[int(kf.stamp_ns)] = kf.T_wc.detach().cpu().numpy().astype(np.float64).copy()

    def apply_frontend_poses(self, mapper, poses: dict[int, np.ndarray]) -> int:
        """Front-end keyframe poses (absolute ``T_wc``; a :class:`PoseUpdates` carries the batch
        ``ack``, a plain dict counts as having seen every batch) -> increments on the mapper's
        poses. Unknown stamps are ignored. Returns how many keyframes moved."""
        ack = getattr(poses, "ack", None)
        ack = self.batch if ack is None else int(ack)
        have = mapper.keyframe_poses()
        new = {}
        for s, P in poses.items():
            s = int(s)
            if s not in have or s not in self.fe:
                if s not in have:
                    self.pending[s] = np.asarray(P, np.float64).copy()
                    while len(self.pending) > 1000:
                        self.pending.pop(min(self.pending))
                continue
            # corrections the front end had not seen yet when it sent P are not part of P; it will
            # hold F P once it accepts them (F their product), and fe[s] already includes them: so
            # the front end's own move is F P fe[s]^-1 (with no correction in flight: P fe[s]^-1)
            ahead = np.asarray(P, np.float64).copy()
            for b, C in self.in_flight.get(s, []):
                if b > ack:
                    ahead = np_pose_compose(C, ahead)
            old, self.fe[s] = self.fe[s], ahead
            if _differs(ahead, old, 1e-12):
                new[s] = np_pose_compose(pose_correction(ahead, old), have[s])
        self._acknowledged(ack)
        if new:
            mapper.set_keyframe_poses(new)
        return len(new)

    def _acknowledged(self, ack: int) -> None:
        for s in list(self.in_flight):
            left = [(b, C) for b, C in self.in_flight[s] if b > ack]
            if left:
                self.in_flight[s] = left
            else:
                del self.in_flight[s]

    def refine(self, mapper, batch: Optional[int] = None) -> PoseCorrections:
        """Run the mapper's pose refinement; returns ``{stamp: C}`` world-frame increments of the
        keyframes it moved (``T_new = C T_old``), to be offered to the front end, numbered ``batch``
        (default: the next number; always raised above the previous batch)."""
        base = mapper.keyframe_poses()
        refined = mapper.refine_poses()
        out = PoseCorrections()
        for s, T in refined.items():
            if s in base and _differs(T, base[s], 1e-12):
                out[int(s)] = pose_correction(T, base[s])
        if out:
            self.batch = max(self.batch + 1, int(batch or 0))
            out.batch = self.batch
            for s, C in out.items():
                if s in self.fe:
                    self.fe[s] = np_pose_compose(C, self.fe[s])
                    self.in_flight.setdefault(s, []).append((self.batch, C))
        return out


class FrontendPoseLink:
    """Front-end side of the pose exchange, with the write-back policy (``RunConfig.pose_writeback``).

    ``sent[s]``: the pose of keyframe ``s`` the mapper holds as far as the front end knows (the
    packet pose, every update sent, advanced by every correction received). :meth:`outgoing` returns
    the keyframes whose front-end pose differs from it (window BA moved them, or a correction was
    rejected: sending the front-end pose then makes the mapper undo it)."""

    def __init__(self, cfg: Optional[RunConfig] = None) -> None:
        self.cfg = cfg
        self.sent: dict[int, np.ndarray] = {}
        self.ack = 0            # last correction batch processed (echoed with every update)
        self.stats = dict(corrections=0, applied=0, rejected=0, tests=0, tests_failed=0, last_q=None,
                          last_q_limit=None)
        self._version = 0       # the front end's kf_pose_version at the last outgoing()
        self._recheck: set[int] = set()   # keyframes with a correction since (maybe rejected)

    def keyframe_sent(self, kf: Keyframe) -> None:
        self.sent[int(kf.stamp_ns)] = kf.T_wc.detach().cpu().numpy().astype(np.float64).copy()
        # compared at the next outgoing() whatever the write log says: a pose written after the
        # packet was made, but before this call, would otherwise never be sent
        self._recheck.add(int(kf.stamp_ns))

    def outgoing(self, frontend) -> PoseUpdates:
        """Keyframe poses to send to the mapper (absolute ``T_wc``), with the batch ``ack``. Only
        keyframes the front end wrote since the last call, or that got a correction, are compared
        (``frontend.keyframes_moved_since``): the cost does not grow with the history."""
        stamps = set(frontend.keyframes_moved_since(self._version)) | self._recheck
        self._version = frontend.kf_pose_version
        self._recheck = set()
        moved = PoseUpdates(ack=self.ack)
        for s in sorted(stamps):
            old = self.sent.get(int(s))
            if old is None:
                continue
            P = frontend.pose(s)
            if _differs(P, old):
                moved[int(s)] = P.copy()
                self.sent[int(s)] = P.copy()
        return moved

    def apply_corrections(self, frontend, corrections: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Apply the mapper's increments the policy accepts; returns the applied ``{stamp: C}``."""
        batch = getattr(corrections, "batch", 0)
        self.ack = max(self.ack, int(batch))
        corrections = {int(s): np.asarray(C, np.float64) for s, C in corrections.items() if int(s) in self.sent}
        if not corrections:
            return {}
        for s, C in corrections.items():
            self.sent[s] = np_pose_compose(C, self.sent[s])          # what the mapper now holds
        self._recheck.update(corrections)     # a rejected one is undone by the next outgoing()
        self.stats["corrections"] += len(corrections)
        accepted = self._accept(frontend, corrections)
        if accepted:
            frontend.set_poses({s: np_pose_compose(C, frontend.pose(s)) for s, C in accepted.items()})
        self.stats["applied"] += len(accepted)
        self.stats["rejected"] += len(corrections) - len(accepted)
        return accepted

    def _accept(self, frontend, corrections: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        policy = str(getattr(self.cfg, "pose_writeback", "consistent"))
        if policy == "all":
            return dict(corrections)
        if policy == "none":
            return {}
        ok, q, limit = correction_consistency(frontend, corrections, getattr(self.cfg, "writeback_confidence", 0.99))
        if q is not None:
            self.stats["tests"] += 1
            self.stats["tests_failed"] += int(not ok)
            self.stats["last_q"], self.stats["last_q_limit"] = q, limit
        return ok


def map_keyframe(mapper, link: MapperPoseLink, kf: Keyframe, refine: bool = True, chunk: int = 0,
                 stop: Optional[Callable[[], bool]] = None) -> tuple[dict, dict[int, np.ndarray]]:
    """One mapping step, the same in `vings run` and ``mapper_node``: add the keyframe, train
    ``iters_per_keyframe`` iterations (in chunks of ``chunk`` when > 0, ending early once ``stop()``
    is true: prompt shutdown), then (``refine``) the pose refinement. Returns the last training
    stats and the refinement as increments ``{stamp: C}`` for the front end."""
    mapper.add_keyframe(kf)
    link.keyframe_added(kf)
    later = link.pending.pop(int(kf.stamp_ns), None)
    if later is not None:   # the front end moved it while it waited in the queue
        link.apply_frontend_poses(mapper, {int(kf.stamp_ns): later})
    iters = int(mapper.cfg.iters_per_keyframe)
    step = iters if chunk <= 0 else int(chunk)
    stats: dict = {}
    done = 0
    while done < iters:
        if stop is not None and stop():
            break
        n = min(step, iters - done)
        stats = mapper.train(n)
        done += n
    stats["iterations_total"] = done
    corrections = (link.refine(mapper, batch=int(kf.stamp_ns)) if refine and not (stop is not None and stop())
                   else PoseCorrections())
    return stats, corrections


