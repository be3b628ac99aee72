"""msg_adapters: every message type round-trips exactly (through CDR serialisation, as on the wire)
and malformed messages raise InputError naming the topic and field."""
from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("rclpy")

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import Image, PointCloud2, PointField  # noqa: E402

import msg_adapters as ma  # noqa: E402
from msg_adapters import keyframe as kfa  # noqa: E402
from msg_adapters import markers as mk  # noqa: E402
from msg_adapters import pose as pa  # noqa: E402
from vings_core.errors import InputError  # noqa: E402
from vings_core.geometry import np_se3_exp, np_so3_log  # noqa: E402
from vings_core.types import (CameraModel, ImuSample, Keyframe, PoseEstimate,  # noqa: E402
                              Trajectory)

STAMPS = [0, 1, 999_999_999, 1_000_000_000, 1_403_636_579_763_555_584, 1_700_000_000_123_456_789,
          -1, -1_500_000_001]


def wire(msg):
    """Serialise to CDR and back, as a publisher/subscriber pair would."""
    return deserialize_message(serialize_message(msg), type(msg))


def random_pose(rng, scale=1.0):
    return np_se3_exp(rng.normal(size=6) * scale)


# --------------------------------------------------------------------------------------- stamps


@pytest.mark.parametrize("ns", STAMPS)
def test_stamp_round_trip_is_exact(ns):
    t = wire(ma.ns_to_time(ns))
    assert 0 <= t.nanosec < 1_000_000_000
    assert ma.time_to_ns(t) == ns
    h = wire(ma.make_header(ns, "map"))
    assert ma.header_ns(h) == ns and h.frame_id == "map"


def test_stamp_out_of_range_names_field():
    with pytest.raises(InputError, match=r"/camera/image_raw.*int32"):
        ma.ns_to_time(2 ** 31 * 1_000_000_000, "/camera/image_raw")
    with pytest.raises(InputError, match="nanoseconds"):
        ma.ns_to_time("soon")
    # a float (seconds by mistake) is refused, not taken as 1.7 s of nanoseconds
    with pytest.raises(InputError, match="integer number of nanoseconds, got 1700000000.0"):
        ma.ns_to_time(1.7e9)
    assert ma.ns_to_time(np.int64(5)).nanosec == 5


# --------------------------------------------------------------------------------------- images


@pytest.fixture
def rgb():
    return np.random.default_rng(0).integers(0, 256, (37, 53, 3), dtype=np.uint8)


def test_rgb8_and_mono8_round_trip(rgb):
    stamp = 1_403_636_579_763_555_584
    for img, enc in ((rgb, "rgb8"), (rgb[..., 1].copy(), "mono8")):
        msg = wire(ma.image_to_msg(img, stamp, "camera_optical_frame"))
        assert msg.encoding == enc and msg.width == 53 and msg.height == 37
        assert msg.header.frame_id == "camera_optical_frame"
        out = ma.msg_to_image(msg)
        assert out.dtype == np.uint8 and np.array_equal(out, img)
        assert ma.image.stamp_of(msg) == stamp


def test_image_accepts_torch_and_frame(rgb):
    cam = CameraModel(53, 37, 40.0, 40.0, 26.0, 18.0)
    from vings_core.types import Frame
    f = Frame(stamp_ns=42, image=rgb, camera=cam)
    back = ma.msg_to_frame(wire(ma.frame_to_msg(f, "cam")), cam, "/camera/image_raw")
    assert back.stamp_ns == 42 and np.array_equal(back.image, rgb) and back.camera is cam
    msg = ma.image_to_msg(torch.from_numpy(rgb), 5, "cam")
    assert np.array_equal(ma.msg_to_image(msg), rgb)


def _raw_msg(arr_bytes_rows: np.ndarray, encoding: str, width: int, height: int, step: int,
             big: bool = False) -> Image:
    msg = Image(height=height, width=width, encoding=encoding, step=step, is_bigendian=int(big))
    msg.data = ma.image._byte_array(np.ascontiguousarray(arr_bytes_rows))
    return msg


def _padded(a: np.ndarray, pad: int) -> tuple[np.ndarray, int]:
    """Rows of ``a`` as bytes followed by ``pad`` junk bytes each."""
    h = a.shape[0]
    rows = np.ascontiguousarray(a).view(np.uint8).reshape(h, -1)
    junk = np.full((h, pad), 0xAB, np.uint8)
    return np.concatenate([rows, junk], axis=1), rows.shape[1] + pad


