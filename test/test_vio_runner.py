"""`vings run` with the IMU of a simulated recording: the fusion goes metric and gravity-aligned,
the map follows the alignment, and ``--no-imu`` stays visual-only."""
from __future__ import annotations

import json

import numpy as np
import pytest

from vings_core.eval.traj import associate, ate


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from vings_core.sim import generate
    d = tmp_path_factory.mktemp("vio") / "room"
    generate("room", d, frames=70, width=192, height=128, seed=5, mcap=False)
    return d


def _run(room, out, enabled: bool):
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    from vings_core.vio.config import ViConfig
    p = out.parent / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 10\n")
    r = SlamRunner(open_source(room), out, str(p), RunConfig(sync=True, eval_novel=0), progress=False,
                   vio_cfg=ViConfig(enabled=enabled))
    r.run()
    return r, json.loads((out / "metrics.json").read_text())


def test_fused_run_is_metric_and_gravity_aligned_and_the_map_follows(room, tmp_path):
    r, m = _run(room, tmp_path / "vio", True)
    assert m["vi_state"] == "visual-inertial" and m["scale_observable"] is True
    assert 0.5 < m["vi_initialised_at_s"] < 3.0
    assert abs(m["sim3_scale"] - 1.0) < 0.03                  # metric
    assert m["ate_se3_m"] < 0.02                              # no scale needed to fit the truth
    assert len(m["gyro_bias"]) == 3 and len(m["acc_bias"]) == 3
    # gravity: the estimated world z axis is the true one (the simulator's world is z-up)
    gt = r.source.gt_camera_trajectory()
    e, g = associate(r.trajectory(), gt, max_dt_ns=5_000_000)
    z = np.array([0.0, 0.0, -1.0])
    ang = [np.degrees(np.arccos(np.clip((Pe[:3, :3].T @ z) @ (Pg[:3, :3].T @ z), -1, 1)))
           for Pe, Pg in zip(e.poses, g.poses)]
    assert np.median(ang) < 1.0
    # the map was scaled with the poses (its keyframes render as well as a visual-only map's)
    assert m["psnr_keyframes_db"] > 20.0
    assert ate(e, g, "se3")["rmse_m"] == pytest.approx(m["ate_se3_m"], rel=1e-6)


def test_no_imu_stays_visual_only(room, tmp_path):
    _, m = _run(room, tmp_path / "vo", False)
    assert m["vi_state"] == "visual-only" and m["scale_observable"] is False
    assert m["vi_initialised_at_s"] is None and m["gyro_bias"] is None
    assert abs(m["sim3_scale"] - 1.0) > 0.2                   # the arbitrary monocular scale
