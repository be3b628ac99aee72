"""Mapping benchmark: quality, score manager, pose refinement, storage tiers, speed.

Synthetic scenes come from ``vings_core.sim`` (the scenes ``vings sim`` writes), rendered in memory
with ground-truth poses and depth; keyframes are every ``--kf-every``-th frame and get
``inv_depth_var = 0`` (certain depth).

Experiments (``--exp``, comma separated; default all):

* ``room``: room, >= 200 frames at 376x240, GT poses + depth: PSNR/SSIM on keyframes and on novel
  (non-keyframe) views, Gaussian count, mapping time per keyframe.
* ``frontend``: the full SLAM as ``vings run --sync`` (front end + mapper + pose exchange) on a
  generated room (>= 200 frames): ATE, PSNR on keyframes and novel views from its metrics.json.
* ``score``: score-manager ablation (manager off, several ``sc_storage`` with the per-view rule, the
  window sum rule ``*_sum``, and the paper's storage
  rule on every Gaussian, ``*_all``): Gaussian count and PSNR.
* ``pose``: pose-refinement ablation from GT + injected noise (2 cm, 1 deg on every keyframe but the
  first, which fixes the gauge): keyframe ATE with no refinement / rendered pose only / all visible
  keyframes (single-to-multi).
* ``pose_frontend``: the same ablation starting from the front end's final keyframe poses and its
  depth (ATE after Sim(3) alignment: the front end's world frame and scale are its own); on the
  generated room, or on any recording with ground truth given by ``--pose-source`` (e.g.
  ``../shared/data/kitti07_160``, at the working size ``vings run`` picks, mapped as outdoors
  when ``--pose-outdoor``). Each refined mode also reports ``blend``: the errors of poses that keep
  a fraction (0.25, 0.5, 0.75) of its correction to the front end's poses, which shows whether a
  weighting of the two estimates would beat the front end alone.
* ``score_frontend`` (not in the default list): the score-manager ablation on the front end's
  keyframes (poses and depth) of the room or of ``--pose-source`` (e.g. real KITTI images):
  Gaussian count and keyframe PSNR with the manager off and at each ``--sc-storage``.
* ``storage``: street --loop drive (>= 300 m), few iterations per keyframe: active set vs cap, total
  count, passive store spill, peak RSS of the experiment, PSNR of the start region at first visit,
  on the return (the first keyframe back within ``tau``: rendered right after the tiers reload the
  region, before any training there, so it measures the round trip through the passive store) and
  at the end of the loop (after retraining).
* ``timing``: mapping time per keyframe at 376x240 with 50 iterations, split in add/train.

PSNR figures are the mean of per-view PSNR (dB) over [0, 1] images, all pixels and channels
(``*_surface_db``: only pixels with a surface). Timings per keyframe are add + train (pose refinement,
when it runs, is reported apart).

Prints progress to stderr and ONE JSON object (keyed by experiment) as the last stdout line, also
when an experiment fails (its entry is then ``{"error": ...}``, listed in ``failed``, exit code 1).
``--quick`` shrinks everything for development (numbers are then not the reported ones).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import replace

import numpy as np
import torch

from vings_core.eval.image import psnr, ssim
from vings_core.eval.output import peak_rss_mb  # since start or the last reset_peak_rss()
from vings_core.geometry import np_se3_exp, np_se3_log, rotation_angle_deg
from vings_core.mapping import Mapper, MapperConfig
from vings_core.types import Keyframe

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _harness import run_experiments  # noqa: E402

FPS = 20.0
T0_NS = 1_700_000_000_000_000_000


def log(*a) -> None:
    print("[bench mapping]", *a, file=sys.stderr, flush=True)


_EARLIER_PEAK_MB = 0.0      # the process's peak before the last reset


def process_peak_rss_mb() -> float:
    """Peak RSS (MB) of the whole process, across :func:`reset_peak_rss` calls."""
    return max(_EARLIER_PEAK_MB, peak_rss_mb())


def reset_peak_rss() -> bool:
    """Restart the peak-RSS count (Linux ``clear_refs`` 5), so one experiment's peak is not an
    earlier experiment's; False where the system does not allow it (the peak is then the process's)."""
    global _EARLIER_PEAK_MB
    _EARLIER_PEAK_MB = process_peak_rss_mb()
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


# ------------------------------------------------------------------------------------ data


class SimSequence:
    """Frames of a simulator scene rendered on demand (cached), with GT camera poses and depth."""

    def __init__(self, scene_name: str, frames: int | None, width: int, height: int, seed: int = 0,
                 loop: bool = False, length_m: float | None = None, cache: bool = True):
        self.cache = cache
        from vings_core import sim
        self.sim = sim
        self.scene = sim.build_scene(scene_name, seed=seed, loop=loop, length_m=length_m, fps=FPS)
        self.cam = sim.default_camera(width, height)
        if frames is None:
            frames = int(math.floor(self.scene.motion.duration * FPS)) + 1
        self.n = int(frames)
        self.t = np.arange(self.n) / FPS
        self.T_wc = self.scene.T_wc(self.t)
        self.stamps = T0_NS + np.round(self.t * 1e9).astype(np.int64)
        self._cache: dict[int, tuple] = {}

    def view(self, i: int, keep: bool = False):
        if i in self._cache:
            return self._cache[i]
        rgb, depth, _ = self.sim.render_view(self.scene, self.cam, self.T_wc[i], t=float(self.t[i]))
        if self.cache or keep:
            self._cache[i] = (rgb, depth)
        return rgb, depth

    def keyframe(self, i: int, T_wc: np.ndarray | None = None) -> Keyframe:
        rgb, depth = self.view(i)
        d = torch.from_numpy(depth)
        return Keyframe(stamp_ns=int(self.stamps[i]), image=torch.from_numpy(rgb.astype(np.float32) / 255.0),
                        T_wc=torch.from_numpy(self.T_wc[i] if T_wc is None else T_wc), depth=d,
                        inv_depth_var=torch.zeros_like(d), valid=d > 0, camera=self.cam, index=i)

    def path_length(self, n: int | None = None) -> float:
        """Length (m) of the camera path over the first ``n`` frames (all by default)."""
        p = self.T_wc[: self.n if n is None else n, :3, 3]
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def eval_views(m: Mapper, seq: SimSequence, idx) -> dict:
    """Mean PSNR / SSIM of renders at the GT poses of frames ``idx``; ``psnr_surface_db`` only over
    pixels with a surface (GT depth > 0: the sky is not mapped)."""
    ps, ss, pm = [], [], []
    for i in idx:
        r = m.render(seq.T_wc[i], seq.cam)
        gt, depth = seq.view(i)
        g = gt.astype(np.float32) / 255.0
        ps.append(psnr(r["color"], g))
        ss.append(ssim(r["color"], g))
        pm.append(psnr(r["color"], g, mask=depth > 0))
    # mean of the per-view PSNR in dB (as the paper's tables); a perfect view (inf) or none at all
    # gives null, not a non-JSON Infinity/NaN
    return {"psnr_db": _finite_mean(ps), "ssim": _finite_mean(ss), "psnr_surface_db": _finite_mean(pm),
            "views": len(ps)}


def _finite_mean(v) -> float | None:
    m = float(np.mean(v)) if len(v) else float("nan")
    return m if math.isfinite(m) else None


def run_mapping(seq: SimSequence | None, cfg: MapperConfig, kf_idx, poses: dict | None = None,
                refine: bool = False, tag: str = "", keyframes: list | None = None) -> tuple[Mapper, dict]:
    """Map keyframes ``kf_idx`` of ``seq`` (``poses`` optionally overrides their poses: noisy runs),
    or the given ``keyframes`` (front-end keyframes; ``seq`` and ``kf_idx`` unused)."""
    m = Mapper(cfg)
    add_t, train_t, refine_t = [], [], []
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    if keyframes is not None:
        kf_idx = list(range(len(keyframes)))
    for n, i in enumerate(kf_idx):
        if keyframes is not None:
            kf = keyframes[i]
        else:
            kf = seq.keyframe(i, None if poses is None else poses[i])
        t0 = time.perf_counter()
        m.add_keyframe(kf)
        t1 = time.perf_counter()
        st = m.train()
        t2 = time.perf_counter()
        if refine:
            m.refine_poses()
        t3 = time.perf_counter()
        add_t.append(t1 - t0)
        train_t.append(t2 - t1)
        refine_t.append(t3 - t2)
        if n % 10 == 0 or n == len(kf_idx) - 1:
            log(f"{tag} kf {n + 1}/{len(kf_idx)} frame {i}: active {m.num_active} passive {m.num_passive} "
                f"psnr(train) {st['psnr']:.2f} add {t1 - t0:.2f}s train {t2 - t1:.2f}s refine {t3 - t2:.2f}s")
    stats = {"keyframes": len(kf_idx), "wall_s": time.perf_counter() - t_start,
             "cpu_s": time.process_time() - cpu_start,
             "cpu_per_kf_s": (time.process_time() - cpu_start) / max(1, len(kf_idx)),
             "load_avg_1m_end": os.getloadavg()[0],
             # add + train; the simulator's rendering of the keyframe is outside, and so is pose
             # refinement (reported apart, only when it ran); the first keyframe includes loading the
             # compiled kernels, hence the median beside the mean
             "time_per_kf_s": float(np.mean(np.array(add_t) + np.array(train_t))),
             "time_per_kf_median_s": float(np.median(np.array(add_t) + np.array(train_t))),
             "time_scope": "add_keyframe + train per keyframe (excludes pose refinement and data generation)",
             "add_per_kf_s": float(np.mean(add_t)), "train_per_kf_s": float(np.mean(train_t)),
             "num_gaussians": m.num_gaussians, "counters": dict(m.counters)}
    if refine:
        stats["refine_per_kf_s"] = float(np.mean(refine_t))
    return m, stats


def split_views(n: int, kf_every: int, max_novel: int):
    """Keyframes every ``kf_every``-th frame and novel views half-way between them (never a
    keyframe: ``kf_every >= 2``), at most ``max_novel`` of them."""
    if kf_every < 2:
        raise ValueError(f"kf_every must be >= 2 (novel views lie between keyframes), got {kf_every}")
    kf = list(range(0, n, kf_every))
    novel = [i for i in range(n) if i % kf_every == kf_every // 2]
    if len(novel) > max_novel:
        novel = novel[:: int(math.ceil(len(novel) / max_novel))]
    assert not set(kf) & set(novel)
    return kf, novel


# ------------------------------------------------------------------------------------ experiments


def exp_room(a, cfg: MapperConfig) -> tuple[dict, Mapper, SimSequence]:
    seq = SimSequence("room", a.room_frames, a.width, a.height)
    kf, novel = split_views(seq.n, a.kf_every, a.max_novel)
    log(f"room: {seq.n} frames, {len(kf)} keyframes, {len(novel)} novel views, {seq.path_length():.1f} m")
    m, st = run_mapping(seq, cfg, kf, tag="room")
    ek = eval_views(m, seq, kf)
    en = eval_views(m, seq, novel)
    out = {"frames": seq.n, "resolution": [a.width, a.height], "iters_per_keyframe": cfg.iters_per_keyframe,
           "psnr_keyframes_db": ek["psnr_db"], "ssim_keyframes": ek["ssim"],
           "psnr_novel_db": en["psnr_db"], "ssim_novel": en["ssim"], "novel_views": en["views"], **st}
    log("room:", json.dumps({k: v for k, v in out.items() if k != "counters"}))
    return out, m, seq


def _relative_to_off(res: dict) -> None:
    """In place: each variant's Gaussian reduction (%) and keyframe PSNR loss (dB) against "off"."""
    off = res["off"]
    for name, r in res.items():
        if name != "off":
            r["reduction_pct"] = 100.0 * (1 - r["num_gaussians"] / max(1, off["num_gaussians"]))
            r["psnr_loss_db"] = off["psnr_keyframes_db"] - r["psnr_keyframes_db"]


