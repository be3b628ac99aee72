"""The output contract of a SLAM run (documented in docs/output_contract.md).

An output folder holds::

    trajectory.tum   the tracked frames of the main map segment, cam0 T_wc, TUM (ns stamps, 9 decimals)
    segments.json    the map segments (a new one after tracking was lost), trajectory_segments/ each
    keyframes.tum    the keyframes' final poses, cam0 T_wc, TUM
    map.ply          the 2D Gaussian map (written by the mapper, not here)
    metrics.json     one object with exactly the keys of METRIC_KEYS (null where not applicable)
    loops.json       every loop candidate checked (stamps, figures, verdict, reason) and each correction
    renders/         PNG renders (uint8 RGB)
    masks/           the dynamic eraser's masks, masks/kf_<stamp>.png (mono8, 255 = dynamic)

Every file is written atomically (temp file + rename).
"""
from __future__ import annotations

import json
import math
import os
import re
import resource
import shutil
import sys
from pathlib import Path
from typing import Any, Union

import numpy as np

from ..errors import InputError
from ..trajectory_io import write_tum
from ..types import Trajectory
from ..util import atomic_write_bytes, atomic_write_text, log, probe_writable_dir, remove_stale_temps

TRAJECTORY_FILE = "trajectory.tum"
KEYFRAMES_FILE = "keyframes.tum"
MAP_FILE = "map.ply"
SEGMENTS_FILE = "segments.json"
SEGMENTS_DIR = "trajectory_segments"
LOOPS_FILE = "loops.json"
METRICS_FILE = "metrics.json"
RENDERS_DIR = "renders"
MASKS_DIR = "masks"
CHECKPOINT_FILE = "checkpoint.pt"
# a run in progress writes these; the previous complete run's files stay untouched until the end
CHECKPOINT_PARTIAL_FILE = "checkpoint.partial.pt"
TRAJECTORY_PARTIAL_FILE = "trajectory.partial.tum"
KEYFRAMES_PARTIAL_FILE = "keyframes.partial.tum"
RUN_RENDER_PREFIX = "kf_"       # the runner's renders: renders/kf_<stamp>.png
VIEWS_DIR = "views"             # the report's keyframe views: views/kf_<stamp>_{input,depth,normal}.png
#: the report and its data (docs/report.md), removed with the previous run's outputs
REPORT_FILES = ("report.html", "bev.png", "timeline.jsonl", "run.json", "ground_truth.tum", "views/index.json")
STAGING_DIR = ".staging"        # a run's final files before they replace the previous run's

#: metrics.json keys, in file order. Units: wall_s s, fps frames/s, ate_* m, psnr_* dB,
#: peak_rss_mb MiB; rpe is the dict of vings_core.eval.traj.rpe (or null).
METRIC_KEYS = (
    "frames", "frames_tracked", "keyframes", "wall_s", "fps",
    "ate_sim3_m", "ate_se3_m", "sim3_scale", "rpe",
    "psnr_keyframes_db", "psnr_novel_db", "ssim_keyframes",
    "num_gaussians", "peak_rss_mb",
    "keyframes_light", "queue_peak_keyframes", "queue_spilled",
    "frames_unposed", "frames_unposed_reason", "segments", "ate_segments_m",
    "vi_state", "vi_initialised_at_s", "scale_observable", "acc_bias", "gyro_bias", "td_s",
    "td_estimates", "imu_only_frames", "vi_error",
    "loops_accepted", "loop_candidates_rejected", "loop_detect_ms_mean",
    "masked_fraction", "eraser_ms_mean", "eraser_error", "frames_bad",
)
_INT_KEYS = {"frames", "frames_tracked", "keyframes", "num_gaussians", "keyframes_light",
             "queue_peak_keyframes", "queue_spilled", "frames_unposed", "segments", "td_estimates",
             "imu_only_frames", "loops_accepted", "loop_candidates_rejected", "frames_bad"}
