"""The report's plots (matplotlib, Agg backend), each returned as PNG bytes.

Positions are drawn in the plane of the bird's-eye view (:class:`~vings_core.report.bev.ViewBasis`)
in the run's frame and units: the ground truth is brought into the run's frame by the inverse of
the Sim(3) alignment the metrics use, so the map, the estimate and the truth share one picture.
"""
from __future__ import annotations

import io
from typing import Optional, Sequence

import numpy as np

from .bev import BevImage, ViewBasis

DPI = 80
STAGE_COLOURS = {"io": "#8c8c8c", "tracking": "#1f77b4", "eraser": "#d62728", "mapping": "#2ca02c",
                 "loop": "#9467bd"}


def _figure(w: float = 8.0, h: float = 4.5, ncols: int = 1):
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, ncols, figsize=(w, h), dpi=DPI, squeeze=False)
    return fig, ax[0]


def _png(fig) -> bytes:
    import matplotlib.pyplot as plt
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return buf.getvalue()


def trajectory_top(basis: ViewBasis, est: np.ndarray, gt: Optional[np.ndarray], bev: Optional[BevImage],
                   kf: Optional[np.ndarray] = None, loops: Sequence[tuple[np.ndarray, np.ndarray, bool]] = (),
                   unit: str = "run units") -> bytes:
    """The path from above over the map: estimate ``est`` ``(N, 3)``, aligned truth ``gt``
    ``(M, 3)`` (run frame), keyframes ``kf``, loop constraints ``(p_older, p_newer, accepted)``."""
    fig, (ax,) = _figure(8, 7)
    if bev is not None:
        ax.imshow(bev.rgb, extent=bev.extent, interpolation="nearest", alpha=0.9)
    if gt is not None and len(gt):
        g = basis.plane(gt)
        ax.plot(g[:, 0], g[:, 1], "-", color="#333333", lw=1.5, label="ground truth (aligned)")
    if len(est):
        e = basis.plane(est)
        ax.plot(e[:, 0], e[:, 1], "-", color="#1f77b4", lw=1.5, label="estimate")
        ax.plot(e[:1, 0], e[:1, 1], "o", color="#2ca02c", ms=7, label="start")
    if kf is not None and len(kf):
        k = basis.plane(kf)
        ax.plot(k[:, 0], k[:, 1], ".", color="#ff7f0e", ms=4, label="keyframes")
    for i, (a, b, ok) in enumerate(loops):
        p = basis.plane(np.stack([a, b]))
        ax.plot(p[:, 0], p[:, 1], "-" if ok else ":", color="#d62728" if ok else "#9467bd", lw=2,
                label=("loop accepted" if ok else "loop refused") if i == 0 or ok != loops[i - 1][2] else None)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"e1 [{unit}]")
    ax.set_ylabel(f"e2 [{unit}]")
    ax.set_title(f"trajectory from above (up: {basis.source.value})")
    ax.legend(loc="best", fontsize=8)
    return _png(fig)


def error_along_path(t_s: np.ndarray, err_m: np.ndarray, basis: ViewBasis, est: np.ndarray) -> bytes:
    """Position error after alignment (m) against time, and the path coloured by it."""
    fig, (a0, a1) = _figure(11, 4.2, 2)
    a0.plot(t_s, err_m, "-", color="#d62728", lw=1.2)
    a0.set_xlabel("time from the first frame [s]")
    a0.set_ylabel("position error [m]")
    a0.set_title(f"ATE along the path (RMSE {np.sqrt(np.mean(err_m ** 2)):.3g} m)")
    a0.grid(alpha=0.3)
    e = basis.plane(est)
    sc = a1.scatter(e[:, 0], e[:, 1], c=err_m, s=6, cmap="viridis")
    a1.set_aspect("equal", adjustable="datalim")
    a1.set_title("path coloured by error")
    fig.colorbar(sc, ax=a1, label="m")
    return _png(fig)


def rpe_per_length(rpe: dict) -> bytes:
    """RPE translation (%) and rotation (deg/m) per segment length."""
    per = rpe["per_length"]
    keys = list(per)
    fig, (a0, a1) = _figure(9, 3.6, 2)
    x = np.arange(len(keys))
    a0.bar(x, [per[k]["trans_pct"] for k in keys], color="#1f77b4")
    a1.bar(x, [per[k]["rot_deg_per_m"] for k in keys], color="#ff7f0e")
    for a, lab in ((a0, "translation error [%]"), (a1, "rotation error [deg/m]")):
        a.set_xticks(x, [f"{k} m" for k in keys])
        a.set_xlabel("segment length")
        a.set_ylabel(lab)
        a.grid(axis="y", alpha=0.3)
    a0.set_title(f"RPE, {rpe['pairs']} pairs{' (scale corrected)' if rpe.get('scale_corrected') else ''}")
    return _png(fig)


def gaussians_memory(timeline: list[dict]) -> bytes:
    """Gaussians (active, passive, on disk, total) and resident memory over the run."""
    t = np.array([ln["t_s"] for ln in timeline])
    fig, (ax,) = _figure(9, 4)
    for key, col in (("total", "#000000"), ("active", "#2ca02c"), ("passive", "#1f77b4"), ("on_disk", "#8c564b")):
        ax.plot(t, [ln["gaussians"].get(key, 0) for ln in timeline], "-", color=col, label=key, lw=1.3)
    ax.set_xlabel("wall time of the run [s]")
    ax.set_ylabel("Gaussians")
    ax.grid(alpha=0.3)
    rss = [ln.get("rss_mb") for ln in timeline]
    if any(r is not None for r in rss):
        a2 = ax.twinx()
        a2.plot(t, [np.nan if r is None else r for r in rss], "--", color="#d62728", label="resident memory", lw=1.2)
        a2.set_ylabel("resident memory [MiB]", color="#d62728")
        a2.legend(loc="lower right", fontsize=8)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("map size and memory per keyframe")
    return _png(fig)


def stage_times(timeline: list[dict]) -> bytes:
    """Stacked seconds per stage between consecutive keyframes."""
    fig, (ax,) = _figure(9, 4)
    x = np.arange(len(timeline))
    bottom = np.zeros(len(timeline))
    for stage, col in STAGE_COLOURS.items():
        v = np.array([ln.get("stage_s", {}).get(stage, 0.0) for ln in timeline])
        if v.any():
            ax.bar(x, v, bottom=bottom, color=col, label=stage, width=1.0)
            bottom += v
    ax.set_xlabel("keyframe")
    ax.set_ylabel("seconds since the previous keyframe")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("time per stage per keyframe")
    return _png(fig)


def masked_fraction(timeline: list[dict]) -> bytes:
    """The eraser's masked fraction per keyframe."""
    fig, (ax,) = _figure(9, 2.8)
    rows = [(ln["index"], ln["eraser"]["masked_fraction"]) for ln in timeline if ln.get("eraser")]
    if rows:
        i, f = np.array(rows).T
        ax.bar(i, 100 * f, color="#d62728", width=1.0)
    ax.set_xlabel("keyframe")
    ax.set_ylabel("masked [% of pixels]")
    ax.grid(axis="y", alpha=0.3)
    ax.set_title("dynamic eraser: masked fraction per keyframe")
    return _png(fig)
