"""Front end on real and simulated recordings (static EuRoC excerpt: fast; the rest: slow)."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_path
from vings_core.frontend import Frontend, FrontendConfig


def _run(src, cfg=None, max_frames=None):
    fe = Frontend(cfg or FrontendConfig(), src.calibration.camera)
    kfs = []
    for k, frame in enumerate(src.frames()):
        if max_frames is not None and k >= max_frames:
            break
        fe.process(frame)
        kfs.extend(fe.pop_keyframes())
    kfs.extend(fe.finish())
    return fe, kfs


def _ate(fe, src):
    from vings_core.eval.traj import associate, ate
    e, g = associate(fe.trajectory(states=("tracking",)), src.gt_camera_trajectory(), 5_000_000)
    return ate(e, g, mode="sim3")["rmse_m"], g.path_length(), len(e)


def test_static_euroc_excerpt_never_initialises():
    from vings_core.io import SourceOptions, open_source
    src = open_source(shared_path("euroc_v101_micro"), SourceOptions(width=376, height=240))
    fe, kfs = _run(src)
    states = set(fe.frame_states().values())
    assert states == {"waiting"}
    assert kfs == [] and fe.stats["keyframes"] == 0
    assert fe.state == "waiting" and "no motion" in fe.reason
    assert not fe.motion_detected
    assert np.allclose(fe.trajectory().poses, np.eye(4))
    assert len(fe.trajectory()) == len(src.frame_stamps())


@pytest.mark.slow
def test_kitti06_snippet_accuracy():
    from vings_core.io import SourceOptions, open_source
    src = open_source(shared_path("kitti06_snippet"), SourceOptions(width=613, height=185))
    fe, _ = _run(src)
    rmse, path, n = _ate(fe, src)
    assert n == len(src.frame_stamps())          # runs to the end, every frame tracked
    assert rmse <= 0.15, rmse


@pytest.mark.slow
def test_synthetic_room_accuracy(tmp_path):
    from scipy.stats import spearmanr
    from vings_core.io import open_source
    from vings_core.sim import generate
    out = generate("room", tmp_path / "room", frames=150, width=376, height=240, mcap=False)
    src = open_source(out)
    fe, kfs = _run(src)
    rmse, path, n = _ate(fe, src)
    assert n == 150 and rmse <= 0.01 * path, (rmse, path)
    rel, std, err, nval, npx = [], [], [], 0, 0
    for kf in kfs:
        gt = src.gt_depth(kf.stamp_ns)
        v = kf.valid.numpy() & (gt > 0)
        d = kf.depth.numpy()
        s = np.median(gt[v] / d[v])
        rel.append(np.abs(s * d[v] - gt[v]) / gt[v])
        std.append(np.sqrt(kf.inv_depth_var.numpy()[v]) / s)
        err.append(np.abs(1 / (s * d[v]) - 1 / gt[v]))
        nval += v.sum()
        npx += v.size
    assert np.median(np.concatenate(rel)) <= 0.05
    assert nval / npx >= 0.6
    assert spearmanr(np.concatenate(std), np.concatenate(err))[0] >= 0.3
