"""The report's data files of a run (docs/output_contract.md), written by the runner at its end into
the staging folder with its other outputs: ``timeline.jsonl``, ``run.json``, ``ground_truth.tum``,
``views/`` (index and images); then ``bev.png`` and ``report.html`` drawn from them."""
from __future__ import annotations

import dataclasses
import datetime
import enum
import json
import platform
import sys
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import numpy as np

from ..trajectory_io import write_tum
from ..types import Trajectory
from ..util import atomic_write_bytes, atomic_write_text
from .build import BEV_FILE, GT_FILE, RUN_INFO_FILE, VIEWS_DIR, VIEWS_INDEX, build_report, compute_bev, load_run
from .bev import write_bev
from .timeline import TIMELINE_FILE, Timeline

if TYPE_CHECKING:
    from ..pipeline import SlamRunner

#: distributions whose versions ``run.json`` records
PACKAGES = ("torch", "numpy", "opencv-python-headless", "gtsam", "scipy", "numba", "evo", "rosbags", "mcap",
            "matplotlib", "scikit-image")


def _plain(v: Any) -> Any:
    if isinstance(v, enum.Enum):
        return v.value
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: _plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.integer, np.floating)):
        return v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return None
    if v is None or isinstance(v, (str, int, float, bool)):
        return v
    return str(v)


def versions() -> dict[str, str]:
    """Python, VINGS and the main libraries' versions (installed distributions only)."""
    from .. import __version__
    out = {"python": platform.python_version(), "vings-ros": __version__}
    for p in PACKAGES:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            continue
    return out


def run_info(runner: "SlamRunner") -> dict:
    """``run.json``: what produced the run (source, command line, every stage's parameters as
    used, versions) and how to draw it (``metric``, ``gravity_aligned``)."""
    from ..vio.config import ViState
    cam = runner.camera
    vi = runner.vio is not None and runner.vio.state == ViState.VISUAL_INERTIAL
    params = {"run": runner.cfg, "mapping": runner.mapper.cfg, "exchange": runner.xcfg}
    if runner.frontend is not None:
        params["frontend"] = runner.frontend.cfg
    if runner.vio is not None:
        params["vio"] = runner.vio.cfg
    if runner.loop is not None:
        params["loop"] = runner.loop.cfg
    if runner.eraser is not None:
        params["eraser"] = runner.eraser.cfg
    return {"source": str(runner.source.path), "format": getattr(runner.source, "format", None),
            "command": " ".join(sys.argv), "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "camera": {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy},
            "metric": bool(vi or runner.cfg.gt_poses), "gravity_aligned": bool(vi),
            "stages": {"frontend": runner.frontend is not None, "imu": runner.vio is not None,
                       "loop": runner.loop is not None, "eraser": runner.eraser is not None},
            "params": _plain(params), "versions": versions()}


def depth_png(depth: np.ndarray) -> bytes:
    """Depth (m, 0 = empty) as a colour PNG: inverse depth through the turbo map, near bright;
    empty pixels black."""
    import cv2
    d = np.asarray(depth, np.float64)
    ok = d > 0
    img = np.zeros(d.shape + (3,), np.uint8)
    if ok.any():
        inv = 1.0 / d[ok]
        lo, hi = np.percentile(inv, [2, 98])
        v = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
        img[ok] = cv2.applyColorMap((v * 255).astype(np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0]
    return cv2.imencode(".png", img)[1].tobytes()


def normal_png(normal: np.ndarray) -> bytes:
    """Camera-frame unit normals as an RGB PNG (``(n + 1) / 2``; empty pixels black)."""
    import cv2
    n = np.asarray(normal, np.float32)
    ok = np.linalg.norm(n, axis=-1) > 0.5
    img = np.where(ok[..., None], np.round((n + 1) * 127.5), 0).astype(np.uint8)
    return cv2.imencode(".png", img[..., ::-1])[1].tobytes()


def rgb_png(rgb: np.ndarray) -> bytes:
    import cv2
    return cv2.imencode(".png", np.ascontiguousarray(np.asarray(rgb, np.uint8)[..., ::-1]))[1].tobytes()


def write_data(folder: Path, timeline: Optional[Timeline], info: dict, gt: Optional[Trajectory],
               views: list[dict]) -> None:
    """``timeline.jsonl``, ``run.json``, ``ground_truth.tum`` (when ``gt``) and ``views/`` into
    ``folder`` (the run's staging folder)."""
    folder = Path(folder)
    if timeline is not None:
        atomic_write_text(folder / TIMELINE_FILE, timeline.text())
    atomic_write_text(folder / RUN_INFO_FILE, json.dumps(info, indent=1, allow_nan=False) + "\n")
    if gt is not None and len(gt):
        write_tum(folder / GT_FILE, gt)
    index = []
    for v in views:
        s = int(v["stamp_ns"])
        atomic_write_bytes(folder / VIEWS_DIR / f"kf_{s}_input.png", rgb_png(v["input"]))
        atomic_write_bytes(folder / VIEWS_DIR / f"kf_{s}_depth.png", depth_png(v["depth"]))
        atomic_write_bytes(folder / VIEWS_DIR / f"kf_{s}_normal.png", normal_png(v["normal"]))
        fin = lambda x: float(x) if x is not None and np.isfinite(x) else None  # noqa: E731
        index.append({"stamp_ns": s, "psnr_db": fin(v.get("psnr_db")), "ssim": fin(v.get("ssim"))})
    if index:
        atomic_write_text(folder / VIEWS_DIR / VIEWS_INDEX, json.dumps({"views": index}, indent=1) + "\n")


def write_report(folder: Path, metrics: dict, gt: Optional[Trajectory], shown_folder: Optional[Path] = None) -> Path:
    """``bev.png`` (when the map has surfels) and ``report.html`` in ``folder`` (the staging folder;
    ``shown_folder``: the output folder the page names)."""
    data = load_run(folder, gt, metrics)
    bev = compute_bev(folder, data)
    if bev is not None:
        write_bev(folder / BEV_FILE, bev)
    return build_report(folder, gt=gt, metrics=metrics, bev=bev, data=data, shown_folder=shown_folder)
