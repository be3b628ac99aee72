"""The keeper's side of the pose exchange (the front end)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..geometry import np_pose_inverse, sim3_apply_to_pose, sim3_compose
from .batch import IncrementBatch
from .config import KEEPER, ExchangeConfig, WritebackPolicy
from .owner import KeeperOwner
from .policy import correction_consistency


def _differs(A: np.ndarray, B: np.ndarray, tol: float) -> bool:
    return bool(np.abs(np.asarray(A) - np.asarray(B)).max() > tol)


class PoseKeeper:
    """Applies the writers' increments under their write-back policies and publishes its own net
    moves.

    ``published[s]``: the pose of keyframe ``s`` as the followers know it (the pose the keyframe
    was emitted with, moved by every published batch). ``accepted[s]``: the product of the
    increments accepted since the last published batch, so that a similarity's scale travels on
    to the followers with it. :meth:`outgoing` sends, per keyframe that moved, the increment from
    ``published`` to the current pose (own moves composed on top of the accepted increments),
    with the last batch processed of every writer."""

    def __init__(self, owner: KeeperOwner, cfg: Optional[ExchangeConfig] = None, source: str = KEEPER) -> None:
        self.owner = owner
        self.cfg = cfg or ExchangeConfig()
        self.source = source
        self.seq = 0
        self.published: dict[int, np.ndarray] = {}
        self.accepted: dict[int, np.ndarray] = {}
        self.acks: dict[str, int] = {}          # last batch processed per writer
        self._acks_sent: dict[str, int] = {}
        self._version = 0                       # owner's kf_pose_version at the last outgoing()
        self._recheck: set[int] = set()
        self.stats = dict(corrections=0, applied=0, rejected=0, duplicates=0, jumps=0, tests=0, tests_failed=0,
                          unknown_stamps=0, last_q=None, last_q_limit=None)

    def keyframe_sent(self, stamp_ns: int, T_wc: np.ndarray) -> None:
        """A keyframe left with pose ``T_wc``: the followers start from it."""
        s = int(stamp_ns)
        self.published[s] = np.asarray(T_wc, np.float64).copy()
        # compared at the next outgoing() whatever the owner's write log says: a pose written after
        # the packet was made, but before this call, would otherwise never be sent
        self._recheck.add(s)

    def receive(self, batch: IncrementBatch) -> dict[int, np.ndarray]:
        """Apply the increments of a writer's batch that its policy accepts; returns them. A batch
        not newer than the last one of its source is a duplicate and ignored."""
        if batch.seq <= self.acks.get(batch.source, 0):
            self.stats["duplicates"] += 1
            return {}
        self.acks[batch.source] = batch.seq
        incs = {s: C for s, C in batch.increments.items() if s in self.published}
        # stamps of keyframes the keeper never sent (another run's, a forged message): ignored, counted
        self.stats["unknown_stamps"] += len(batch.increments) - len(incs)
        if not incs:
            return {}
        self.stats["corrections"] += len(incs)
        ok = self._accept(batch.source, incs)
        if ok:
            for s, C in ok.items():
                self.accepted[s] = sim3_compose(C, self.accepted[s]) if s in self.accepted else C
            if self.cfg.jumps(batch.source) and callable(getattr(self.owner, "apply_jump", None)):
                self.owner.apply_jump(ok)
                self.stats["jumps"] += 1
            else:
                self.owner.apply_increments(ok)
        self.stats["applied"] += len(ok)
        self.stats["rejected"] += len(incs) - len(ok)
        return ok

    def _accept(self, source: str, incs: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        policy = self.cfg.policy(source)
        if policy is WritebackPolicy.ALL:
            return dict(incs)
        if policy is WritebackPolicy.NONE:
            return {}
        ok, q, limit = correction_consistency(self.owner.pose_system, self.owner.pose, incs, self.cfg.confidence)
        if q is not None:
            self.stats["tests"] += 1
            self.stats["tests_failed"] += int(not ok)
            self.stats["last_q"], self.stats["last_q_limit"] = q, limit
        return ok

    def own_similarity(self, increments: dict[int, np.ndarray]) -> None:
        """The owner moved keyframes by similarities of its own (``{stamp: C}``, already applied to
        its poses; e.g. the visual-inertial alignment into the metric frame): they are composed
        into the pending increments like accepted ones, so the next batch carries their scale and
        the followers scale their content, not only move it. Unpublished stamps are ignored (the
        followers get those keyframes with their new pose)."""
        for s, C in increments.items():
            s = int(s)
            if s in self.published:
                C = np.asarray(C, np.float64)
                self.accepted[s] = sim3_compose(C, self.accepted[s]) if s in self.accepted else C

    def outgoing(self, seq_hint: int = 0) -> Optional[IncrementBatch]:
        """The keeper's batch since the last call: per keyframe that moved, the increment from its
        published pose to its current pose; None when nothing moved and no writer's batch was
        processed since (a batch that moves nothing still tells a writer its increments were
        refused). ``seq_hint``: a number the sequence should reach (e.g. the frame stamp, so a
        restarted keeper keeps counting up); the sequence always increases. Only keyframes written
        since the last call, or that received increments, are compared: the cost does not grow
        with the history."""
        stamps = set(self.owner.keyframes_moved_since(self._version)) | self._recheck | set(self.accepted)
        self._version = self.owner.kf_pose_version
        self._recheck = set()
        incs: dict[int, np.ndarray] = {}
        for s in sorted(stamps):
            old = self.published.get(s)
            if old is None:
                continue
            P = self.owner.pose(s)
            acc = self.accepted.pop(s, None)
            if acc is None:
                if _differs(P, old, 1e-7):
                    incs[s] = P @ np_pose_inverse(old)
                    self.published[s] = P.copy()
                continue
            own = P @ np_pose_inverse(sim3_apply_to_pose(acc, old))     # own moves on top of acc
            incs[s] = sim3_compose(own, acc)
            self.published[s] = P.copy()
        if not incs and self.acks == self._acks_sent:
            return None
        self._acks_sent = dict(self.acks)
        self.seq = max(self.seq + 1, int(seq_hint))
        return IncrementBatch(self.source, self.seq, incs, dict(self.acks))