def exp_score(a, cfg: MapperConfig, base: dict | None) -> dict:
    seq = SimSequence(a.score_scene, a.score_frames, a.width, a.height, seed=a.score_seed)
    kf, novel = split_views(seq.n, a.kf_every, a.max_novel)
    res = {}
    variants = [("off", replace(cfg, score_manager=False))]
    variants += [(f"{v:g}", replace(cfg, score_manager=True, sc_storage=v, sc_storage_per_view=True,
                                    prune_window_owned_only=True)) for v in a.sc_storage]
    # S_C summed over the window (paper) instead of per viewing keyframe
    variants += [(f"{v:g}_sum", replace(cfg, score_manager=True, sc_storage=v, sc_storage_per_view=False,
                                        prune_window_owned_only=True))
                 for v in a.sc_storage_sum]
    # the paper's storage rule on every Gaussian (not only those whose ID(g) is a window keyframe)
    variants += [(f"{v:g}_all", replace(cfg, score_manager=True, sc_storage=v, prune_window_owned_only=False,
                                        sc_storage_per_view=False))
                 for v in a.sc_storage_all]
    # the per-view rule sparing the Gaussians where the render is still wrong
    variants += [(f"{v:g}_spare", replace(cfg, score_manager=True, sc_storage=v, sc_storage_per_view=True,
                                          prune_window_owned_only=True, prune_spare_high_error=True))
                 for v in a.sc_storage_spare]
    for name, c in variants:
        m, st = run_mapping(seq, c, kf, tag=f"score[{name}]")
        ek = eval_views(m, seq, kf)
        en = eval_views(m, seq, novel)
        res[name] = {"num_gaussians": m.num_gaussians, "psnr_keyframes_db": ek["psnr_db"],
                     # pixels with a surface only (the street's sky is not mapped and would dilute
                     # a difference of the map into its own large error)
                     "psnr_keyframes_surface_db": ek["psnr_surface_db"],
                     "psnr_novel_db": en["psnr_db"], "pruned": m.counters["pruned"],
                     "stable": int(m.gm.stable.sum()), "time_per_kf_s": st["time_per_kf_s"]}
        log(f"score[{name}]:", res[name])
        m.close()
    off = res["off"]
    _relative_to_off(res)
    for name, r in res.items():
        if name != "off":
            if off["psnr_keyframes_surface_db"] is not None and r["psnr_keyframes_surface_db"] is not None:
                r["psnr_surface_loss_db"] = off["psnr_keyframes_surface_db"] - r["psnr_keyframes_surface_db"]
    return {"scene": a.score_scene, "seed": a.score_seed, "frames": seq.n, "keyframes": len(kf), "variants": res}


