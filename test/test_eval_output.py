"""The output contract of a SLAM run (vings_core.eval.output)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from vings_core.errors import InputError
from vings_core.eval.output import (METRIC_KEYS, RunOutput, metrics_template, peak_rss_mb,
                                    validate_metrics)
from vings_core.trajectory_io import read_tum
from vings_core.types import Trajectory

CONTRACT_KEYS = ["frames", "frames_tracked", "keyframes", "wall_s", "fps", "ate_sim3_m", "ate_se3_m",
                 "sim3_scale", "rpe", "psnr_keyframes_db", "psnr_novel_db", "ssim_keyframes",
                 "num_gaussians", "peak_rss_mb", "keyframes_light", "queue_peak_keyframes", "queue_spilled", "frames_unposed", "frames_unposed_reason", "segments", "ate_segments_m",
                 "vi_state", "vi_initialised_at_s", "scale_observable", "acc_bias", "gyro_bias", "td_s",
                 "td_estimates", "imu_only_frames", "vi_error",
                 "loops_accepted", "loop_candidates_rejected", "loop_detect_ms_mean",
                 "masked_fraction", "eraser_ms_mean", "eraser_error", "frames_bad"]


def test_metric_keys_are_the_contract():
    assert list(METRIC_KEYS) == CONTRACT_KEYS
    t = metrics_template()
    assert list(t) == CONTRACT_KEYS and all(v is None for v in t.values())


def test_write_metrics_fills_validates_and_is_json(tmp_path):
    out = RunOutput(tmp_path / "run")
    written = out.write_metrics({"frames": np.int64(100), "fps": np.float32(12.5), "wall_s": 8,
                                 "rpe": {"lengths_m": [5.0], "trans_pct": 1.2},
                                 "psnr_keyframes_db": float("inf")})
    d = json.loads(out.metrics_path.read_text())
    assert list(d) == CONTRACT_KEYS and d == written
    assert d["frames"] == 100 and d["fps"] == 12.5 and d["rpe"]["trans_pct"] == 1.2
    assert d["psnr_keyframes_db"] is None  # non-finite -> null
    assert d["keyframes"] is None and d["ate_sim3_m"] is None
    with pytest.raises(ValueError, match="unknown metrics key.*'ate'"):
        out.write_metrics({"ate": 1.0})
    with pytest.raises(ValueError, match="'rpe' must be a dict"):
        out.write_metrics({"rpe": 3.0})
    with pytest.raises(ValueError, match="'frames' must be an integer"):
        out.write_metrics({"frames": 2.5})
    with pytest.raises(ValueError, match="'fps' must be a number"):
        out.write_metrics({"fps": "fast"})
    with pytest.raises(ValueError, match="'scale_observable' must be true, false or None"):
        out.write_metrics({"scale_observable": 1})
    with pytest.raises(ValueError, match="'gyro_bias' must be a list"):
        out.write_metrics({"gyro_bias": 0.1})
    # failed writes left the old file intact and no temp files behind
    assert json.loads(out.metrics_path.read_text()) == written
    assert sorted(p.name for p in out.out_dir.iterdir()) == ["metrics.json"]


def test_update_metrics_merges(tmp_path):
    out = RunOutput(tmp_path)
    out.write_metrics({"frames": 10, "wall_s": 2.0})
    m = out.update_metrics({"ate_sim3_m": 0.1, "sim3_scale": 1.01})
    assert m["frames"] == 10 and m["ate_sim3_m"] == 0.1
    assert out.read_metrics() == m
    assert validate_metrics({}) == metrics_template()
    # numpy 0-d arrays (what np.mean(..., keepdims=False) of an array can give) are numbers
    assert validate_metrics({"frames": np.array(3), "ate_sim3_m": np.array(0.5),
                             "rpe": {"trans_pct": np.array(np.nan)}})["ate_sim3_m"] == 0.5
    # a folder without metrics.json holds no complete run: not silently marked complete
    with pytest.raises(InputError, match="no metrics.json"):
        RunOutput(tmp_path / "incomplete").update_metrics({"ate_sim3_m": 0.1})
    assert not (tmp_path / "incomplete" / "metrics.json").exists()
    # a hand-edited metrics.json with an unknown key: one-line error naming the file
    out.metrics_path.write_text('{"frames": 3, "notes": "x"}')
    with pytest.raises(InputError, match=r"metrics.json: unknown metrics key"):
        out.update_metrics({"ate_sim3_m": 0.1})


def test_trajectories_and_renders(tmp_path):
    out = RunOutput(tmp_path / "o")
    P = np.tile(np.eye(4), (3, 1, 1))
    P[:, 0, 3] = [0.0, 1.0, 2.0]
    traj = Trajectory(np.array([1, 2, 3], dtype=np.int64) * 10**9 + 123, P)
    out.write_trajectory(traj)
    out.write_keyframes(Trajectory(traj.stamps_ns[[0, 2]], P[[0, 2]]))
    back = read_tum(out.trajectory_path)
    np.testing.assert_array_equal(back.stamps_ns, traj.stamps_ns)
    np.testing.assert_allclose(back.poses, P, atol=1e-9)
    assert len(read_tum(out.keyframes_path)) == 2
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red
    p = out.save_render("kf_000001", rgb)
    assert p == out.renders_dir / "kf_000001.png"
    np.testing.assert_array_equal(cv2.imread(str(p))[..., ::-1], rgb)
    # float torch input in [0, 1], name with .png, mono
    p2 = out.save_render("novel.png", torch.full((6, 8, 3), 0.5))
    assert cv2.imread(str(p2))[0, 0, 0] == 128
    out.save_render("mono", np.ones((6, 8), np.float32))
    for bad in ("../x", "a/b", ""):
        with pytest.raises(InputError, match="plain file name"):
            out.save_render(bad, rgb)
    with pytest.raises(InputError, match="expected"):
        out.save_render("bad", np.zeros((6, 8, 4), np.uint8))
    # the contract: no placeholder map written by the output helper
    assert not out.map_path.exists()
    assert sorted(x.name for x in out.out_dir.iterdir()) == ["keyframes.tum", "renders", "trajectory.tum"]


def test_run_output_rejects_file_path(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        RunOutput(f)


def test_prepare_checks_the_folder_and_the_end_clears_a_previous_runs_marker(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="cannot write to the output folder"):
        RunOutput(f / "sub").prepare()          # found before any work, not at the end
    out = RunOutput(tmp_path / "o")
    out.write_metrics(metrics_template())
    out.save_render("kf_1", np.zeros((4, 4, 3), np.uint8))
    out.save_render("figure", np.zeros((4, 4, 3), np.uint8))
    (out.renders_dir / "notes.txt").write_text("mine")
    killed = out.out_dir / ".map.ply.k3j9x.tmp"   # a run killed while writing map.ply
    killed.write_bytes(b"half a map")
    out.prepare()                                # a new run into the same folder: nothing removed yet
    assert out.metrics_path.exists() and (out.renders_dir / "kf_1.png").exists()
    assert not killed.exists()                   # but the dead writer's temporary file is
    out.begin_final()                            # its final outputs come next
    assert not out.metrics_path.exists()         # no stale "complete run" marker
    assert sorted(p.name for p in out.renders_dir.iterdir()) == ["figure.png", "notes.txt"]


def test_outputs_get_the_umask_mode_not_0600(tmp_path):
    import os
    old = os.umask(0o022)
    os.umask(old)
    out = RunOutput(tmp_path / "o")
    out.write_metrics(metrics_template())
    assert out.metrics_path.stat().st_mode & 0o777 == 0o666 & ~old


def test_peak_rss_mb():
    """The process's peak RSS in MiB (the kernel's VmHWM, on Linux), and a child's peak added."""
    import subprocess
    import sys

    def status_mb(key: str) -> float:
        for line in open("/proc/self/status"):
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
        pytest.skip(f"no {key} in /proc/self/status here")
    a = peak_rss_mb()
    # touch enough to end 64 MiB above the earlier peak (the kernel may reclaim some of it at once,
    # e.g. with DAMON: the figure must follow VmHWM and never fall)
    big = np.ones(int((status_mb("VmHWM") - status_mb("VmRSS") + 64.0) * 2**20) // 8)
    hwm = status_mb("VmHWM")
    assert abs(peak_rss_mb() - hwm) <= 0.02 * hwm + 1.0 and peak_rss_mb() >= a
    del big
    child = "import numpy as np; a = np.ones(200 * 2**20 // 8); print(a.sum())"
    subprocess.run([sys.executable, "-c", child], check=True, capture_output=True)
    assert peak_rss_mb(include_children=True) >= peak_rss_mb() + 200


def test_failed_run_stops_the_mapper_instead_of_mapping_its_queue(tmp_path):
    """An input error (or Ctrl-C) in the middle of a concurrent `vings run`: the keyframes still
    queued for the mapper are dropped, not mapped first (a long run made the user wait minutes)."""
    from vings_core.errors import InputError as _IE
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    from vings_core.sim import generate
    generate("room", tmp_path / "room", frames=60, width=192, height=128, seed=5, mcap=False)
    p = tmp_path / "p.yaml"     # a slow mapper, so that keyframes queue up behind it
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 400\n"
                 "      points_per_keyframe: 1500\n")
    src = open_source(tmp_path / "room")
    frames = src.frames

    def failing_frames():
        for i, f in enumerate(frames()):
            if i == 56:
                raise _IE("frame 56: corrupt image (test)")
            yield f
    src.frames = failing_frames
    r = SlamRunner(src, tmp_path / "out", str(p), RunConfig(sync=False), progress=False)
    with pytest.raises(_IE, match="frame 56"):
        r.run()
    submitted, mapped = len(r._kf_stamps), len(r.mapper.keyframe_poses())
    assert submitted >= 3, submitted
    assert mapped < submitted, (mapped, submitted)
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_gt_poses_mode_never_extrapolates_or_bridges_gaps():
    """`vings run --gt-poses`: frames outside the ground truth's span or inside a gap in it get no
    pose (skipped with a warning), instead of a crash or an invented pose."""
    from vings_core.pipeline import RunConfig, _GtKeyframer
    from vings_core.types import Trajectory
    st = np.r_[np.arange(0, 10), np.arange(20, 30)].astype(np.int64) * 5_000_000   # 200 Hz, 50 ms gap
    poses = np.tile(np.eye(4), (len(st), 1, 1))
    poses[:, 0, 3] = st * 1e-9

    class _Src:
        path = "fake"

        def gt_camera_trajectory(self):
            return Trajectory(st, poses)
    k = _GtKeyframer(_Src(), RunConfig())
    T = k.pose(22_500_000)                        # between two samples 5 ms apart: interpolated
    assert T is not None and T[0, 3] == pytest.approx(0.0225)
    assert k.pose(75_000_000) is None             # inside the 50 ms gap
    assert k.pose(-50_000_000) is None and k.pose(400_000_000) is None    # outside the span
    assert k.pose(147_000_000) is not None        # 2 ms after the last sample: nearest within 10 ms