def test_decode_every_camera_encoding_with_row_padding(rgb):
    """Messages as other drivers publish them: BGR order, alpha, 16 bit both endiannesses, row
    padding (step > width * bpp)."""
    h, w = rgb.shape[:2]
    cases = {
        "rgb8": (rgb, rgb),
        "bgr8": (rgb[..., ::-1], rgb),
        "rgba8": (np.concatenate([rgb, np.full((h, w, 1), 7, np.uint8)], 2), rgb),
        "bgra8": (np.concatenate([rgb[..., ::-1], np.full((h, w, 1), 7, np.uint8)], 2), rgb),
        "mono8": (rgb[..., 0], rgb[..., 0]),
    }
    for enc, (stored, expected) in cases.items():
        data, step = _padded(stored, 3)
        out = ma.msg_to_image(wire(_raw_msg(data, enc, w, h, step)), f"/cam/{enc}")
        assert np.array_equal(out, expected), enc
    mono16 = np.random.default_rng(1).integers(0, 65536, (h, w), dtype=np.uint16)
    for big in (False, True):
        stored = mono16.astype(">u2" if big else "<u2")
        data, step = _padded(stored, 2)
        out = ma.msg_to_image(wire(_raw_msg(data, "mono16", w, h, step, big)))
        assert out.dtype == np.uint16 and np.array_equal(out, mono16)


def test_16bit_camera_needs_a_stream_converter():
    cam = CameraModel(4, 2, 5.0, 5.0, 2.0, 1.0)
    img = (np.arange(8, dtype=np.uint16).reshape(2, 4) * 500)  # 12-bit range
    msg = _raw_msg(img.astype("<u2").view(np.uint8), "mono16", 4, 2, 8)
    with pytest.raises(InputError, match="8 bit"):
        ma.msg_to_frame(msg, cam, "/camera/image_raw")
    dec = ma.FrameDecoder("/camera/image_raw")
    f = dec(msg, cam)
    assert f.image.dtype == np.uint8 and f.image.max() == 3500 >> 4 and dec.warnings


def test_float_images_32fc1_exact_with_nan_and_endianness():
    rng = np.random.default_rng(2)
    d = rng.uniform(0.1, 80.0, (24, 31)).astype(np.float32)
    d[3, 4] = 0.0
    d[5, 6] = np.nan
    msg = wire(ma.float_image_to_msg(d, 77, "cam", "/vings/keyframe/depth"))
    assert msg.encoding == "32FC1" and msg.step == 31 * 4
    out = ma.msg_to_float_image(msg)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, d)  # NaN == NaN for assert_array_equal
    # big-endian with padding, as another platform might send it
    data, step = _padded(d.astype(">f4"), 4)
    out = ma.msg_to_float_image(_raw_msg(data, "32FC1", 31, 24, step, big=True))
    np.testing.assert_array_equal(out, d)
    # torch input
    t = torch.from_numpy(d)
    np.testing.assert_array_equal(ma.msg_to_float_image(ma.float_image_to_msg(t, 1, "c")), d)


def test_depth_16uc1_millimetres_rep118():
    mm = np.array([[0, 1000, 2500], [65535, 1, 42]], np.uint16)
    msg = _raw_msg(mm.astype("<u2").view(np.uint8), "16UC1", 3, 2, 6)
    d = ma.msg_to_depth(msg)
    # exactly the float32 nearest to mm / 1000 (x 1e-3 gave 1500 mm -> 1.5000001 m)
    np.testing.assert_array_equal(d, mm.astype(np.float32) / np.float32(1000.0))
    assert ma.msg_to_depth(_raw_msg(np.array([1500], "<u2").view(np.uint8), "16UC1", 1, 1, 2))[0, 0] == np.float32(1.5)
    with pytest.raises(InputError, match="16UC1"):
        ma.msg_to_float_image(msg, "/vings/keyframe/depth")
    neg = ma.float_image_to_msg(np.array([[-1.0, np.inf, 2.0]], np.float32), 0, "c")
    assert ma.msg_to_depth(neg).tolist() == [[0.0, 0.0, 2.0]]


def test_bad_images_raise_input_error_naming_topic(rgb):
    msg = ma.image_to_msg(rgb, 1, "cam")
    short = Image(height=msg.height, width=msg.width, encoding="rgb8", step=msg.step)
    short.data = ma.image._byte_array(bytes(len(msg.data) - 10))
    with pytest.raises(InputError, match=r"/camera/image_raw.*bytes"):
        ma.msg_to_image(short, "/camera/image_raw")
    weird = Image(height=2, width=2, encoding="yuv420_fancy", step=6)
    weird.data = ma.image._byte_array(bytes(12))
    with pytest.raises(InputError, match=r"/camera/image_raw.*yuv420_fancy"):
        ma.msg_to_image(weird, "/camera/image_raw")
    with pytest.raises(InputError, match=r"/camera/image_raw.*step"):
        ma.msg_to_image(_raw_msg(np.zeros(12, np.uint8), "rgb8", 2, 2, 3), "/camera/image_raw")
    with pytest.raises(InputError, match="32FC1"):
        ma.msg_to_float_image(msg, "/vings/keyframe/depth")
    with pytest.raises(InputError, match="uint8"):
        ma.image_to_msg(rgb.astype(np.float64), 1, "cam", "/vings/render/color")
    cam = CameraModel(10, 10, 5.0, 5.0, 5.0, 5.0)
    with pytest.raises(InputError, match="53x37.*10x10"):
        ma.msg_to_frame(msg, cam, "/camera/image_raw")