def exp_score_frontend(a, cfg: MapperConfig) -> dict:
    """Score-manager ablation on the front end's keyframes (poses and depth), e.g. of a real
    recording given by ``--pose-source``: Gaussian count and keyframe PSNR with the manager off and
    at the ``--sc-storage`` values (per-view rule, the default)."""
    kfs, _ = _frontend_keyframes(a, a.pose_frames)
    if a.pose_outdoor:
        cfg = replace(cfg, outdoor=True)
    cam = kfs[0].camera
    res = {}
    variants = [("off", replace(cfg, score_manager=False))]
    variants += [(f"{v:g}", replace(cfg, score_manager=True, sc_storage=v)) for v in a.sc_storage]
    for name, c in variants:
        m, st = run_mapping(None, c, None, tag=f"score_fe[{name}]",
                            keyframes=[replace(k, T_wc=k.T_wc.clone()) for k in kfs])
        poses = m.keyframe_poses()
        ps = [psnr(m.render(poses[k.stamp_ns], cam)["color"], k.image.numpy()) for k in kfs]
        res[name] = {"num_gaussians": m.num_gaussians, "psnr_keyframes_db": float(np.mean(ps)),
                     "pruned": m.counters["pruned"], "stable": int(m.gm.stable.sum()),
                     "time_per_kf_s": st["time_per_kf_s"]}
        log(f"score_fe[{name}]:", res[name])
        m.close()
    _relative_to_off(res)
    return {"source": a.pose_source or "room", "frames": a.pose_frames, "keyframes": len(kfs),
            "width": cam.width, "height": cam.height, "variants": res}


