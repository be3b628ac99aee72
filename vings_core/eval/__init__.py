"""Evaluation: trajectory accuracy (:mod:`.traj`, :mod:`.align`), image quality (:mod:`.image`,
:mod:`.lpips`) and the output contract of a SLAM run (:mod:`.output`).

See docs/evaluation.md and docs/output_contract.md.
"""
from .align import apply_sim3, umeyama
from .image import psnr, ssim
from .output import METRIC_KEYS, RunOutput, metrics_template, peak_rss_mb
from .traj import associate, ate, default_rpe_lengths, evaluate_trajectory, rpe

__all__ = ["umeyama", "apply_sim3", "psnr", "ssim", "METRIC_KEYS", "RunOutput", "metrics_template",
           "peak_rss_mb", "associate", "ate", "rpe", "default_rpe_lengths", "evaluate_trajectory"]
