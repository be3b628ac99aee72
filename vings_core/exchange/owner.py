"""What a stage that owns keyframe poses offers the exchange."""
from __future__ import annotations

from typing import Optional, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class PoseOwner(Protocol):
    """A stage holding keyframe poses that follows the exchange (mapper, loop closer, ...)."""

    def apply_increments(self, increments: dict[int, np.ndarray]) -> object:
        """Move keyframes by world-frame similarities ``{stamp: C}``
        (``T_new = sim3_apply_to_pose(C, T_old)``; content moves as ``x -> s R x + t``); unknown
        stamps are the owner's to ignore or refuse."""


@runtime_checkable
class KeeperOwner(PoseOwner, Protocol):
    """The stage whose poses are the trajectory (the front end): it also tells the current pose by
    stamp, what moved since a version, and the pose information a consistency gate needs."""

    #: a counter raised by every write of a keyframe pose
    kf_pose_version: int

    def pose(self, stamp_ns: int) -> np.ndarray:
        """Current ``T_wc`` (4x4 float64) of a frame or keyframe."""

    def keyframes_moved_since(self, version: int) -> list[int]:
        """Stamps of the keyframes written since ``kf_pose_version`` was ``version``."""

    @property
    def pose_system(self) -> Optional[object]:
        """The last window BA's Schur-reduced pose system
        (:class:`~vings_core.frontend.ba.PoseSystem`), or None."""

    def apply_jump(self, increments: dict[int, np.ndarray]) -> object:
        """Apply a correction of the past (a jump writer's batch, ``ExchangeConfig.jump_writers``)
        as :meth:`apply_increments` does, and move every frame newer than the newest stamp in it by
        that stamp's increment. An owner without it takes such batches as plain increments."""
