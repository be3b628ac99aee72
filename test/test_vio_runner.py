"""The IMU of a simulated recording fused end to end: the front end goes metric and
gravity-aligned, the alignment's similarity reaches the pose exchange, and `vings run` reports it
(the full run is slow: marked)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from vings_core.eval.traj import associate, ate


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from vings_core.sim import generate
    d = tmp_path_factory.mktemp("vio") / "room"
    generate("room", d, frames=60, width=376, height=240, seed=0, mcap=False)
    return d


def _gravity_err_deg(est, gt) -> float:
    e, g = associate(est, gt, max_dt_ns=5_000_000)
    z = np.array([0.0, 0.0, -1.0])
    return float(np.median([np.degrees(np.arccos(np.clip((Pe[:3, :3].T @ z) @ (Pg[:3, :3].T @ z), -1, 1)))
                            for Pe, Pg in zip(e.poses, g.poses)]))


def test_fused_front_end_is_metric_gravity_aligned_and_hands_its_similarity_on(room):
    from vings_core.frontend import Frontend, FrontendConfig
    from vings_core.io import open_source
    from vings_core.types import Frame
    from vings_core.vio.config import ViConfig
    from vings_core.vio.fusion import ViFusion, ViState
    src = open_source(room)
    vio, why = ViFusion.for_source(ViConfig(), src.calibration, True)
    assert vio is not None, why
    fe = Frontend(FrontendConfig(), src.calibration.camera, vio=vio)
    sims, emitted, batches = {}, [], []
    for item in src.stream():
        if isinstance(item, Frame):
            fe.process(item)
            emitted += [k.stamp_ns for k in fe.pop_keyframes()]
            batch = fe.take_similarities()
            if batch:
                batches.append(batch)
            sims.update(batch)
        else:
            fe.add_imu(item)
    assert vio.state == ViState.VISUAL_INERTIAL, vio.reason
    assert 0.5 < (vio.initialised_at_ns - src.frame_stamps()[0]) * 1e-9 < 2.0
    assert fe.status()["segments"] == 1
    gt = src.gt_camera_trajectory()
    e, g = associate(fe.trajectory(states=("tracking",)), gt, max_dt_ns=5_000_000)
    a = ate(e, g, "sim3")
    assert abs(a["scale"] - 1.0) < 0.02                      # metric
    assert ate(e, g, "se3")["rmse_m"] < 0.01                  # no scale needed to fit the truth
    assert _gravity_err_deg(fe.trajectory(states=("tracking",)), gt) < 0.5
    # the alignment similarity of every keyframe made before it, for the followers
    assert sims and all(s in sims for s in emitted[:2])
    # the first batch: the alignment's similarity (composed with the smoother's first write-back,
    # made in the same keyframe), scale about the alignment's
    scale = lambda M: float(np.cbrt(np.linalg.det(M[:3, :3])))  # noqa: E731
    assert all(abs(scale(M) / vio.alignment.scale - 1.0) < 0.05 for M in batches[0].values())
    # later batches: the smoother's window moves, as similarities with small scale corrections
    assert len(batches) > 1
    assert all(abs(scale(M) - 1.0) < 0.05 for b in batches[1:] for M in b.values())
    st = fe.status()
    assert st["vi_state"] == "visual-inertial" and len(st["gyro_bias"]) == 3
    # odometry twist of a late frame, in the camera frame, against finite differences of the truth
    stamps = gt.stamps_ns
    k = int(np.searchsorted(stamps, src.frame_stamps()[-3]))
    s = int(stamps[k])
    v_c, w_c, cov = vio.twist(s, fe.pose(s))
    assert cov.shape == (6, 6) and np.all(np.diag(cov) > 0) and np.allclose(cov, cov.T)
    dt = (stamps[k + 1] - stamps[k - 1]) * 1e-9
    R = gt.poses[k][:3, :3]
    v_true = R.T @ (gt.poses[k + 1][:3, 3] - gt.poses[k - 1][:3, 3]) / dt
    from scipy.spatial.transform import Rotation
    w_true = Rotation.from_matrix(gt.poses[k - 1][:3, :3].T @ gt.poses[k + 1][:3, :3]).as_rotvec() / dt
    assert np.linalg.norm(v_c - v_true) < 0.1 * np.linalg.norm(v_true) + 0.02
    assert np.linalg.norm(w_c - w_true) < 0.1 * np.linalg.norm(w_true) + 0.02


def test_without_fusion_the_same_recording_has_an_arbitrary_scale(room):
    from vings_core.frontend import Frontend, FrontendConfig
    from vings_core.io import open_source
    src = open_source(room)
    fe = Frontend(FrontendConfig(), src.calibration.camera)
    for f in src.frames():
        fe.process(f)
        fe.pop_keyframes()
    e, g = associate(fe.trajectory(states=("tracking",)), src.gt_camera_trajectory(), max_dt_ns=5_000_000)
    assert abs(ate(e, g, "sim3")["scale"] - 1.0) > 0.2
    assert fe.status()["vi_state"] == "visual-only" and fe.take_similarities() == {}


def _run(room, out, enabled: bool):
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    from vings_core.vio.config import ViConfig
    out.parent.mkdir(parents=True, exist_ok=True)
    p = out.parent / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 5\n")
    r = SlamRunner(open_source(room), out, str(p), RunConfig(sync=True, eval_novel=0, eval_keyframes=4),
                   progress=False, vio_cfg=ViConfig(enabled=enabled))
    r.run()
    return r, json.loads((out / "metrics.json").read_text())


@pytest.mark.slow
def test_vings_run_fuses_the_imu_and_the_map_follows_the_alignment(room, tmp_path):
    r, m = _run(room, tmp_path / "vio", True)
    assert m["vi_state"] == "visual-inertial" and m["scale_observable"] is True
    assert 0.5 < m["vi_initialised_at_s"] < 3.5
    assert abs(m["sim3_scale"] - 1.0) < 0.02 and m["ate_se3_m"] < 0.01
    assert len(m["gyro_bias"]) == 3 and len(m["acc_bias"]) == 3 and m["td_s"] == 0.0
    # the Gaussians were moved and scaled with the poses: the keyframes render as well as
    # without the IMU
    _, m0 = _run(room, tmp_path / "vo", False)
    assert m0["vi_state"] == "visual-only" and m0["scale_observable"] is False
    assert m0["vi_initialised_at_s"] is None and m0["gyro_bias"] is None
    assert m["psnr_keyframes_db"] > m0["psnr_keyframes_db"] - 1.5


def _run(path, opts=None):
    from vings_core.frontend import Frontend, FrontendConfig
    from vings_core.io import open_source
    from vings_core.types import Frame
    from vings_core.vio.config import ViConfig
    from vings_core.vio.fusion import ViFusion
    src = open_source(path, opts) if opts is not None else open_source(path)
    vio, why = ViFusion.for_source(ViConfig(), src.calibration, True)
    assert vio is not None, why
    fe = Frontend(FrontendConfig(), src.calibration.camera, vio=vio)
    modes = []
    for item in src.stream():
        if isinstance(item, Frame):
            fe.process(item)
            fe.pop_keyframes()
            modes.append(vio.status()["vi_state"])
        else:
            fe.add_imu(item)
    fe.finish()
    return src, fe, vio, modes


def test_a_vision_outage_is_bridged_by_the_imu_in_the_same_world_frame(tmp_path):
    from vings_core.sim import generate
    from vings_core.types import POSED_STATES, TrackState
    d = generate("room", tmp_path / "blind", frames=90, width=376, height=240, seed=1, mcap=False,
                 blind=(3.5, 4.0))
    src, fe, vio, modes = _run(d)
    states = fe.frame_states()
    blind = [s for s in states if 3.5 <= (s - src.frame_stamps()[0]) * 1e-9 < 4.0 - 1e-6]
    assert len(blind) == 10
    assert all(states[s] == TrackState.INERTIAL for s in blind)        # posed by the IMU alone
    assert modes.count("imu-only") == 10
    assert len(fe.segments()) == 1                                     # same world frame
    assert all(v in POSED_STATES for v in states.values())
    assert any("IMU-propagated" in e for e in fe.events)
    # the IMU-only poses stay near the truth (the whole run aligned with SE(3): metric frame)
    gt = src.gt_camera_trajectory()
    e, g = associate(fe.trajectory(states=POSED_STATES), gt, max_dt_ns=5_000_000)
    from vings_core.eval.align import umeyama
    _, R, t = umeyama(e.poses[:, :3, 3], g.poses[:, :3, 3], with_scale=False)
    err = np.linalg.norm((R @ e.poses[:, :3, 3].T).T + t - g.poses[:, :3, 3], axis=1)
    in_blind = np.isin(e.stamps_ns, blind)
    assert err[in_blind].max() < 0.05, err[in_blind].max()
    # the odometry covariance says the pose came from the IMU: it grows through the outage
    covs = [fe.buffer._records[s].covariance for s in blind]
    assert all(c is not None for c in covs)
    assert np.trace(covs[-1][:3, :3]) > np.trace(covs[0][:3, :3])


def test_standstill_on_real_euroc_poses_every_frame_gravity_aligned_without_scale():
    from pathlib import Path
    from vings_core.io import SourceOptions
    from vings_core.types import POSED_STATES
    d = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc_v101_micro"
    if not d.exists():
        pytest.skip(f"{d} not here")
    src, fe, vio, modes = _run(d, SourceOptions(width=376, height=240))
    traj = fe.trajectory(states=POSED_STATES)
    assert len(traj) == len(src.frame_stamps()) == 95                 # every frame posed
    assert modes.count("standstill") >= 80
    assert vio.initialised_at_ns is None                                # no scale claimed
    p = traj.poses[:, :3, 3]
    assert np.linalg.norm(p - p[0], axis=1).max() < 0.01                # zero velocity
    assert _gravity_err_deg(traj, src.gt_camera_trajectory()) < 1.0