def _noisy_poses(seq: SimSequence, kf_idx, trans_m: float, rot_deg: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    out = {}
    for n, i in enumerate(kf_idx):
        if n == 0:
            out[i] = seq.T_wc[i].copy()        # the first keyframe defines the world (gauge)
            continue
        d = rng.normal(size=3)
        w = rng.normal(size=3)
        xi = np.concatenate([d / np.linalg.norm(d) * trans_m, w / np.linalg.norm(w) * math.radians(rot_deg)])
        # perturb the camera centre by trans_m and the orientation by rot_deg (about the camera)
        T = seq.T_wc[i].copy()
        R = np_se3_exp(np.concatenate([np.zeros(3), xi[3:]]))[:3, :3]
        T[:3, :3] = T[:3, :3] @ R
        T[:3, 3] = T[:3, 3] + xi[:3]
        out[i] = T
    return out


def _kf_errors(m: Mapper, seq: SimSequence, kf_idx) -> dict:
    poses = m.keyframe_poses()
    et, er = [], []
    for i in kf_idx:
        T = poses[int(seq.stamps[i])]
        G = seq.T_wc[i]
        et.append(np.linalg.norm(T[:3, 3] - G[:3, 3]))
        er.append(float(rotation_angle_deg(T[:3, :3].T @ G[:3, :3])))
    et, er = np.array(et[1:]), np.array(er[1:])
    est = np.stack([poses[int(seq.stamps[i])] for i in kf_idx])
    gt = np.stack([seq.T_wc[i] for i in kf_idx])
    from vings_core.eval.align import umeyama
    _, R, t = umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=False)
    al = est[:, :3, 3] @ R.T + t
    ate_se3 = float(np.sqrt((np.linalg.norm(al - gt[:, :3, 3], axis=1) ** 2).mean()))
    # relative pose error between consecutive keyframes (translation, m)
    rel_e = [np.linalg.inv(est[k]) @ est[k + 1] for k in range(len(est) - 1)]
    rel_g = [np.linalg.inv(gt[k]) @ gt[k + 1] for k in range(len(gt) - 1)]
    rpe = np.array([np.linalg.norm((np.linalg.inv(g) @ e)[:3, 3]) for e, g in zip(rel_e, rel_g)])
    return {"ate_rmse_m": float(np.sqrt((et ** 2).mean())), "rot_rmse_deg": float(np.sqrt((er ** 2).mean())),
            "ate_max_m": float(et.max()), "ate_se3_aligned_m": ate_se3,
            "rpe_consecutive_rmse_m": float(np.sqrt((rpe ** 2).mean()))}


def exp_pose(a, cfg: MapperConfig) -> dict:
    seq = SimSequence("room", a.pose_frames, a.width, a.height)
    kf, novel = split_views(seq.n, a.kf_every, a.max_novel)
    noisy = _noisy_poses(seq, kf, a.noise_trans, a.noise_rot, seed=1)
    res = {}
    for mode in a.pose_modes:
        c = replace(cfg, refine_mode=mode)
        m, st = run_mapping(seq, c, kf, poses=noisy, refine=mode != "none", tag=f"pose[{mode}]")
        if mode == "none":
            res["initial"] = _kf_errors(m, seq, kf)
        err = _kf_errors(m, seq, kf)
        ek = eval_views(m, seq, kf)
        res[mode] = {**err, "psnr_keyframes_db": ek["psnr_db"], "refine_per_kf_s": st.get("refine_per_kf_s", 0.0)}
        log(f"pose[{mode}]:", res[mode])
        m.close()
    return {"frames": seq.n, "keyframes": len(kf), "noise": {"trans_m": a.noise_trans, "rot_deg": a.noise_rot},
            "refine_iters_per_keyframe": cfg.refine_iters, "refine_solver": cfg.refine_solver,
            "refine_gn_decay": cfg.refine_gn_decay, "results": res,
            **_multi_beats(res, "ate_rmse_m")}


# ------------------------------------------------------------------ front-end poses and depth


def _room_dir(a, frames: int):
    """A synthetic room written by ``vings_core.sim.generate`` (the files ``vings sim`` writes), cached
    in ``--workdir``."""
    from pathlib import Path
    from vings_core.sim import generate
    out = Path(a.workdir) / f"room_{frames}_{a.width}x{a.height}"
    if not (out / "sim.json").is_file():
        if out.exists():
            import shutil
            shutil.rmtree(out)
        log(f"generating {out}")
        generate("room", out, frames=frames, width=a.width, height=a.height, mcap=False)
    return out


def _open(a, path):
    from vings_core.io import SourceOptions, open_source
    return open_source(path, SourceOptions(width=a.width, height=a.height))


