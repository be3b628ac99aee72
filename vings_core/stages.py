"""Stage steps shared by ``vings run`` (:class:`~vings_core.pipeline.SlamRunner`) and the nodes, so
both compute the same thing."""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from .exchange import IncrementBatch, PoseFollower
from .geometry import pose_increment
from .types import Keyframe
from .profiling import profiled

#: the mapper's source name in the pose exchange
MAPPER_SOURCE = "mapper"


def _differs(A: np.ndarray, B: np.ndarray, tol: float = 1e-12) -> bool:
    return bool(np.abs(np.asarray(A) - np.asarray(B)).max() > tol)


@profiled("mapping", "keyframe (total)")
def map_keyframe(mapper, follower: PoseFollower, kf: Keyframe, refine: bool = True, chunk: int = 0,
                 stop: Optional[Callable[[], bool]] = None, backlog: int = 0) -> tuple[dict, Optional[IncrementBatch]]:
    """One mapping step: add the keyframe to ``mapper`` (:class:`~vings_core.mapping.Mapper`) and to
    its exchange ``follower``, train ``iters_per_keyframe`` iterations (in chunks of ``chunk`` when
    > 0, ending early once ``stop()`` is true: prompt shutdown), then (``refine``) refine the poses.
    ``backlog``: keyframes waiting behind this one; from ``catch_up_backlog`` on (when > 0) the
    keyframe is trained lightly (``catch_up_iters``, no refinement) so the mapper catches up.
    Returns the last training stats (``light``: whether it was trained lightly) and the refinement
    as an increment batch for the keeper (None when no pose moved), numbered at least the
    keyframe's stamp."""
    mapper.add_keyframe(kf)
    follower.keyframe_added(int(kf.stamp_ns), kf.T_wc.detach().cpu().numpy().astype(np.float64))
    cfg = mapper.cfg
    light = 0 < cfg.catch_up_backlog <= backlog
    iters = int(cfg.catch_up_iters if light else cfg.iters_per_keyframe)
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
    stats["light"] = light
    if light or not refine or (stop is not None and stop()):
        return stats, None
    base = mapper.keyframe_poses()
    refined = mapper.refine_poses()
    moved = {int(s): pose_increment(T, base[s]) for s, T in refined.items()
             if s in base and _differs(T, base[s])}
    return stats, follower.send(moved, seq_hint=int(kf.stamp_ns))


def retrain_after_loop(mapper, batch: IncrementBatch, last_ack: int, iters: int, max_s: float,
                       prune: bool = True, source: str = "loop_closer") -> tuple[int, Optional[dict]]:
    """The mapper's follow-up of a loop correction: when a keeper batch (already applied) is the
    first to acknowledge a newer batch of the loop closer (``source``; ``last_ack``: the last one
    acknowledged before), a short retrain of the revisited region and a prune by contribution
    (:meth:`~vings_core.mapping.Mapper.retrain_region`). Returns the new last acknowledgement and
    the retrain's counts (None when there was none)."""
    ack = int(batch.acks.get(source, 0))
    if ack <= last_ack:
        return last_ack, None
    if not batch.increments or iters <= 0:
        return ack, None
    return ack, mapper.retrain_region(iters, max_s, prune)
