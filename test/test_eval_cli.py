"""`vings eval` end to end through vings_ros.cli.main."""
from __future__ import annotations

import json

import numpy as np
import pytest

from vings_core.eval.align import apply_sim3
from vings_core.eval.output import RunOutput
from vings_core.geometry import np_pose_inverse, np_so3_exp
from vings_core.trajectory_io import write_tum
from vings_core.types import Trajectory
from vings_ros.cli import main

from test_eval_traj import sim3_copy, wavy


def run_json(capsys, argv):
    rc = main(argv + ["--json"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    last = cap.out.strip().splitlines()[-1]
    return json.loads(last)


def run_err(capsys, argv):
    rc = main(argv)
    cap = capsys.readouterr()
    assert rc == 2
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vings eval: error: "), cap.err
    assert "Traceback" not in cap.err
    return lines[0]


@pytest.fixture
def trajs(tmp_path):
    gt = wavy(300)
    est = sim3_copy(gt, 2.5, [0.3, 0.2, -0.8], [3.0, 1.0, -2.0])
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", est)
    return tmp_path, gt, est


def test_cli_self_and_sim3_copy(capsys, trajs):
    d, gt, _ = trajs
    r = run_json(capsys, ["eval", str(d / "gt.tum"), "--gt", str(d / "gt.tum")])
    assert r["ate_sim3_m"] < 1e-6 and r["ate_se3_m"] < 1e-6 and r["matched_poses"] == 300
    r = run_json(capsys, ["eval", str(d / "est.tum"), "--gt", str(d / "gt.tum")])
    assert r["ate_sim3_m"] < 1e-6
    assert r["sim3_scale"] == pytest.approx(0.4, rel=1e-6)
    assert r["ate_se3_m"] > 0.5
    assert r["gt_source"] == "tum" and r["gt_frame"] == "camera"
    assert set(r["rpe"]["per_length"]) == {f"{L:g}" for L in r["rpe"]["lengths_m"]}
    # human-readable output
    assert main(["eval", str(d / "est.tum"), "--gt", str(d / "gt.tum")]) == 0
    out = capsys.readouterr().out
    assert "ATE Sim(3)" in out and "scale 0.4" in out


def test_cli_options(capsys, trajs):
    d, gt, _ = trajs
    off = Trajectory(gt.stamps_ns + 4_000_000, gt.poses)
    write_tum(d / "off.tum", off)
    r = run_json(capsys, ["eval", str(d / "off.tum"), "--gt", str(d / "gt.tum"), "--rpe-lengths", "1,2"])
    assert r["max_match_dt_ms"] == pytest.approx(4.0) and r["rpe"]["lengths_m"] == [1.0, 2.0]
    msg = run_err(capsys, ["eval", str(d / "off.tum"), "--gt", str(d / "gt.tum"), "--max-dt-ms", "3"])
    assert "too few matched poses" in msg and "3 ms" in msg
    msg = run_err(capsys, ["eval", str(d / "off.tum"), "--gt", str(d / "gt.tum"), "--rpe-lengths", "a,b"])
    assert "--rpe-lengths" in msg


def test_cli_errors(capsys, trajs):
    d, gt, _ = trajs
    assert "nope.tum: estimated trajectory not found" in run_err(
        capsys, ["eval", str(d / "nope.tum"), "--gt", str(d / "gt.tum")])
    assert "ground truth not found" in run_err(capsys, ["eval", str(d / "est.tum"), "--gt", str(d / "x.tum")])
    assert "--gt is required" in run_err(capsys, ["eval", str(d / "est.tum")])
    assert "nothing to evaluate" in run_err(capsys, ["eval"])
    write_tum(d / "late.tum", Trajectory(gt.stamps_ns + 10**13, gt.poses))
    assert "no overlap in time" in run_err(capsys, ["eval", str(d / "late.tum"), "--gt", str(d / "gt.tum")])
    (d / "bad.tum").write_text("1.0 2 3\n")
    assert "bad.tum:1: expected 8 columns" in run_err(capsys, ["eval", str(d / "bad.tum"), "--gt", str(d / "gt.tum")])
    (d / "poses.txt").write_text(" ".join(["1"] * 12) + "\n")
    assert "KITTI poses file" in run_err(capsys, ["eval", str(d / "est.tum"), "--gt", str(d / "poses.txt")])
    write_tum(d / "two.tum", Trajectory(gt.stamps_ns[:2], gt.poses[:2]))
    assert "too few matched poses" in run_err(capsys, ["eval", str(d / "two.tum"), "--gt", str(d / "gt.tum")])
    assert "needs --calib" in run_err(capsys, ["eval", str(d / "est.tum"), "--gt", str(d / "gt.tum"),
                                               "--gt-frame", "body"])
    assert "calibration file not found" in run_err(
        capsys, ["eval", str(d / "est.tum"), "--gt", str(d / "gt.tum"), "--gt-frame", "body", "--calib",
                 str(d / "none.yaml")])
    assert "needs ESTIMATE to be a run output folder" in run_err(
        capsys, ["eval", str(d / "est.tum"), "--gt", str(d / "gt.tum"), "--write-metrics"])
    assert "has no trajectory.tum" in run_err(capsys, ["eval", str(d), "--gt", str(d / "gt.tum")])
    (d / "bin.tum").write_bytes(b"# header\n\x7fELF\xf0\x9f\xff binary")
    assert "bin.tum: not UTF-8 text" in run_err(
        capsys, ["eval", str(d / "bin.tum"), "--gt", str(d / "gt.tum")])
    assert "cannot read" in run_err(capsys, ["eval", str(d / "est.tum"), "--gt", "/proc/self/mem"])


def test_cli_body_ground_truth_with_calib(capsys, tmp_path):
    from vings_core.io.calib_yaml import save_calibration_yaml
    from vings_core.types import Calibration, CameraModel

    T_bc = np.eye(4)
    T_bc[:3, :3] = np_so3_exp(np.array([1.2, -1.2, 1.2]))
    T_bc[:3, 3] = [0.05, -0.02, 0.1]
    cam = wavy(200)
    body = cam.right_multiply(np_pose_inverse(T_bc))  # T_wb = T_wc T_cb
    write_tum(tmp_path / "body.tum", body)
    write_tum(tmp_path / "cam.tum", cam)
    save_calibration_yaml(tmp_path / "calib.yaml", Calibration(CameraModel(64, 48, 50, 50, 32, 24), T_bc=T_bc))
    r = run_json(capsys, ["eval", str(tmp_path / "cam.tum"), "--gt", str(tmp_path / "body.tum"),
                          "--gt-frame", "body", "--calib", str(tmp_path / "calib.yaml")])
    assert r["ate_se3_m"] < 1e-6 and r["gt_frame"] == "body"
    # without the extrinsic the body trajectory differs from the camera's
    r = run_json(capsys, ["eval", str(tmp_path / "cam.tum"), "--gt", str(tmp_path / "body.tum")])
    assert r["ate_se3_m"] > 1e-3
    # --calib alone does not make a TUM file body poses: said on stderr, not silently ignored
    assert main(["eval", str(tmp_path / "cam.tum"), "--gt", str(tmp_path / "body.tum"), "--json",
                 "--calib", str(tmp_path / "calib.yaml")]) == 0
    assert "--gt-frame body" in capsys.readouterr().err


def test_cli_dataset_body_ground_truth_needs_a_known_extrinsic(capsys, tmp_path):
    """A dataset whose ground truth is of the body but which gives no T_bc (here a TUM RGB-D
    folder, forced to body, and a EuRoC folder without T_BS) is refused like a TUM file without
    --calib, not evaluated through an identity extrinsic."""
    from fixtures_io import T_BC, make_euroc, make_tum

    tum = make_tum(tmp_path / "rgbd_dataset_freiburg1_xyz", n=4)
    write_tum(tmp_path / "est.tum", open_source_gt(tum))
    assert "no camera-to-body extrinsic T_bc" in run_err(
        capsys, ["eval", str(tmp_path / "est.tum"), "--gt", str(tum), "--gt-frame", "body"])
    eu = make_euroc(tmp_path / "eu", n=4)
    y = eu / "mav0/cam0/sensor.yaml"
    y.write_text("\n".join(ln for ln in y.read_text().splitlines()
                           if not ln.startswith(("T_BS", "  cols", "  rows", "  data"))) + "\n")
    cam = open_source_gt(eu).right_multiply(T_BC)          # the true cam0 poses
    write_tum(tmp_path / "est_eu.tum", cam)
    assert "--calib FILE" in run_err(capsys, ["eval", str(tmp_path / "est_eu.tum"), "--gt", str(eu)])
    (tmp_path / "c.yaml").write_text("T_bc: " + str([[float(v) for v in r] for r in T_BC]) + "\n")
    r = run_json(capsys, ["eval", str(tmp_path / "est_eu.tum"), "--gt", str(eu), "--calib", str(tmp_path / "c.yaml")])
    assert r["gt_frame"] == "body" and r["ate_se3_m"] < 1e-6


def test_cli_bag_ground_truth_takes_the_source_topic_options(capsys, tmp_path):
    """The bag reader's own errors point at --imu-topic / --camera-info-topic: eval has them."""
    from fixtures_io import BagSpec, make_bag
    bag = make_bag(tmp_path / "two.mcap", BagSpec(imu_topics=("/imu0", "/imu1"), gt_topic="/gt", n_images=6))
    write_tum(tmp_path / "est.tum", open_source_gt(bag, imu_topic="/imu0", gt_topic="/gt"))
    assert "choose one with --imu-topic" in run_err(
        capsys, ["eval", str(tmp_path / "est.tum"), "--gt", str(bag), "--gt-topic", "/gt", "--gt-frame", "camera"])
    r = run_json(capsys, ["eval", str(tmp_path / "est.tum"), "--gt", str(bag), "--gt-topic", "/gt",
                          "--gt-frame", "camera", "--imu-topic", "/imu0", "--camera-info-topic", "/cam0/camera_info"])
    assert r["ate_se3_m"] < 1e-9 and r["gt_frame"] == "camera"


def open_source_gt(root, **options):
    from vings_core.io import SourceOptions, open_source
    return open_source(root, SourceOptions(**options)).ground_truth


def test_cli_run_folder_write_metrics(capsys, trajs):
    d, gt, est = trajs
    out = RunOutput(d / "run")
    out.write_trajectory(est)
    out.write_metrics({"frames": 300, "wall_s": 10.0})
    r = run_json(capsys, ["eval", str(d / "run"), "--gt", str(d / "gt.tum"), "--write-metrics"])
    m = out.read_metrics()
    assert m["frames"] == 300 and m["ate_sim3_m"] == pytest.approx(r["ate_sim3_m"])
    assert m["sim3_scale"] == pytest.approx(0.4) and m["rpe"] == r["rpe"]


def test_cli_images(capsys, tmp_path):
    import cv2
    import skimage.data

    a_dir, b_dir = tmp_path / "a", tmp_path / "b"
    a_dir.mkdir()
    b_dir.mkdir()
    img = skimage.data.astronaut()[::8, ::8]  # 64x64 RGB
    rng = np.random.default_rng(0)
    for i in range(3):
        noisy = np.clip(img.astype(int) + rng.integers(-20, 21, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(a_dir / f"{i:03d}.png"), noisy[..., ::-1])
        cv2.imwrite(str(b_dir / f"{i:03d}.png"), img[..., ::-1])
    cv2.imwrite(str(a_dir / "extra.png"), img[..., ::-1])
    r = run_json(capsys, ["eval", "--images", str(a_dir), str(b_dir)])
    im = r["images"]
    assert im["images"] == 3 and im["only_in_first"] == 1 and im["lpips"] is None
    assert 20 < im["psnr_db"] < 30 and 0 < im["ssim"] < 1
    from vings_core.eval.image import psnr
    a0 = cv2.imread(str(a_dir / "000.png"))[..., ::-1]
    assert im["per_image"][0]["psnr_db"] == pytest.approx(psnr(a0, img))
    # identical folders: PSNR inf is reported as identical, JSON stays valid
    r = run_json(capsys, ["eval", "--images", str(b_dir), str(b_dir)])
    assert r["images"]["identical_images"] == 3 and r["images"]["psnr_db"] is None
    assert r["images"]["ssim"] == pytest.approx(1.0)
    # LPIPS with a local weights file
    from test_eval_image import _random_weights
    _random_weights("alex", tmp_path / "w.pth")
    r = run_json(capsys, ["eval", "--images", str(a_dir), str(b_dir), "--lpips-weights", str(tmp_path / "w.pth")])
    assert r["images"]["lpips"] > 0
    assert "weights file not found" in run_err(
        capsys, ["eval", "--images", str(a_dir), str(b_dir), "--lpips-weights", str(tmp_path / "no.pth")])
    (tmp_path / "c").mkdir()
    assert "no images with the same name" in run_err(capsys, ["eval", "--images", str(a_dir), str(tmp_path / "c")])
    cv2.imwrite(str(tmp_path / "c" / "000.png"), img[:32])
    assert "has shape" in run_err(capsys, ["eval", "--images", str(a_dir), str(tmp_path / "c")])
    # two images of the same name: which one is compared must not depend on the sort order
    cv2.imwrite(str(b_dir / "000.bmp"), img[..., ::-1])
    assert "000.bmp and 000.png share the name" in run_err(capsys, ["eval", "--images", str(a_dir), str(b_dir)])
    # the runner's renders (kf_<stamp>.png) pair with a recording's frames (<stamp>.png)
    (tmp_path / "renders").mkdir()
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "renders" / "kf_1700000000000000000.png"), img[..., ::-1])
    cv2.imwrite(str(tmp_path / "frames" / "1700000000000000000.png"), img[..., ::-1])
    r = run_json(capsys, ["eval", "--images", str(tmp_path / "renders"), str(tmp_path / "frames")])
    assert r["images"]["images"] == 1 and r["images"]["identical_images"] == 1
    # a file that is not a weights archive: one line, without torch's weights_only advice
    err = run_err(capsys, ["eval", "--images", str(a_dir), str(a_dir), "--lpips-weights",
                           str(a_dir / "000.png")])
    assert "not a readable LPIPS weights file" in err and "weights_only" not in err


def test_cli_dataset_ground_truth_kitti(capsys, tmp_path, shared_data):
    io = pytest.importorskip("vings_core.io")
    if not hasattr(io, "open_source"):
        pytest.skip("vings_core.io.open_source not available yet")
    path = shared_data("kitti07_160")
    src = io.open_source(str(path))
    gt = src.gt_camera_trajectory()
    est = Trajectory(gt.stamps_ns, apply_sim3(gt.poses, 0.3, np_so3_exp(np.array([0.1, 0.5, -0.2])),
                                              np.array([1.0, 2.0, 3.0])))
    write_tum(tmp_path / "est.tum", est)
    r = run_json(capsys, ["eval", str(tmp_path / "est.tum"), "--gt", str(path)])
    assert r["gt_source"] == src.kind and r["matched_poses"] == len(gt)
    assert r["ate_sim3_m"] < 1e-6 and r["sim3_scale"] == pytest.approx(1 / 0.3, rel=1e-6)
    assert r["rpe"]["lengths_m"] == [5.0, 10.0, 25.0]  # ~90 m drive


@pytest.mark.parametrize("argv", [["info", ".", "--width", "100000"],
                                  ["sim", "--out", "x", "--height", "90000"]])
def test_absurd_image_sizes_are_refused_by_the_parser(capsys, argv):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2 and "must be <= 8192" in capsys.readouterr().err


def test_cli_max_dt_out_of_range_is_one_line(capsys, tmp_path):
    est = tmp_path / "e.tum"
    est.write_text("".join(f"{i}.0 {i} 0 0 0 0 0 1\n" for i in range(5)))
    assert "--max-dt-ms must be in [0, 1e9] ms" in run_err(
        capsys, ["eval", str(est), "--gt", str(est), "--max-dt-ms", "1e13"])