def _room_source(tmp_path, frames=24):
    from vings_core.io import open_source
    from vings_core.sim import generate
    d = tmp_path / f"room{frames}"
    if not d.exists():
        generate("room", d, frames=frames, width=192, height=128, seed=5, mcap=False)
    return open_source(d)


def _fast_params(tmp_path, iters=2):
    p = tmp_path / f"p{iters}.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: "
                 f"{iters}\n      points_per_keyframe: 1500\n      refine_iters: 2\n")
    return str(p)


def _failing(src, at):
    from vings_core.errors import InputError as _IE
    frames = src.frames

    def gen():
        for i, f in enumerate(frames()):
            if i == at:
                raise _IE(f"frame {at}: corrupt image (test)")
            yield f
    src.frames = gen
    return src


def _assert_metrics_match_the_files(out: Path, m: dict) -> None:
    """metrics.json describes the files beside it: trajectory and keyframe counts, the map's
    vertex count, the rate, and renders named after keyframe stamps."""
    from vings_core.mapping import read_ply
    from vings_core.trajectory_io import read_tum
    assert json.loads((out / "metrics.json").read_text()) == m
    traj, kfs = read_tum(out / "trajectory.tum"), read_tum(out / "keyframes.tum")
    assert m["frames_tracked"] == len(traj) > 0 and m["keyframes"] == len(kfs) > 0
    assert m["num_gaussians"] == len(read_ply(out / "map.ply")["x"]) > 0
    assert m["fps"] == pytest.approx(m["frames"] / m["wall_s"], rel=1e-9)
    renders = sorted((out / "renders").glob("kf_*.png"))
    assert renders and {int(p.stem[3:]) for p in renders} <= set(kfs.stamps_ns.tolist())
    assert set(kfs.stamps_ns.tolist()) <= set(traj.stamps_ns.tolist())


