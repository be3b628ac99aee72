"""Configuration of the pose exchange (params section ``exchange``)."""
from __future__ import annotations

import enum
from dataclasses import dataclass, field

#: the keeper's source name (the front end)
KEEPER = "frontend"


class WritebackPolicy(str, enum.Enum):
    """What the keeper does with a writer's increments."""

    NONE = "none"               #: never applied: the writer undoes them when it sees the ack
    ALL = "all"                 #: every increment applied
    CONSISTENT = "consistent"   #: applied when the keeper's own visual evidence agrees (chi-square)

    def __str__(self) -> str:
        return self.value


@dataclass
class ExchangeConfig:
    """Pose exchange settings (params section ``exchange``).

    ``mapper`` / ``loop_closer``: write-back policy for the increments of that writer; ``other``: for
    any other writer. ``consistent`` accepts a batch's increments of keyframes inside the keeper's
    BA window together when their joint cost under the window's Schur-reduced pose information
    passes a chi-square test at ``confidence``; increments of keyframes outside the window are
    refused (nothing to check them against). A loop closure's correction fails such a gate by
    design (it moves keyframes by far more than their noise), so its writer is ``all``.
    ``extra_writers``: names of further writers the keeper node listens to (topic
    ``/vings/exchange/<name>``), besides ``mapper`` and ``loop_closer``. ``jump_writers``: writers
    whose batches are corrections of the whole past (a loop closure): the keeper also moves every
    frame and keyframe newer than the newest one in such a batch by that keyframe's increment
    (its window, velocities and biases with it), so the present follows the corrected past.
    """

    mapper: WritebackPolicy = WritebackPolicy.CONSISTENT
    loop_closer: WritebackPolicy = WritebackPolicy.ALL
    other: WritebackPolicy = WritebackPolicy.ALL
    confidence: float = 0.99
    extra_writers: list[str] = field(default_factory=list)
    jump_writers: list[str] = field(default_factory=lambda: ["loop_closer"])

    def validate(self) -> None:
        if not 0 < self.confidence < 1:
            raise ValueError(f"confidence must be in (0, 1), got {self.confidence}")
        for name in [*self.extra_writers, *self.jump_writers]:
            if not name or not name.replace("_", "").isalnum() or name == KEEPER:
                raise ValueError(f"extra_writers: {name!r} is not a valid writer name (letters, digits, _; "
                                 f"not {KEEPER!r})")

    def jumps(self, source: str) -> bool:
        """Whether ``source``'s batches carry forward to newer frames (see ``jump_writers``)."""
        return source in self.jump_writers

    def policy(self, source: str) -> WritebackPolicy:
        """The write-back policy for increments from ``source``."""
        if source in ("mapper", "loop_closer"):
            return WritebackPolicy(getattr(self, source))
        return WritebackPolicy(self.other)

    def writers(self) -> list[str]:
        """Every writer the keeper listens to."""
        return list(dict.fromkeys(["mapper", "loop_closer", *self.extra_writers]))
