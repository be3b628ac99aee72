"""Compile (or load from numba's on-disk cache) every kernel a SLAM run uses, before it is needed.

The numba kernels of the rasterizer and the mapper are ``cache=True``: the first call on a machine
compiles them (tens of seconds on two cores) and writes the result next to the sources; later
processes load it in well under a second. :func:`warm_kernels` runs a tiny mapping round (densify,
training with the sampled backward, score control, pose refinement, a render) on a synthetic
keyframe, so that happens at install time (``make install`` runs ``python -m vings_core.warmup``)
instead of stalling the first keyframe of the first run.
"""
from __future__ import annotations

import time

import numpy as np
import torch


def warm_kernels() -> float:
    """One small mapping round on a synthetic 64x48 keyframe pair; returns the seconds it took."""
    from .mapping import Mapper, MapperConfig
    from .types import CameraModel, Keyframe

    t0 = time.perf_counter()
    cam = CameraModel(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    g = torch.Generator().manual_seed(0)
    m = Mapper(MapperConfig(iters_per_keyframe=2, points_per_keyframe=500, refine_iters=1, window_size=2))
    try:
        for i in range(2):
            T = np.eye(4)
            T[0, 3] = 0.05 * i
            depth = 2.0 + 0.1 * torch.rand(cam.height, cam.width, generator=g)
            kf = Keyframe(stamp_ns=1_000_000_000 * (i + 1), image=torch.rand(cam.height, cam.width, 3, generator=g),
                          T_wc=torch.from_numpy(T), depth=depth, inv_depth_var=torch.zeros_like(depth),
                          valid=depth > 0, camera=cam, index=i)
            m.add_keyframe(kf)
            m.train(2)
            m.refine_poses()
        if m.num_gaussians == 0:
            raise RuntimeError("kernel warm-up mapped nothing: the training kernels were not exercised")
        m.render(np.eye(4), cam)
    finally:
        m.close()
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"vings: numba kernels compiled and cached in {warm_kernels():.1f} s")