# ---------------------------------------------------------------------------------- camera info


@pytest.mark.parametrize("model,coeffs,ros_model,ros_d", [
    ("none", [], "plumb_bob", [0, 0, 0, 0, 0]),
    ("radtan", [-0.28, 0.07, 1.9e-4, 1.8e-5, 0.01], "plumb_bob", None),
    ("radtan", [-0.28, 0.07, 1.9e-4, 1.8e-5], "plumb_bob", [-0.28, 0.07, 1.9e-4, 1.8e-5, 0.0]),
    ("equidistant", [0.1, -0.02, 0.003, -0.0004], "equidistant", None),
])
def test_camera_info_round_trip(model, coeffs, ros_model, ros_d):
    cam = CameraModel(752, 480, 458.654, 457.296, 367.215, 248.375, model, np.array(coeffs))
    msg = wire(ma.camera_to_camera_info(cam, 1_403_636_579_763_555_584, "camera_optical_frame"))
    assert msg.distortion_model == ros_model
    assert list(msg.d) == pytest.approx(ros_d if ros_d is not None else coeffs)
    assert ma.time_to_ns(msg.header.stamp) == 1_403_636_579_763_555_584
    np.testing.assert_array_equal(np.asarray(msg.k).reshape(3, 3), cam.K)
    np.testing.assert_array_equal(np.asarray(msg.p).reshape(3, 4)[:, :3], cam.K)
    np.testing.assert_array_equal(np.asarray(msg.r).reshape(3, 3), np.eye(3))
    back = ma.camera_info_to_camera(msg)
    assert (back.width, back.height) == (752, 480)
    assert (back.fx, back.fy, back.cx, back.cy) == (cam.fx, cam.fy, cam.cx, cam.cy)
    assert back.distortion_model == model
    np.testing.assert_array_equal(back.distortion[:len(coeffs)], coeffs)


def test_camera_info_binning_roi_and_tolerated_variants():
    cam = CameraModel(752, 480, 400.0, 410.0, 370.0, 250.0)
    msg = ma.camera_to_camera_info(cam, 0, "cam")
    msg.binning_x = msg.binning_y = 2
    msg.roi.x_offset, msg.roi.y_offset, msg.roi.width, msg.roi.height = 100, 40, 400, 300
    b = ma.camera_info_to_camera(wire(msg))
    assert (b.width, b.height) == (200, 150)
    assert (b.fx, b.fy, b.cx, b.cy) == (200.0, 205.0, 135.0, 105.0)     # image_geometry's formulas
    msg = ma.camera_to_camera_info(cam, 0, "cam")
    msg.distortion_model = "rational_polynomial"
    msg.d = [0.1, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    b = ma.camera_info_to_camera(msg)
    assert b.distortion_model == "radtan" and b.distortion.tolist() == [0.1, 0.01, 0, 0, 0]
    msg.distortion_model, msg.d = "", []
    assert ma.camera_info_to_camera(msg).distortion_model == "none"
    msg.distortion_model = "plumb_bob"        # plumb_bob with an empty d: no distortion (as bags)
    assert ma.camera_info_to_camera(msg).distortion_model == "none"


def test_camera_info_errors_name_field():
    cam = CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0)
    msg = ma.camera_to_camera_info(cam, 0, "cam")
    msg.k = np.zeros(9)
    with pytest.raises(InputError, match=r"/camera/camera_info.*field k.*uncalibrated"):
        ma.camera_info_to_camera(msg, "/camera/camera_info")
    msg = ma.camera_to_camera_info(cam, 0, "cam")
    msg.distortion_model = "kannala_brandt_8"
    with pytest.raises(InputError, match=r"/camera/camera_info.*kannala_brandt_8"):
        ma.camera_info_to_camera(msg, "/camera/camera_info")
    msg = ma.camera_to_camera_info(cam, 0, "cam")
    msg.distortion_model, msg.d = "rational_polynomial", [0.1, 0, 0, 0, 0, 0.2, 0, 0]
    with pytest.raises(InputError, match="k4..k6"):
        ma.camera_info_to_camera(msg, "/camera/camera_info")
    msg = ma.camera_to_camera_info(cam, 0, "cam")
    msg.width = 0
    with pytest.raises(InputError, match="width/height"):
        ma.camera_info_to_camera(msg, "/camera/camera_info")
    msg = ma.camera_to_camera_info(cam, 0, "cam")
    msg.k = np.asarray(msg.k).reshape(3, 3).T.reshape(-1)    # written column-major
    with pytest.raises(InputError, match=r"/camera/camera_info.*row-major"):
        ma.camera_info_to_camera(msg, "/camera/camera_info")