def test_failed_rerun_keeps_the_previous_complete_run(tmp_path, monkeypatch):
    """A second run into the same folder that fails part-way leaves the first run's outputs
    complete and readable (nothing removed up front), and writes its trajectory so far beside
    them; a later successful run replaces everything and removes the partial files, but not
    files of the user's in renders/."""
    from vings_core.pipeline import RunConfig, SlamRunner
    out = tmp_path / "out"
    cfg = RunConfig(sync=True, eval_keyframes=2, eval_novel=1, save_renders=2, checkpoint_every=1)
    first = SlamRunner(_room_source(tmp_path, 40), out, _fast_params(tmp_path), cfg, progress=False).run()
    _assert_metrics_match_the_files(out, first)
    (out / "renders" / "figure1.png").write_bytes(b"mine")
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    renders = sorted(p.name for p in (out / "renders").iterdir())
    assert {"metrics.json", "trajectory.tum", "keyframes.tum", "map.ply", "checkpoint.pt"} <= set(before)
    assert not (out / "checkpoint.partial.pt").exists()
    r = SlamRunner(_failing(_room_source(tmp_path, 40), 36), out, _fast_params(tmp_path), cfg, progress=False)
    with pytest.raises(InputError, match="frame 36"):
        r.run()
    for name, data in before.items():
        assert (out / name).read_bytes() == data, name
    assert sorted(p.name for p in (out / "renders").iterdir()) == renders
    assert json.loads((out / "metrics.json").read_text())["frames"] == first["frames"]
    part = (out / "trajectory.partial.tum").read_text().splitlines()
    assert 5 < len(part) <= 37 and len((out / "keyframes.partial.tum").read_text().splitlines()) > 1
    assert (out / "checkpoint.partial.pt").exists()     # the new run's map, as of a keyframe
    # a Ctrl-C (or disk full) while the final files are written: still nothing of the first run
    # replaced (they are staged, then renamed in place), and this run's trajectory so far is kept
    (out / "trajectory.partial.tum").unlink()
    from vings_core.mapping import Mapper
    real = Mapper.save_checkpoint

    def interrupted(self, path):
        if Path(path).name == "checkpoint.pt":
            raise KeyboardInterrupt
        return real(self, path)
    monkeypatch.setattr(Mapper, "save_checkpoint", interrupted)
    r = SlamRunner(_room_source(tmp_path, 40), out, _fast_params(tmp_path), cfg, progress=False)
    with pytest.raises(KeyboardInterrupt):
        r.run()
    monkeypatch.undo()
    for name, data in before.items():
        assert (out / name).read_bytes() == data, name
    assert sorted(p.name for p in (out / "renders").iterdir()) == renders
    assert (out / "trajectory.partial.tum").read_bytes() == before["trajectory.tum"]   # deterministic
    assert not (out / ".staging").exists()
    SlamRunner(_room_source(tmp_path, 40), out, _fast_params(tmp_path), cfg, progress=False).run()
    names = {p.name for p in out.iterdir()}
    assert not {n for n in names if ".partial." in n}, names
    assert (out / "renders" / "figure1.png").read_bytes() == b"mine"


