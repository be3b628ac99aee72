"""Dynamic eraser configuration: section ``eraser`` of the params YAML."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import Enum


class ProposalMethod(str, Enum):
    """How a keyframe is cut into segment proposals (:mod:`vings_core.eraser.proposals`)."""

    FELZENSZWALB = "felzenszwalb"   #: graph-based segmentation (scikit-image), weight-free default
    SLIC = "slic"                   #: SLIC superpixels (scikit-image), weight-free
    MODEL = "model"                 #: a learned segmenter from ``model_path`` (TorchScript or ONNX)

    def __str__(self) -> str:
        return self.value


class Cue(str, Enum):
    """Which evidence marks a proposal dynamic."""

    RERENDER = "rerender"   #: the paper's re-render loss (needs the map to cover the proposal)
    MOTION = "motion"       #: measured flow against the flow the camera's motion induces
    BOTH = "both"           #: the motion cue, or the re-render cue where the flow does not show the
                            #: proposal static (default)

    def __str__(self) -> str:
        return self.value


class LossTerms(str, Enum):
    """Terms of the per-pixel re-render loss (the ablation of the paper's Table)."""

    L1 = "l1"                     #: ``L_1``
    SSIM_L1 = "ssim_l1"           #: ``L_SSIM * L_1``
    SSIM_L1_SIGMA = "ssim_l1_sigma"   #: ``L_SSIM * L_1 * Sigma_{d^-1}`` (the paper's, default)

    def __str__(self) -> str:
        return self.value


@dataclass
class EraserConfig:
    """Units: pixels of the working resolution, colour in [0, 1], seconds."""

    enabled: bool = True                    #: run the eraser (``--no-eraser``: false)
    proposals: ProposalMethod = ProposalMethod.FELZENSZWALB
    proposal_downscale: int = 2             #: weight-free segmentation runs at 1/this resolution
    felz_scale: float = 100.0               #: Felzenszwalb ``scale`` (larger: larger segments)
    felz_sigma: float = 0.5                 #: Felzenszwalb pre-smoothing (px, segmentation resolution)
    felz_min_size: int = 15                 #: Felzenszwalb least segment size (px, same)
    slic_segments: int = 300                #: SLIC superpixels per keyframe
    model_path: str = ""                    #: ``proposals: model``: local TorchScript (.pt) or ONNX
                                            #: (.onnx) file; never downloaded
    cue: Cue = Cue.BOTH
    # ---- re-render cue (the paper)
    loss_terms: LossTerms = LossTerms.SSIM_L1_SIGMA
    percentile: float = 90.0                #: per-keyframe percentile of the loss over covered pixels
    gamma: float = 0.2                      #: a proposal is dynamic when more than this fraction of
                                            #: its covered pixels exceed the percentile ...
    loss_threshold: float = 0.2             #: ... and its mean loss exceeds this
    sigma_clip: float = 10.0                #: Sigma_{d^-1} is taken relative to its median over the
                                            #: covered pixels and clipped to [1/clip, clip]
    min_alpha: float = 0.5                  #: a pixel is covered by the map when the render's
                                            #: accumulated opacity exceeds this
    min_covered_fraction: float = 0.5       #: the re-render cue judges a proposal only when this
                                            #: fraction of it is covered
    # ---- motion cue
    motion_px: float = 1.5                  #: residual flow (px) above which a pixel moves ...
    motion_rel: float = 0.5                 #: ... along its epipolar line: plus this fraction of
                                            #: the translational induced flow (the map's depth error)
    motion_fraction: float = 0.4            #: a proposal moves when this fraction of its reliable
                                            #: pixels moves
    motion_min_reliable: float = 0.3        #: ... and at least this fraction of it is reliable
    motion_grazing_cos_min: float = 1.0     #: the along-line tolerance is divided by the |cos| of
                                            #: the angle between the map's normal and the ray, at
                                            #: least this (a grazing surface's depth is uncertain;
                                            #: 1 = off, the default; 0.2 for streets, see
                                            #: docs/eraser.md)
    motion_median_k: float = 0.0            #: a pixel moves only above this many times the
                                            #: keyframe's median residual ratio (0 = off, the
                                            #: default; 3 for streets, see docs/eraser.md)
    motion_refine_pose: bool = True         #: refine the keyframes' relative pose on the flow first
    motion_max_fraction: float = 0.5        #: more reliable pixels moving than this: the relative
                                            #: motion was not found, no motion cue for the keyframe
    static_fraction: float = 0.1            #: (cue both) a proposal the re-render cue flags is kept
                                            #: static when its flow is reliable and at most this
                                            #: fraction of it moves (a map artefact, not an object)
    fb_check_px: float = 1.0                #: forward-backward flow disagreement above which a
                                            #: pixel's flow is unreliable
    motion_max_gap_s: float = 1.0           #: no motion cue against a previous keyframe older than this
    # ---- mask
    min_proposal_px: int = 30               #: smaller proposals are never dynamic
    dilate_px: int = 1                      #: the mask is dilated by this many pixels
    max_masked_fraction: float = 0.6        #: a mask covering more than this is not trusted
                                            #: (map or tracking broke): the keyframe gets none
    # ---- timing (the graph and ``vings run``)
    mask_timeout_s: float = 1.0             #: the mapper waits at most this long for a keyframe's mask
    ablation: bool = False                  #: also compute every cue and loss variant (benchmarks)

    def validate(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{f.name} must be finite, got {v}")
        self.proposals = ProposalMethod(self.proposals)
        self.cue = Cue(self.cue)
        self.loss_terms = LossTerms(self.loss_terms)
        if not 0 < self.percentile < 100:
            raise ValueError(f"percentile must be in (0, 100), got {self.percentile}")
        for name in ("gamma", "min_alpha", "min_covered_fraction", "motion_fraction", "motion_min_reliable",
                     "max_masked_fraction", "motion_max_fraction", "static_fraction"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not 0 < self.motion_grazing_cos_min <= 1:
            raise ValueError(f"motion_grazing_cos_min must be in (0, 1], got {self.motion_grazing_cos_min}")
        for name in ("felz_scale", "felz_sigma", "motion_px", "fb_check_px", "sigma_clip", "motion_max_gap_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("loss_threshold", "motion_rel", "motion_median_k", "mask_timeout_s", "felz_min_size", "dilate_px",
                     "min_proposal_px"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.proposal_downscale < 1:
            raise ValueError(f"proposal_downscale must be >= 1, got {self.proposal_downscale}")
        if self.slic_segments < 2:
            raise ValueError(f"slic_segments must be >= 2, got {self.slic_segments}")
        if self.proposals == ProposalMethod.MODEL and not self.model_path:
            raise ValueError("proposals: model needs model_path (a local TorchScript .pt or ONNX .onnx file)")