# ------------------------------------------------------------------------------------------ imu


def test_imu_round_trip_with_variances():
    from vings_core.types import Calibration
    cal = Calibration(camera=CameraModel(10, 10, 5.0, 5.0, 5.0, 5.0), imu_rate_hz=200.0)
    gv, av = ma.imu_variances(cal)
    assert gv == pytest.approx(cal.gyro_noise_density ** 2 * 200.0)
    s = ImuSample(stamp_ns=1_403_636_579_758_555_392, gyro=np.array([-0.0991, 0.1424, 0.0250]),
                  accel=np.array([8.1476, -0.3799, -2.5869]))
    msg = wire(ma.imu_sample_to_msg(s, "imu_link", gv, av))
    assert msg.header.frame_id == "imu_link" and msg.orientation_covariance[0] == -1.0
    np.testing.assert_array_equal(np.asarray(msg.angular_velocity_covariance).reshape(3, 3),
                                  np.eye(3) * gv)
    np.testing.assert_array_equal(np.asarray(msg.linear_acceleration_covariance).reshape(3, 3),
                                  np.eye(3) * av)
    back = ma.msg_to_imu_sample(msg)
    assert back.stamp_ns == s.stamp_ns
    np.testing.assert_array_equal(back.gyro, s.gyro)
    np.testing.assert_array_equal(back.accel, s.accel)
    msg.linear_acceleration.y = float("nan")
    with pytest.raises(InputError, match=r"/imu/data.*linear_acceleration"):
        ma.msg_to_imu_sample(msg, "/imu/data")
    msg.linear_acceleration.y = 0.0
    cov = np.zeros(9)
    cov[0] = -1.0                                   # "not provided": not a zero reading
    msg.angular_velocity_covariance = cov
    with pytest.raises(InputError, match=r"/imu/data.angular_velocity_covariance\[0\] = -1"):
        ma.msg_to_imu_sample(msg, "/imu/data")
    cov[0] = float("nan")
    msg.angular_velocity_covariance = cov
    with pytest.raises(InputError, match="not finite"):
        ma.msg_to_imu_sample(msg, "/imu/data")


# -------------------------------------------------------------------------------------- poses


def test_pose_stamped_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        T = random_pose(rng, 2.0)
        msg = wire(ma.matrix_to_pose_stamped(T, 123_456_789_012, "map"))
        s, back = ma.pose_stamped_to_matrix(msg)
        assert s == 123_456_789_012 and msg.header.frame_id == "map"
        np.testing.assert_allclose(back, T, atol=1e-12)
        assert msg.pose.orientation.w >= 0


def test_bad_quaternion_raises():
    msg = ma.matrix_to_pose_stamped(np.eye(4), 1, "map")
    msg.pose.orientation.w = 0.0
    with pytest.raises(InputError, match=r"/vings/keyframe/pose.*unit quaternion"):
        ma.pose_stamped_to_matrix(msg, "/vings/keyframe/pose")
    # a matrix whose rotation block is no rotation has no quaternion: refused, not published as
    # another rotation (a reflection came out as the identity)
    for bad in (np.diag([1.0, 1.0, -1.0, 1.0]), np.diag([2.0, 2.0, 2.0, 1.0])):
        with pytest.raises(InputError, match="odom: not a rigid pose"):
            ma.matrix_to_pose_stamped(bad, 1, "map", "odom")