def test_run_without_keyframes_still_creates_renders_folder(tmp_path):
    from vings_core.pipeline import RunConfig, SlamRunner
    src = _room_source(tmp_path, frames=2)
    m = SlamRunner(src, tmp_path / "o", _fast_params(tmp_path), RunConfig(sync=True), progress=False).run()
    assert m["keyframes"] == 0 and (tmp_path / "o" / "renders").is_dir()
    # still the whole contract: empty trajectories, a valid empty map, metrics with nulls
    from vings_core.mapping import read_ply
    o = tmp_path / "o"
    for name in ("trajectory.tum", "keyframes.tum"):     # no poses: comment lines at most
        assert all(ln.startswith("#") for ln in (o / name).read_text().splitlines()), name
    assert len(read_ply(o / "map.ply")["x"]) == 0
    assert json.loads((o / "metrics.json").read_text()) == m and m["psnr_keyframes_db"] is None
    assert (o / "checkpoint.pt").exists() and not list(o.glob("*.partial.*"))


def test_gt_poses_run_reports_no_ate_of_the_ground_truth_against_itself(tmp_path):
    from vings_core.pipeline import RunConfig, SlamRunner
    m = SlamRunner(_room_source(tmp_path), tmp_path / "o", _fast_params(tmp_path),
                   RunConfig(sync=True, gt_poses=True, eval_keyframes=1, eval_novel=1), progress=False).run()
    assert m["keyframes"] >= 2 and m["frames_tracked"] > 0
    assert m["ate_sim3_m"] is None and m["sim3_scale"] is None and m["rpe"] is None
    # the map renders the scene (a black or wrong render would be far below), novel views included
    assert m["psnr_keyframes_db"] > 18 and 0.3 < m["ssim_keyframes"] <= 1
    assert m["psnr_novel_db"] is not None and m["psnr_novel_db"] > 12


