"""``report.html`` of a run's output folder (docs/report.md): :func:`build_report`.

Everything drawn is read from the output folder (docs/output_contract.md): ``metrics.json``,
``trajectory.tum``, ``keyframes.tum``, ``ground_truth.tum`` (when the source had ground truth),
``timeline.jsonl``, ``loops.json``, ``views/``, ``renders/``, ``masks/``, ``run.json``,
``profile.json`` and ``map.ply`` (for the bird's-eye view when ``bev.png``'s geometry is not
given). A part that is absent is said in its section, never an error: a folder of an older run or
of a recording converted by :mod:`vings_core.report.recording` gives what it has.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import InputError
from ..trajectory_io import read_tum
from ..types import Trajectory
from ..util import atomic_write_text
from . import html as H
from . import plots
from .bev import BevImage, splat_bev, surfels_from_ply, view_basis, write_bev
from .timeline import TIMELINE_FILE, read_timeline

log = logging.getLogger("vings")

REPORT_FILE = "report.html"
RUN_INFO_FILE = "run.json"
GT_FILE = "ground_truth.tum"
BEV_FILE = "bev.png"
VIEWS_DIR = "views"
VIEWS_INDEX = "index.json"
MAX_VIEWS = 6
MAX_MASKS = 8
JPEG_QUALITY = 85


@dataclass
class RunData:
    """What a report is drawn from (absent parts empty or None)."""

    folder: Path
    metrics: dict
    run: dict
    traj: Trajectory
    keyframes: Trajectory
    gt: Optional[Trajectory]
    timeline: list[dict] = field(default_factory=list)
    loops: Optional[dict] = None
    views: list[dict] = field(default_factory=list)
    masks: dict[int, Path] = field(default_factory=dict)
    profile: Optional[dict] = None

    @property
    def metric(self) -> bool:
        return bool(self.run.get("metric", self.metrics.get("scale_observable") or False))

    @property
    def path(self) -> Trajectory:
        """The path the views are laid out on: the keyframes, else the tracked frames."""
        return self.keyframes if len(self.keyframes) else self.traj

    @property
    def gravity_aligned(self) -> bool:
        return bool(self.run.get("gravity_aligned", self.metrics.get("vi_state") == "visual-inertial"))


def _json(path: Path) -> Optional[dict]:
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: not readable JSON ({e})") from None
    if not isinstance(d, dict):
        raise InputError(f"{path}: expected a JSON object")
    return d


def _tum(path: Path) -> Trajectory:
    return read_tum(path) if path.is_file() else Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))


def load_run(folder: str | Path, gt: Optional[Trajectory] = None, metrics: Optional[dict] = None) -> RunData:
    """Read an output folder (module doc). ``gt`` (cam0 ``T_wc``) overrides ``ground_truth.tum``;
    ``metrics`` overrides ``metrics.json`` (the runner passes its metrics before writing them)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder (give a `vings run` output folder)")
    m = metrics if metrics is not None else _json(folder / "metrics.json")
    if m is None:
        raise InputError(f"{folder}: no metrics.json: not the output of a completed run")
    if gt is None and (folder / GT_FILE).is_file():
        gt = read_tum(folder / GT_FILE)
    views = (_json(folder / VIEWS_DIR / VIEWS_INDEX) or {}).get("views", [])
    masks = {}
    if (folder / "masks").is_dir():
        for p in sorted((folder / "masks").glob("kf_*.png")):
            try:
                masks[int(p.stem[3:])] = p
            except ValueError:
                continue
    return RunData(folder=folder, metrics=m, run=_json(folder / RUN_INFO_FILE) or {},
                   traj=_tum(folder / "trajectory.tum"), keyframes=_tum(folder / "keyframes.tum"), gt=gt,
                   timeline=read_timeline(folder / TIMELINE_FILE) if (folder / TIMELINE_FILE).is_file() else [],
                   loops=_json(folder / "loops.json"), views=views, masks=masks,
                   profile=_json(folder / "profile.json"))


def compute_bev(folder: Path, data: RunData, size_px: int = 1024) -> Optional[BevImage]:
    """The bird's-eye view from ``map.ply`` over the run's keyframe (else frame) path."""
    ply = folder / "map.ply"
    path = data.path
    if not ply.is_file():
        return None
    s = surfels_from_ply(ply)
    if len(s) == 0:
        return None
    return splat_bev(s, path.poses, data.gravity_aligned, metric=data.metric, size_px=size_px)


# ------------------------------------------------------------------------------ sections