def test_odometry_round_trip_and_frames():
    rng = np.random.default_rng(4)
    T = random_pose(rng, 3.0)
    L = rng.normal(size=(6, 6)) * 0.01
    cov = L @ L.T + np.eye(6) * 1e-6
    est = PoseEstimate(stamp_ns=1_700_000_000_123_456_789, T_wc=T, covariance=cov)
    msg = wire(ma.estimate_to_odometry(est, child_frame_id="cam0_optical_frame"))
    assert msg.header.frame_id == "map" and msg.child_frame_id == "cam0_optical_frame"
    assert msg.twist.covariance[0] == -1.0
    C = np.asarray(msg.pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(C, C.T, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(C) > 0)
    back = ma.odometry_to_estimate(msg)
    assert back.stamp_ns == est.stamp_ns
    np.testing.assert_allclose(back.T_wc, T, atol=1e-12)
    np.testing.assert_allclose(back.covariance, cov, rtol=1e-9, atol=1e-15)
    # unknown covariance <-> covariance[0] = -1
    msg = wire(ma.estimate_to_odometry(PoseEstimate(stamp_ns=5, T_wc=T)))
    assert msg.pose.covariance[0] == -1.0 and ma.odometry_to_estimate(msg).covariance is None
    # a twist (camera frame) when the IMU is fused; non-finite is refused
    msg = wire(ma.estimate_to_odometry(est, twist=([1.0, -2.0, 0.5], [0.1, 0.0, -0.3])))
    tw = msg.twist.twist
    assert (tw.linear.x, tw.linear.y, tw.linear.z) == (1.0, -2.0, 0.5)
    assert (tw.angular.x, tw.angular.y, tw.angular.z) == (0.1, 0.0, -0.3)
    assert msg.twist.covariance[0] != -1.0
    tcov = np.diag([0.01, 0.01, 0.02, 1e-4, 1e-4, 2e-4])
    msg = wire(ma.estimate_to_odometry(est, twist=([1.0, -2.0, 0.5], [0.1, 0.0, -0.3], tcov)))
    np.testing.assert_allclose(np.asarray(msg.twist.covariance).reshape(6, 6), tcov)
    with pytest.raises(InputError, match="twist must be finite"):
        ma.estimate_to_odometry(est, twist=([np.nan, 0, 0], [0, 0, 0]))


def test_odometry_covariance_follows_ros_convention():
    """Sample left perturbations with the tangent covariance; the position error and the world
    fixed-axis rotation error must have the covariance written into the Odometry message."""
    rng = np.random.default_rng(5)
    T_hat = random_pose(rng, 1.0)
    T_hat[:3, 3] = [4.0, -3.0, 2.0]  # far from the origin: rho and position errors differ
    sd = np.array([0.02, 0.01, 0.03, 0.01, 0.02, 0.015])
    Corr = np.eye(6)
    Corr[0, 4] = Corr[4, 0] = 0.3
    cov = Corr * np.outer(sd, sd)
    xi = rng.multivariate_normal(np.zeros(6), cov, size=20000)
    T = np_se3_exp(xi) @ T_hat  # batched
    dt = T[:, :3, 3] - T_hat[:3, 3]
    dth = np_so3_log(T[:, :3, :3] @ T_hat[:3, :3].T)
    emp = np.cov(np.concatenate([dt, dth], 1).T)
    ros = pa.tangent_cov_to_ros(cov, T_hat)
    np.testing.assert_allclose(emp, ros, atol=0.05 * np.abs(ros).max())
    assert np.abs(ros - cov).max() > 0.3 * np.abs(ros).max()  # the conversion matters here


def test_path_round_trip_exact_stamps():
    rng = np.random.default_rng(6)
    n = 300
    stamps = 1_403_636_579_000_000_000 + np.cumsum(rng.integers(1, 10 ** 8, n))
    poses = np.stack([random_pose(rng, 2.0) for _ in range(n)])
    msg = wire(ma.trajectory_to_path(Trajectory(stamps, poses)))
    assert len(msg.poses) == n and msg.header.frame_id == "map"
    assert ma.header_ns(msg.header) == int(stamps[-1])
    back = ma.path_to_trajectory(msg)
    np.testing.assert_array_equal(back.stamps_ns, stamps)
    np.testing.assert_allclose(back.poses, poses, atol=1e-12)
    empty = ma.path_to_trajectory(wire(ma.trajectory_to_path(Trajectory(np.zeros(0), np.zeros((0, 4, 4))))))
    assert len(empty) == 0
    msg.poses[7].pose.orientation.x = 3.0
    with pytest.raises(InputError, match=r"/vings/keyframes/refined.*unit quaternion"):
        ma.path_to_trajectory(msg, "/vings/keyframes/refined")


# -------------------------------------------------------------------------------- point clouds


def test_pointcloud2_round_trip_with_colour():
    rng = np.random.default_rng(7)
    xyz = rng.normal(size=(1000, 3)).astype(np.float32) * 10
    rgb = rng.integers(0, 256, (1000, 3), dtype=np.uint8)
    msg = wire(ma.points_to_pointcloud2(xyz, rgb, 99, "map"))
    assert [f.name for f in msg.fields] == ["x", "y", "z", "rgb"]
    assert all(f.datatype == PointField.FLOAT32 for f in msg.fields)
    assert msg.point_step == 16 and msg.width == 1000 and msg.height == 1 and msg.is_dense
    # PCL packing: rgb float's bits are 0x00RRGGBB
    bits = np.frombuffer(msg.data, np.uint8).reshape(1000, 16)[:, 12:16].copy().view("<u4")[:, 0]
    assert bits[0] == (int(rgb[0, 0]) << 16 | int(rgb[0, 1]) << 8 | int(rgb[0, 2]))
    p, c = ma.pointcloud2_to_points(msg)
    np.testing.assert_array_equal(p, xyz)
    np.testing.assert_array_equal(c, rgb)
    p, c = ma.pointcloud2_to_points(wire(ma.points_to_pointcloud2(torch.from_numpy(xyz))))
    np.testing.assert_array_equal(p, xyz)
    assert c is None
    # float colours in [0, 1]
    _, c = ma.pointcloud2_to_points(ma.points_to_pointcloud2(xyz, rgb / 255.0))
    np.testing.assert_array_equal(c, rgb)
    # integer colours of another dtype are 0..255 already (they all came out 255)
    _, c = ma.pointcloud2_to_points(ma.points_to_pointcloud2(xyz, rgb.astype(np.int64)))
    np.testing.assert_array_equal(c, rgb)
    with pytest.raises(InputError, match=r"integer colours must lie in 0..255, got \[0, 300\]"):
        ma.points_to_pointcloud2(xyz[:2], np.array([[0, 1, 2], [3, 4, 300]]))


def test_pointcloud2_foreign_layout():
    """Organised 2x3 cloud, big-endian, float64 xyz, uint32 rgba, padding and a strided row."""
    rng = np.random.default_rng(8)
    xyz = rng.normal(size=(6, 3))
    rgb = rng.integers(0, 256, (6, 3), dtype=np.uint8)
    dt = np.dtype({"names": ["intensity", "x", "y", "z", "rgba"],
                   "formats": [">f4", ">f8", ">f8", ">f8", ">u4"],
                   "offsets": [0, 8, 16, 24, 32], "itemsize": 40})
    rec = np.zeros(6, dt)
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["rgba"] = ma.pointcloud.pack_rgb(rgb) | np.uint32(0xFF000000)
    rows = rec.view(np.uint8).reshape(2, 3 * 40)
    rows = np.concatenate([rows, np.zeros((2, 8), np.uint8)], 1)  # row padding
    msg = PointCloud2(height=2, width=3, is_bigendian=True, point_step=40, row_step=128,
                      fields=[PointField(name="intensity", offset=0, datatype=7, count=1),
                              PointField(name="x", offset=8, datatype=8, count=1),
                              PointField(name="y", offset=16, datatype=8, count=1),
                              PointField(name="z", offset=24, datatype=8, count=1),
                              PointField(name="rgba", offset=32, datatype=6, count=1)])
    msg.data = ma.image._byte_array(np.ascontiguousarray(rows))
    p, c = ma.pointcloud2_to_points(wire(msg))
    np.testing.assert_allclose(p, xyz.astype(np.float32))
    np.testing.assert_array_equal(c, rgb)
    msg.row_step = 120
    with pytest.raises(InputError, match=r"/vings/map/points.*row_step"):
        ma.pointcloud2_to_points(msg, "/vings/map/points")
    msg.row_step, msg.fields = 128, msg.fields[1:3]
    with pytest.raises(InputError, match=r"/vings/map/points.*'z'"):
        ma.pointcloud2_to_points(msg, "/vings/map/points")


# ---------------------------------------------------------------------------------- diagnostics


def test_diagnostics_round_trip():
    st = [ma.tracking_status("vings/frontend", "lost", {"rate_hz": 19.87654321, "drops": 3,
                                                         "initialised": True}),
          ma.make_status("vings/mapper", "ok", "mapping", {"gaussians": 123456,
                                                            "memory_mb": 1024.5},
                         hardware_id="cpu")]
    msg = wire(ma.diagnostic_array(1_000_000_001, st))
    d = ma.parse_diagnostic_array(msg)
    assert d["stamp_ns"] == 1_000_000_001
    fe, mp = d["status"]["vings/frontend"], d["status"]["vings/mapper"]
    assert fe["level"] == "error" and fe["message"] == "lost"
    assert fe["values"] == {"state": "lost", "rate_hz": "19.8765", "drops": "3",
                            "initialised": "true"}
    assert mp == {"level": "ok", "message": "mapping", "hardware_id": "cpu",
                  "values": {"gaussians": "123456", "memory_mb": "1024.5"}}
    assert ma.parse_diagnostic_array(wire(ma.diagnostic_array(
        0, [ma.tracking_status("fe", "waiting")])))["status"]["fe"]["level"] == "warn"
    with pytest.raises(InputError, match="unknown level"):
        ma.make_status("x", "fine", "")
    with pytest.raises(InputError, match="tracking state"):
        ma.tracking_status("x", "confused")


# -------------------------------------------------------------------------------------- markers


def test_frustum_geometry_projects_to_image_corners():
    cam = CameraModel(640, 480, 500.0, 480.0, 320.0, 240.0)
    rng = np.random.default_rng(9)
    poses = np.stack([np.eye(4), random_pose(rng, 2.0)])
    seg = mk.frustum_segments(poses, cam, scale=0.5)
    assert seg.shape == (32, 3)
    for i, T in enumerate(poses):
        s = seg[16 * i: 16 * (i + 1)]
        Tinv = np.linalg.inv(T)
        local = s @ Tinv[:3, :3].T + Tinv[:3, 3]
        np.testing.assert_allclose(local[0:8:2], 0.0, atol=1e-12)        # optical centre
        corners = local[1:8:2]
        np.testing.assert_allclose(corners[:, 2], 0.5)                    # at depth = scale
        uv = corners[:, :2] / corners[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        np.testing.assert_allclose(uv, [[-0.5, -0.5], [639.5, -0.5], [639.5, 479.5], [-0.5, 479.5]],
                                   atol=1e-9)
        np.testing.assert_allclose(local[8::2], corners)                  # rectangle edges
        np.testing.assert_allclose(local[9::2], np.roll(corners, -1, 0))


def test_marker_array_round_trip():
    from visualization_msgs.msg import Marker
    cam = CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0)
    rng = np.random.default_rng(10)
    poses = np.stack([random_pose(rng) for _ in range(5)])
    fr = ma.keyframe_frustums_marker(poses, cam, 17, scale=0.3)
    tr = ma.trajectory_marker(poses[:, :3, 3], 17)
    arr = wire(ma.marker_array([fr, tr]))
    assert [m.action for m in arr.markers] == [Marker.DELETEALL, Marker.ADD, Marker.ADD]
    f2, t2 = arr.markers[1], arr.markers[2]
    assert f2.type == Marker.LINE_LIST and t2.type == Marker.LINE_STRIP
    assert f2.header.frame_id == "map" and ma.header_ns(f2.header) == 17
    assert f2.ns == "keyframes" and t2.ns == "trajectory" and f2.color.a == 1.0
    np.testing.assert_allclose(ma.marker_points(f2), mk.frustum_segments(poses, cam, 0.3))
    np.testing.assert_allclose(ma.marker_points(t2), poses[:, :3, 3])
    assert len(ma.keyframe_frustums_marker(np.zeros((0, 4, 4)), cam, 0).points) == 0


# ------------------------------------------------------------------------------------ keyframes


def _keyframe(stamp=1_403_636_580_013_555_456, w=40, h=30, seed=11):
    rng = np.random.default_rng(seed)
    cam = CameraModel(w, h, 30.0, 31.0, 19.5, 14.5)
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8).astype(np.float32) / 255.0
    depth = rng.uniform(0.5, 20, (h, w)).astype(np.float32)
    valid = rng.random((h, w)) > 0.2
    var = rng.uniform(1e-4, 1.0, (h, w)).astype(np.float32)
    return Keyframe(stamp_ns=stamp, image=torch.from_numpy(img), T_wc=random_pose(rng, 1.0),
                    depth=torch.from_numpy(depth), inv_depth_var=torch.from_numpy(var),
                    valid=torch.from_numpy(valid), camera=cam, index=4)


