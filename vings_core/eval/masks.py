"""Figures of dynamic masks against the truth (the simulator's ``mask0``): per keyframe IoU,
recall of dynamic pixels and false positives among static pixels, and their aggregate over a run.

A keyframe "with objects" is one whose true mask covers at least ``min_object_fraction`` of the
image (0.5 %); IoU and recall are averaged over those, false positives over every keyframe.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: a keyframe "with objects": the true mask covers at least this fraction of the pixels
MIN_OBJECT_FRACTION = 0.005


@dataclass
class MaskScore:
    """One keyframe: ``iou`` (None when neither mask has a pixel), ``tp``, ``fp``, ``fn`` and
    ``static`` (pixel counts; ``static`` = pixels the truth says are static), ``truth_fraction``."""

    iou: float | None
    tp: int
    fp: int
    fn: int
    static: int
    truth_fraction: float


def score_mask(pred: np.ndarray, truth: np.ndarray) -> MaskScore:
    """``pred`` and ``truth`` ``(H, W)`` bool (True = dynamic)."""
    p = np.asarray(pred, dtype=bool)
    t = np.asarray(truth, dtype=bool)
    if p.shape != t.shape:
        raise ValueError(f"mask shapes differ: predicted {p.shape}, truth {t.shape}")
    tp = int((p & t).sum())
    fp = int((p & ~t).sum())
    fn = int((~p & t).sum())
    union = tp + fp + fn
    return MaskScore(tp / union if union else None, tp, fp, fn, int((~t).sum()), float(t.mean()))


def aggregate(scores: list[MaskScore], min_object_fraction: float = MIN_OBJECT_FRACTION) -> dict:
    """Run figures: ``iou_mean`` and ``recall`` (pooled over pixels) on keyframes with objects,
    ``false_positive_fraction`` (pooled over the static pixels of every keyframe), counts."""
    obj = [s for s in scores if s.truth_fraction >= min_object_fraction]
    tp = sum(s.tp for s in obj)
    fn = sum(s.fn for s in obj)
    static = sum(s.static for s in scores)
    return {"keyframes": len(scores), "keyframes_with_objects": len(obj),
            "iou_mean": float(np.mean([s.iou or 0.0 for s in obj])) if obj else None,
            "recall": tp / (tp + fn) if tp + fn else None,
            "false_positive_fraction": sum(s.fp for s in scores) / static if static else None,
            "masked_fraction": float(np.mean([(s.tp + s.fp) / max(1, s.tp + s.fn + s.static)
                                              for s in scores])) if scores else None}
