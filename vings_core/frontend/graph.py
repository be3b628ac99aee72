"""Covisibility graph of the keyframe window: directed edges ``(i, j)`` (depth of ``i`` observed in
``j``) keyed by keyframe stamps, each carrying its grid flow target and weight.

Edges come from temporal adjacency (the previous ``temporal_radius`` keyframes) plus proximity (mean
flow induced by the current poses and depths below a threshold). Edges leave with their keyframes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .projective import Intrinsics, project_edges


@dataclass
class Edge:
    i: int                 #: stamp of the keyframe whose depths are observed
    j: int                 #: stamp of the observing keyframe
    target: np.ndarray     #: (P, 2) float64 flow target in j (working-resolution px)
    weight: np.ndarray     #: (P,) float64 confidence in [0, 1]


class CovisibilityGraph:
    """Directed edges between window keyframes, keyed by ``(stamp_i, stamp_j)``."""

    def __init__(self) -> None:
        self.edges: dict[tuple[int, int], Edge] = {}

    def add(self, e: Edge) -> None:
        self.edges[(e.i, e.j)] = e

    def has(self, i: int, j: int) -> bool:
        return (i, j) in self.edges

    def remove_keyframe(self, stamp: int) -> None:
        for k in [k for k in self.edges if stamp in k]:
            del self.edges[k]

    def clear(self) -> None:
        self.edges.clear()

    def __len__(self) -> int:
        return len(self.edges)

    def tensors(self, stamps: list[int]):
        """Edges among ``stamps`` as window indices and stacked data:
        ``(ii, jj, target (E,P,2), conf (E,P))`` torch float64."""
        pos = {s: k for k, s in enumerate(stamps)}
        es = [e for e in self.edges.values() if e.i in pos and e.j in pos]
        ii = torch.tensor([pos[e.i] for e in es], dtype=torch.long)
        jj = torch.tensor([pos[e.j] for e in es], dtype=torch.long)
        tg = torch.from_numpy(np.stack([e.target for e in es])) if es else torch.zeros(0, 0, 2)
        w = torch.from_numpy(np.stack([e.weight for e in es])) if es else torch.zeros(0, 0)
        return ii, jj, tg.to(torch.float64), w.to(torch.float64)


def mean_induced_flow(T_cw: torch.Tensor, d: torch.Tensor, i: int, j: int, rays: torch.Tensor,
                      uv: torch.Tensor, K: Intrinsics, width: int, height: int) -> tuple[float, float]:
    """Mean induced flow magnitude (working-res px) of keyframe ``i``'s grid in ``j`` and the
    fraction of its pixels that land inside ``j``."""
    ii = torch.tensor([i])
    jj = torch.tensor([j])
    uvj, valid = project_edges(T_cw, d, ii, jj, rays, K)
    uvj, valid = uvj[0], valid[0]
    inside = valid & (uvj[:, 0] >= 0) & (uvj[:, 0] <= width - 1) & (uvj[:, 1] >= 0) & \
        (uvj[:, 1] <= height - 1)
    frac = float(inside.double().mean())
    if not inside.any():
        return float("inf"), 0.0
    return float(torch.linalg.norm(uvj[inside] - uv[inside], dim=-1).mean()), frac


def select_edges(T_cw: torch.Tensor, d: torch.Tensor, new: int, rays: torch.Tensor, uv: torch.Tensor,
                 K: Intrinsics, width: int, height: int, temporal_radius: int,
                 proximity_px: float, max_proximity: int, min_overlap: float = 0.5) -> list[int]:
    """Window indices that the new keyframe ``new`` (the last) should be connected to (both
    directions): the ``temporal_radius`` previous ones, plus up to ``max_proximity`` older ones whose
    mean induced flow from ``new`` is below ``proximity_px`` (closest first) with enough overlap."""
    temporal = list(range(max(0, new - temporal_radius), new))
    cands = []
    for m in range(0, max(0, new - temporal_radius)):
        f, ov = mean_induced_flow(T_cw, d, new, m, rays, uv, K, width, height)
        if f < proximity_px and ov >= min_overlap:
            cands.append((f, m))
    cands.sort()
    return sorted(temporal + [m for _, m in cands[:max_proximity]])
