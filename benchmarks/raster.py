"""Benchmark of the CPU 2DGS rasterizer (vings_core.render) on a realistic room scene.

Scene: Gaussians back-projected from the simulator's exact depth of `room` views (several nearby
views along the trajectory when more Gaussians than pixels are needed), subsampled to N; colour
from the simulated image, normal from the depth map (surfels lie on the surfaces), scale = mean
distance to the 3 nearest neighbours (scipy cKDTree), opacity 0.8 -- as the map initialises.
Rendered at 376x240 from a viewpoint offset from the first view (5 cm, 2 deg). Loss: L1 to the
simulator's image of that viewpoint; the sampled backward (r = 0.5) keeps, per tile, the pixels of
highest L1 error (RenderOutput.set_sample_map).

Timings: warm-up first (numba compile excluded), median of --repeat runs, float32; the full and the
sampled backward steps alternate, so load from other jobs hits both alike. `fwd_ms` is the
whole forward (per-Gaussian set-up + kernels), `bwd_ms` the whole `loss.backward()` (kernels + chain
rule to means/quats/scales/opacities/colours), wall clock; `*_cpu_ms` are the process CPU times of the
same calls (summed over threads; on a machine shared with other jobs they show what the wall clock
would be without the contention). `bwd_raster_ms` / `bwd_raster_sampled_ms`: the
rasterizer's own part of the backward (pixel selection + tile kernel + per-Gaussian reduction),
i.e. what the paper's "sample rasterizer" ablation times. `pairs_per_s`: pixel-Gaussian alpha
evaluations of the forward per second of `fwd_ms`. `gaussians_per_pixel`: mean number of Gaussians composited
per pixel. The reference is the pure-torch renderer with per-tile culling (same output as dense),
timed on the same scene and loss: one warm-up run, then the median of 3.
`bwd_speedup_sampled` (wall), `bwd_speedup_sampled_cpu` (process CPU) and
`bwd_raster_speedup_sampled` (rasterizer share only) are full / sampled backward time ratios.
On a loaded machine run with NUMBA_NUM_THREADS=1 as well: the CPU-time ratio of one thread is far
less disturbed than the wall time of two threads that other jobs keep descheduling.

Usage: python benchmarks/raster.py [--repeat 7] [--sizes 10k,100k,300k] [--no-ref]
Per-size progress lines go to stderr; the last stdout line is one JSON object keyed by size, also
when a size fails (its entry is then ``{"error": ...}`` and the exit code 1).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np
import torch

from vings_core.geometry import np_pose, np_pose_inverse, np_rotmat_to_quat, np_so3_exp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _harness import run_experiments  # noqa: E402

SIZES = {"10k": 10_000, "100k": 100_000, "300k": 300_000}


def _normals_from_depth(depth: np.ndarray, cam) -> np.ndarray:
    """Camera-frame unit normals (H, W, 3) from central differences of the back-projected depth."""
    H, W = depth.shape
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    P = np.stack([(xs - cam.cx) / cam.fx * depth, (ys - cam.cy) / cam.fy * depth, depth], -1)
    dx = np.zeros_like(P)
    dy = np.zeros_like(P)
    dx[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dx[:, 0], dx[:, -1] = P[:, 1] - P[:, 0], P[:, -1] - P[:, -2]
    dy[1:-1] = P[2:] - P[:-2]
    dy[0], dy[-1] = P[1] - P[0], P[-1] - P[-2]
    n = np.cross(dx, dy)
    n /= np.linalg.norm(n, axis=-1, keepdims=True).clip(1e-12)
    return n


def _quat_from_normal(n: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """xyzw quaternions of rotations whose third column is ``n`` (random in-plane angle)."""
    a = np.where(np.abs(n[:, 0:1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    ang = rng.uniform(0, 2 * np.pi, len(n))[:, None]
    u = np.cos(ang) * t1 + np.sin(ang) * t2
    v = np.cross(n, u)
    R = np.stack([u, v, n], -1)
    return np_rotmat_to_quat(R)


def build_room_gaussians(n: int, seed: int = 0, width: int = 376, height: int = 240):
    """``n`` Gaussians from back-projected `room` views. Returns (dict of float32 tensors,
    camera, T_cw of the render viewpoint, target image float (H,W,3))."""
    from scipy.spatial import cKDTree

    from vings_core.sim import default_camera, make_scene, render_view
    rng = np.random.default_rng(seed)
    scene = make_scene("room", seed=0)
    cam = default_camera(width, height)
    n_views = int(np.ceil(n / (width * height * 0.9))) + (1 if n > width * height // 2 else 0)
    times = 0.6 + 0.12 * np.arange(n_views)
    pts, cols, nrms = [], [], []
    for T_wc in scene.T_wc(times):
        rgb, depth, _ = render_view(scene, cam, T_wc)
        nc = _normals_from_depth(depth.astype(np.float64), cam)
        ys, xs = np.nonzero(depth > 0)
        z = depth[ys, xs].astype(np.float64)
        Pc = np.stack([(xs - cam.cx) / cam.fx * z, (ys - cam.cy) / cam.fy * z, z], -1)
        pts.append(Pc @ T_wc[:3, :3].T + T_wc[:3, 3])
        nrms.append(nc[ys, xs] @ T_wc[:3, :3].T)
        cols.append(rgb[ys, xs].astype(np.float64) / 255.0)
    pts, cols, nrms = np.concatenate(pts), np.concatenate(cols), np.concatenate(nrms)
    idx = rng.choice(len(pts), size=n, replace=len(pts) < n)
    pts, cols, nrms = pts[idx], cols[idx], nrms[idx]
    if len(np.unique(idx)) < n:  # upsampled: jitter duplicates a little
        pts = pts + rng.normal(0, 2e-3, pts.shape)
    d, _ = cKDTree(pts).query(pts, k=4)
    scale = np.clip(d[:, 1:].mean(1), 1e-4, None)
    quats = _quat_from_normal(nrms, rng)
    T_wc0 = scene.T_wc(times[:1])[0]
    offset = np_pose(np_so3_exp(np.radians(2.0) * np.array([0.3, 0.9, 0.3])), [0.03, -0.02, 0.035])
    T_wc = T_wc0 @ offset
    target, _, _ = render_view(scene, cam, T_wc)
    f32 = torch.float32
    g = {"means": torch.tensor(pts, dtype=f32), "quats": torch.tensor(quats, dtype=f32),
         "scales": torch.tensor(np.stack([scale, scale], 1), dtype=f32),
         "opacities": torch.full((n,), 0.8, dtype=f32), "colors": torch.tensor(cols, dtype=f32)}
    return g, cam, np_pose_inverse(T_wc), torch.tensor(target / 255.0, dtype=f32)


def _time(fn, repeat: int) -> tuple:
    """(wall ms list, process-CPU ms list) of ``repeat`` calls."""
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return wall, cpu


def bench_size(name: str, n: int, repeat: int, with_ref: bool) -> dict:
    from vings_core.render import rasterize_2dgs, render_reference
    g, cam, T_cw, target = build_room_gaussians(n)
    leaves = {k: v.clone().requires_grad_(True) for k, v in g.items()}

    def fwd(ratio=1.0):
        return rasterize_2dgs(leaves["means"], leaves["quats"], leaves["scales"],
                              leaves["opacities"], leaves["colors"], T_cw, cam, sample_ratio=ratio)

    def step(ratio):
        out = fwd(ratio)
        err = (out.color - target).abs()
        if ratio < 1.0:
            out.set_sample_map(err.detach().sum(-1))
        loss = err.mean()
        for v in leaves.values():
            v.grad = None
        t0, c0 = time.perf_counter(), time.process_time()
        loss.backward()
        return (time.perf_counter() - t0) * 1e3, out, (time.process_time() - c0) * 1e3

    # warm-up: compiles (or loads cached) kernels for float32
    for _ in range(2):
        step(1.0)
        step(0.5)
    fwd_ms, fwd_cpu = _time(lambda: fwd(1.0), repeat)
    # full and sampled backward interleaved, so that load from other jobs hits both alike
    # only the figures of each step are kept: holding every render (its forward state is ~100 MB
    # at 300k) would make each backward fault in fresh memory, which a training loop does not
    bwd, bwd_s = [], []
    for k in range(repeat):
        for ratio, acc in ((1.0, bwd), (0.5, bwd_s)):
            wall, o, cpu = step(ratio)
            acc.append((wall, dict(o.stats), cpu))
            if ratio == 1.0 and k == repeat - 1:
                out = o     # the last full render, for the scene figures below
            del o
    stats = out.stats
    med = statistics.median
    res = {
        "fwd_ms": round(med(fwd_ms), 2),
        "bwd_ms": round(med([b[0] for b in bwd]), 2),
        "bwd_sampled_ms": round(med([b[0] for b in bwd_s]), 2),
        "pairs_per_s": round(stats["pairs_evaluated"] / (med(fwd_ms) / 1e3)),
        "gaussians_per_pixel": round(float(out.n_contrib.float().mean()), 3),
        "pairs_evaluated": stats["pairs_evaluated"],
        "visible": stats["visible"],
        "bwd_raster_ms": round(med([b[1]["bwd_raster_ms"] for b in bwd]), 2),
        "bwd_raster_sampled_ms": round(med([b[1]["bwd_raster_ms"] for b in bwd_s]), 2),
        "bwd_pairs_full": stats.get("bwd_pairs_evaluated"),
        "bwd_pairs_sampled": bwd_s[-1][1].get("bwd_pairs_evaluated"),
        "psnr_vs_sim_db": round(float(-10 * torch.log10(((out.color.detach() - target) ** 2).mean())), 2),
        # process CPU time (all threads): robust to other load on the machine
        "fwd_cpu_ms": round(med(fwd_cpu), 2),
        "bwd_cpu_ms": round(med([b[2] for b in bwd]), 2),
        "bwd_sampled_cpu_ms": round(med([b[2] for b in bwd_s]), 2),
    }
    if with_ref:
        def ref_fwd():
            return render_reference(leaves["means"], leaves["quats"], leaves["scales"],
                                    leaves["opacities"], leaves["colors"], torch.tensor(T_cw),
                                    cam, tile_cull=True)
        rf, rb = [], []
        for k in range(4):      # one warm-up, then the median of 3 (the fast path's statistic)
            t0 = time.perf_counter()
            r = ref_fwd()
            rf.append((time.perf_counter() - t0) * 1e3)
            loss = (r["color"] - target).abs().mean()
            for v in leaves.values():
                v.grad = None
            t0 = time.perf_counter()
            loss.backward()
            rb.append((time.perf_counter() - t0) * 1e3)
            del r, loss
        rf, rb = rf[1:], rb[1:]
        res["ref_fwd_ms"] = round(med(rf), 1)
        res["ref_bwd_ms"] = round(med(rb), 1)
        res["speedup_fwd_bwd_vs_ref"] = round((med(rf) + med(rb)) / (res["fwd_ms"] + res["bwd_ms"]), 1)
    res["bwd_speedup_sampled"] = round(res["bwd_ms"] / res["bwd_sampled_ms"], 2)
    res["bwd_speedup_sampled_cpu"] = round(res["bwd_cpu_ms"] / res["bwd_sampled_cpu_ms"], 2)
    res["bwd_raster_speedup_sampled"] = round(res["bwd_raster_ms"] / res["bwd_raster_sampled_ms"], 2)
    res["loadavg_1m"] = round(os.getloadavg()[0], 2)
    res["threads"] = __import__("numba").get_num_threads()
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--sizes", default="10k,100k,300k")
    ap.add_argument("--no-ref", action="store_true", help="skip the pure-torch reference at 10k")
    args = ap.parse_args(argv)
    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    bad = [s for s in sizes if s not in SIZES]
    if bad or not sizes:
        ap.error(f"--sizes: unknown size(s) {bad or args.sizes!r}; choose from {', '.join(SIZES)}")
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    torch.set_grad_enabled(True)
    results: dict = {}

    def one(name: str) -> dict:
        r = bench_size(name, SIZES[name], args.repeat, with_ref=(name == "10k" and not args.no_ref))
        print(f"{name}: {json.dumps(r)}", file=sys.stderr, flush=True)
        return r
    return run_experiments([(name, lambda name=name: one(name)) for name in sizes], results)


if __name__ == "__main__":
    sys.exit(main())