def exp_frontend(a, cfg: MapperConfig) -> dict:
    """The full SLAM (``vings run --sync``: front end + mapper + pose exchange both ways) on a room
    of >= 200 frames; figures from the runner's metrics.json (the mapper uses the benchmark config)."""
    import tempfile
    from vings_core.pipeline import RunConfig, SlamRunner
    src_dir = _room_dir(a, a.frontend_frames)
    out_dir = tempfile.mkdtemp(prefix="vings_bench_frontend_run_")
    from vings_core.config import load_section
    run_cfg = replace(load_section(RunConfig, "run", a.params), sync=True, width=a.width, height=a.height)
    runner = SlamRunner(_open(a, src_dir), out_dir, params_file=a.params, run_cfg=run_cfg, progress=False)
    runner.mapper.close()
    runner.mapper = Mapper(cfg)
    t0 = time.perf_counter()
    metrics = runner.run()
    wall = time.perf_counter() - t0
    tm = runner.mapper.timings
    nk = max(1, metrics.get("keyframes") or 1)
    res = {"source": str(src_dir), "out_dir": out_dir, "command_equivalent":
           f"vings run {src_dir} --out OUT --sync", "iters_per_keyframe": cfg.iters_per_keyframe,
           "refine_mode": cfg.refine_mode,
           **{k: metrics.get(k) for k in ("frames", "frames_tracked", "keyframes", "ate_sim3_m", "ate_se3_m",
                                           "sim3_scale", "psnr_keyframes_db", "ssim_keyframes", "psnr_novel_db",
                                           "fps", "num_gaussians", "peak_rss_mb")},
           "wall_s": wall, "map_add_per_kf_s": tm["add_s"] / nk, "map_train_per_kf_s": tm["train_s"] / nk,
           "map_refine_per_kf_s": tm["refine_s"] / nk, "counters": dict(runner.mapper.counters)}
    runner.mapper.close()
    null = [k for k in ("ate_sim3_m", "psnr_keyframes_db", "psnr_novel_db") if res[k] is None]
    if null or not res["keyframes"]:
        res["incomplete"] = f"{res['keyframes']} keyframes, null figures: {', '.join(null) or '-'}"
    log("frontend:", json.dumps(res))
    return res


def _frontend_keyframes(a, frames: int) -> tuple[list, dict]:
    """Run the front end alone over the first ``frames`` frames of the room; returns its keyframes
    (its dense depth and inverse-depth variance) carrying the front end's final keyframe poses, and
    the ground-truth ``T_wc`` per keyframe stamp."""
    from vings_core.eval.traj import interpolate_poses
    from vings_core.frontend import Frontend, FrontendConfig
    from vings_core.config import load_section
    if a.pose_source:
        from vings_core.io import SourceOptions
        from vings_core.pipeline import open_working_source
        src = open_working_source(a.pose_source, SourceOptions())
        if src.gt_camera_trajectory() is None:
            raise ValueError(f"--pose-source {a.pose_source}: the recording has no ground-truth poses")
    else:
        src = _open(a, _room_dir(a, max(frames, a.frontend_frames)))
    fe = Frontend(load_section(FrontendConfig, "frontend", a.params), src.calibration.camera)
    kfs = []
    for n, frame in enumerate(src.frames()):
        if n >= frames:
            break
        fe.process(frame)
        kfs.extend(fe.pop_keyframes())
    kfs.extend(fe.finish())
    traj = fe.keyframe_trajectory()
    final = dict(zip(traj.stamps_ns.tolist(), traj.poses))
    kfs = [replace(k, T_wc=torch.from_numpy(np.array(final.get(k.stamp_ns, k.T_wc.numpy())))) for k in kfs]
    kfs.sort(key=lambda k: k.stamp_ns)
    st = np.array([k.stamp_ns for k in kfs], np.int64)
    gt = dict(zip(st.tolist(), interpolate_poses(src.gt_camera_trajectory(), st)))
    log(f"front end: {frames} frames -> {len(kfs)} keyframes")
    return kfs, gt


def _errors_vs_gt(est: dict, gt: dict) -> dict:
    """Keyframe pose errors after Sim(3) alignment (front-end world frame and scale differ from the
    ground truth's)."""
    from vings_core.eval.align import umeyama
    st = sorted(gt)
    E = np.stack([est[s] for s in st])
    G = np.stack([gt[s] for s in st])
    sc, R, t = umeyama(E[:, :3, 3], G[:, :3, 3], with_scale=True)
    p = sc * E[:, :3, 3] @ R.T + t
    e = np.linalg.norm(p - G[:, :3, 3], axis=1)
    rot = [float(rotation_angle_deg((R @ E[k, :3, :3]).T @ G[k, :3, :3])) for k in range(len(st))]
    return {"ate_sim3_m": float(np.sqrt((e ** 2).mean())), "ate_max_m": float(e.max()),
            "rot_rmse_deg": float(np.sqrt(np.mean(np.square(rot)))), "sim3_scale": float(sc)}