def test_keyframe_packet_round_trip():
    kf = _keyframe()
    msgs = kfa.keyframe_to_msgs(kf)
    parts = {k: wire(m) for k, m in msgs.as_dict().items()}
    for k, m in parts.items():
        assert ma.header_ns(m.header) == kf.stamp_ns, k
    assert parts["pose"].header.frame_id == "map"
    assert parts["image"].header.frame_id == "camera_optical_frame"
    assert parts["depth"].encoding == "32FC1" and parts["inv_depth_var"].encoding == "32FC1"
    back = ma.msgs_to_keyframe(**parts)
    assert back.stamp_ns == kf.stamp_ns and back.camera == kf.camera
    assert torch.equal(back.image, kf.image)  # k/255 survives exactly
    assert torch.equal(back.valid, kf.valid)
    assert torch.equal(back.depth, torch.where(kf.valid, kf.depth, torch.zeros(())))
    assert torch.equal(back.inv_depth_var, kf.inv_depth_var)
    torch.testing.assert_close(back.T_wc, kf.T_wc, atol=1e-12, rtol=0)


def test_keyframe_assembler_pairs_by_stamp_and_drops_incomplete():
    kfs = [_keyframe(stamp=1000 + i, seed=i) for i in range(4)]
    packets = [kfa.keyframe_to_msgs(k).as_dict() for k in kfs]
    asm = ma.KeyframeAssembler()
    out = []
    # keyframe 1 loses its depth part; parts of 0 and 2 interleave across topics
    order = [(0, "image"), (0, "pose"), (1, "image"), (0, "depth"), (1, "pose"), (0, "camera_info"),
             (2, "image"), (1, "inv_depth_var"), (1, "camera_info"), (2, "depth"), (2, "pose"),
             (0, "inv_depth_var"), (2, "inv_depth_var"), (2, "camera_info"), (3, "image")]
    for i, part in order:
        k = asm.add(part, packets[i][part])
        if k is not None:
            out.append(k.stamp_ns)
    assert out == [1000, 1002]
    assert asm.dropped == 1 and asm.pending == 1 and asm.completed == 2
    # with a known camera, camera_info is not needed
    asm2 = ma.KeyframeAssembler(camera=kfs[3].camera)
    got = [asm2.add(p, packets[3][p]) for p in ("image", "depth", "inv_depth_var", "pose")]
    assert got[:3] == [None] * 3 and got[3].stamp_ns == 1003