_STR_KEYS = {"frames_unposed_reason", "vi_state", "vi_error", "eraser_error"}
_BOOL_KEYS = {"scale_observable"}
_LIST_KEYS = {"ate_segments_m", "acc_bias", "gyro_bias"}
#: Keys of :func:`vings_core.eval.traj.evaluate_trajectory`'s result that go into metrics.json.
TRAJECTORY_METRIC_KEYS = ("ate_sim3_m", "ate_se3_m", "sim3_scale", "rpe")


def metrics_template() -> dict:
    """A metrics dict with every key of :data:`METRIC_KEYS` set to None."""
    return {k: None for k in METRIC_KEYS}


def _clean(v: Any, where: str) -> Any:
    """JSON-safe copy: numpy scalars/arrays -> Python, non-finite floats -> None."""
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (np.bool_,)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, dict):
        return {str(k): _clean(x, f"{where}.{k}") for k, x in v.items()}
    if isinstance(v, np.ndarray) and v.ndim == 0:
        return _clean(v.item(), where)
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_clean(x, f"{where}[]") for x in (v.tolist() if isinstance(v, np.ndarray) else v)]
    if hasattr(v, "item") and callable(v.item):  # torch scalar
        return _clean(v.item(), where)
    raise ValueError(f"metrics value {where} has unsupported type {type(v).__name__}")


def validate_metrics(metrics: dict) -> dict:
    """Check keys and types; returns a complete JSON-safe dict in :data:`METRIC_KEYS` order.

    Unknown keys raise ValueError (a programming error); missing keys become None; non-finite
    numbers (e.g. the PSNR of identical images) become None; ``rpe`` must be a dict or None,
    ``frames_unposed_reason`` and ``vi_state`` strings or None, ``scale_observable`` a bool or None,
    ``ate_segments_m``, ``acc_bias`` and ``gyro_bias`` lists of numbers or nulls or None; the other
    values numbers or None."""
    unknown = [k for k in metrics if k not in METRIC_KEYS]
    if unknown:
        raise ValueError(f"unknown metrics key(s) {unknown}; allowed: {list(METRIC_KEYS)}")
    out = metrics_template()
    for k, v in metrics.items():
        v = _clean(v, k)
        if k == "rpe":
            if v is not None and not isinstance(v, dict):
                raise ValueError(f"metrics 'rpe' must be a dict or None, got {type(v).__name__}")
        elif k in _LIST_KEYS:
            if v is not None and not (isinstance(v, list) and all(
                    x is None or (isinstance(x, (int, float)) and not isinstance(x, bool)) for x in v)):
                raise ValueError(f"metrics {k!r} must be a list of numbers or nulls, got {v!r}")
        elif k in _BOOL_KEYS:
            if v is not None and not isinstance(v, bool):
                raise ValueError(f"metrics {k!r} must be true, false or None, got {v!r}")
        elif k in _STR_KEYS:
            if v is not None and not isinstance(v, str):
                raise ValueError(f"metrics {k!r} must be a string or None, got {v!r}")
        elif v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ValueError(f"metrics {k!r} must be a number or None, got {v!r}")
        elif k in _INT_KEYS and v is not None:
            if float(v) != int(v):
                raise ValueError(f"metrics {k!r} must be an integer, got {v!r}")
            v = int(v)
        out[k] = v
    return out


def peak_rss_mb(include_children: bool = False) -> float:
    """Peak resident set size of this process in MiB (``getrusage`` ``ru_maxrss``).

    With ``include_children`` the peak of the largest terminated-and-waited-for child is added
    (an upper bound of the footprint when children ran alongside)."""
    unit = 1.0 if sys.platform == "darwin" else 1024.0  # bytes on macOS, KiB on Linux
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * unit
    if include_children:
        rss += resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * unit
    return rss / 2 ** 20


_NAME_RE = re.compile(r"^[A-Za-z0-9._-]+$")