def _summary(d: RunData) -> H.Section:
    m = d.metrics
    keys = ("frames", "frames_tracked", "keyframes", "wall_s", "fps", "ate_sim3_m", "ate_se3_m", "sim3_scale",
            "psnr_keyframes_db", "psnr_novel_db", "ssim_keyframes", "num_gaussians", "peak_rss_mb", "segments",
            "vi_state", "loops_accepted", "loop_candidates_rejected", "masked_fraction", "eraser_ms_mean")
    rows = [(k, _fmt(m.get(k))) for k in keys if k in m]
    sec = H.Section("summary", "Summary").add(H.table(rows, ("metric", "value")))
    if m.get("wall_s") is None and m.get("frames"):
        sec.note("wall_s and fps are in metrics.json (the report is drawn before the run's last file)")
    if m.get("frames_unposed_reason"):
        sec.note(f"unposed frames: {m['frames_unposed_reason']}")
    return sec


def _fmt(v: object) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def aligned_ground_truth(traj: Trajectory, gt: Optional[Trajectory]
                         ) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Ground truth in the estimate's frame (inverse of the Sim(3) alignment, as ``ate_sim3_m``),
    the per-frame position error (GT metres), the matched frames' times (s from the first frame)
    and their estimated positions; None without ground truth or matches."""
    from ..eval.align import umeyama
    from ..eval.traj import DEFAULT_MAX_DT_NS, associate_indices
    if gt is None or len(traj) < 3 or len(gt) < 3:
        return None
    try:
        a = associate_indices(traj, gt, DEFAULT_MAX_DT_NS, True)
    except InputError as e:
        log.warning("report: ground truth not associated with the trajectory: %s", e)
        return None
    if len(a["est_idx"]) < 3:
        return None
    est = traj.positions[a["est_idx"]]
    gtp = np.asarray(a["gt_poses"])[:, :3, 3]
    s, R, t = umeyama(est, gtp, with_scale=True)
    err = np.linalg.norm(s * est @ R.T + t - gtp, axis=1)
    gt_run = ((gtp - t) @ R) / s
    ts = (traj.stamps_ns[a["est_idx"]] - traj.stamps_ns[0]) * 1e-9
    return gt_run, err, ts, est


def _loop_lines(d: RunData) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    if not d.loops or not len(d.keyframes):
        return []
    pos = dict(zip(d.keyframes.stamps_ns.tolist(), d.keyframes.positions))
    out = []
    for c in d.loops.get("candidates", []):
        a, b = pos.get(c.get("older")), pos.get(c.get("newer"))
        if a is not None and b is not None and (c.get("verdict") == "accepted" or c.get("inliers")):
            out.append((a, b, c.get("verdict") == "accepted"))
    return out


def _trajectory(d: RunData, bev: Optional[BevImage]) -> H.Section:
    sec = H.Section("trajectory", "Trajectory")
    if len(d.traj) == 0:
        return sec.note("no tracked frames")
    path = d.path
    basis = bev.basis if bev is not None else view_basis(path.poses, d.gravity_aligned)
    al = aligned_ground_truth(d.traj, d.gt)
    unit = "m" if d.metric else "run units"
    sec.add(H.img_tag(plots.trajectory_top(basis, d.traj.positions, None if al is None else al[0], bev,
                                           d.keyframes.positions if len(d.keyframes) else None,
                                           _loop_lines(d), unit), "image/png", "trajectory from above"))
    if al is None:
        sec.note("no ground truth: the estimate alone (ground_truth.tum absent)")
        return sec
    _, err, ts, est = al
    sec.add(H.img_tag(plots.error_along_path(ts, err, basis, est), "image/png", "error along the path"))
    rpe = d.metrics.get("rpe")
    if rpe and rpe.get("per_length"):
        sec.add(H.img_tag(plots.rpe_per_length(rpe), "image/png", "RPE per segment length"))
    else:
        sec.note("RPE: no segment length fits this path (docs/evaluation.md)")
    return sec


def _rel_s(d: RunData, stamp_ns: int) -> str:
    """A stamp as seconds from the first tracked frame (or keyframe)."""
    ref = d.traj if len(d.traj) else d.keyframes
    t0 = int(ref.stamps_ns[0]) if len(ref) else 0
    return f"{(int(stamp_ns) - t0) * 1e-9:.3f} s"


def _jpeg(path: Path) -> Optional[bytes]:
    import cv2
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        return None
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    return buf.tobytes() if ok else None


def _figure(path: Path, caption: str) -> str:
    data = _jpeg(path) if path.is_file() else None
    if data is None:
        return f"<figure><figcaption>{H.esc(caption)}: missing</figcaption></figure>"
    return f"<figure>{H.img_tag(data, 'image/jpeg', caption)}<figcaption>{H.esc(caption)}</figcaption></figure>"


def _bev_section(d: RunData, bev: Optional[BevImage]) -> H.Section:
    sec = H.Section("map", "Map from above")
    p = d.folder / BEV_FILE
    if bev is None and not p.is_file():
        return sec.note("no map (map.ply absent or empty)")
    if bev is not None:
        import cv2
        ok, buf = cv2.imencode(".png", cv2.cvtColor(bev.rgb, cv2.COLOR_RGB2BGR))
        sec.add(H.img_tag(buf.tobytes(), "image/png", "bird's-eye view of the map"))
        sec.note(f"{bev.surfels_drawn} surfels below the camera path's highest point, seen along "
                 f"{bev.basis.source.value}; pixel {bev.px:.3g} {'m' if bev.metric else 'run units'}"
                 f"{'' if bev.metric else ' (no scale bar: the run is not metric)'}")
    else:
        sec.add(_figure(p, "bird's-eye view"))
    return sec


def _views(d: RunData) -> H.Section:
    sec = H.Section("keyframes", "Keyframes: input, render, depth, normals")
    if not d.views:
        return sec.note("no keyframe views in this output (views/ absent)")
    for v in d.views[:MAX_VIEWS]:
        s = int(v["stamp_ns"])
        psnr = v.get("psnr_db")
        cap = f"keyframe at {_rel_s(d, s)}" + (f", PSNR {psnr:.2f} dB" if psnr is not None else "")
        row = [_figure(d.folder / VIEWS_DIR / f"kf_{s}_input.png", f"input ({cap})"),
               _figure(d.folder / "renders" / f"kf_{s}.png", "render"),
               _figure(d.folder / VIEWS_DIR / f"kf_{s}_depth.png", "depth (near: bright)"),
               _figure(d.folder / VIEWS_DIR / f"kf_{s}_normal.png", "normals")]
        sec.add('<div class="row">' + "".join(row) + "</div>")
    return sec


def _resources(d: RunData) -> H.Section:
    sec = H.Section("resources", "Gaussians, memory and time")
    if not d.timeline:
        return sec.note("no timeline.jsonl in this output")
    sec.add(H.img_tag(plots.gaussians_memory(d.timeline), "image/png", "Gaussians and memory"))
    sec.add(H.img_tag(plots.stage_times(d.timeline), "image/png", "time per stage per keyframe"))
    if d.profile and d.profile.get("steps"):
        rows = [(r["stage"], r["step"], r["calls"], f"{r['total_s']:.2f}", f"{r['mean_ms']:.1f}")
                for r in d.profile["steps"]]
        sec.add(H.table(rows, ("stage", "step", "calls", "total s", "mean ms")))
    return sec


def _loops(d: RunData) -> H.Section:
    sec = H.Section("loops", "Loop closures")
    if d.loops is None:
        return sec.note("loop closer off (no loops.json)")
    cands = d.loops.get("candidates", [])
    acc = [c for c in cands if c.get("verdict") == "accepted"]
    sec.note(f"{len(acc)} accepted of {len(cands)} candidates checked"
             + (f"; the loop closer stopped: {d.loops['error']}" if d.loops.get("error") else ""))
    shown = acc + [c for c in cands if c.get("verdict") != "accepted" and c.get("inliers")][:20]
    if shown:
        rows = [(_rel_s(d, c.get("newer", 0)), _rel_s(d, c.get("older", 0)), c.get("verdict"),
                 c.get("matches"), c.get("inliers"), c.get("reason")) for c in shown]
        sec.add(H.table(rows, ("newer keyframe", "older keyframe", "verdict", "matches", "inliers",
                               "reason")))
    reasons: dict[str, int] = {}
    for c in cands:
        if c.get("verdict") != "accepted":
            key = " ".join(str(c.get("reason", "")).split(" ")[:3])
            reasons[key] = reasons.get(key, 0) + 1
    if reasons:
        sec.add(H.table(sorted(reasons.items(), key=lambda kv: -kv[1]), ("refusal (first words)", "candidates")))
    return sec


def _eraser(d: RunData) -> H.Section:
    sec = H.Section("eraser", "Dynamic eraser")
    if not d.masks and not any(ln.get("eraser") for ln in d.timeline):
        return sec.note("eraser off (no masks/)")
    if d.timeline:
        sec.add(H.img_tag(plots.masked_fraction(d.timeline), "image/png", "masked fraction"))
    import cv2
    frac = {}
    for s, p in d.masks.items():
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if m is not None:
            frac[s] = (float((m > 127).mean()), m)
    top = sorted(frac, key=lambda s: -frac[s][0])[:MAX_MASKS]
    figs = []
    for s in sorted(top):
        f, m = frac[s]
        if f == 0:
            continue
        inp = d.folder / VIEWS_DIR / f"kf_{s}_input.png"
        base = cv2.imread(str(inp)) if inp.is_file() else None
        img = np.dstack([m] * 3) if base is None or base.shape[:2] != m.shape else base.copy()
        if base is not None and base.shape[:2] == m.shape:
            img[m > 127] = (0.5 * img[m > 127] + [0, 0, 127]).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        cap = f"keyframe at {_rel_s(d, s)}, {100 * f:.1f} % masked"
        figs.append(f"<figure>{H.img_tag(buf.tobytes(), 'image/jpeg', cap)}<figcaption>{H.esc(cap)}</figcaption></figure>")
    if figs:
        sec.add('<div class="row">' + "".join(figs) + "</div>")
    else:
        sec.note("no keyframe was masked")
    return sec


def _parameters(d: RunData) -> H.Section:
    sec = H.Section("parameters", "Parameters and versions")
    if not d.run:
        return sec.note("no run.json in this output")
    info = {k: v for k, v in d.run.items() if k not in ("params", "versions")}
    sec.add(H.table([(k, json.dumps(v) if not isinstance(v, str) else v) for k, v in info.items()], ("item", "value")))
    if d.run.get("versions"):
        sec.add(H.table(sorted(d.run["versions"].items()), ("package", "version")))
    if d.run.get("params"):
        sec.add(f"<pre>{H.esc(json.dumps(d.run['params'], indent=1))}</pre>")
    return sec


def trajectory_plots(traj: Trajectory, gt: Trajectory, rpe: Optional[dict]) -> dict[str, bytes]:
    """``vings eval --plots``: ``trajectory.png``, ``error.png`` and (when ``rpe`` has lengths)
    ``rpe.png`` for any estimate / ground-truth pair, as in the report."""
    basis = view_basis(traj.poses, gravity_aligned=False)
    al = aligned_ground_truth(traj, gt)
    if al is None:
        raise InputError("--plots: the estimate and the ground truth have fewer than 3 matched poses")
    gt_run, err, ts, est = al
    out = {"trajectory.png": plots.trajectory_top(basis, traj.positions, gt_run, None, unit="estimate units"),
           "error.png": plots.error_along_path(ts, err, basis, est)}
    if rpe and rpe.get("per_length"):
        out["rpe.png"] = plots.rpe_per_length(rpe)
    return out


def build_report(folder: str | Path, out_path: Optional[str | Path] = None, gt: Optional[Trajectory] = None,
                 metrics: Optional[dict] = None, bev: Optional[BevImage] = None, write_bev_png: bool = False,
                 data: Optional[RunData] = None, shown_folder: Optional[Path] = None) -> Path:
    """Write ``report.html`` (default: in ``folder``) and return its path. ``bev``: the bird's-eye
    view already computed (else it is computed from ``map.ply``; ``write_bev_png`` then also
    writes ``bev.png`` when absent). ``data``: the folder already read (:func:`load_run`);
    ``shown_folder``: the folder named in the page (default ``folder``)."""
    t0 = time.perf_counter()
    folder = Path(folder)
    d = data if data is not None else load_run(folder, gt, metrics)
    if bev is None:
        bev = compute_bev(folder, d)
        if bev is not None and write_bev_png and not (folder / BEV_FILE).is_file():
            write_bev(folder / BEV_FILE, bev)
    sections = [_summary(d), _trajectory(d, bev), _bev_section(d, bev), _views(d), _resources(d), _loops(d),
                _eraser(d), _parameters(d)]
    src = d.run.get("source", str(folder))
    text = H.page("VINGS run report", f"{src}; output folder {Path(shown_folder or folder).resolve()}; "
                  f"{d.run.get('created', '')}", sections)
    out = Path(out_path) if out_path is not None else folder / REPORT_FILE
    atomic_write_text(out, text)
    log.debug("report written in %.2f s: %s", time.perf_counter() - t0, out)
    return out
