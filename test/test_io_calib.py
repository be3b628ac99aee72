"""Calibration YAML: every readable layout, the VINGS round trip, and clear errors."""
from __future__ import annotations

import numpy as np
import pytest

from vings_core.errors import InputError
from vings_core.io.calib_yaml import (PRESETS, load_calibration_yaml, read_calibration_parts,
                                      save_calibration_yaml)
from vings_core.types import Calibration, CameraModel

T = np.array([[0.0, -1.0, 0.0, 0.1], [1.0, 0.0, 0.0, 0.2], [0.0, 0.0, 1.0, 0.3], [0, 0, 0, 1.0]])


def test_vings_round_trip(tmp_path):
    cam = CameraModel(752, 480, 458.6, 457.3, 367.2, 248.4, "radtan", np.array([-0.28, 0.07, 2e-4, 1.8e-5]))
    c = Calibration(camera=cam, T_bc=T, gyro_noise_density=1e-4, gyro_random_walk=2e-5,
                    accel_noise_density=3e-3, accel_random_walk=4e-3, imu_rate_hz=400.0, has_imu=True)
    p = tmp_path / "c.yaml"
    save_calibration_yaml(p, c)
    back = load_calibration_yaml(p)
    assert back.to_dict() == c.to_dict()


def test_euroc_sensor_yaml(tmp_path):
    p = tmp_path / "sensor.yaml"
    p.write_text("%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: "
                 + str(T.reshape(-1).tolist()) + "\nresolution: [752, 480]\ncamera_model: pinhole\n"
                 "intrinsics: [458.654, 457.296, 367.215, 248.375]\n"
                 "distortion_model: radial-tangential\n"
                 "distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]\n")
    c = load_calibration_yaml(p)
    assert (c.camera.width, c.camera.fx, c.camera.distortion_model) == (752, 458.654, "radtan")
    assert np.allclose(c.T_bc, T)


def test_kalibr_camchain_with_imu_noise(tmp_path):
    p = tmp_path / "camchain.yaml"
    Tci = np.linalg.inv(T)
    p.write_text(f"cam0:\n  camera_model: pinhole\n  intrinsics: [200.0, 201.0, 320.0, 240.0]\n"
                 f"  distortion_model: equidistant\n  distortion_coeffs: [0.01, -0.02, 0.003, -0.001]\n"
                 f"  resolution: [640, 480]\n  T_cam_imu: {Tci.tolist()}\n"
                 f"imu0:\n  gyroscope_noise_density: 0.001\n  accelerometer_noise_density: 0.02\n"
                 f"  update_rate: 400.0\n")
    c = load_calibration_yaml(p)
    assert c.camera.distortion_model == "equidistant" and c.camera.distortion.size == 4
    assert np.allclose(c.T_bc, T)
    assert (c.gyro_noise_density, c.accel_noise_density, c.imu_rate_hz) == (0.001, 0.02, 400.0)


def test_kalibr_stereo_camchain_gives_the_image_topics_camera(tmp_path):
    from vings_core.io.calib_yaml import read_calibration_parts
    p = tmp_path / "camchain.yaml"
    blocks = []
    for k, (fx, tx) in enumerate(((200.0, 0.0), (210.0, -0.1))):
        Tci = np.eye(4)
        Tci[0, 3] = tx
        blocks.append(f"cam{k}:\n  camera_model: pinhole\n  intrinsics: [{fx}, {fx}, 320.0, 240.0]\n"
                      f"  distortion_model: radtan\n  distortion_coeffs: [0.0, 0.0, 0.0, 0.0]\n"
                      f"  resolution: [640, 480]\n  T_cam_imu: {Tci.tolist()}\n  rostopic: /cam{k}/image_raw\n")
    p.write_text("".join(blocks))
    assert read_calibration_parts(p).camera.fx == 200.0                  # no topic: cam0
    right = read_calibration_parts(p, "/cam1/image_raw/compressed")
    assert right.camera.fx == 210.0 and np.isclose(right.T_bc[0, 3], 0.1)
    with pytest.raises(InputError, match=r"camchain has 2 cameras \(cam0: /cam0/image_raw, cam1: "
                                         r"/cam1/image_raw\); none is for the image topic /cam2/image_raw"):
        read_calibration_parts(p, "/cam2/image_raw")


