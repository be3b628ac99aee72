"""Folder loaders (EuRoC/ASL, TUM RGB-D, KITTI) on small fixtures, and their bad-input handling."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
from fixtures_io import (CX, CY, FX, FY, H, T0, T_BC, W, gt_series, imu_series, make_euroc, make_kitti,
                         make_tum, texture, write_png)

from vings_core.errors import InputError
from vings_core.io import (EurocSource, KittiSource, SourceOptions, TumSource, detect_format,
                           open_source, write_euroc)


# ------------------------------------------------------------------------------------------ EuRoC
def test_body_ground_truth_without_extrinsic_is_refused_not_mapped_by_identity(tmp_path):
    """EuRoC ground truth is of the body; without T_BS in cam0/sensor.yaml there is no extrinsic, so
    mapping it to cam0 is refused, not done through an identity (which would put the lever arm
    into every metric)."""
    root = make_euroc(tmp_path / "seq", n=3)
    assert np.allclose(open_source(root).gt_camera_trajectory().poses,
                       open_source(root).ground_truth.right_multiply(T_BC).poses)
    y = root / "mav0/cam0/sensor.yaml"
    y.write_text("\n".join(ln for ln in y.read_text().splitlines()
                           if not ln.startswith(("T_BS", "  cols", "  rows", "  data"))) + "\n")
    src = open_source(root)
    assert not src.calibration.T_bc_known and np.allclose(src.calibration.T_bc, np.eye(4))
    with pytest.raises(InputError, match=r"seq: the ground truth is of the body .* no camera-to-body extrinsic T_bc"):
        src.gt_camera_trajectory()
    src.gt_frame = "camera"          # taken as camera poses: no extrinsic needed
    assert src.gt_camera_trajectory() is src.ground_truth
    # an extrinsic from --calib makes it known again
    (tmp_path / "c.yaml").write_text("T_bc: " + str([[float(v) for v in r] for r in T_BC]) + "\n")
    src = open_source(root, SourceOptions(calib_file=str(tmp_path / "c.yaml")))
    assert src.calibration.T_bc_known
    assert np.allclose(src.gt_camera_trajectory().poses, src.ground_truth.right_multiply(T_BC).poses)


def test_euroc_loader_reads_everything(tmp_path):
    root = make_euroc(tmp_path / "seq", n=5, depth=True, mask=True)
    src = open_source(root)
    assert isinstance(src, EurocSource) and src.kind == "euroc"
    st = src.frame_stamps()
    assert st.tolist() == [T0 + i * 50_000_000 for i in range(5)]
    frames = list(src.frames())
    assert [f.stamp_ns for f in frames] == st.tolist()
    for i, f in enumerate(frames):
        assert f.image.dtype == np.uint8 and np.array_equal(f.image, texture(i))  # no distortion
        assert f.camera.distortion_model == "none"
    cal = src.calibration
    assert (cal.camera.fx, cal.camera.fy, cal.camera.cx, cal.camera.cy) == (FX, FY, CX, CY)
    assert np.allclose(cal.T_bc, T_BC) and cal.has_imu
    assert (cal.gyro_noise_density, cal.gyro_random_walk, cal.accel_noise_density,
            cal.accel_random_walk, cal.imu_rate_hz) == (1e-4, 2e-5, 3e-3, 4e-3, 200.0)
    ist, g, a = imu_series(60)
    imu = src.imu_samples()
    assert [s.stamp_ns for s in imu] == ist.tolist()
    assert np.array_equal(np.stack([s.gyro for s in imu]), g)
    assert np.array_equal(np.stack([s.accel for s in imu]), a)
    gst, T = gt_series(5)
    assert src.gt_frame == "body" and np.array_equal(src.ground_truth.stamps_ns, gst)
    assert np.allclose(src.ground_truth.poses, T, atol=1e-9)
    assert np.allclose(src.gt_camera_trajectory().poses, T @ T_BC)
    d = src.gt_depth(int(st[2]))
    assert d.dtype == np.float32 and d.shape == (H, W) and np.all(d == 3.0)
    m = src.gt_mask(int(st[0]))
    assert m.dtype == bool and m[15, 10] and not m[0, 0] and m.sum() == 200
    assert src.gt_depth(123) is None
    info = src.info()
    assert (info["frames"], info["imu_samples"], info["has_depth"], info["has_mask"]) == (5, 60, True, True)
    assert info["frame_rate_hz"] == pytest.approx(20.0) and info["imu_rate_hz"] == pytest.approx(200.0)
    assert info["ground_truth"]["frame"] == "body" and info["warnings"] == []
    # stream: time order, IMU first on equal stamps
    items = list(src.stream())
    stamps = [x.stamp_ns for x in items]
    assert stamps == sorted(stamps) and len(items) == 65


def test_euroc_resize_and_undistort(tmp_path):
    root = make_euroc(tmp_path / "seq", n=2, distortion=[-0.2, 0.05, 0.001, 0.0], depth=True, mask=True)
    src = open_source(root, SourceOptions(width=32))
    cam = src.calibration.camera
    assert (cam.width, cam.height, cam.distortion_model) == (32, 24, "none")
    assert src.raw_camera.distortion_model == "radtan"
    f = next(iter(src.frames()))
    assert f.image.shape == (24, 32) and f.camera == cam
    assert src.gt_depth(int(src.frame_stamps()[0])).shape == (24, 32)
    assert src.gt_mask(int(src.frame_stamps()[0])).shape == (24, 32)
    assert len(list(src.frames())) == 2
    assert len(list(open_source(root, SourceOptions(max_frames=1)).frames())) == 1


def test_euroc_mav0_path_and_color(tmp_path):
    root = make_euroc(tmp_path / "seq", n=2, color=True, imu_n=0, gt=False)
    src = open_source(root / "mav0")
    f = next(iter(src.frames()))
    assert f.image.shape == (H, W, 3) and np.array_equal(f.image, texture(0, color=True))
    assert not src.calibration.has_imu and src.imu_samples() == [] and src.ground_truth is None


def test_euroc_out_of_order_and_duplicates_are_repaired(tmp_path):
    st = [T0 + 100, T0 + 300, T0 + 200, T0 + 300, T0 + 400]
    ist = [T0 + 10, T0 + 30, T0 + 20, T0 + 20, T0 + 40]
    root = make_euroc(tmp_path / "seq", stamps=st, imu_stamps=ist, gt=False)
    src = open_source(root)
    assert src.frame_stamps().tolist() == [T0 + 100, T0 + 200, T0 + 300, T0 + 400]
    assert [f.stamp_ns for f in src.frames()] == src.frame_stamps().tolist()
    assert [s.stamp_ns for s in src.imu_samples()] == [T0 + 10, T0 + 20, T0 + 30, T0 + 40]
    w = " | ".join(src.warnings)
    assert "cam0/data.csv: 1 time stamp(s) out of order" in w
    assert "cam0/data.csv: 1 duplicated time stamp(s)" in w
    assert "imu0/data.csv: 1 time stamp(s) out of order" in w and "imu0/data.csv: 1 duplicated" in w
    # the kept duplicate is the first in file order: image 1 (texture(1)) for T0 + 300
    frames = {f.stamp_ns: f for f in src.frames()}
    assert np.array_equal(frames[T0 + 300].image, texture(1))


def test_euroc_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="no such file or folder"):
        open_source(tmp_path / "missing")
    with pytest.raises(InputError, match="EuRoC folder not found"):
        EurocSource(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not an EuRoC/ASL folder"):
        EurocSource(tmp_path / "empty")
    root = make_euroc(tmp_path / "nocal", n=2, cam_yaml=False)
    with pytest.raises(InputError, match=r"cam0/sensor.yaml: camera calibration not found"):
        open_source(root)
    # ... unless one is given
    (tmp_path / "c.yaml").write_text(f"camera: {{width: {W}, height: {H}, fx: 40, fy: 40, cx: 31.5, cy: 23.5}}\n")
    assert open_source(root, SourceOptions(calib_file=str(tmp_path / "c.yaml"))).calibration.camera.fx == 40
    # a missing image file is skipped with a warning naming it; a corrupt one is an error naming it
    root = make_euroc(tmp_path / "holes", n=3)
    files = sorted((root / "mav0/cam0/data").iterdir())
    files[1].unlink()
    src = open_source(root)
    assert len(src.frame_stamps()) == 2 and "1 listed image file(s) missing" in src.warnings[0]
    files[2].write_bytes(b"not a png")
    with pytest.raises(InputError, match=files[2].name + ": corrupt or unreadable image"):
        list(open_source(root, SourceOptions(on_bad_frame="abort")).frames())
    src = open_source(root)                 # the default: skipped, counted, warned
    assert len(list(src.frames())) == 1 and len(src.bad_frames) == 1 and files[2].name in src.bad_frames[0]
    assert any("frame skipped" in w for w in src.warnings)
    # a bad IMU row names file and line
    root = make_euroc(tmp_path / "badimu", n=2)
    with open(root / "mav0/imu0/data.csv", "a") as f:
        f.write("1700000000900000000,0.1,0.2\n")
    with pytest.raises(InputError, match=r"imu0/data.csv:62: expected at least 7 columns"):
        open_source(root)
    # images of another size than the calibration
    root = make_euroc(tmp_path / "size", n=2)
    write_png(root / f"mav0/cam0/data/{T0 + 50_000_000}.png", np.zeros((10, 10), np.uint8))
    with pytest.raises(InputError, match=r"image is 10x10 but the calibration"):
        list(open_source(root, SourceOptions(on_bad_frame="abort")).frames())


def test_write_euroc_round_trip(tmp_path):
    root = make_euroc(tmp_path / "seq", n=3, color=True, depth=True, mask=True)
    src = open_source(root)
    out = write_euroc(tmp_path / "copy", src.frames(), src.imu_samples(), src.calibration,
                      gt_body=src.ground_truth, depth=src.gt_depth, mask=src.gt_mask)
    back = open_source(out)
    assert back.frame_stamps().tolist() == src.frame_stamps().tolist()
    for a, b in zip(src.frames(), back.frames()):
        assert np.array_equal(a.image, b.image)
    assert [(s.stamp_ns, s.gyro.tolist(), s.accel.tolist()) for s in back.imu_samples()] == \
        [(s.stamp_ns, s.gyro.tolist(), s.accel.tolist()) for s in src.imu_samples()]
    assert back.calibration.to_dict() == src.calibration.to_dict()
    assert np.allclose(back.ground_truth.poses, src.ground_truth.poses, atol=1e-12)
    s0 = int(src.frame_stamps()[1])
    assert np.array_equal(back.gt_depth(s0), src.gt_depth(s0))
    assert np.array_equal(back.gt_mask(s0), src.gt_mask(s0))
    with pytest.raises(InputError, match="exists and is not empty"):
        write_euroc(out, [], [], src.calibration)
    write_euroc(out, [], [], src.calibration, overwrite=True)
    assert open_source(out).frame_stamps().tolist() == []


# -------------------------------------------------------------------------------------------- TUM
def test_tum_loader(tmp_path):
    root = make_tum(tmp_path / "rgbd_dataset_x", n=4)
    src = open_source(root)
    assert isinstance(src, TumSource) and detect_format(root) == "tum"
    st = src.frame_stamps()
    assert st[0] == 1305031102175304000 and len(st) == 4
    frames = list(src.frames())
    assert frames[1].image.shape == (H, W, 3) and np.array_equal(frames[1].image, texture(1, color=True))
    assert src.gt_frame == "camera" and len(src.ground_truth) == 4
    assert src.gt_camera_trajectory() is src.ground_truth
    assert np.allclose(src.ground_truth.poses[1][:3, 3], [0.1, 0.2, 0.3])
    assert np.all(src.gt_depth(int(st[2])) == 3.0)        # 15000 / 5000
    assert src.gt_depth(int(st[-1]) + 30_000_000) is None  # no depth within 20 ms
    assert src.imu_samples() == [] and not src.calibration.has_imu
    assert src.calibration.camera.fx == FX


def test_tum_calibration_rules(tmp_path):
    root = make_tum(tmp_path / "bonn_balloon", n=2, calib=False, depth=False)
    with pytest.raises(InputError, match=r"bonn_balloon: TUM RGB-D folder has no calibration: pass --calib"):
        open_source(root)
    # preset by name: intrinsics for 640x480 scaled to the fixture's 64x48 images, with a warning
    src = open_source(root, SourceOptions(calib_file="tum-fr3"))
    assert src.calibration.camera.fx == pytest.approx(53.54)
    assert any("calibration is for 640x480" in w for w in src.warnings)
    fr1 = make_tum(tmp_path / "rgbd_dataset_freiburg1_xyz", n=2, calib=False, depth=False)
    src = open_source(fr1)
    assert any("tum-fr1" in w for w in src.warnings) and src.raw_camera.distortion_model == "radtan"


def test_tum_bad_inputs(tmp_path):
    root = make_tum(tmp_path / "t", n=3)
    with open(root / "groundtruth.txt", "a") as f:
        f.write("1305031103.0 1 2 3 0 0 0\n")
    with pytest.raises(InputError, match=r"groundtruth.txt:\d+: expected at least 8 columns"):
        open_source(root)
    root = make_tum(tmp_path / "u", n=2)
    (root / "rgb.txt").write_text("# nothing\n")
    src = open_source(root)
    assert len(src.frame_stamps()) == 0 and any("no images listed" in w for w in src.warnings)
    shutil.rmtree(root / "rgb")
    (root / "rgb.txt").write_text("1.0 rgb/a.png\n2.0 rgb/b.png\n")
    with pytest.raises(InputError, match="none of the 2 listed images exist"):
        open_source(root)


# ------------------------------------------------------------------------------------------ KITTI
@pytest.mark.parametrize("image_dir,labelled,poses", [("image_0", True, "poses.txt"),
                                                      ("image_l", False, "poses/NN"),
                                                      ("image_2", True, "poses.txt")])
def test_kitti_loader(tmp_path, image_dir, labelled, poses):
    root = make_kitti(tmp_path / "06", n=4, image_dir=image_dir, labelled=labelled, poses=poses,
                      color=image_dir == "image_2")
    src = open_source(root)
    assert isinstance(src, KittiSource) and src.kind == "kitti"
    assert src.frame_stamps().tolist() == [0, 100_000_000, 200_000_000, 300_000_000]
    f = list(src.frames())[3]
    assert np.array_equal(f.image, texture(3, color=image_dir == "image_2"))
    c = src.calibration.camera
    assert (c.fx, c.fy, c.cx, c.cy) == (FX, FX, CX, CY)
    assert src.gt_frame == "camera" and len(src.ground_truth) == 4
    if image_dir == "image_2":  # P2 = K [I | t]: t = K^-1 (2.5, 0.1, 0.005) -> camera 2 sits at -t
        t = np.linalg.solve(np.array([[FX, 0, CX], [0, FX, CY], [0, 0, 1]]), [2.5, 0.1, 0.005])
        assert np.allclose(src.ground_truth.poses[:, :3, 3], np.array([[0, 0, i] for i in range(4)]) - t)
    else:
        assert np.allclose(src.ground_truth.poses[:, :3, 3], [[0, 0, i] for i in range(4)])


def test_kitti_image_2_with_calib_file_still_moves_ground_truth_to_camera_2(tmp_path):
    # --calib replaces the intrinsics; the lever arm to camera 0 comes from the sequence's calib.txt
    root = make_kitti(tmp_path / "06", n=3, image_dir="image_2", color=True)
    calib = tmp_path / "cam.yaml"
    h, w = texture(0).shape[:2]
    calib.write_text(f"camera: {{width: {w}, height: {h}, fx: {FX}, fy: {FX}, cx: {CX}, cy: {CY}}}\n")
    src = open_source(root, SourceOptions(calib_file=str(calib)))
    t = np.linalg.solve(np.array([[FX, 0, CX], [0, FX, CY], [0, 0, 1]]), [2.5, 0.1, 0.005])
    assert np.allclose(src.ground_truth.poses[:, :3, 3], np.array([[0, 0, i] for i in range(3)]) - t)
    (root / "calib.txt").write_text(f"P0: {FX} 0 {CX} 0 0 {FX} {CY} 0 0 0 1 0\n")
    src = open_source(root, SourceOptions(calib_file=str(calib)))
    assert np.allclose(src.ground_truth.poses[:, :3, 3], [[0, 0, i] for i in range(3)])
    assert any("no P2 to move the camera-0 ground truth" in w for w in src.warnings)
    (root / "calib.txt").write_text("P0: 1 2 3\n")          # damaged: --calib still opens it
    src = open_source(root, SourceOptions(calib_file=str(calib)))
    assert any("P0 needs 12 numbers" in w for w in src.warnings) and src.ground_truth is not None
    (root / "poses.txt").unlink()                            # no ground truth: nothing to move
    src = open_source(root, SourceOptions(calib_file=str(calib)))
    assert src.ground_truth is None and not any("calib.txt" in w for w in src.warnings)


def test_kitti_bad_inputs(tmp_path):
    root = make_kitti(tmp_path / "07", n=3, times=False)
    src = open_source(root)
    assert src.frame_stamps().tolist() == [0, 100_000_000, 200_000_000]
    assert any("times.txt not found: assuming 10 Hz" in w for w in src.warnings)
    (root / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(InputError, match=r"calib.txt:1: P0 needs 12 numbers, got 3"):
        open_source(root)
    (root / "calib.txt").unlink()
    (root / "times.txt").write_text("0.0\n0.1\n0.1\n")
    with pytest.raises(InputError, match="KITTI calib.txt not found"):
        KittiSource(root)
    make_kitti(tmp_path / "08", n=3)
    (tmp_path / "08" / "times.txt").write_text("0.0\n0.2\n0.1\n")
    src = open_source(tmp_path / "08")
    assert src.frame_stamps().tolist() == [0, 100_000_000, 200_000_000]
    assert any("out of order" in w for w in src.warnings)
    # GT follows the frames through the re-ordering: frame at t=0.1 s is image 2 with pose z=2
    gt = src.ground_truth
    assert gt.stamps_ns.tolist() == [0, 100_000_000, 200_000_000] and np.allclose(gt.poses[:, 2, 3], [0, 2, 1])
    frames = list(src.frames())
    assert np.array_equal(frames[1].image, texture(2))


def test_detect_format_errors(tmp_path):
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(InputError, match=r"x.txt: unknown file type '.txt'"):
        detect_format(tmp_path / "x.txt")
    (tmp_path / "d").mkdir()
    with pytest.raises(InputError, match="not a recognised recording"):
        open_source(tmp_path / "d")


def test_kitti_pairs_times_and_poses_by_frame_number(tmp_path):
    """times.txt and poses.txt have one line per frame number: a subset of the images (frames
    5..9) or a missing image keeps each image's own time and pose; a subset whose files were cut
    to it (one line per image) is paired by position, warned."""
    root = make_kitti(tmp_path / "k", n=10)
    for i in range(5):
        (root / "image_0" / f"{i:06d}.png").unlink()
    (root / "image_0" / "000007.png").unlink()
    src = open_source(root)
    assert src.frame_stamps().tolist() == [500_000_000, 600_000_000, 800_000_000, 900_000_000]
    gt = src.ground_truth
    assert gt.stamps_ns.tolist() == src.frame_stamps().tolist()
    assert gt.poses[:, 2, 3].tolist() == [5.0, 6.0, 8.0, 9.0]          # pose line = frame number
    # the times and poses files cut to the subset (one line per image): by position, warned
    lines = (root / "times.txt").read_text().splitlines()
    (root / "times.txt").write_text("\n".join(lines[5:7] + lines[8:]) + "\n")
    rows = (root / "poses.txt").read_text().splitlines()
    (root / "poses.txt").write_text("\n".join(rows[5:7] + rows[8:]) + "\n")
    src = open_source(root)
    assert src.frame_stamps().tolist() == [500_000_000, 600_000_000, 800_000_000, 900_000_000]
    assert src.ground_truth.poses[:, 2, 3].tolist() == [5.0, 6.0, 8.0, 9.0]
    assert any("paired by position" in w for w in src.warnings)
    # too few times for the numbers: the images without a time are left out, warned
    (root / "times.txt").write_text("\n".join(lines[:9]) + "\n")
    src = open_source(root)
    assert src.frame_stamps().tolist() == [500_000_000, 600_000_000, 800_000_000]
    assert any("numbered 9 and above have none" in w for w in src.warnings)
    # the files cut to 5..9 (a line for the missing image 7 too), the poses file whole
    (root / "times.txt").write_text("\n".join(lines[5:]) + "\n")
    (root / "poses.txt").write_text("\n".join(rows) + "\n")
    src = open_source(root)
    assert src.frame_stamps().tolist() == [500_000_000, 600_000_000, 800_000_000, 900_000_000]
    assert src.ground_truth.poses[:, 2, 3].tolist() == [5.0, 6.0, 8.0, 9.0]       # by number
    assert any("line 0 taken as image 5" in w for w in src.warnings)
    (root / "times.txt").write_text("\n".join(lines[:2]) + "\n")
    with pytest.raises(InputError, match="2 times, none for the images numbered 5..9"):
        open_source(root)
