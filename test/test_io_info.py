"""`vings info` on fixtures and on every sequence in ../shared/data (skipped when absent)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import shared_path
from fixtures_io import BagSpec, make_bag, make_euroc

from vings_ros.cli import main


def _info_json(capsys, *argv) -> dict:
    rc = main(["info", "--json", *argv])
    out = capsys.readouterr().out
    assert rc == 0, out
    return json.loads(out)


def test_info_json_and_text_on_fixture(tmp_path, capsys):
    root = make_euroc(tmp_path / "seq", n=4, depth=True)
    info = _info_json(capsys, str(root), "--width", "32")
    assert info["kind"] == "euroc" and info["frames"] == 4 and info["imu_samples"] == 60
    assert info["resolution"] == [32, 24] and info["native_resolution"] == [64, 48]
    assert info["calibration"]["camera"]["distortion_model"] == "none" and info["has_depth"]
    assert info["frame_rate_hz"] == pytest.approx(20.0)
    assert main(["info", str(root)]) == 0
    text = capsys.readouterr().out
    assert "frames      : 4  rate 20.000 Hz" in text and "resolution  : 64x48" in text
    assert "ground truth: 4 poses of the body" in text


def test_info_errors_are_one_line(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing: no such file or folder" in err and "Traceback" not in err
    p = make_bag(tmp_path / "two", BagSpec(image_topics={"/a": "mono8", "/b": "mono8"}), "mcap")
    assert main(["info", str(p)]) == 2
    assert "several image topics: /a, /b" in capsys.readouterr().err
    assert main(["info", str(p), "--image-topic", "/b", "--calib", str(tmp_path / "none.yaml")]) == 2
    assert "none.yaml: calibration file not found" in capsys.readouterr().err
    # the bag's only CameraInfo (/cam0/camera_info) is not /b's camera: named explicitly it is used
    assert main(["info", str(p), "--image-topic", "/b"]) == 2
    assert "not in the namespace / of the image topic" in capsys.readouterr().err
    used = _info_json(capsys, str(p), "--image-topic", "/b", "--camera-info-topic", "/cam0/camera_info")
    assert used["topics_used"]["image"] == "/b"


def test_info_on_simulator_output(tmp_path, capsys):
    sim = pytest.importorskip("vings_core.sim")
    out = sim.generate("room", tmp_path / "s", frames=3, width=48, height=32, mcap=True)
    a = _info_json(capsys, str(out))
    b = _info_json(capsys, str(out / "room.mcap"))
    assert a["kind"] == "euroc" and b["kind"] == "mcap"
    for k in ("frames", "imu_samples", "first_stamp_ns", "last_stamp_ns", "resolution", "calibration"):
        assert a[k] == b[k], k
    assert a["frames"] == 3 and a["has_depth"] and a["ground_truth"]["frame"] == b["ground_truth"]["frame"] == "body"
    assert a["ground_truth"]["poses"] == b["ground_truth"]["poses"]


# ------------------------------------------------------------------------------- shared real data
def test_info_euroc_micro(capsys):
    info = _info_json(capsys, str(shared_path("euroc_v101_micro")))
    assert (info["frames"], info["imu_samples"]) == (95, 29120)
    assert info["frame_rate_hz"] == pytest.approx(20.0, rel=1e-3)
    assert info["imu_rate_hz"] == pytest.approx(200.0, rel=1e-3)
    assert info["native_resolution"] == [752, 480]
    cal = info["calibration"]
    assert cal["has_imu"] and cal["gyro_noise_density"] == pytest.approx(1.6968e-4)
    assert np.allclose(np.array(cal["T_bc"])[:3, 3], [-0.0216401454975, -0.064676986768, 0.00981073058949])
    gt = info["ground_truth"]
    assert gt["poses"] == 2895 and gt["frame"] == "body" and gt["path_length_m"] == pytest.approx(58.35, abs=0.01)


@pytest.mark.parametrize("name,frames,path_m", [("kitti06_snippet", 51, 59.9), ("kitti07_160", 160, 90.6)])
def test_info_kitti(capsys, name, frames, path_m):
    info = _info_json(capsys, str(shared_path(name)))
    assert info["frames"] == frames and info["imu_samples"] == 0
    assert info["resolution"] == [1226, 370]
    assert info["calibration"]["camera"]["fx"] == pytest.approx(707.0912)
    assert info["ground_truth"]["frame"] == "camera"
    assert info["ground_truth"]["path_length_m"] == pytest.approx(path_m, abs=0.1)
    assert info["frame_rate_hz"] == pytest.approx(9.6, abs=0.1)


@pytest.mark.parametrize("name,topic,count,rate", [
    ("robot_localization_test1.bag", "/imu/data", 11865, 30.0),
    ("imu_tools_phidgets_imu_upside_down.bag", "/imu/data_raw", 13964, 248.0),
])
def test_info_imu_only_bags(capsys, name, topic, count, rate):
    info = _info_json(capsys, str(shared_path("bags", name)))
    assert info["frames"] == 0 and info["calibration"]["camera"] is None and info["resolution"] is None
    assert info["calibration"]["has_imu"]
    assert info["imu_samples"] == count and info["topics_used"]["imu"] == topic
    assert info["imu_rate_hz"] == pytest.approx(rate, rel=0.01)


def test_info_fiducials_compressed_image(capsys):
    p = shared_path("bags", "fiducials_aruco_images.bag")
    info = _info_json(capsys, str(p))
    assert info["frames"] == 1 and info["native_resolution"] == [1280, 960]
    assert info["topics_used"]["camera_info"] == "/raspicam_node/camera_info"
    from vings_core.io import open_source
    src = open_source(p)
    assert src.raw_camera.fx == pytest.approx(1014.3431) and src.raw_camera.distortion_model == "radtan"
    f = next(iter(src.frames()))
    assert f.image.shape == (960, 1280, 3) and f.image.dtype == np.uint8 and f.image.std() > 10