def _to_uint8_rgb(rgb: Any, name: str) -> np.ndarray:
    if hasattr(rgb, "detach"):
        rgb = rgb.detach().cpu().numpy()
    a = np.asarray(rgb)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise InputError(f"render {name!r}: expected (H, W, 3) or (H, W), got shape {a.shape}")
    if a.dtype == np.uint8:
        return a
    if np.issubdtype(a.dtype, np.floating):
        if not np.all(np.isfinite(a)):
            raise InputError(f"render {name!r}: non-finite pixel values")
        return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    raise InputError(f"render {name!r}: expected uint8 or float in [0, 1], got dtype {a.dtype}")


class RunOutput:
    """Writer of one SLAM run's output folder (created on first write). All writes are atomic."""

    def __init__(self, out_dir: Union[str, os.PathLike]) -> None:
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise InputError(f"{self.out_dir}: output path exists and is not a folder")

    def prepare(self) -> None:
        """Before a run's work: create the folder and ``renders/`` and check that they are
        writable, so a bad ``--out`` fails at once, not after hours of SLAM. A previous run's
        outputs stay complete and readable until this run reaches its end (:meth:`begin_final`);
        until then this run writes only ``*.partial.*`` files (an interrupted earlier run's
        partial files are removed here, so they cannot pass for this run's)."""
        try:
            for d in (self.out_dir, self.renders_dir):
                probe_writable_dir(d)
        except OSError as e:
            raise InputError(f"{self.out_dir}: cannot write to the output folder "
                             f"({e.strerror or e})") from None
        if any(p.exists() for p in (self.metrics_path, self.trajectory_path, self.map_path)):
            log.warning("%s holds the outputs of a previous run; they are kept until this run "
                        "completes, then replaced", self.out_dir)
        # an earlier run's partial files (it was interrupted) must not pass for this run's
        stale = [p for p in self._partial_paths() if p.exists()]
        if stale:
            log.warning("%s: removing an interrupted earlier run's partial files %s", self.out_dir,
                        ", ".join(p.name for p in stale))
            self.remove_partials()
        # temporary files of a process killed while writing (atomic_write's .<name>.*.tmp)
        for p in (self.checkpoint_path, self.trajectory_path, self.keyframes_path, self.map_path,
                  self.metrics_path) + self._partial_paths():
            remove_stale_temps(p)
        self.discard_staged()       # a run killed while writing its final files

    def _partial_paths(self) -> tuple[Path, ...]:
        return (self.partial_checkpoint_path, self.out_dir / TRAJECTORY_PARTIAL_FILE,
                self.out_dir / KEYFRAMES_PARTIAL_FILE)

    def begin_final(self) -> None:
        """At the end of a run, before its final files: remove what would make the previous run's
        outputs look like this run's: ``metrics.json`` (written last: its presence marks a
        complete run), the runner's renders ``renders/kf_*.png`` (other files there are not
        ours and stay), the eraser's masks ``masks/kf_*.png``, the segment trajectories
        ``trajectory_segments/segment_*.tum``, ``loops.json`` (a run without the loop closer has
        none), the report and its data (``report.html``, ``bev.png``, ``timeline.jsonl``,
        ``run.json``, ``ground_truth.tum``, ``views/kf_*``). The other files are replaced when
        written."""
        try:
            for p in (self.metrics_path, self.out_dir / LOOPS_FILE) + tuple(self.out_dir / f for f in REPORT_FILES):
                if p.exists():
                    p.unlink()
            for d in (self.renders_dir, self.masks_dir, self.out_dir / VIEWS_DIR):
                if d.is_dir():
                    for p in d.glob(f"{RUN_RENDER_PREFIX}*.png"):
                        p.unlink()
            seg_dir = self.out_dir / SEGMENTS_DIR      # the previous run may have had more segments
            if seg_dir.is_dir():
                for p in seg_dir.glob("segment_*.tum"):
                    p.unlink()
            self.renders_dir.mkdir(exist_ok=True)
        except OSError as e:
            raise InputError(f"{self.out_dir}: cannot replace a previous run's outputs "
                             f"({e.strerror or e})") from None

    @property
    def staging_dir(self) -> Path:
        """The folder the end of a run writes into before :meth:`commit_staged`."""
        return self.out_dir / STAGING_DIR

    def staging_path(self, final: Path) -> Path:
        """Where the end of a run writes the file ``final`` (a path in the output folder) before
        :meth:`commit_staged` moves it in place."""
        return self.out_dir / STAGING_DIR / Path(final).relative_to(self.out_dir)

    def commit_staged(self) -> list[Path]:
        """Move every staged file onto its final name (one rename each: the whole set lands in
        milliseconds, after the slow writes). Returns the final paths."""
        root = self.out_dir / STAGING_DIR
        done = []
        try:
            for p in sorted(q for q in root.rglob("*") if q.is_file()):
                dest = self.out_dir / p.relative_to(root)
                dest.parent.mkdir(parents=True, exist_ok=True)
                os.replace(p, dest)
                done.append(dest)
        except OSError as e:
            raise InputError(f"{self.out_dir}: cannot move the final outputs in place "
                             f"({e.strerror or e})") from None
        self.discard_staged()
        return done

    def discard_staged(self) -> None:
        """Remove the staging folder (files of a run that did not reach its end)."""
        shutil.rmtree(self.out_dir / STAGING_DIR, ignore_errors=True)

    def remove_partials(self) -> None:
        """After a run's final files: the partial files of this (or an interrupted) run go."""
        for p in self._partial_paths():
            try:
                p.unlink(missing_ok=True)
            except OSError as e:
                log.warning("could not remove %s (%s)", p, e.strerror or e)

    def write_partial(self, traj: Trajectory, keyframes: Trajectory) -> tuple[Path, Path]:
        """The trajectories of a run that stopped early (interrupted or failed), beside the
        previous run's files: ``trajectory.partial.tum``, ``keyframes.partial.tum``."""
        a, b = self.out_dir / TRAJECTORY_PARTIAL_FILE, self.out_dir / KEYFRAMES_PARTIAL_FILE
        write_tum(a, traj)
        write_tum(b, keyframes)
        return a, b

    @property
    def checkpoint_path(self) -> Path:
        return self.out_dir / CHECKPOINT_FILE

    @property
    def partial_checkpoint_path(self) -> Path:
        """Where a run in progress writes its periodic map checkpoints."""
        return self.out_dir / CHECKPOINT_PARTIAL_FILE

    @property
    def trajectory_path(self) -> Path:
        return self.out_dir / TRAJECTORY_FILE

    @property
    def keyframes_path(self) -> Path:
        return self.out_dir / KEYFRAMES_FILE

    @property
    def map_path(self) -> Path:
        """Where the mapper writes the Gaussian map (nothing here writes it)."""
        return self.out_dir / MAP_FILE

    @property
    def metrics_path(self) -> Path:
        return self.out_dir / METRICS_FILE

    @property
    def renders_dir(self) -> Path:
        return self.out_dir / RENDERS_DIR

    def write_trajectory(self, traj: Trajectory, staged: bool = False) -> Path:
        """Every frame after initialisation, cam0 ``T_wc`` -> ``trajectory.tum`` (``staged``: to
        its :meth:`staging_path`)."""
        path = self.staging_path(self.trajectory_path) if staged else self.trajectory_path
        write_tum(path, traj)
        return path

    def write_keyframes(self, traj: Trajectory, staged: bool = False) -> Path:
        """Keyframe poses (stamp = keyframe identity), cam0 ``T_wc`` -> ``keyframes.tum``."""
        path = self.staging_path(self.keyframes_path) if staged else self.keyframes_path
        write_tum(path, traj)
        return path

    def write_segments(self, segments: list[dict], trajectories: dict[int, Trajectory],
                       staged: bool = False) -> Path:
        """``segments.json`` (``{"segments": [...]}``, one entry per map segment) and
        ``trajectory_segments/segment_<index>.tum`` for each (``staged``: to the staging folder).
        Returns the path of ``segments.json``."""
        path = self.out_dir / SEGMENTS_FILE
        if staged:
            path = self.staging_path(path)
        for k, traj in trajectories.items():
            p = self.out_dir / SEGMENTS_DIR / f"segment_{int(k)}.tum"
            write_tum(self.staging_path(p) if staged else p, traj)
        atomic_write_text(path, json.dumps({"segments": segments}, indent=2, allow_nan=False) + "\n")
        return path

    def write_loops(self, loops: dict, staged: bool = False) -> Path:
        """``loops.json``: ``{"candidates": [...], "corrections": [...], "summary": {...}}``."""
        path = self.out_dir / LOOPS_FILE
        atomic_write_text(self.staging_path(path) if staged else path,
                          json.dumps(_clean(loops, LOOPS_FILE), indent=2, allow_nan=False) + "\n")
        return path

    @property
    def masks_dir(self) -> Path:
        return self.out_dir / MASKS_DIR

    def write_mask(self, stamp_ns: int, png: bytes, staged: bool = False) -> Path:
        """``masks/kf_<stamp>.png``: one keyframe's dynamic mask, already PNG-encoded (mono8,
        255 = dynamic, the working resolution)."""
        path = self.masks_dir / f"{RUN_RENDER_PREFIX}{int(stamp_ns)}.png"
        atomic_write_bytes(self.staging_path(path) if staged else path, bytes(png))
        return path

    def write_metrics(self, metrics: dict) -> dict:
        """Validate (:func:`validate_metrics`) and write ``metrics.json``; returns what was written."""
        m = validate_metrics(metrics)
        atomic_write_text(self.metrics_path, json.dumps(m, indent=2, allow_nan=False) + "\n")
        return m

    def write_json(self, name: str, data: dict) -> Path:
        """Write a further JSON file of the run (``profile.json``) into the output folder, atomically."""
        path = self.out_dir / name
        atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")
        return path

    def read_metrics(self) -> dict:
        """The current ``metrics.json`` (a template if absent)."""
        if not self.metrics_path.is_file():
            return metrics_template()
        try:
            d = json.loads(self.metrics_path.read_text())
        except json.JSONDecodeError as e:
            raise InputError(f"{self.metrics_path}: not valid JSON ({e})") from None
        if not isinstance(d, dict):
            raise InputError(f"{self.metrics_path}: expected a JSON object")
        try:
            return validate_metrics(d)
        except ValueError as e:
            raise InputError(f"{self.metrics_path}: {e}") from None

    def update_metrics(self, partial: dict) -> dict:
        """Merge ``partial`` into the existing ``metrics.json`` (e.g. ATE added after the run). A
        folder without ``metrics.json`` holds no complete run (the file is written last): an
        :class:`InputError`, not a new file that would mark it complete."""
        if not self.metrics_path.is_file():
            raise InputError(f"{self.out_dir}: no {METRICS_FILE}: not the output of a completed run "
                             f"(metrics.json is written last), so there is nothing to update")
        m = self.read_metrics()
        m.update(partial)
        return self.write_metrics(m)

    def save_render(self, name: str, rgb: Any, staged: bool = False) -> Path:
        """Write ``renders/<name>.png`` from ``(H, W, 3)``/``(H, W)`` uint8 or float [0, 1]
        (numpy or torch) RGB. ``name`` is a plain file name (``[A-Za-z0-9._-]``)."""
        import cv2

        stem = name[:-4] if name.lower().endswith(".png") else name
        if not _NAME_RE.match(stem) or stem in (".", ".."):
            raise InputError(f"render name {name!r} must be a plain file name of [A-Za-z0-9._-]")
        img = _to_uint8_rgb(rgb, name)
        if img.ndim == 3:
            img = np.ascontiguousarray(img[..., ::-1])  # RGB -> BGR for OpenCV
        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise InputError(f"render {name!r}: PNG encoding failed")
        path = self.renders_dir / f"{stem}.png"
        if staged:
            path = self.staging_path(path)
        atomic_write_bytes(path, buf.tobytes())
        return path
