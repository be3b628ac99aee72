"""The dynamic eraser stage: one mask per keyframe (``True`` = dynamic), from segment proposals
scored by the re-render cue (:mod:`.score`) and the motion cue (:mod:`.motion`).

:class:`DynamicEraser` keeps only the previous keyframe (for the motion cue); it never blocks on
anything: ``vings run`` calls it in the mapper's thread before the keyframe's Gaussians are added,
``eraser_node`` on the keyframe packet and the mapper's render of that keyframe.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

from ..types import Keyframe
from .config import Cue, EraserConfig, LossTerms
from .motion import motion_residual, moving_proposals, static_proposals
from .proposals import make_segmenter
from .score import dynamic_proposals, rerender_loss, rerender_maps

log = logging.getLogger(__name__)

#: the variants an ablation run computes besides the configured mask (name -> description)
ABLATION_VARIANTS = {
    "l1": "re-render cue with L_1 only",
    "ssim_l1": "re-render cue with L_SSIM * L_1",
    "ssim_l1_sigma": "re-render cue with L_SSIM * L_1 * Sigma (the paper's)",
    "motion": "motion cue alone",
    "combined": "motion, or re-render (the paper's) where the flow does not show the proposal static",
}


@dataclass
class EraserResult:
    """One keyframe's mask and its figures. ``mask`` ``(H, W)`` bool, True = dynamic;
    ``variants`` (``ablation`` only) name -> ``(H, W)`` bool mask per :data:`ABLATION_VARIANTS`."""

    stamp_ns: int
    mask: np.ndarray
    proposals: int
    dynamic_rerender: int
    dynamic_motion: int
    covered_fraction: float
    time_ms: float
    note: str = ""
    variants: dict = field(default_factory=dict)

    @property
    def masked_fraction(self) -> float:
        return float(self.mask.mean()) if self.mask.size else 0.0

    def summary(self) -> dict:
        return {"stamp_ns": int(self.stamp_ns), "proposals": self.proposals,
                "dynamic_rerender": self.dynamic_rerender, "dynamic_motion": self.dynamic_motion,
                "covered_fraction": round(self.covered_fraction, 4),
                "masked_fraction": round(self.masked_fraction, 5), "time_ms": round(self.time_ms, 1),
                **({"note": self.note} if self.note else {})}


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    if px <= 0 or not mask.any():
        return mask
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


class DynamicEraser:
    """Masks moving objects in keyframes (module docstring). ``process`` one keyframe at a time, in
    keyframe order."""

    def __init__(self, config: Optional[EraserConfig] = None) -> None:
        self.cfg = config or EraserConfig()
        self.cfg.validate()
        self.segment = make_segmenter(self.cfg)
        self._prev: Optional[tuple[int, np.ndarray, np.ndarray]] = None   # stamp, gray, T_wc

    def reset(self) -> None:
        """Forget the previous keyframe (a new map segment, or poses moved by a loop)."""
        self._prev = None

    def process(self, kf: Keyframe, render: Optional[dict]) -> EraserResult:
        """The mask of keyframe ``kf``. ``render``: the map rendered at ``kf.T_wc`` before the
        keyframe's own Gaussians were added (``color`` (H, W, 3), ``depth`` (H, W) m, ``alpha``
        (H, W), as :meth:`~vings_core.mapping.Mapper.render` returns), or None (empty map)."""
        t0 = time.perf_counter()
        cfg = self.cfg
        image = kf.image.detach().cpu().numpy().astype(np.float32)[..., :3]
        H, W = image.shape[:2]
        T_wc = kf.T_wc.detach().cpu().numpy().astype(np.float64)
        labels = self.segment(image)
        n = int(labels.max()) + 1
        covered = np.zeros((H, W), bool) if render is None else np.asarray(render["alpha"]) > cfg.min_alpha
        var = kf.inv_depth_var.detach().cpu().numpy()
        want_rr = cfg.cue in (Cue.RERENDER, Cue.BOTH) or cfg.ablation
        want_mo = cfg.cue in (Cue.MOTION, Cue.BOTH) or cfg.ablation
        terms = [cfg.loss_terms] if not cfg.ablation else list(LossTerms)
        dyn_rr: dict[LossTerms, np.ndarray] = {}
        if want_rr and render is not None and covered.any():
            maps = rerender_maps(np.asarray(render["color"]), image)      # once for every variant
            for tm in terms:
                loss = rerender_loss(None, None, var, covered, tm, cfg.sigma_clip, maps=maps)
                dyn_rr[tm], _ = dynamic_proposals(labels, loss, covered, cfg)
        for tm in terms:
            dyn_rr.setdefault(tm, np.zeros(n, bool))
        dyn_mo = np.zeros(n, bool)
        still = np.zeros(n, bool)       # proposals the flow shows static
        note = ""
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if want_mo and self._prev is not None:
            stamp0, gray0, T0 = self._prev
            if 0 < (int(kf.stamp_ns) - stamp0) * 1e-9 <= cfg.motion_max_gap_s:
                depth = None if render is None else np.where(covered, np.asarray(render["depth"]), 0.0)
                normal = None if render is None or "normal" not in render else np.asarray(render["normal"])
                res = motion_residual(gray, gray0, T_wc, T0, kf.camera, depth, cfg.motion_px, cfg.motion_rel,
                                      cfg.fb_check_px, cfg.motion_refine_pose, normal=normal,
                                      grazing_cos_min=cfg.motion_grazing_cos_min, median_k=cfg.motion_median_k)
                if res.moving.sum() <= cfg.motion_max_fraction * max(1, res.reliable.sum()):
                    dyn_mo = moving_proposals(labels, res, cfg.min_proposal_px, cfg.motion_fraction,
                                              cfg.motion_min_reliable)
                    still = static_proposals(labels, res, cfg.motion_min_reliable, cfg.static_fraction)
                else:
                    note = (f"{100 * res.moving.sum() / max(1, res.reliable.sum()):.0f} % of the flow disagrees "
                            f"with the camera's motion (> motion_max_fraction): no motion cue")
        self._prev = (int(kf.stamp_ns), gray, T_wc)

        rr = dyn_rr[cfg.loss_terms]
        pick = {Cue.RERENDER: rr, Cue.MOTION: dyn_mo, Cue.BOTH: dyn_mo | (rr & ~still)}[cfg.cue]
        mask = self._finish(labels, pick)
        if mask.mean() > cfg.max_masked_fraction:
            drop = (f"mask covered {100 * mask.mean():.0f} % of the image (> max_masked_fraction "
                    f"{100 * cfg.max_masked_fraction:.0f} %): map or tracking disagree with the whole view; no mask")
            note = f"{note}; {drop}" if note else drop
            log.warning("eraser: keyframe %d: %s", int(kf.stamp_ns), note)
            mask = np.zeros((H, W), bool)
        variants = {}
        if cfg.ablation:
            variants = {tm.value: self._finish(labels, dyn_rr[tm]) for tm in LossTerms}
            variants["motion"] = self._finish(labels, dyn_mo)
            variants["combined"] = self._finish(labels, dyn_mo | (dyn_rr[LossTerms.SSIM_L1_SIGMA] & ~still))
        return EraserResult(int(kf.stamp_ns), mask, n, int(rr.sum()), int(dyn_mo.sum()),
                            float(covered.mean()), 1e3 * (time.perf_counter() - t0), note, variants)

    def _finish(self, labels: np.ndarray, dynamic: np.ndarray) -> np.ndarray:
        return _dilate(dynamic[labels], int(self.cfg.dilate_px))