def test_keyframe_parts_must_agree():
    a, b = kfa.keyframe_to_msgs(_keyframe(stamp=1)), kfa.keyframe_to_msgs(_keyframe(stamp=2))
    with pytest.raises(InputError, match="different stamps"):
        ma.msgs_to_keyframe(a.image, a.depth, b.inv_depth_var, a.pose, a.camera_info)
    small = kfa.keyframe_to_msgs(_keyframe(stamp=1, w=20, h=10))
    with pytest.raises(InputError, match=r"/vings/keyframe/depth.*20x10.*40x30"):
        ma.msgs_to_keyframe(a.image, small.depth, a.inv_depth_var, a.pose, a.camera_info)


def test_keyframe_variance_nan_means_unknown_and_negative_is_refused():
    """A third-party publisher's NaN variance ("unknown") reaches the mapper as inf (which its input
    check accepts); a negative variance is refused here, naming the topic."""
    from dataclasses import replace
    kf = _keyframe()
    var = kf.inv_depth_var.clone()
    var[0, :5] = float("nan")
    parts = {k: wire(m) for k, m in kfa.keyframe_to_msgs(replace(kf, inv_depth_var=var)).as_dict().items()}
    back = ma.msgs_to_keyframe(**parts)
    assert torch.isinf(back.inv_depth_var[0, :5]).all() and not torch.isnan(back.inv_depth_var).any()
    var[0, :5] = -1.0
    parts = {k: wire(m) for k, m in kfa.keyframe_to_msgs(replace(kf, inv_depth_var=var)).as_dict().items()}
    with pytest.raises(InputError, match="/vings/keyframe/inv_depth_var.*negative"):
        ma.msgs_to_keyframe(**parts)


