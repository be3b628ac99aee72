"""Dynamic eraser (``vings_core.eraser``, docs/eraser.md): masks against the simulator's, the
ablation of its cues, and what the masks do to the map and to tracking.

Every run is ``vings run --sync`` in-process (``SlamRunner``; the loop closer off), on simulator
sequences at 376x240 with the IMU (visual-inertial).

Experiments (``--exp``, comma list):

* ``dynamic``: ``room --dynamic`` and ``street --dynamic`` for each seed, each run twice: with the
  eraser (in ablation mode: every cue's mask is computed on the same inputs, the configured one is
  used) and with ``--no-eraser``. Per run and pooled:
  - masks against the simulator's on keyframes with objects (true mask >= 0.5 % of the pixels):
    mean IoU, recall of dynamic pixels, false positives among static pixels (every keyframe), for
    each variant: ``l1``, ``ssim_l1``, ``ssim_l1_sigma`` (the paper's), ``motion``, ``combined``
    (the default: motion, or the paper's re-render cue where the flow does not show the proposal
    static);
  - the map, eraser on / off: PSNR over static pixels (the simulator's mask) of the final map
    rendered at every keyframe's pose and at held-out frames' poses; Gaussians whose centres lie
    in the volume the moving objects swept (their boxes at every frame, in the truth's frame after
    aligning the trajectory);
  - tracking: ATE (SE(3)) on / off; the share of frames where objects cover >= 15 %;
  - cost: the eraser's time per keyframe (render of the keyframe's pose included).
* ``static``: ``room``, ``street`` without moving objects and ``kitti06_snippet``, eraser on / off:
  ``masked_fraction``, PSNR of the keyframes, ATE.

The last stdout line is one JSON object keyed by experiment (``benchmarks/_harness.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _harness import run_selected  # noqa: E402

WORK = Path(os.environ.get("TMPDIR", "/tmp")) / "vings_bench_eraser"
DATA = HERE.parent.parent / "shared" / "data"
HELD_OUT = 20           # held-out frames per run for the static-pixel PSNR
BIG = 0.15              # "objects cover >= 15 % of the image"


def log(*a) -> None:
    print("[bench eraser]", *a, file=sys.stderr, flush=True)


def _sim(scene: str, seed: int, dynamic: bool, a) -> tuple[Path, dict]:
    """The simulated sequence (cached under WORK) and the keyword arguments that built it."""
    from vings_core.sim import generate
    kw = {"frames": a.room_frames} if scene == "room" else {"length_m": a.street_length, "fps": 10.0}
    d = WORK / f"{scene}{'_dyn' if dynamic else ''}_s{seed}_{kw.get('frames') or int(kw['length_m'])}"
    if not (d / "sim.json").exists():
        t = time.perf_counter()
        generate(scene, d, width=376, height=240, seed=seed, dynamic=dynamic, mcap=False, **kw)
        log(f"simulated {d.name} in {time.perf_counter() - t:.0f} s")
    return d, kw


def _truth_mask(path: Path, stamp: int, shape) -> np.ndarray:
    import cv2
    m = cv2.imread(str(path / "mav0" / "mask0" / "data" / f"{stamp}.png"), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise FileNotFoundError(f"{path}: no simulator mask for frame {stamp}")
    if m.shape != tuple(shape):
        m = cv2.resize(m, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return m > 127


def _image(path: Path, stamp: int) -> np.ndarray:
    import cv2
    im = cv2.imread(str(path / "mav0" / "cam0" / "data" / f"{stamp}.png"), cv2.IMREAD_COLOR)
    return cv2.cvtColor(im, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def _run(path: Path, eraser: bool, truth: bool):
    """``vings run --sync`` (``--no-loop``, ``--no-eraser`` unless ``eraser``); with ``truth``, each
    keyframe's ablation masks are scored against the simulator's. Returns metrics, runner, scores
    (variant -> list of MaskScore)."""
    from vings_core.eraser import EraserConfig
    from vings_core.eval.masks import score_mask
    from vings_core.io.base import SourceOptions
    from vings_core.loop import LoopConfig
    from vings_core.pipeline import RunConfig, SlamRunner, open_working_source

    scores: dict[str, list] = {}
    delays: list[float] = []
    cfg = RunConfig(sync=True)
    src = open_working_source(path, SourceOptions(), cfg.width, cfg.height)
    out = WORK / "runs" / f"{path.name}_{'eraser' if eraser else 'noeraser'}"
    runner = SlamRunner(src, out, run_cfg=cfg, progress=False, loop_cfg=LoopConfig(enabled=False),
                        eraser_cfg=EraserConfig(enabled=eraser, ablation=truth))
    if eraser and truth:
        process = runner.eraser.process

        def scored(kf, render):
            t = time.perf_counter()
            res = process(kf, render)
            delays.append(time.perf_counter() - t)
            gt = _truth_mask(path, int(kf.stamp_ns), res.mask.shape)
            for name, m in [*res.variants.items(), ("used", res.mask)]:
                scores.setdefault(name, []).append(score_mask(m, gt))
            return res
        runner.eraser.process = scored
    t = time.perf_counter()
    m = runner.run()
    log(f"{out.name}: {time.perf_counter() - t:.0f} s, ATE se3 {m.get('ate_se3_m')} sim3 {m.get('ate_sim3_m')} "
        f"(metric: {m.get('scale_observable')}), masked {m.get('masked_fraction')}")
    return m, runner, scores


def _alignment(runner, path: Path):
    """``(s, R, t)`` taking the run's world to the truth's (SE(3) when the run is metric)."""
    from vings_core.eval.align import umeyama
    from vings_core.eval.traj import associate
    from vings_core.io import SourceOptions, open_source
    gt = open_source(path, SourceOptions()).gt_camera_trajectory()
    e, g = associate(runner.trajectory(), gt)
    metric = runner.vio is not None and runner.vio.initialised_at_ns is not None
    return umeyama(e.positions, g.positions, with_scale=not metric)


def _static_psnr(runner, path: Path) -> dict:
    """PSNR over the simulator's static pixels of the final map at the keyframes' and at held-out
    frames' final poses."""
    import torch  # noqa: F401 - the renders are torch inside
    kf = runner.keyframe_trajectory()
    traj = runner.trajectory()
    kf_set = set(int(s) for s in kf.stamps_ns)
    others = [i for i, s in enumerate(traj.stamps_ns) if int(s) not in kf_set]
    held = [others[i] for i in np.linspace(0, len(others) - 1, min(HELD_OUT, len(others))).astype(int)] if others else []

    def score(stamps, poses):
        vals = []
        for s, T in zip(stamps, poses):
            r = runner.mapper.render(T, runner.camera)["color"]
            img = _image(path, int(s))
            if img.shape != r.shape:
                continue
            static = ~_truth_mask(path, int(s), r.shape[:2])
            mse = float(((r - img) ** 2).mean(-1)[static].mean()) if static.any() else None
            if mse is not None:
                vals.append(-10 * np.log10(max(mse, 1e-12)))
        return round(float(np.mean(vals)), 3) if vals else None
    return {"psnr_static_keyframes_db": score(kf.stamps_ns, kf.poses),
            "psnr_static_heldout_db": score([traj.stamps_ns[i] for i in held], [traj.poses[i] for i in held])}