def test_ros_camera_info_yaml(tmp_path):
    p = tmp_path / "ost.yaml"
    p.write_text("image_width: 640\nimage_height: 480\ncamera_name: narrow\ncamera_matrix:\n  rows: 3\n"
                 "  cols: 3\n  data: [500.0, 0, 320.5, 0, 501.0, 240.5, 0, 0, 1]\n"
                 "distortion_model: rational_polynomial\ndistortion_coefficients:\n  rows: 1\n  cols: 8\n"
                 "  data: [0.1, -0.2, 0.001, 0.002, 0.03, 0.01, 0.0, 0.0]\n")
    c = load_calibration_yaml(p)
    assert c.camera.distortion_model == "radtan" and c.camera.distortion.size == 8
    assert (c.camera.fx, c.camera.cy) == (500.0, 240.5) and np.allclose(c.T_bc, np.eye(4))


def test_orbslam_settings(tmp_path):
    p = tmp_path / "TUM1.yaml"
    p.write_text("%YAML:1.0\nCamera.type: \"PinHole\"\nCamera.fx: 517.306408\nCamera.fy: 516.469215\n"
                 "Camera.cx: 318.643040\nCamera.cy: 255.313989\nCamera.k1: 0.262383\nCamera.k2: -0.953104\n"
                 "Camera.p1: -0.005358\nCamera.p2: 0.002628\nCamera.k3: 1.163314\nCamera.width: 640\n"
                 "Camera.height: 480\nIMU.T_b_c1: !!opencv-matrix\n   rows: 4\n   cols: 4\n   dt: f\n"
                 f"   data: {T.reshape(-1).tolist()}\nIMU.NoiseGyro: 1.7e-4\n")
    c = load_calibration_yaml(p)
    assert c.camera.distortion.tolist() == [0.262383, -0.953104, -0.005358, 0.002628, 1.163314]
    assert np.allclose(c.T_bc, T) and c.gyro_noise_density == 1.7e-4


def test_presets_are_640x480():
    assert set(PRESETS) == {"tum-fr1", "tum-fr2", "tum-fr3"}
    assert all((c.width, c.height) == (640, 480) for c in PRESETS.values())


def test_imu_only_file_has_no_camera(tmp_path):
    p = tmp_path / "imu.yaml"
    p.write_text("gyroscope_noise_density: 0.001\naccelerometer_random_walk: 0.0004\n")
    parts = read_calibration_parts(p)
    assert parts.camera is None and parts.noise == {"gyro_noise_density": 0.001, "accel_random_walk": 0.0004}
    with pytest.raises(InputError, match=r"imu.yaml: no camera calibration in this file"):
        load_calibration_yaml(p)


@pytest.mark.parametrize("text,match", [
    ("camera: {width: 10, height: 10, fx: 5}", "camera block lacks fy, cx, cy"),
    ("intrinsics: [1, 2, 3]\nresolution: [4, 4]", "'intrinsics' must be"),
    ("intrinsics: [1, 2, 3, 4]\nresolution: [4, 4]\ndistortion_model: mystery", "unknown distortion model 'mystery'"),
    ("intrinsics: [1, 2, 3, 4]\nresolution: [4, 4]\ndistortion_model: equidistant\n"
     "distortion_coefficients: [0.1, 0.2]", "equidistant needs 4 coefficients"),
    ("intrinsics: [1, 2, 3, 4]\nresolution: [4, 4]\nT_BS: {data: [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}",
     "T_BS: not a rigid pose"),
    ("foo: 1", "no camera calibration found"),
    ("a: [unclosed", "not valid YAML"),
    ("- 1\n- 2", "expected a YAML mapping"),
])
def test_bad_calibration_files(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as e:
        load_calibration_yaml(p)
    assert "bad.yaml" in str(e.value) and "\n" not in str(e.value)   # one line, no YAML excerpt


def test_binary_calibration_file_is_an_input_error(tmp_path):
    p = tmp_path / "bin.yaml"
    p.write_bytes(b"\x7fELF\xff\xfe binary")
    with pytest.raises(InputError, match="bin.yaml: not UTF-8 text.*calibration file"):
        load_calibration_yaml(p)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="calibration file not found"):
        load_calibration_yaml(tmp_path / "none.yaml")


def test_presets_outside_tum_folders_and_the_remap_size_limit():
    from vings_core.io.calib_yaml import read_calibration_parts
    from vings_core.io.undistort import Undistorter
    from vings_core.types import CameraModel
    with pytest.raises(InputError, match="tum-fr1: calibration file not found \\(the presets .* apply to TUM"):
        read_calibration_parts("tum-fr1")
    cam = CameraModel(33000, 16, 1000.0, 1000.0, 16500.0, 8.0, "radtan", np.array([0.1, 0.0, 0.0, 0.0]))
    with pytest.raises(InputError, match="33000x16: distorted images of 32767 px"):
        Undistorter(cam)