def exp_pose_frontend(a, cfg: MapperConfig) -> dict:
    """Pose-refinement ablation starting from the front end's keyframe poses and depth."""
    kfs, gt = _frontend_keyframes(a, a.pose_frames)
    if a.pose_outdoor:
        cfg = replace(cfg, outdoor=True)
    start = {k.stamp_ns: k.T_wc.numpy().copy() for k in kfs}
    res = {"initial": _errors_vs_gt(start, gt)}
    for mode in a.pose_modes:
        c = replace(cfg, refine_mode=mode)
        m, st = run_mapping(None, c, None, refine=mode != "none", tag=f"pose_fe[{mode}]",
                            keyframes=[replace(k, T_wc=k.T_wc.clone()) for k in kfs])
        r = _errors_vs_gt(m.keyframe_poses(), gt)
        cam = kfs[0].camera
        ps = [psnr(m.render(m.keyframe_poses()[k.stamp_ns], cam)["color"], k.image.numpy()) for k in kfs]
        res[mode] = {**r, "psnr_keyframes_db": float(np.mean(ps)), "refine_per_kf_s": st.get("refine_per_kf_s", 0.0)}
        if mode != "none":
            # the front end's poses blended with the refined ones: does any weighting help?
            res[mode]["blend"] = _blend_errors(start, m.keyframe_poses(), gt)
        log(f"pose_fe[{mode}]:", res[mode])
        m.close()
    return {"source": a.pose_source or "room", "frames": a.pose_frames, "keyframes": len(kfs),
            "width": kfs[0].camera.width, "height": kfs[0].camera.height, "refine_solver": cfg.refine_solver,
            "refine_gn_decay": cfg.refine_gn_decay,
            "results": res, **_multi_beats(res, "ate_sim3_m")}


#: fractions of the refinement's correction kept by :func:`_blend_errors`
BLEND_FRACTIONS = (0.25, 0.5, 0.75)


def _blend_errors(start: dict, refined: dict, gt: dict) -> dict:
    """Errors of poses part-way between the start and the refined ``T_wc`` of every keyframe:
    ``T_start exp(f log(T_start^-1 T_refined))`` for ``f`` in :data:`BLEND_FRACTIONS` (a fusion
    that trusts the refinement by ``f`` in every direction; if no ``f`` beats ``f = 0``, no such
    uniform weighting of the two estimates would). ``{f: {ate_sim3_m, rot_rmse_deg}}``."""
    out = {}
    for f in BLEND_FRACTIONS:
        est = {s: start[s] @ np_se3_exp(f * np_se3_log(np.linalg.inv(start[s]) @ refined[s])) for s in start}
        e = _errors_vs_gt(est, gt)
        out[str(f)] = {"ate_sim3_m": e["ate_sim3_m"], "rot_rmse_deg": e["rot_rmse_deg"]}
    return out


def _multi_beats(res: dict, key: str) -> dict:
    """``multi_beats_single`` / ``multi_beats_none`` for the modes that ran."""
    return {f"multi_beats_{o}": res["multi"][key] < res[o][key]
            for o in ("single", "none") if "multi" in res and o in res}


