"""The score manager (paper Algorithm 1) as a strategy the trainer calls, in the style of gsplat's
``strategy/``: hooks at fixed points of the training loop, its own state (which window keyframe
scores into which column of the Gaussians' ``win_c`` / ``win_e``), and the per-Gaussian scores kept
as rows of the :class:`~.gaussians.GaussianMap` so they travel with the Gaussians (passive store,
checkpoints). The score arithmetic is in :mod:`.scores`.

Hooks, in the order the mapper calls them:

* :meth:`ScoreManager.keyframe_added`: a keyframe entered the window (one may have left it);
* :meth:`ScoreManager.step_post_backward`: after a training render's backward pass (window
  keyframes only): record each Gaussian's contribution and error;
* :meth:`ScoreManager.after_train_step`: after the optimiser step and the render clock's tick:
  status control every ``delta_status`` and storage control every ``delta_storage`` renders;
* :meth:`ScoreManager.gaussians_returned`: passive Gaussians came back to the active set.

Units: pixel weights at the working resolution (see :mod:`.config`).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from . import scores as S
from .config import MapperConfig
from .gaussians import GaussianMap


class ScoreManager:
    """Algorithm 1 of the paper. ``counters``: the mapper's event counters, updated in place
    (``to_stable``, ``to_unstable``, ``pruned``)."""

    def __init__(self, cfg: MapperConfig, counters: dict[str, int]) -> None:
        self.cfg = cfg
        self.counters = counters
        self.slots: list[int] = [-1] * cfg.window_size    # window keyframe stamp per score column, -1: free

    def keyframe_added(self, gm: GaussianMap, stamp: int, left: Optional[int]) -> None:
        """Keyframe ``stamp`` entered the window; ``left`` (if not None) left it: its column is
        cleared (window turnover) and given to the new keyframe."""
        if left is not None:
            slot = self.slots.index(left)
            S.clear_slot(gm.win_c, gm.win_e, slot)
            self.slots[slot] = -1
        self.slots[self.slots.index(-1)] = stamp

    @torch.no_grad()
    def step_post_backward(self, gm: GaussianMap, stamp: int, out) -> None:
        """Record a training render of window keyframe ``stamp`` (``out``: the rasterizer's
        result with per-Gaussian ``contribution`` and ``error``, the error w.r.t. the keyframe's
        previous loss map)."""
        err = out.error if out.error is not None else torch.zeros(len(gm))
        S.record_render(gm.win_c, gm.win_e, gm.kf_id, gm.id_score, self.slots.index(stamp),
                        out.contribution.to(torch.float32), err.to(torch.float32), stamp)

    @torch.no_grad()
    def after_train_step(self, gm: GaussianMap, step: int, loss_maps: dict[int, torch.Tensor]) -> GaussianMap:
        """Status control every ``delta_status`` and storage control every ``delta_storage``
        training renders (status first when both are due); ``step``: training renders so far,
        ``loss_maps``: the window keyframes' latest per-pixel L1 maps. Returns the map without the
        pruned Gaussians (``gm`` itself when none is pruned, or with ``score_manager`` off)."""
        cfg = self.cfg
        if not cfg.score_manager:
            return gm
        status_now = step % cfg.delta_status == 0
        storage_now = step % cfg.delta_storage == 0
        if not (status_now or storage_now):
            return gm
        s_c, s_e = S.window_scores(gm.win_c, gm.win_e)
        judged = S.scored_long_enough(gm.score_since, step, cfg.min_score_age)
        if status_now:
            self._status_control(gm, s_c, s_e, judged, step)
            s_c, s_e = S.window_scores(gm.win_c, gm.win_e)
            judged = S.scored_long_enough(gm.score_since, step, cfg.min_score_age)
        if storage_now:
            prune = self._storage_prune(gm, s_c, judged, loss_maps)
            n = int(prune.sum())
            if n:
                gm = gm.remove(prune)
                self.counters["pruned"] += n
        return gm

    def gaussians_returned(self, back: GaussianMap, step: int) -> None:
        """Passive Gaussians ``back`` re-enter the active set at training render ``step``: their
        window scores refer to keyframes that have left the window, so their scoring restarts."""
        S.reset_scores(back.win_c, back.win_e, back.score_since, None, step)

    def _status_control(self, gm: GaussianMap, s_c: torch.Tensor, s_e: torch.Tensor, judged: torch.Tensor,
                        step: int) -> None:
        cfg = self.cfg
        to_stable, to_unstable = S.status_control(gm.stable, s_c, s_e, judged, cfg.sc_status, cfg.se_status)
        gm.stable[to_stable] = True
        gm.stable[to_unstable] = False
        S.reset_scores(gm.win_c, gm.win_e, gm.score_since, to_unstable, step)
        self.counters["to_stable"] += int(to_stable.sum())
        self.counters["to_unstable"] += int(to_unstable.sum())

    def _storage_prune(self, gm: GaussianMap, s_c: torch.Tensor, judged: torch.Tensor,
                       loss_maps: dict[int, torch.Tensor]) -> torch.Tensor:
        """``(N,)`` bool: the Gaussians storage control removes."""
        cfg = self.cfg
        owned = None
        if cfg.prune_window_owned_only:
            win = torch.tensor([x for x in self.slots if x != -1], dtype=gm.kf_id.dtype, device=gm.kf_id.device)
            owned = torch.isin(gm.kf_id, win)
        s_store = S.per_view_contribution(gm.win_c, cfg.sc_view_floor) if cfg.sc_storage_per_view else s_c
        spared = None
        if cfg.prune_spare_high_error and loss_maps:
            # the window keyframes' mean L1 error (their latest training renders)
            ref = float(np.mean([float(lm.mean()) for lm in loss_maps.values()]))
            spared = S.error_density(gm.win_c, gm.win_e) > ref
        return S.storage_control(gm.stable, s_store, judged, cfg.sc_storage, cfg.sc_status, owned, spared)
