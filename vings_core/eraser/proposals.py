"""Segment proposals of a keyframe: a label image ``(H, W)`` int32, labels ``0 .. n-1``.

Weight-free by default (scikit-image graph-based segmentation or SLIC superpixels, run at
``1/proposal_downscale`` of the working resolution and brought back by nearest neighbour). A
learned segmenter is a plug-in: :class:`ModelSegmenter` loads a local TorchScript or ONNX file the
user names (never downloaded).

Model contract (TorchScript or ONNX): input float32 ``(1, 3, H, W)`` RGB in [0, 1] at the working
resolution; output either ``(1, H, W)`` / ``(H, W)`` integer-valued labels, or ``(1, K, H, W)``
per-instance mask logits (a pixel takes the instance of its largest logit; pixels whose largest
logit is <= 0 form one background proposal).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from ..errors import ConfigError
from .config import EraserConfig, ProposalMethod


def relabel(labels: np.ndarray) -> np.ndarray:
    """Labels renumbered to ``0 .. n-1`` (int32) in order of first value."""
    _, inv = np.unique(labels.ravel(), return_inverse=True)
    return inv.reshape(labels.shape).astype(np.int32)


def _upsample(labels: np.ndarray, H: int, W: int) -> np.ndarray:
    if labels.shape == (H, W):
        return labels
    return cv2.resize(labels.astype(np.int32), (W, H), interpolation=cv2.INTER_NEAREST)


def segment_weight_free(image: np.ndarray, cfg: EraserConfig) -> np.ndarray:
    """Proposals of an RGB ``image`` ``(H, W, 3)`` float in [0, 1] by ``cfg.proposals``
    (Felzenszwalb or SLIC) at ``1/cfg.proposal_downscale`` resolution."""
    from skimage.segmentation import felzenszwalb, slic

    H, W = image.shape[:2]
    f = int(cfg.proposal_downscale)
    small = image if f == 1 else cv2.resize(image, (max(1, W // f), max(1, H // f)), interpolation=cv2.INTER_AREA)
    small = np.ascontiguousarray(small, dtype=np.float64)
    if cfg.proposals == ProposalMethod.SLIC:
        lab = slic(small, n_segments=int(cfg.slic_segments), start_label=0, channel_axis=-1)
    else:
        lab = felzenszwalb(small, scale=float(cfg.felz_scale), sigma=float(cfg.felz_sigma),
                           min_size=int(cfg.felz_min_size), channel_axis=-1)
    return relabel(_upsample(lab, H, W))


class ModelSegmenter:
    """A learned segmenter from a local file: TorchScript (``.pt``, ``.pth``, ``.ts``) or ONNX
    (``.onnx``, needs ``onnxruntime``). See the module docstring for the model contract."""

    def __init__(self, path: str) -> None:
        p = Path(path).expanduser()
        if not p.is_file():
            raise ConfigError(f"eraser model_path {p}: no such file (a local TorchScript .pt or ONNX "
                              f".onnx segmenter; models are never downloaded)")
        self.path = p
        self._onnx = None
        self._ts = None
        if p.suffix.lower() == ".onnx":
            try:
                import onnxruntime  # noqa: PLC0415 - optional dependency
            except ImportError:
                raise ConfigError(f"eraser model_path {p}: an ONNX model needs onnxruntime "
                                  f"(pip install onnxruntime), or export the model to TorchScript") from None
            try:
                self._onnx = onnxruntime.InferenceSession(str(p), providers=["CPUExecutionProvider"])
            except Exception as e:  # noqa: BLE001 - any loader failure is the file's
                raise ConfigError(f"eraser model_path {p}: not a loadable ONNX model ({e})") from None
        else:
            try:
                self._ts = torch.jit.load(str(p), map_location="cpu").eval()
            except Exception as e:  # noqa: BLE001
                raise ConfigError(f"eraser model_path {p}: not a loadable TorchScript model "
                                  f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None

    def __call__(self, image: np.ndarray) -> np.ndarray:
        H, W = image.shape[:2]
        x = np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)
        try:
            if self._onnx is not None:
                name = self._onnx.get_inputs()[0].name
                y = np.asarray(self._onnx.run(None, {name: x})[0])
            else:
                with torch.no_grad():
                    y = self._ts(torch.from_numpy(x))
                y = (y[0] if isinstance(y, (tuple, list)) else y).detach().cpu().numpy()
        except Exception as e:  # noqa: BLE001 - a model failing on our input is the model's problem
            raise ConfigError(f"eraser model {self.path}: failed on a (1, 3, {H}, {W}) image "
                              f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
        return model_output_labels(y, H, W, str(self.path))


def model_output_labels(y: np.ndarray, H: int, W: int, what: str = "model") -> np.ndarray:
    """Labels ``(H, W)`` from a segmenter's output (see the module docstring)."""
    y = np.asarray(y)
    if y.ndim == 4 and y.shape[0] == 1:
        y = y[0]
    if y.ndim == 3 and y.shape[0] == 1 and y.shape[1:] == (H, W):
        y = y[0]                            # one channel: labels (checked integer-valued below)
    if y.ndim == 3 and y.shape[1:] == (H, W):   # (K, H, W) logits
        best = y.argmax(0)
        bg = y.max(0) <= 0
        lab = np.where(bg, y.shape[0], best)
        return relabel(lab)
    if y.ndim == 2 and y.shape == (H, W):
        if not np.all(np.isfinite(y)) or not np.allclose(y, np.round(y)):
            raise ConfigError(f"eraser model {what}: a (H, W) output must hold integer labels")
        return relabel(np.round(y).astype(np.int64))
    raise ConfigError(f"eraser model {what}: output shape {tuple(y.shape)} is neither (1, H, W) labels "
                      f"nor (1, K, H, W) logits for a {H}x{W} image")


def make_segmenter(cfg: EraserConfig):
    """A callable ``image (H, W, 3) float [0, 1] -> labels (H, W) int32`` for ``cfg``."""
    if cfg.proposals == ProposalMethod.MODEL:
        return ModelSegmenter(cfg.model_path)
    from skimage.segmentation import felzenszwalb, slic  # noqa: F401, PLC0415 - loaded now, not on the first keyframe (~2 s)
    return lambda image: segment_weight_free(image, cfg)

