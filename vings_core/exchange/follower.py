"""A writer's side of the pose exchange (mapper, loop closer, any other stage)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..geometry import sim3_apply_to_pose, sim3_compose, sim3_inverse
from .batch import IncrementBatch
from .config import KEEPER
from .owner import PoseOwner

_I = np.eye(4)


def _product(incs: list[tuple[int, np.ndarray]]) -> np.ndarray:
    """``C_n ... C_1`` of increments listed oldest first."""
    F = _I
    for _, C in incs:
        F = sim3_compose(C, F)
    return F


class PoseFollower:
    """Follows the keeper's batches and sends its owner's own moves.

    ``keeper[s]``: keyframe ``s``'s pose as the keeper holds it, as far as the batches received
    tell (the pose it was emitted with, moved by every keeper batch). ``in_flight[s]``: own
    increments sent and not yet processed by the keeper, ``[(seq, C)]`` oldest first. The owner's
    pose is kept at ``F keeper[s]``, ``F`` the product of the increments in flight: when a keeper
    batch ``D`` arrives that processed own batches up to ``ack``, the owner moves by
    ``F_new D F_old^-1``: the keeper's move is kept, an own increment the keeper accepted is not
    applied twice (it is inside ``D``), one it refused is undone, and one it had not seen yet stays
    on top."""

    def __init__(self, source: str, owner: PoseOwner, keeper: str = KEEPER) -> None:
        if source == keeper:
            raise ValueError(f"a follower cannot be the keeper {keeper!r}")
        self.source, self.owner, self.keeper_name = source, owner, keeper
        self.seq = 0
        self.seen = 0                   # last keeper batch processed
        self.keeper: dict[int, np.ndarray] = {}
        self.in_flight: dict[int, list[tuple[int, np.ndarray]]] = {}
        #: keeper increments of keyframes not added yet (the graph: still in the owner's queue)
        self.pending: dict[int, np.ndarray] = {}
        self.stats = dict(batches=0, duplicates=0, moved=0)

    def resumed(self, poses: dict[int, np.ndarray], seen: int = 0) -> None:
        """After loading a checkpoint: the stored poses are the keeper's as far as known."""
        self.keeper.update({int(s): np.array(T, np.float64) for s, T in poses.items()})
        self.seen = max(self.seen, int(seen))

    def keyframe_added(self, stamp_ns: int, T_wc: np.ndarray) -> None:
        """The owner took a keyframe emitted by the keeper with pose ``T_wc``; keeper moves that
        arrived before it are applied now."""
        s = int(stamp_ns)
        self.keeper[s] = np.asarray(T_wc, np.float64).copy()
        D = self.pending.pop(s, None)
        if D is not None:
            self.keeper[s] = sim3_apply_to_pose(D, self.keeper[s])
            self.owner.apply_increments({s: D})

    def receive(self, batch: IncrementBatch) -> int:
        """Apply a keeper batch; returns how many keyframes moved. Duplicates are ignored."""
        if batch.seq <= self.seen:
            self.stats["duplicates"] += 1
            return 0
        self.seen = batch.seq
        self.stats["batches"] += 1
        ack = batch.acks.get(self.source, 0)
        moves: dict[int, np.ndarray] = {}
        for s in sorted(set(batch.increments) | set(self.in_flight)):
            D = batch.increments.get(s)
            if s not in self.keeper:
                if D is not None:
                    self.pending[s] = sim3_compose(D, self.pending[s]) if s in self.pending else D
                    while len(self.pending) > 1000:
                        self.pending.pop(min(self.pending))
                continue
            old = self.in_flight.get(s, [])
            left = [(q, C) for q, C in old if q > ack]
            if D is None and len(left) == len(old):
                continue
            F_old, F_new = _product(old), _product(left)
            if left:
                self.in_flight[s] = left
            else:
                self.in_flight.pop(s, None)
            if D is not None:
                self.keeper[s] = sim3_apply_to_pose(D, self.keeper[s])
            else:
                D = _I
            U = sim3_compose(F_new, sim3_compose(D, sim3_inverse(F_old)))
            if np.abs(U - _I).max() > 1e-12:
                moves[s] = U
        if moves:
            self.owner.apply_increments(moves)
        self.stats["moved"] += len(moves)
        return len(moves)

    def abandon(self) -> int:
        """The keeper is gone for good (it stopped): undo the own increments it never answered, so
        the owner ends at the keeper's poses, whose trajectory never held them. Returns how many
        keyframes moved back."""
        moves = {s: sim3_inverse(_product(incs)) for s, incs in self.in_flight.items() if s in self.keeper}
        self.in_flight.clear()
        if moves:
            self.owner.apply_increments(moves)
        return len(moves)

    def send(self, increments: dict[int, np.ndarray], seq_hint: int = 0) -> Optional[IncrementBatch]:
        """The owner's own moves ``{stamp: C}`` (already applied to it) as a batch for the keeper;
        None when there is nothing to send. Increments of keyframes the keeper never emitted are
        left out. ``seq_hint``: a number the sequence should reach (e.g. the mapped keyframe's
        stamp, so a restarted writer keeps counting up)."""
        incs = {int(s): np.asarray(C, np.float64) for s, C in increments.items() if int(s) in self.keeper}
        if not incs:
            return None
        self.seq = max(self.seq + 1, int(seq_hint))
        for s, C in incs.items():
            self.in_flight.setdefault(s, []).append((self.seq, C))
        return IncrementBatch(self.source, self.seq, incs, {self.keeper_name: self.seen})

    def keeper_pose(self, stamp_ns: int) -> Optional[np.ndarray]:
        """The keeper's pose of a keyframe as far as the batches received tell (None: unknown)."""
        T = self.keeper.get(int(stamp_ns))
        return None if T is None else T.copy()