def test_ctrl_c_while_the_mapper_drains_its_queue_stops_it(tmp_path):
    """Ctrl-C after tracking ended, while the main thread waits for the mapper's backlog: the
    queue is dropped, the mapper thread has left before run() returns (else the interpreter
    aborts), and the trajectory so far is kept."""
    import threading
    import time
    from vings_core.pipeline import RunConfig, SlamRunner
    r = SlamRunner(_room_source(tmp_path, frames=40), tmp_path / "o", _fast_params(tmp_path, iters=300),
                   RunConfig(sync=False, checkpoint_every=0, max_mapper_lag=1000), progress=False)
    stop = r._stop_worker
    timers = []
    # the mapper starts only when tracking has ended, so a backlog is certain at the Ctrl-C (otherwise,
    # on a loaded machine, a GIL-starved front end can let the mapper catch up: nothing to drain)
    tracking_done = threading.Event()
    add = r.mapper.add_keyframe

    def gated_add(*a, **k):
        tracking_done.wait(120)
        return add(*a, **k)
    r.mapper.add_keyframe = gated_add

    def interrupted_wait(worker):
        r._stop_worker = stop       # one Ctrl-C only (the failure path waits again)
        tracking_done.set()
        wait = r._mapper_done.wait

        def ctrl_c_once(timeout=None):
            # Ctrl-C while the main thread waits for the backlog, at the point the signal lands
            # (a real SIGINT from a timer was dropped under CI load: the test must not depend on it)
            if not timers:
                timers.append(time.monotonic())
                time.sleep(0.5)
                raise KeyboardInterrupt
            return wait(timeout)
        r._mapper_done.wait = ctrl_c_once
        stop(worker)
    r._stop_worker = interrupted_wait
    with pytest.raises(KeyboardInterrupt):
        r.run()
    assert len(timers) == 1
    assert r._mapper_done.is_set() and r._abort
    assert len(r.mapper.keyframe_poses()) < len(r._kf_stamps)
    assert (tmp_path / "o" / "trajectory.partial.tum").exists()
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_user_error_in_the_mapper_thread_is_one_line(tmp_path, caplog, monkeypatch):
    """A VingsError raised in the concurrent mapper (disk full while checkpointing) reaches the
    caller unchanged, without a traceback in the log (as in --sync)."""
    from vings_core.errors import VingsError
    from vings_core.pipeline import RunConfig, SlamRunner
    r = SlamRunner(_room_source(tmp_path), tmp_path / "o", _fast_params(tmp_path),
                   RunConfig(sync=False, checkpoint_every=1), progress=False)

    def full(path):
        raise VingsError(f"{path}: no space left on device (test)")
    monkeypatch.setattr(r.mapper, "save_checkpoint", full)
    with caplog.at_level("DEBUG", logger="vings.run"):
        with pytest.raises(VingsError, match="no space left") as e:
            r.run()
    assert "mapper failed" not in str(e.value)
    assert not [rec for rec in caplog.records if rec.levelname == "ERROR"]


