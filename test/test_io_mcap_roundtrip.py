"""write_mcap: a sequence written to a ROS 2 MCAP and read back gives identical images, IMU samples
and time stamps; the MCAP is also readable by rosbags' AnyReader and by mcap-ros2-support."""
from __future__ import annotations

import numpy as np
import pytest
from fixtures_io import make_bag, make_euroc, make_kitti, BagSpec

from vings_core.errors import ConfigError, InputError
from vings_core.io import SourceOptions, calib_yaml_path, open_source, write_mcap


def _same_imu(a, b):
    assert [s.stamp_ns for s in a] == [s.stamp_ns for s in b]
    assert np.array_equal(np.stack([s.gyro for s in a]), np.stack([s.gyro for s in b]))
    assert np.array_equal(np.stack([s.accel for s in a]), np.stack([s.accel for s in b]))


@pytest.mark.parametrize("color", [False, True], ids=["mono8", "rgb8"])
def test_mcap_round_trip_is_identical(tmp_path, color):
    root = make_euroc(tmp_path / "seq", n=5, color=color, distortion=[-0.1, 0.02, 0.0, 0.001])
    src = open_source(root, SourceOptions(width=48))
    out = tmp_path / "out" / "seq.mcap"
    write_mcap(out, src)
    assert out.is_file() and calib_yaml_path(out) == tmp_path / "out" / "seq.calib.yaml"
    assert calib_yaml_path(out).is_file()
    assert sorted(p.name for p in out.parent.iterdir()) == ["seq.calib.yaml", "seq.mcap"]  # no temp left

    back = open_source(out)
    assert back.kind == "mcap" and back.calib_source == str(calib_yaml_path(out))
    assert back.frame_stamps().tolist() == src.frame_stamps().tolist()
    for a, b in zip(src.frames(), back.frames()):
        assert a.stamp_ns == b.stamp_ns and a.image.dtype == b.image.dtype
        assert np.array_equal(a.image, b.image)
    _same_imu(src.imu_samples(), back.imu_samples())
    assert back.calibration.to_dict() == src.calibration.to_dict()   # T_bc, noise, camera
    assert back.warnings == []
    # ground truth of the body, to float64 precision
    assert back.gt_frame == "body"
    assert back.ground_truth.stamps_ns.tolist() == src.ground_truth.stamps_ns.tolist()
    assert np.allclose(back.ground_truth.poses, src.ground_truth.poses, atol=1e-12)


def test_mcap_readable_by_anyreader_and_mcap_ros2(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    src = open_source(make_euroc(tmp_path / "seq", n=3))
    out = tmp_path / "x.mcap"
    write_mcap(out, src)
    with AnyReader([out]) as r:
        topics = {t: i.msgtype for t, i in r.topics.items()}
        assert topics == {"/cam0/image_raw": "sensor_msgs/msg/Image",
                          "/cam0/camera_info": "sensor_msgs/msg/CameraInfo",
                          "/imu0": "sensor_msgs/msg/Imu",
                          "/ground_truth/pose": "geometry_msgs/msg/PoseStamped"}
    stamps = {}
    with open(out, "rb") as f:
        for _, channel, message, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            h = msg.header.stamp
            stamps.setdefault(channel.topic, []).append(h.sec * 10**9 + h.nanosec)
            if channel.topic == "/cam0/image_raw":
                assert msg.encoding == "mono8" and msg.width == 64
                assert message.log_time == h.sec * 10**9 + h.nanosec
    assert stamps["/cam0/image_raw"] == src.frame_stamps().tolist()
    assert stamps["/imu0"] == [s.stamp_ns for s in src.imu_samples()]


def test_mcap_bag_folder_and_topics(tmp_path):
    src = open_source(make_euroc(tmp_path / "seq", n=2))
    out = tmp_path / "bagdir"
    write_mcap(out, src, topics={"image": "/cam/image", "imu": "/imu"})
    assert (out / "metadata.yaml").is_file() and (tmp_path / "bagdir.calib.yaml").is_file()
    back = open_source(out)
    assert (back.image_topic, back.imu_topic) == ("/cam/image", "/imu")
    assert back.calibration.to_dict() == src.calibration.to_dict()
    with pytest.raises(InputError, match="output bag folder exists already"):
        write_mcap(out, src)
    with pytest.raises(ConfigError, match="unknown topic keys"):
        write_mcap(tmp_path / "y.mcap", src, topics={"camera": "/c"})


def test_camera_ground_truth_is_written_as_body(tmp_path):
    """KITTI GT is of the camera; the MCAP carries the body pose, which maps back with T_bc."""
    src = open_source(make_kitti(tmp_path / "06", n=3))
    out = tmp_path / "k.mcap"
    # KITTI t = 0 is a legal stamp (0 ns)
    write_mcap(out, src)
    back = open_source(out)
    assert back.frame_stamps().tolist() == src.frame_stamps().tolist()
    assert np.allclose(back.gt_camera_trajectory().poses, src.gt_camera_trajectory().poses, atol=1e-12)
    assert not back.calibration.has_imu and back.imu_samples() == []


def test_imu_only_source_round_trip(tmp_path):
    p = make_bag(tmp_path / "imu", BagSpec(image_topics={}, camera_info=None), "mcap")
    src = open_source(p)
    write_mcap(tmp_path / "imu_copy.mcap", src)
    back = open_source(tmp_path / "imu_copy.mcap")
    assert back.calibration.camera is None and len(back.frame_stamps()) == 0
    assert back.calibration.has_imu and back.calibration.imu_rate_hz == pytest.approx(200.0)
    _same_imu(src.imu_samples(), back.imu_samples())
