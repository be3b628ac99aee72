"""The front end's checkpoint (vings_core/frontend/checkpoint.py): a front end restored from it
tracks on as the uninterrupted one, relocalises after a long gap, and bad files are clear errors."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from vings_core.errors import InputError
from vings_core.frontend import DISFlow, Frontend, FrontendConfig
from vings_core.frontend.checkpoint import (RestartMode, load_frontend_checkpoint, restart_policy,
                                            save_frontend_checkpoint)
from vings_core.types import Frame, TrackState

# the synthetic orbit of the front-end state tests (36 frames around a textured box)
from test_frontend_state import CAM, STEP_NS, _cfg, frames  # noqa: E402,F401  (a fixture)

CUT = 18


def _feed(fe: Frontend, frames) -> list[int]:
    kfs = []
    for f in frames:
        fe.process(f)
        kfs += [k.stamp_ns for k in fe.pop_keyframes()]
    return kfs


@pytest.fixture(scope="module")
def straight(frames):
    fe = Frontend(_cfg(), CAM)
    kfs = _feed(fe, frames) + [k.stamp_ns for k in fe.finish()]
    return fe, kfs


def _restore(tmp_path, frames, extra=None):
    fe = Frontend(_cfg(), CAM)
    before = _feed(fe, frames[:CUT])
    assert fe.state == TrackState.TRACKING
    size = save_frontend_checkpoint(tmp_path / "fe.ckpt", {"frontend": fe}, extra)
    assert size > 0 and not list(tmp_path.glob("*.tmp*"))
    ck = load_frontend_checkpoint(tmp_path / "fe.ckpt", _cfg(), DISFlow())
    return fe, ck, before


def test_a_restored_front_end_tracks_on_as_the_uninterrupted_one(tmp_path, frames, straight):
    ref, ref_kfs = straight
    _, ck, before = _restore(tmp_path, frames, extra={"note": [1, 2]})
    fe = ck.frontend
    assert ck.last_stamp_ns == frames[CUT - 1].stamp_ns and ck.extra == {"note": [1, 2]}
    assert fe is not None and fe.ctx.flow_est is not None and fe.state == TrackState.TRACKING
    fe.restarted(True, STEP_NS * 1e-9)
    after = _feed(fe, frames[CUT:]) + [k.stamp_ns for k in fe.finish()]
    assert before + after == ref_kfs
    a, b = ref.trajectory(), fe.trajectory()
    assert np.array_equal(a.stamps_ns, b.stamps_ns)
    assert np.abs(a.poses - b.poses).max() < 1e-6
    assert fe.segments() == ref.segments()


def test_after_a_long_gap_the_restored_front_end_relocalises_in_its_world_frame(tmp_path, frames, straight):
    ref, _ = straight
    _, ck, _ = _restore(tmp_path, frames)
    fe = ck.frontend
    skip = 4                          # frames the dead front end never saw
    first = frames[CUT + skip]
    mode = restart_policy((first.stamp_ns - ck.last_stamp_ns) * 1e-9, 0.1)
    assert mode is RestartMode.RELOCALISING
    fe.restarted(False, (first.stamp_ns - ck.last_stamp_ns) * 1e-9)
    assert fe.state == TrackState.LOST and "relocalising" in fe.reason
    _feed(fe, frames[CUT + skip:])
    assert fe.stats["relocalisations"] == 1 and fe.stats["segments"] == 1
    assert any("relocalised" in e for e in fe.events)
    # the same world frame and scale as the uninterrupted run (both from the same first segment)
    for f in frames[CUT + skip::4]:
        dp = np.linalg.norm(fe.pose(f.stamp_ns)[:3, 3] - ref.pose(f.stamp_ns)[:3, 3])
        assert dp < 0.02, (f.stamp_ns, dp)


def test_restart_policy_by_gap():
    assert restart_policy(0.05, 1.0) is RestartMode.RESUMED
    assert restart_policy(1.0, 1.0) is RestartMode.RESUMED
    assert restart_policy(1.5, 1.0) is RestartMode.RELOCALISING
    assert restart_policy(-1.0, 1.0) is RestartMode.RELOCALISING
    assert restart_policy(0.5, 0.0) is RestartMode.RELOCALISING


def test_bad_front_end_checkpoints_are_clear_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_frontend_checkpoint(tmp_path / "none.ckpt", _cfg(), DISFlow())
    (tmp_path / "junk.ckpt").write_bytes(b"junk")
    with pytest.raises(InputError, match="junk.ckpt: not a VINGS front-end checkpoint"):
        load_frontend_checkpoint(tmp_path / "junk.ckpt", _cfg(), DISFlow())
    (tmp_path / "other.ckpt").write_bytes(pickle.dumps({"format": "something else"}))
    with pytest.raises(InputError, match="not a VINGS front-end checkpoint"):
        load_frontend_checkpoint(tmp_path / "other.ckpt", _cfg(), DISFlow())
    (tmp_path / "v0.ckpt").write_bytes(pickle.dumps({"format": "vings-frontend-checkpoint", "version": 0}))
    with pytest.raises(InputError, match="version 0"):
        load_frontend_checkpoint(tmp_path / "v0.ckpt", _cfg(), DISFlow())


def test_a_visual_inertial_front_end_survives_its_checkpoint(tmp_path):
    """With the IMU fused: the smoother (GTSAM) and the IMU buffer (its lock) go through the file,
    and the restored front end takes IMU readings and tracks on in the same gravity-aligned frame."""
    from vings_core.io.base import SourceOptions
    from vings_core.pipeline import open_working_source
    from vings_core.sim import generate
    from vings_core.vio.config import ViConfig
    from vings_core.vio.fusion import ViFusion

    generate("room", tmp_path / "room", frames=70, seed=0, mcap=False)
    src = open_working_source(str(tmp_path / "room"), SourceOptions())
    cam = src.calibration.camera
    vio, _ = ViFusion.for_source(ViConfig(), src.calibration, True)
    fe = Frontend(FrontendConfig(), cam, vio=vio)
    items = list(src.stream())
    k = next(i for i, it in enumerate(items) if isinstance(it, Frame) and it.stamp_ns >= items[0].stamp_ns + 2.5e9)
    for it in items[:k]:
        if isinstance(it, Frame):
            fe.process(it)
            fe.pop_keyframes()
        else:
            fe.add_imu(it)
    assert fe.vio.status()["vi_state"] == "visual-inertial"
    save_frontend_checkpoint(tmp_path / "vi.ckpt", {"frontend": fe})
    fe2 = load_frontend_checkpoint(tmp_path / "vi.ckpt", FrontendConfig(), DISFlow()).frontend
    fe2.restarted(True, 0.05)
    for it in items[k:]:
        if isinstance(it, Frame):
            fe2.process(it)
            fe2.pop_keyframes()
        else:
            assert fe2.add_imu(it)
    st = fe2.status()
    assert st["vi_state"] == "visual-inertial" and fe2.state == TrackState.TRACKING
    gt = src.gt_camera_trajectory()
    est = fe2.trajectory(states=(TrackState.TRACKING,))
    last = est.stamps_ns[-1]
    i = int(np.argmin(np.abs(gt.stamps_ns - last)))
    # metric, gravity-aligned: the last pose is within decimetres of the truth (world frames of
    # the sim and the fusion differ by a yaw and an offset: compare the distance travelled)
    d_est = np.linalg.norm(est.poses[-1][:3, 3] - est.poses[0][:3, 3])
    j = int(np.argmin(np.abs(gt.stamps_ns - est.stamps_ns[0])))
    d_gt = np.linalg.norm(gt.poses[i][:3, 3] - gt.poses[j][:3, 3])
    assert abs(d_est - d_gt) < 0.1 * max(d_gt, 0.1), (d_est, d_gt)