@pytest.mark.parametrize("sync", [True, False])
def test_a_bug_in_the_mapper_is_one_line_in_both_modes(tmp_path, caplog, monkeypatch, sync):
    """A non-VingsError in the mapper (a bug) is logged with its traceback and reaches the caller as
    one VingsError line, the same with --sync as with the mapper thread."""
    from vings_core.errors import VingsError
    from vings_core.pipeline import RunConfig, SlamRunner
    r = SlamRunner(_room_source(tmp_path), tmp_path / "o", _fast_params(tmp_path),
                   RunConfig(sync=sync), progress=False)

    def boom(*a, **k):
        raise RuntimeError("boom (test)")
    monkeypatch.setattr(r.mapper, "train", boom)
    with caplog.at_level("WARNING", logger="vings.run"):
        with pytest.raises(VingsError, match=r"mapper failed: RuntimeError: boom \(test\)"):
            r.run()
    errors = [rec for rec in caplog.records if rec.levelname == "ERROR"]
    assert len(errors) == 1 and errors[0].exc_info is not None        # the traceback, once
    assert not [rec for rec in caplog.records if "had stopped too" in rec.message]
    assert (tmp_path / "o" / "trajectory.partial.tum").exists()


def test_max_mapper_lag_makes_tracking_wait(tmp_path, monkeypatch):
    """With run.max_mapper_lag set, tracking waits once that many keyframes are queued."""
    import time as _time
    from vings_core.mapping import Mapper
    from vings_core.pipeline import RunConfig, SlamRunner
    r = SlamRunner(_room_source(tmp_path, 40), tmp_path / "o", _fast_params(tmp_path),
                   RunConfig(sync=False, max_mapper_lag=2, eval_keyframes=1, eval_novel=1), progress=False)
    seen = []
    real = Mapper.add_keyframe

    def slow(self, kf):
        seen.append(r._queue.keyframes)
        _time.sleep(0.3)
        return real(self, kf)
    monkeypatch.setattr(Mapper, "add_keyframe", slow)
    m = r.run()
    assert m["keyframes"] >= 4 and max(seen) <= 2, seen


def test_tracking_never_waits_and_queued_keyframes_spill_to_disk(tmp_path, monkeypatch):
    """Default concurrent mode: a slow mapper never holds tracking up; beyond
    queue_memory_keyframes the waiting keyframes go to disk, and every one is mapped."""
    import threading
    from vings_core.mapping import Mapper
    from vings_core.pipeline import RunConfig, SlamRunner
    r = SlamRunner(_room_source(tmp_path, 40), tmp_path / "o", _fast_params(tmp_path),
                   RunConfig(sync=False, queue_memory_keyframes=1, eval_keyframes=1, eval_novel=1),
                   progress=False)
    gate = threading.Event()
    mapped = []
    real = Mapper.add_keyframe

    def blocked(self, kf):
        gate.wait(60)           # the mapper is stuck until tracking has read every frame
        mapped.append(kf.stamp_ns)
        return real(self, kf)
    monkeypatch.setattr(Mapper, "add_keyframe", blocked)
    real_stop = SlamRunner._stop_worker
    seen = {}

    def stop(self, worker):     # tracking is done: every keyframe is queued or with the mapper
        seen["on_disk"] = self._queue.keyframes_on_disk
        seen["files"] = len(list((tmp_path / "o" / ".queue").glob("kf-*.pt")))
        gate.set()
        return real_stop(self, worker)
    monkeypatch.setattr(SlamRunner, "_stop_worker", stop)
    m = r.run()
    assert seen["on_disk"] >= 2 and seen["files"] == seen["on_disk"], seen
    assert m["queue_spilled"] >= 2 and m["queue_peak_keyframes"] >= 3
    assert sorted(mapped) == sorted(r._kf_stamps) and len(mapped) == m["keyframes"]
    assert not (tmp_path / "o" / ".queue").exists()


@pytest.mark.parametrize("field,value", [("gt_kf_max_gap", 0), ("gt_kf_trans_m", -0.1),
                                         ("gt_kf_rot_deg", float("nan")), ("gt_inv_depth_var", -5.0),
                                         ("checkpoint_every", -3), ("max_mapper_lag", -1)])
def test_run_config_refuses_nonsense(field, value):
    from vings_core.pipeline import RunConfig
    with pytest.raises(ValueError, match=field):
        RunConfig(**{field: value}).validate()