def _swept_count(runner, path: Path, kw: dict, seed: int) -> int | None:
    """Gaussians (active and passive) whose centre lies inside a moving object's box at any frame
    time, in the truth's frame."""
    from vings_core.sim.sequence import build_scene
    info = json.loads((path / "sim.json").read_text())
    scene = build_scene(info.get("scene", path.name.split("_")[0]), seed=seed, dynamic=True,
                        length_m=kw.get("length_m"), fps=kw.get("fps", 20.0))
    if not scene.movers:
        return None
    s, R, t = _alignment(runner, path)
    X = runner.mapper.all_gaussians().means.detach().cpu().numpy().astype(np.float64)
    X = s * X @ R.T + t
    stamps = runner.source.frame_stamps()
    times = (np.asarray(stamps, np.int64) - int(stamps[0])) * 1e-9
    inside = np.zeros(len(X), bool)
    for mv in scene.movers:
        q = mv.local
        corners = np.concatenate([q.origin, q.origin + q.u * q.extent[:, :1], q.origin + q.v * q.extent[:, 1:],
                                  q.origin + q.u * q.extent[:, :1] + q.v * q.extent[:, 1:]])
        lo, hi = corners.min(0), corners.max(0)
        for tt in times:
            Rb, p = mv.pose(float(tt))
            loc = (X - p) @ Rb
            inside |= np.all((loc >= lo) & (loc <= hi), axis=1)
    return int(inside.sum())


def _safe(fn, *args) -> dict:
    """A figure's function; its failure is recorded, the runs already done are kept."""
    try:
        return fn(*args)
    except Exception as e:  # noqa: BLE001 - one figure failing must not lose the runs
        log(f"{fn.__name__} failed: {type(e).__name__}: {e}")
        return {"error": f"{fn.__name__}: {type(e).__name__}: {e}"}


def _swept(runner, path: Path, kw: dict, seed: int) -> dict:
    return {"swept_gaussians": _swept_count(runner, path, kw, seed)}


def _save(name: str, r: dict) -> None:
    """Each run's figures as they come (``WORK/results/<name>.json``)."""
    d = WORK / "results"
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{name}.json").write_text(json.dumps(r, indent=1, default=str))


