"""The state the mapper's parts share: the Gaussian map (active set, passive store), the keyframes
(local window, history, poses) and the clocks and random generator every part draws from.

Frames: keyframe poses ``T_wc`` 4x4 float64 camera-to-world; Gaussians in the world frame (m).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from ..render import rasterize_2dgs
from ..types import CameraModel, Keyframe
from .config import MapperConfig
from .gaussians import SH_C0, GaussianMap
from .history import HistoryStore
from .storage import PassiveStore


def new_counters() -> dict[str, int]:
    """The mapper's event counters (reported by ``Mapper.train`` and kept in checkpoints)."""
    return dict(added=0, deleted=0, pruned=0, nonfinite_grads=0, to_stable=0, to_unstable=0, to_passive=0,
                from_passive=0, tier_updates=0, erased_dynamic=0)


@dataclass
class MapState:
    """Mutable state of one mapper, shared by its parts (growth, training, score manager, pose
    refinement, checkpoints). ``gm`` is replaced (not only changed in place) when Gaussians are
    added, deleted or pruned: parts read it from here each time, never keep it."""

    cfg: MapperConfig
    device: torch.device
    gm: GaussianMap
    passive: PassiveStore
    history: HistoryStore                # keyframes that left the window (compact, spilled to disk)
    rng: torch.Generator                 # every random draw of the mapper, in one order
    background: torch.Tensor             # (3,) float32 RGB in [0, 1]
    window: list[Keyframe] = field(default_factory=list)
    poses: dict[int, np.ndarray] = field(default_factory=dict)    # stamp -> T_wc of every keyframe
    order: list[int] = field(default_factory=list)                # keyframe stamps, in stamp order
    camera: Optional[CameraModel] = None
    render_count: int = 0                # training renders so far (score clock)
    kf_count: int = 0
    loss_maps: dict[int, torch.Tensor] = field(default_factory=dict)  # last per-pixel L1 of window keyframes
    #: history keyframes' depth factors not yet applied to their stored depth (similarity increments)
    depth_scale: dict[int, float] = field(default_factory=dict)
    counters: dict[str, int] = field(default_factory=new_counters)

    @staticmethod
    def create(cfg: MapperConfig, device: torch.device) -> "MapState":
        """An empty map for ``cfg`` on ``device``."""
        gm = GaussianMap.empty(cfg.sh_degree, cfg.window_size, device)
        passive = PassiveStore(int(cfg.passive_memory_mb * 2**20), cfg.spill_dir or None)
        rng = torch.Generator().manual_seed(int(cfg.seed))
        history = HistoryStore(int(cfg.history_memory_mb * 2**20), cfg.spill_dir or None)
        return MapState(cfg=cfg, device=device, gm=gm, passive=passive, history=history, rng=rng,
                        background=torch.tensor(cfg.background, dtype=torch.float32))

    def pose_table(self) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe stamps ``(K,)`` int64 ascending and their camera centres ``(K, 3)`` (world, m)."""
        stamps = np.array(sorted(self.poses), dtype=np.int64)
        pos = np.stack([self.poses[int(s)][:3, 3] for s in stamps]) if len(stamps) else np.zeros((0, 3))
        return stamps, pos

    def window_keyframe(self, stamp: int) -> Keyframe:
        """The window keyframe with ``stamp``."""
        for kf in self.window:
            if kf.stamp_ns == stamp:
                return kf
        raise RuntimeError("window keyframe vanished")  # pragma: no cover

    def rasterize(self, gm: GaussianMap, T_cw: torch.Tensor, camera: CameraModel, sample_ratio: float = 1.0,
                  loss_map: Optional[torch.Tensor] = None, means: Optional[torch.Tensor] = None,
                  quats: Optional[torch.Tensor] = None, sh: Optional[torch.Tensor] = None,
                  log_scales: Optional[torch.Tensor] = None, opacity_logits: Optional[torch.Tensor] = None):
        """Render ``gm`` from world-to-camera ``T_cw`` (4x4) with the map's background; parameters
        given here (e.g. autograd leaves, moved copies) replace the map's own."""
        means = gm.means if means is None else means
        quats = gm.quats if quats is None else quats
        scales = torch.exp(gm.log_scales if log_scales is None else log_scales)
        opac = torch.sigmoid(gm.opacity_logits if opacity_logits is None else opacity_logits)
        sh = gm.sh if sh is None else sh
        if self.cfg.sh_degree == 0:
            colors = (sh[:, 0] * SH_C0 + 0.5).clamp_min(0.0)
            return rasterize_2dgs(means, quats, scales, opac, colors, T_cw, camera, background=self.background,
                                  sample_ratio=sample_ratio, loss_map=loss_map)
        return rasterize_2dgs(means, quats, scales, opac, sh, T_cw, camera, sh_degree=self.cfg.sh_degree,
                              background=self.background, sample_ratio=sample_ratio, loss_map=loss_map)