def exp_storage(a, cfg: MapperConfig) -> dict:
    seq = SimSequence("street", None, a.width, a.height, loop=True, length_m=a.street_length, cache=False)
    n = seq.n if a.street_frames is None else min(seq.n, a.street_frames)
    kf = list(range(0, n, a.street_kf_every))
    L = seq.path_length(n)             # the route actually mapped (--street-frames may cut the loop)
    start = seq.T_wc[0, :3, 3]
    loop_closed = bool(np.linalg.norm(seq.T_wc[n - 1, :3, 3] - start) < 0.05 * max(L, 1e-9))
    rss_reset = reset_peak_rss()
    log(f"storage: street loop {L:.0f} m mapped ({seq.path_length():.0f} m route), {n} of {seq.n} frames, "
        f"{len(kf)} keyframes, loop closed: {loop_closed}")
    c = replace(cfg, iters_per_keyframe=a.street_iters, outdoor=True, max_active=a.max_active, tau=a.tau,
                delta_k=a.delta_k, passive_memory_mb=a.passive_mb, points_per_keyframe=a.street_points)
    m = Mapper(c)
    start_views = [i for i in range(0, min(n, 6 * a.street_kf_every)) if i % a.street_kf_every == a.street_kf_every // 2]
    for i in start_views:
        seq.view(i, keep=True)
    first_visit = None
    on_return = None
    left = False
    trace = []
    t0 = time.perf_counter()
    for k, i in enumerate(kf):
        d_start = float(np.linalg.norm(seq.T_wc[i, :3, 3] - start))
        left = left or d_start > 2 * c.tau
        if left and on_return is None and d_start < c.tau:
            # first keyframe back within tau of the start: the tiers bring the start region back
            # from the passive store; its views are rendered BEFORE any training on the return, so
            # the figure is the round trip's (active -> passive -> spilled -> reloaded), not a rebuild
            tin = m.update_tiers(seq.T_wc[i])
            on_return = {**eval_views(m, seq, start_views), "kf": k, "frame": i,
                         "distance_to_start_m": d_start, "tier_in": tin["tier_in"]}
            log("storage: start region on the return, before retraining:", on_return)
        m.add_keyframe(seq.keyframe(i))
        m.train()
        trace.append({"kf": k, "frame": i, "active": m.num_active, "passive": m.num_passive,
                      "total": m.num_gaussians, "passive_mem_mb": m.passive.memory_bytes / 2**20,
                      "passive_disk_mb": m.passive.disk_bytes / 2**20})
        if k == 10 and first_visit is None:
            first_visit = eval_views(m, seq, start_views)
            log("storage: first visit of the start region:", first_visit)
        if k % 10 == 0:
            log(f"storage kf {k + 1}/{len(kf)}: {trace[-1]}")
    # the end of the loop (after retraining on the return)
    m.update_tiers(seq.T_wc[n - 1])
    back = eval_views(m, seq, start_views)
    log("storage: after the loop:", back)

    def drop(first, later, key):
        return (first[key] - later[key]) if first and later and first[key] is not None \
            and later[key] is not None else None
    act = np.array([t["active"] for t in trace])
    tot = np.array([t["total"] for t in trace])
    res = {"route_m": L, "loop_closed": loop_closed, "frames": n, "keyframes": len(kf),
           "iters_per_keyframe": c.iters_per_keyframe,
           "max_active": c.max_active, "tau_m": c.tau, "active_max": int(act.max()),
           "active_under_cap": bool((act <= c.max_active).all()), "total_final": int(tot[-1]),
           "total_max": int(tot.max()), "total_exceeds_active_max": bool(tot[-1] > act.max()),
           "passive_final": m.num_passive, "spilled_chunks_written": m.passive.spilled_total,
           "chunks_loaded_from_disk": m.passive.loaded_total,
           "passive_disk_mb_max": float(max(t["passive_disk_mb"] for t in trace)),
           "passive_memory_budget_mb": c.passive_memory_mb, "peak_rss_mb": peak_rss_mb(),
           "peak_rss_scope": "this experiment" if rss_reset else "whole process (run --exp storage alone)",
           "first_visit_psnr_db": first_visit["psnr_db"] if first_visit else None,
           "first_visit_psnr_surface_db": first_visit["psnr_surface_db"] if first_visit else None,
           # on the return, before retraining: what the round trip through the passive store kept
           "return": on_return,
           "return_drop_db": drop(first_visit, on_return, "psnr_db"),
           "return_drop_surface_db": drop(first_visit, on_return, "psnr_surface_db"),
           # at the end of the loop, after the return keyframes trained the region again
           "revisit_psnr_db": back["psnr_db"] if loop_closed else None,
           "revisit_drop_db": drop(first_visit, back, "psnr_db") if loop_closed else None,
           "revisit_psnr_surface_db": back["psnr_surface_db"] if loop_closed else None,
           "revisit_drop_surface_db": drop(first_visit, back, "psnr_surface_db") if loop_closed else None,
           "wall_s": time.perf_counter() - t0,
           "trace_every_10": trace[::10]}
    m.close()
    return res


def exp_timing(a, cfg: MapperConfig, room: dict | None) -> dict:
    if room is not None:
        return {"source": "room run", "iters_per_keyframe": cfg.iters_per_keyframe,
                "time_per_kf_s": room["time_per_kf_s"],
                # the median is robust to a first keyframe that compiles kernels and to load spikes
                "time_per_kf_median_s": room["time_per_kf_median_s"], "cpu_per_kf_s": room["cpu_per_kf_s"],
                "add_per_kf_s": room["add_per_kf_s"],
                "train_per_kf_s": room["train_per_kf_s"],
                "train_per_iter_ms": 1000 * room["train_per_kf_s"] / max(1, cfg.iters_per_keyframe),
                "num_gaussians_final": room["num_gaussians"], "cpu_count": os.cpu_count(),
                "load_avg_1m_at_end": os.getloadavg()[0]}
    seq = SimSequence("room", 60, a.width, a.height)
    kf = list(range(0, 60, a.kf_every))
    m, st = run_mapping(seq, cfg, kf, tag="timing")
    m.close()
    return {"source": "60-frame room", "iters_per_keyframe": cfg.iters_per_keyframe, **st,
            "cpu_count": os.cpu_count(), "load_avg_1m_at_end": os.getloadavg()[0]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--exp", default="room,frontend,score,pose,pose_frontend,storage,timing",
                   help="comma-separated experiments (run in the order of the default)")
    p.add_argument("--quick", action="store_true", help="small sizes for development")
    p.add_argument("--params", default=None, help="ROS params YAML with a 'mapping' section")
    p.add_argument("--width", type=int, default=376)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--kf-every", type=int, default=5)
    p.add_argument("--max-novel", type=int, default=40)
    p.add_argument("--room-frames", type=int, default=200)
    p.add_argument("--score-frames", type=int, default=100)
    p.add_argument("--score-scene", choices=("room", "street"), default="room",
                   help="simulator scene of the score-manager ablation")
    p.add_argument("--score-seed", type=int, default=0,
                   help="simulator seed of the score-manager scene (another layout and textures)")
    p.add_argument("--sc-storage", default="1,1.6,2")
    p.add_argument("--sc-storage-sum", default="4,6",
                   help="sc_storage values run with S_C summed over the window (sc_storage_per_view=False)")
    p.add_argument("--sc-storage-all", default="",
                   help="sc_storage values run with the paper's rule: window sum on every Gaussian "
                        "(sc_storage_per_view=False, prune_window_owned_only=False)")
    p.add_argument("--sc-storage-spare", default="",
                   help="sc_storage values run sparing high-error Gaussians (prune_spare_high_error=True)")
    p.add_argument("--pose-frames", type=int, default=100)
    p.add_argument("--pose-modes", default="none,single,multi",
                   help="refinement modes of the pose / pose_frontend ablations")
    p.add_argument("--pose-source", default=None,
                   help="pose_frontend / score_frontend on this recording (any source with ground truth) "
                        "instead of the room")
    p.add_argument("--pose-outdoor", action="store_true",
                   help="pose_frontend / score_frontend: map with outdoor=True")
    p.add_argument("--frontend-frames", type=int, default=200)
    p.add_argument("--workdir", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "vings_bench_mapping"),
                   help="where generated synthetic sequences are cached")
    p.add_argument("--noise-trans", type=float, default=0.02)
    p.add_argument("--noise-rot", type=float, default=1.0)
    p.add_argument("--street-length", type=float, default=320.0)
    p.add_argument("--street-frames", type=int, default=None)
    p.add_argument("--street-kf-every", type=int, default=4)
    p.add_argument("--street-iters", type=int, default=10)
    p.add_argument("--street-points", type=int, default=8000)
    p.add_argument("--max-active", type=int, default=60000)
    p.add_argument("--tau", type=float, default=40.0)
    p.add_argument("--delta-k", type=int, default=4)
    p.add_argument("--passive-mb", type=float, default=4.0)
    p.add_argument("--threads", type=int, default=0,
                   help="torch intra-op threads (0: torch's default, as `vings run` and the mapper node "
                        "run; numba uses its own). The OpenMP environment (OMP_WAIT_POLICY) is left as "
                        "the caller set it: forcing PASSIVE made mapping 10-40 %% slower here")
    a = p.parse_args(argv)
    for name in ("sc_storage", "sc_storage_all", "sc_storage_sum", "sc_storage_spare"):
        try:
            setattr(a, name, [float(v) for v in getattr(a, name).split(",") if v.strip()])
        except ValueError:
            p.error(f"--{name.replace('_', '-')}: expected comma-separated numbers, got {getattr(a, name)!r}")
    a.pose_modes = [v.strip() for v in a.pose_modes.split(",") if v.strip()]
    if not a.pose_modes or set(a.pose_modes) - {"none", "single", "multi"}:
        p.error(f"--pose-modes: expected a comma-separated subset of none,single,multi, got {a.pose_modes}")
    exps = [e.strip() for e in a.exp.split(",") if e.strip()]
    unknown = [e for e in exps if e not in EXPERIMENTS]
    if unknown or not exps:
        p.error(f"--exp: unknown experiment(s) {unknown or a.exp!r}; choose from {', '.join(EXPERIMENTS)}")
    if a.kf_every < 2:
        p.error("--kf-every must be >= 2 (novel views lie between keyframes)")
    for name in ("max_novel", "street_kf_every", "street_iters", "street_points", "max_active", "delta_k"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1")
    if a.quick:
        a.room_frames = min(a.room_frames, 40)
        a.score_frames = min(a.score_frames, 30)
        a.pose_frames = min(a.pose_frames, 30)
        a.frontend_frames = min(a.frontend_frames, 60)
        a.street_frames = a.street_frames or 120
        a.max_novel = min(a.max_novel, 8)
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    from vings_core.config import load_section
    cfg = load_section(MapperConfig, "mapping", a.params)
    if a.quick:
        cfg = replace(cfg, iters_per_keyframe=min(cfg.iters_per_keyframe, 20))
    for e, frames in (("room", a.room_frames), ("score", a.score_frames), ("pose", a.pose_frames)):
        if e in exps and (frames + a.kf_every - 1) // a.kf_every < 3:
            p.error(f"--exp {e}: {frames} frames at --kf-every {a.kf_every} give fewer than 3 keyframes")
    out: dict = {"config": {k: v for k, v in vars(a).items()}, "load_avg_1m_start": os.getloadavg()[0],
                 "torch_threads": torch.get_num_threads(), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "")}
    room = None

    def room_exp():
        nonlocal room
        room, m, _ = exp_room(a, cfg)
        m.close()
        return room

    run = {"room": room_exp, "frontend": lambda: exp_frontend(a, cfg), "score": lambda: exp_score(a, cfg, room),
           "pose": lambda: exp_pose(a, cfg), "pose_frontend": lambda: exp_pose_frontend(a, cfg),
           "score_frontend": lambda: exp_score_frontend(a, cfg),
           "storage": lambda: exp_storage(a, cfg), "timing": lambda: exp_timing(a, cfg, room)}
    def scoped(fn):          # each experiment's peak RSS is its own, not an earlier one's
        def go():
            reset_peak_rss()
            return fn()
        return go
    # in a fixed order (timing reuses the room run); one failing experiment leaves the others'
    # figures in the JSON, with its error in its place
    return run_experiments([(e, scoped(run[e])) for e in EXPERIMENTS if e in exps], out, log,
                           finish=lambda o: o.update(peak_rss_mb=process_peak_rss_mb()), to_json=_json_safe)


EXPERIMENTS = ("room", "frontend", "score", "pose", "pose_frontend", "score_frontend", "storage", "timing")


def _json_safe(v):
    """Plain JSON (no NaN/Infinity, numpy scalars as numbers)."""
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, (str, int, bool)) or v is None:
        return v
    return str(v)


if __name__ == "__main__":
    sys.exit(main())