def _pooled(scores: dict) -> dict:
    from vings_core.eval.masks import aggregate
    return {k: {kk: (round(v, 4) if isinstance(v, float) else v) for kk, v in aggregate(vs).items()}
            for k, vs in scores.items()}


def _big_share(path: Path) -> float:
    d = path / "mav0" / "mask0" / "data"
    fr = []
    import cv2
    for p in sorted(d.glob("*.png")):
        fr.append(float((cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127).mean()))
    return round(float(np.mean(np.asarray(fr) >= BIG)), 4) if fr else 0.0


def exp_dynamic(a) -> dict:
    runs, pooled = {}, {}
    for scene in a.scenes.split(","):
        for seed in a.seeds:
            path, kw = _sim(scene, seed, True, a)
            on_m, on_r, scores = _run(path, eraser=True, truth=True)
            on = {"ate_se3_m": on_m["ate_se3_m"], "ate_sim3_m": on_m["ate_sim3_m"],
                  "metric": bool(on_m.get("scale_observable")), "masked_fraction": on_m["masked_fraction"],
                  "eraser_ms_mean": on_m["eraser_ms_mean"], "masks": _pooled(scores),
                  **_safe(_swept, on_r, path, kw, seed), **_safe(_static_psnr, on_r, path)}
            for k, v in scores.items():
                pooled.setdefault(k, []).extend(v)
            _save(path.name, {"eraser": on, "scores": {k: [vars(x) for x in v] for k, v in scores.items()}})
            del on_r
            if not a.with_off:
                runs[path.name] = {"eraser": on, "frames_objects_over_15pct": _big_share(path)}
                continue
            off_m, off_r, _ = _run(path, eraser=False, truth=False)
            off = {"ate_se3_m": off_m["ate_se3_m"], "ate_sim3_m": off_m["ate_sim3_m"],
                   "metric": bool(off_m.get("scale_observable")), **_safe(_swept, off_r, path, kw, seed),
                   **_safe(_static_psnr, off_r, path)}
            del off_r
            r = {"eraser": on, "no_eraser": off, "frames_objects_over_15pct": _big_share(path)}
            _save(path.name, {**r, "scores": {k: [vars(x) for x in v] for k, v in scores.items()}})
            if on.get("swept_gaussians") is not None and off.get("swept_gaussians"):
                r["swept_reduction"] = round(1 - on["swept_gaussians"] / off["swept_gaussians"], 4)
            # SE(3) when both runs are metric (visual-inertial initialised), else Sim(3): a run whose
            # scale was never observed has no meaningful rigid-alignment error
            key = "ate_se3_m" if on["metric"] and off["metric"] else "ate_sim3_m"
            if on[key] and off[key]:
                r["ate_change"] = round(on[key] / off[key] - 1, 4)
                r["ate_compared"] = key
            for k in ("psnr_static_keyframes_db", "psnr_static_heldout_db"):
                if on.get(k) is not None and off.get(k) is not None:
                    r[k.replace("psnr_", "psnr_gain_")] = round(on[k] - off[k], 3)
            runs[path.name] = r
            log(json.dumps({path.name: r}))
    return {"runs": runs, "pooled_masks": _pooled(pooled),
            "targets": {"iou_mean": ">= 0.5", "recall": ">= 0.7", "false_positive_fraction": "<= 0.02",
                        "swept_reduction": ">= 0.8", "ate_change": "<= 0 (<= -0.1 with objects >= 15 %)",
                        "eraser_ms_mean": "<= 150"}}


def exp_static(a) -> dict:
    out = {}
    seqs = [(_sim("room", 0, False, a)[0]), (_sim("street", 0, False, a)[0])]
    kitti = DATA / "kitti06_snippet"
    if kitti.exists():
        seqs.append(kitti)
    for path in seqs:
        r = {}
        for on in (True, False):
            m, runner, _ = _run(path, eraser=on, truth=False)
            r["eraser" if on else "no_eraser"] = {k: m.get(k) for k in ("masked_fraction", "psnr_keyframes_db",
                                                                          "ate_se3_m", "ate_sim3_m", "eraser_ms_mean")}
        out[path.name] = r
        log(json.dumps({path.name: r}))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", default="dynamic,static")
    ap.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0, 1, 2])
    ap.add_argument("--scenes", default="room,street", help="dynamic: room,street")
    ap.add_argument("--room-frames", type=int, default=150)
    ap.add_argument("--street-length", type=float, default=150.0, help="street route length (m), at 10 fps")
    ap.add_argument("--no-off", dest="with_off", action="store_false",
                    help="dynamic: only the runs with the eraser (masks and cost; no map/tracking comparison)")
    a = ap.parse_args(argv)
    table = {"dynamic": lambda: exp_dynamic(a), "static": lambda: exp_static(a)}
    return run_selected(ap, a, table, log)


if __name__ == "__main__":
    raise SystemExit(main())
