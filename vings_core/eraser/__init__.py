"""Dynamic eraser (the paper's "Dynamic Object Eraser"): masks of moving objects per keyframe, kept
out of mapping and tracking. See docs/eraser.md."""
from .config import Cue, EraserConfig, LossTerms, ProposalMethod
from .eraser import ABLATION_VARIANTS, DynamicEraser, EraserResult
from .mask_io import encode_mask_png, mask_to_mono8, mono8_to_mask, read_mask_png
from .motion import MotionResidual, motion_residual
from .proposals import ModelSegmenter, make_segmenter, segment_weight_free
from .score import dynamic_proposals, rerender_loss

__all__ = ["Cue", "EraserConfig", "LossTerms", "ProposalMethod", "ABLATION_VARIANTS", "DynamicEraser",
           "EraserResult", "MotionResidual", "motion_residual", "ModelSegmenter", "make_segmenter",
           "segment_weight_free", "dynamic_proposals", "rerender_loss", "encode_mask_png", "mask_to_mono8",
           "mono8_to_mask", "read_mask_png"]
