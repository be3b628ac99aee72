"""Score manager (paper Algorithm 1) as pure tensor functions.

Per training render of window keyframe ``t`` the rasterizer reports, for each Gaussian ``g``, its
contribution ``c_t(g) = sum_u alpha T`` and error ``e_t(g) = sum_u L_rgb(u) alpha T`` over the pixels
it touches. The map keeps one column per slot of the local keyframe window (K slots):

* ``win_c[:, slot(t)] = c_t`` and ``win_e[:, slot(t)] = e_t`` from the latest render of ``t``;
* ``S_C = sum over slots`` (paper: sum over the K keyframes of the list) and
  ``S_E = max over slots`` (paper: max over the list);
* ``kf_id`` / ``id_score``: ID(g) = the keyframe with the highest single-render contribution so far.

When a keyframe leaves the window its slot column is cleared before the new keyframe takes it, so
once the window has fully turned over nothing of the old window remains (the "window turnover
reset"). Units: pixel weights at the working resolution (a Gaussian fully covering one pixel
contributes 1); thresholds scale with ``W * H`` (docs/mapping.md).
"""
from __future__ import annotations

import torch


def window_scores(win_c: torch.Tensor, win_e: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(S_C, S_E)``: window-summed contribution and window-max error, (N,) each."""
    if win_c.shape[1] == 0:
        z = torch.zeros(win_c.shape[0], dtype=win_c.dtype, device=win_c.device)
        return z, z.clone()
    return win_c.sum(1), win_e.max(1).values


def per_view_contribution(win_c: torch.Tensor, view_floor: float = 0.1) -> torch.Tensor:
    """Mean window contribution over the window keyframes that see the Gaussian, (N,) (0 where none
    does). A keyframe "sees" it when its contribution is positive and at least ``view_floor`` x the
    Gaussian's best window view: a faint touch (alpha tails at the edge of a splat) is not a view,
    else it would halve the score of a Gaussian one keyframe sees well. Unlike the sum, it does not
    favour Gaussians seen by many window keyframes over those at the edge of the window's views."""
    if win_c.shape[1] == 0:
        return torch.zeros(win_c.shape[0], dtype=win_c.dtype, device=win_c.device)
    best = win_c.max(1, keepdim=True).values
    seen = (win_c > 0) & (win_c >= view_floor * best)
    return (win_c * seen).sum(1) / seen.sum(1).clamp_min(1).to(win_c.dtype)


def error_density(win_c: torch.Tensor, win_e: torch.Tensor) -> torch.Tensor:
    """Mean per-pixel colour error under each Gaussian over the window, (N,): ``sum_t e_t / sum_t
    c_t`` (the L1 error of the pixels it covers, weighted by its ``alpha T`` there; 0 where no
    window keyframe sees it)."""
    if win_c.shape[1] == 0:
        return torch.zeros(win_c.shape[0], dtype=win_c.dtype, device=win_c.device)
    c = win_c.sum(1)
    return torch.where(c > 0, win_e.sum(1) / c.clamp_min(1e-30), torch.zeros_like(c))


def record_render(win_c: torch.Tensor, win_e: torch.Tensor, kf_id: torch.Tensor, id_score: torch.Tensor,
                  slot: int, contrib: torch.Tensor, error: torch.Tensor, stamp_ns: int) -> None:
    """In place: store one render's per-Gaussian contribution/error of keyframe ``stamp_ns`` in its
    window ``slot`` and update ID(g)."""
    contrib = contrib.to(win_c.dtype)
    win_c[:, slot] = contrib
    win_e[:, slot] = error.to(win_e.dtype)
    better = contrib > id_score
    kf_id[better] = int(stamp_ns)
    id_score[better] = contrib[better]


def clear_slot(win_c: torch.Tensor, win_e: torch.Tensor, slot: int) -> None:
    """In place: forget the scores of a keyframe that left the window."""
    win_c[:, slot] = 0
    win_e[:, slot] = 0


def scored_long_enough(score_since: torch.Tensor, render_count: int, min_age: int) -> torch.Tensor:
    """Bool: Gaussians scored over at least ``min_age`` training renders (newborns are not judged)."""
    return (render_count - score_since) >= min_age


def status_control(stable: torch.Tensor, s_c: torch.Tensor, s_e: torch.Tensor, judged: torch.Tensor,
                   sc_status: float, se_status: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Masks ``(to_stable, to_unstable)``.

    unstable -> stable when ``S_C < sc_status`` (no longer seen by the local window: frozen, kept);
    stable -> unstable when ``S_E > se_status`` (seen again and wrong: trained again, scores reset).
    Only Gaussians in ``judged`` become stable; any stable one may be woken up.
    """
    to_stable = (~stable) & judged & (s_c < sc_status)
    to_unstable = stable & (s_e > se_status)
    return to_stable, to_unstable


def storage_control(stable: torch.Tensor, s_c: torch.Tensor, judged: torch.Tensor,
                    sc_storage: float, sc_status: float = 0.0,
                    owned_by_window: torch.Tensor | None = None,
                    spared: torch.Tensor | None = None) -> torch.Tensor:
    """Prune mask: unstable Gaussians, judged, with ``sc_status <= S_C < sc_storage`` (seen by the
    window but contributing little).

    Gaussians the window does not see at all (``S_C < sc_status``) are left to status control, which
    freezes them: in Algorithm 1 status control runs first on the same iteration, so such Gaussians
    are stable (and protected) before storage control looks at them. Storage control may run more
    often than status control here, so the exclusion is explicit.

    ``owned_by_window`` (optional bool mask): only these Gaussians may be pruned, i.e. those whose
    ID(g) (best view so far) is a window keyframe. A Gaussian whose best view has left the window
    mostly serves that older view; a low window sum then says little about its worth.

    ``spared`` (optional bool mask): never pruned, e.g. Gaussians where the render is still wrong
    (:func:`error_density` above the window's mean error): there the small splats are the detail
    being fitted (fine texture, edges), and removing them costs PSNR that no neighbour recovers.
    """
    prune = (~stable) & judged & (s_c >= sc_status) & (s_c < sc_storage)
    if owned_by_window is not None:
        prune &= owned_by_window
    return prune if spared is None else prune & ~spared


def reset_scores(win_c: torch.Tensor, win_e: torch.Tensor, score_since: torch.Tensor,
                 rows: torch.Tensor | None, render_count: int) -> None:
    """In place: zero S_C and S_E of ``rows`` (mask/indices; None = all) and restart their scoring."""
    if rows is None:
        win_c.zero_()
        win_e.zero_()
        score_since.fill_(int(render_count))
    else:
        win_c[rows] = 0
        win_e[rows] = 0
        score_since[rows] = int(render_count)