def test_rectified_image_topic_takes_the_projection_matrix():
    """An image topic remapped to image_proc's rectified output: the camera is P without
    distortion (K and D describe the raw sensor); no P is an error naming the field."""
    from vings_core.io.calib_yaml import is_rectified_topic
    assert is_rectified_topic("/cam/image_rect") and is_rectified_topic("/cam/image_rect_color/compressed")
    assert not is_rectified_topic("/cam/image_raw/compressed") and not is_rectified_topic("")
    cam = CameraModel(64, 48, 50.0, 50.0, 31.5, 23.5, "radtan", np.array([-0.3, 0.1, 0, 0, 0]))
    msg = ma.camera_to_camera_info(cam, 0, "cam")
    msg.p = [45.0, 0.0, 30.0, 0.0, 0.0, 45.0, 22.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    assert ma.camera_info_to_camera(wire(msg)).distortion_model == "radtan"
    rect = ma.camera_info_to_camera(wire(msg), rectified=True)
    assert rect == CameraModel(64, 48, 45.0, 45.0, 30.0, 22.0)
    msg.p = [0.0] * 12
    with pytest.raises(InputError, match="rectified images but field p"):
        ma.camera_info_to_camera(wire(msg), rectified=True)


def test_exchange_batch_round_trip_keeps_increments_scale_and_acks():
    from nav_msgs.msg import Path

    from msg_adapters.exchange import batch_to_path, exchange_topic, path_to_batch
    from vings_core.exchange import IncrementBatch
    from vings_core.geometry import np_pose, np_so3_exp, sim3

    rng = np.random.default_rng(4)
    incs = {1_000_000_123: np_pose(np_so3_exp(rng.normal(size=3)), rng.normal(size=3)),
            2_000_000_456: sim3(np_so3_exp(rng.normal(size=3)), rng.normal(size=3), 0.8)}
    b = IncrementBatch("loop_closer", 17, incs, {"frontend": 12})
    msg = deserialize_message(serialize_message(batch_to_path(b, "map")), Path)
    assert msg.header.frame_id == "map" and exchange_topic("mapper") == "/vings/exchange/mapper"
    back = path_to_batch(msg, "loop_closer")
    assert back.source == "loop_closer" and back.seq == 17 and back.acks == {"frontend": 12}
    assert set(back.increments) == set(incs)
    for s, C in incs.items():
        np.testing.assert_allclose(back.increments[s], C, atol=1e-12)


def test_exchange_batch_malformed_message_names_the_topic():
    from msg_adapters.exchange import batch_to_path, path_to_batch
    from vings_core.exchange import IncrementBatch

    msg = batch_to_path(IncrementBatch("mapper", 3, {5: np.eye(4)}))
    msg.poses[0].pose.orientation.w = 0.0
    with pytest.raises(InputError, match="/vings/exchange/mapper.poses.0..pose"):
        path_to_batch(msg, "mapper")
