"""LPIPS (Zhang et al. 2018, v0.1) in pure torch, loading ONE local weights file (never downloads).

The network is the official ``lpips.LPIPS(net='alex'|'vgg')`` re-implemented layer for layer
(torchvision is not needed): a scaling layer, the backbone's five ReLU stages, channel-wise unit
normalisation, squared differences, a learned non-negative 1x1 convolution per stage, spatial mean,
sum over stages. Images are float RGB in [0, 1] (mapped to [-1, 1] like ``normalize=True``).

Weights file: a ``torch.save``-d state dict holding BOTH the backbone and the linear layers, with the
official module names (see docs/evaluation.md for how to produce it)::

    net.slice1.0.weight / .bias ... (backbone convolutions, alex: slice1.0, slice2.3, slice3.6,
                                      slice4.8, slice5.10; vgg: slice1.{0,2}, slice2.{5,7},
                                      slice3.{10,12,14}, slice4.{17,19,21}, slice5.{24,26,28})
    lin0.model.1.weight ... lin4.model.1.weight   (1, C_k, 1, 1)
    scaling_layer.shift, scaling_layer.scale      (optional, (1, 3, 1, 1); official constants
                                                    otherwise)

Also accepted: ``lins.K.model.1.weight`` (the official ModuleList alias), ``linK.model.0.weight``
(lin layers without dropout) and torchvision's ``features.I.weight`` / ``features.I.bias`` naming of
the backbone, so ``{**torchvision_alexnet.state_dict(), **lpips_v0.1_alex_lin.pth}`` works too.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
import torch.nn as nn

from ..errors import InputError
from .image import _metric_pair

# (slice number, layer index in torchvision's `features`, in, out, kernel, stride, padding);
# ("pool", kernel, stride) entries are max-pools. Every conv is followed by a ReLU.
_ALEX = [
    [("conv", 0, 3, 64, 11, 4, 2)],
    [("pool", 3, 2), ("conv", 3, 64, 192, 5, 1, 2)],
    [("pool", 3, 2), ("conv", 6, 192, 384, 3, 1, 1)],
    [("conv", 8, 384, 256, 3, 1, 1)],
    [("conv", 10, 256, 256, 3, 1, 1)],
]
_VGG = [
    [("conv", 0, 3, 64, 3, 1, 1), ("conv", 2, 64, 64, 3, 1, 1)],
    [("pool", 2, 2), ("conv", 5, 64, 128, 3, 1, 1), ("conv", 7, 128, 128, 3, 1, 1)],
    [("pool", 2, 2), ("conv", 10, 128, 256, 3, 1, 1), ("conv", 12, 256, 256, 3, 1, 1),
     ("conv", 14, 256, 256, 3, 1, 1)],
    [("pool", 2, 2), ("conv", 17, 256, 512, 3, 1, 1), ("conv", 19, 512, 512, 3, 1, 1),
     ("conv", 21, 512, 512, 3, 1, 1)],
    [("pool", 2, 2), ("conv", 24, 512, 512, 3, 1, 1), ("conv", 26, 512, 512, 3, 1, 1),
     ("conv", 28, 512, 512, 3, 1, 1)],
]
_SPECS = {"alex": _ALEX, "vgg": _VGG}
# torchvision `features` index of the max-pool layers (to name them like the official slices)
_POOL_IDX = {"alex": {1: 2, 2: 5}, "vgg": {1: 4, 2: 9, 3: 16, 4: 23}}
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
MIN_SIZE = 32


class _Scaling(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.shift) / self.scale


class _Lin(nn.Module):
    def __init__(self, chn: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(chn, 1, 1, bias=False))
        nn.init.constant_(self.model[1].weight, 1.0 / chn)  # non-negative, like trained LPIPS


class LPIPS(nn.Module):
    """The LPIPS v0.1 network (``net`` = ``'alex'`` or ``'vgg'``), randomly initialised until
    :func:`load_lpips` fills it. ``forward(x0, x1)``: ``(B, 3, H, W)`` in [0, 1] -> ``(B,)``."""

    def __init__(self, net: str = "alex") -> None:
        super().__init__()
        if net not in _SPECS:
            raise InputError(f"LPIPS network must be 'alex' or 'vgg', got {net!r}")
        self.net_name = net
        self.scaling_layer = _Scaling()
        self.net = nn.Module()
        chns = []
        for k, stage in enumerate(_SPECS[net], 1):
            seq = nn.Sequential()
            for op in stage:
                if op[0] == "pool":
                    idx = _POOL_IDX[net][k - 1]
                    seq.add_module(str(idx), nn.MaxPool2d(op[1], op[2]))
                else:
                    _, idx, cin, cout, ks, st, pad = op
                    seq.add_module(str(idx), nn.Conv2d(cin, cout, ks, st, pad))
                    seq.add_module(str(idx + 1), nn.ReLU(inplace=False))
            setattr(self.net, f"slice{k}", seq)
            chns.append(stage[-1][3])
        self.chns = chns
        for k, c in enumerate(chns):
            setattr(self, f"lin{k}", _Lin(c))
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        h = self.scaling_layer(x)
        for k in range(1, 6):
            h = getattr(self.net, f"slice{k}")(h)
            out.append(h)
        return out

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        if x0.shape != x1.shape or x0.ndim != 4 or x0.shape[1] != 3:
            raise InputError(f"LPIPS needs two (B, 3, H, W) batches of equal shape, got "
                             f"{tuple(x0.shape)} and {tuple(x1.shape)}")
        if min(x0.shape[-2:]) < MIN_SIZE:
            raise InputError(f"LPIPS needs images of at least {MIN_SIZE}x{MIN_SIZE} px, got "
                             f"{x0.shape[-1]}x{x0.shape[-2]}")
        f0 = self.features(2 * x0 - 1)
        f1 = self.features(2 * x1 - 1)
        val = 0
        for k, (a, b) in enumerate(zip(f0, f1)):
            a = a / (torch.sqrt((a * a).sum(1, keepdim=True)) + 1e-10)
            b = b / (torch.sqrt((b * b).sum(1, keepdim=True)) + 1e-10)
            d = getattr(self, f"lin{k}").model((a - b) ** 2)
            val = val + d.mean(dim=(2, 3))
        return val[:, 0]

    @torch.no_grad()
    def distance(self, a: Union[np.ndarray, torch.Tensor], b: Union[np.ndarray, torch.Tensor]) -> float:
        """LPIPS between two ``(H, W, 3)`` (or mono ``(H, W)``) images in [0, 1] (uint8 accepted)."""
        # same checks as psnr/ssim: equal shapes, finite, in [0, 1] (0..255 floats are refused)
        ta, tb, _ = _metric_pair(a, b, None)
        if ta.shape[-1] == 1:
            ta, tb = ta.expand(-1, -1, 3), tb.expand(-1, -1, 3)
        dt = self.lin0.model[1].weight.dtype
        x0 = ta.permute(2, 0, 1)[None].to(dt)
        x1 = tb.permute(2, 0, 1)[None].to(dt)
        return float(self.forward(x0, x1)[0])


def _normalise_keys(sd: dict) -> dict:
    """Map accepted aliases onto the official names used by :class:`LPIPS`."""
    out = {}
    for k, v in sd.items():
        k = k[len("module."):] if k.startswith("module.") else k
        m = re.fullmatch(r"lins\.(\d)\.model\.(\d)\.weight", k)
        if m:
            k = f"lin{m.group(1)}.model.{m.group(2)}.weight"
        m = re.fullmatch(r"lin(\d)\.model\.0\.weight", k)
        if m:
            k = f"lin{m.group(1)}.model.1.weight"
        out.setdefault(k, v)
    return out


def _features_alias(sd: dict, model: LPIPS) -> dict:
    """torchvision ``features.I.*`` -> ``net.sliceK.I.*``."""
    where = {}
    for name, _ in model.net.named_parameters():
        sl, idx, what = name.split(".")
        where[f"features.{idx}.{what}"] = f"net.{sl}.{idx}.{what}"
    return {where.get(k, k): v for k, v in sd.items()}


def _detect_net(sd: dict) -> Optional[str]:
    if any(k.endswith("slice1.2.weight") for k in sd) or "features.2.weight" in sd or "features.28.weight" in sd:
        return "vgg"
    if any(k.endswith("slice1.0.weight") for k in sd) or "features.0.weight" in sd:
        w = sd.get("net.slice1.0.weight", sd.get("features.0.weight"))
        if w is not None and tuple(w.shape[-2:]) == (11, 11):
            return "alex"
        if w is not None and tuple(w.shape[-2:]) == (3, 3):
            return "vgg"
    return None


def load_lpips(path: Union[str, os.PathLike], net: Optional[str] = None) -> LPIPS:
    """Build :class:`LPIPS` from a local state-dict file (``net`` None: detected from the keys).

    Raises :class:`InputError` for a missing/unreadable file, a file that is not a state dict, or
    one lacking keys (listed) or with wrongly shaped tensors. Never downloads anything."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: LPIPS weights file not found (LPIPS needs a local weights file; "
                         "see docs/evaluation.md)")
    try:
        sd = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for corrupt files
        first = (str(e).strip().splitlines() or [""])[0]     # torch's message runs over many lines
        if "Weights only load failed" in first:   # its advice (weights_only=False) is not for us
            first = "not a torch.save archive of tensors"
        raise InputError(f"{path}: not a readable LPIPS weights file ({type(e).__name__}: {first})") from None
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise InputError(f"{path}: not a state dict of tensors")
    sd = _normalise_keys(sd)
    if net is None:
        net = _detect_net(sd)
        if net is None:
            raise InputError(f"{path}: no LPIPS backbone weights found (expected 'net.slice1.0.weight' "
                             "or 'features.0.weight')")
    model = LPIPS(net)
    sd = _features_alias(sd, model)
    expected = model.state_dict()
    missing = [k for k in expected if k not in sd and not k.startswith("scaling_layer.")]
    if missing:
        raise InputError(f"{path}: incomplete LPIPS-{net} weights, missing {len(missing)} key(s): "
                         f"{', '.join(missing[:6])}{' ...' if len(missing) > 6 else ''}")
    load = {}
    for k, ref in expected.items():
        if k not in sd:
            continue
        v = sd[k]
        if tuple(v.shape) != tuple(ref.shape):
            raise InputError(f"{path}: LPIPS weight {k} has shape {tuple(v.shape)}, expected "
                             f"{tuple(ref.shape)}")
        load[k] = v.to(ref.dtype)
    model.load_state_dict(load, strict=False)
    model.eval()
    return model