def test_keyframe_images_for_evaluation_stay_bounded_and_spread():
    """A long run holds at most 2 x eval_keyframes keyframe images, evenly spread over the run."""
    from types import SimpleNamespace
    from vings_core.pipeline import RunConfig, SlamRunner
    r = SlamRunner.__new__(SlamRunner)
    r.cfg, r._kf_images, r._kf_stride = RunConfig(eval_keyframes=5), {}, 1
    img = torch.zeros(2, 2, 3)
    for i in range(1000):
        r._keep_kf_image(i, SimpleNamespace(stamp_ns=10 * i, image=img))
        assert len(r._kf_images) <= 10
    idx = sorted(v[0] for v in r._kf_images.values())
    assert idx[0] == 0 and 1000 - idx[-1] <= r._kf_stride and len(idx) >= 5
    assert len(set(np.diff(idx))) == 1            # one stride: evenly spread
    r.cfg, r._kf_images = RunConfig(eval_keyframes=0), {}
    r._keep_kf_image(0, SimpleNamespace(stamp_ns=0, image=img))
    assert not r._kf_images


def test_prepare_removes_an_interrupted_earlier_runs_partial_files(tmp_path):
    out = RunOutput(tmp_path / "o")
    out.out_dir.mkdir()
    for name in ("checkpoint.partial.pt", "trajectory.partial.tum", "keyframes.partial.tum"):
        (out.out_dir / name).write_text("old")
    out.write_metrics(metrics_template())
    out.prepare()
    assert sorted(p.name for p in out.out_dir.iterdir()) == ["metrics.json", "renders"]


def test_a_run_with_a_covered_lens_writes_its_segments(tmp_path):
    """Tracking lost for a second (lens covered): segments.json and trajectory_segments/ hold each
    map segment, trajectory.tum the main one, metrics count them with an ATE each."""
    import json as _json
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    from vings_core.sim import generate
    from vings_core.trajectory_io import read_tum
    d = generate("room", tmp_path / "blind", frames=90, width=192, height=128, seed=5, mcap=False,
                 blind=(1.5, 2.5))
    out = tmp_path / "o"
    m = SlamRunner(open_source(d), out, _fast_params(tmp_path), RunConfig(sync=True, eval_keyframes=2,
                   eval_novel=2), progress=False).run()
    segs = _json.loads((out / "segments.json").read_text())["segments"]
    assert m["segments"] == len(segs) >= 2 and len(m["ate_segments_m"]) == len(segs)
    main = [s for s in segs if s["in_trajectory"]]
    assert len(main) == 1 and main[0]["frames"] == max(s["frames"] for s in segs) == m["frames_tracked"]
    for s in segs:
        t = read_tum(out / "trajectory_segments" / f"segment_{s['index']}.tum")
        assert len(t) == s["frames"] and t.stamps_ns[0] == s["first_stamp_ns"]
        assert s["joined_to"] is None
    assert len(read_tum(out / "trajectory.tum")) == main[0]["frames"]
    assert m["frames_unposed"] >= 20 and "frame" in m["frames_unposed_reason"]


def test_segments_joined_by_loops_are_one_trajectory():
    """Segment starts and the loop closer's joins -> which segment joined which, and the group of the
    main segment that trajectory.tum holds (joins chained through another segment count)."""
    from types import SimpleNamespace

    from vings_core.pipeline import SlamRunner
    starts = {0: 100, 1: 200, 2: 300, 3: 400}
    fe = SimpleNamespace(segment_starts=lambda: dict(starts),
                         segments=lambda: [{"index": k, "frames": f} for k, f in ((0, 50), (1, 80), (2, 10), (3, 30))])
    # segment 2 rejoined through a loop to a keyframe of segment 0, segment 1 to one of segment 2
    fake = SimpleNamespace(frontend=fe, loop=SimpleNamespace(joins={300: 150, 200: 350}))
    fake.main_segment = lambda: SlamRunner.main_segment(fake)
    fake.segment_joins = lambda: SlamRunner.segment_joins(fake)
    assert fake.main_segment() == 1
    assert SlamRunner.segment_joins(fake) == {2: 0, 1: 2}
    assert SlamRunner.trajectory_segments(fake) == {0, 1, 2}
    fake.loop.joins = {}
    assert SlamRunner.trajectory_segments(fake) == {1}
