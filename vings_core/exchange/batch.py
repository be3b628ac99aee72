"""The unit of the pose exchange: one stage's increments, numbered, with what it had seen."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..geometry import check_sim3


@dataclass
class IncrementBatch:
    """Increments written by one stage.

    ``source``: the writing stage (``frontend``, ``mapper``, ``loop_closer``, ...).
    ``seq``: its sequence number, > 0 and increasing per source (a batch with a number not above the
    last one received from that source is a duplicate and ignored).
    ``increments``: ``{keyframe stamp (ns): C}``, ``C`` a 4x4 float64 world-frame similarity
    ``[[s R, t], [0, 1]]``; the keyframe's new pose is
    :func:`~vings_core.geometry.sim3_apply_to_pose` ``(C, T_wc_old)`` and its content (depth,
    Gaussians) moves as ``x -> s R x + t``. ``s == 1`` for rigid moves.
    ``acks``: ``{source: seq}``, the last batch of each other source this stage had processed when it
    wrote this one.
    """

    source: str
    seq: int
    increments: dict[int, np.ndarray] = field(default_factory=dict)
    acks: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.seq = int(self.seq)
        self.increments = {int(s): np.asarray(C, np.float64) for s, C in self.increments.items()}
        self.acks = {str(k): int(v) for k, v in self.acks.items()}

    def __len__(self) -> int:
        return len(self.increments)

    def check(self, where: str) -> "IncrementBatch":
        """Raise :class:`InputError` (message starting with ``where``) unless this is a well-formed
        batch: a source name, ``seq`` > 0, finite 4x4 similarities with a positive scale."""
        if not self.source:
            raise InputError(f"{where}: increment batch without a source")
        if self.seq <= 0:
            raise InputError(f"{where}: increment batch sequence number must be > 0, got {self.seq}")
        for s, C in self.increments.items():
            check_sim3(C, f"{where}: increment for keyframe {s}", tol=1e-4)
        return self
