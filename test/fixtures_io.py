"""Small recordings built in tmp_path for the I/O tests (written by hand, not by vings writers, so the
loaders are checked against the formats themselves)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np
import yaml

# EuRoC-like cam0 of a 64x48 sensor
FX, FY, CX, CY = 50.0, 52.0, 31.5, 23.5
W, H = 64, 48
T_BC = np.array([[0.0, -1.0, 0.0, 0.05], [1.0, 0.0, 0.0, -0.02], [0.0, 0.0, 1.0, 0.01],
                 [0.0, 0.0, 0.0, 1.0]])
T0 = 1_700_000_000_000_000_000


def texture(i: int, w: int = W, h: int = H, color: bool = False) -> np.ndarray:
    """Deterministic textured uint8 image (RGB if ``color``)."""
    rng = np.random.default_rng(i)
    img = rng.integers(0, 256, size=(h, w, 3) if color else (h, w), dtype=np.uint8)
    return img


def write_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    out = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    assert cv2.imwrite(str(path), out)


def imu_series(n: int, t0: int = T0, dt: int = 5_000_000):
    st = t0 + np.arange(n, dtype=np.int64) * dt
    g = np.stack([0.01 * np.sin(np.arange(n) * 0.1), 0.02 * np.ones(n), -0.01 * np.arange(n) / n], 1)
    a = np.stack([0.1 * np.ones(n), 0.2 * np.cos(np.arange(n) * 0.1), 9.81 * np.ones(n)], 1)
    return st, g, a


def gt_series(n: int, t0: int = T0, dt: int = 50_000_000):
    from vings_core.geometry import np_so3_exp
    st = t0 + np.arange(n, dtype=np.int64) * dt
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = np_so3_exp(np.array([0.01 * i, 0.02 * i, 0.03]))
        T[i, :3, 3] = [0.1 * i, -0.05 * i, 1.0]
    return st, T


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    from vings_core.geometry import np_rotmat_to_quat
    return np_rotmat_to_quat(R)


# ---------------------------------------------------------------------------------------- EuRoC


def make_euroc(root: Path, n: int = 5, color: bool = False, distortion: Optional[Sequence[float]] = None,
               model: str = "radial-tangential", imu_n: int = 60, gt: bool = True,
               depth: bool = False, mask: bool = False, stamps: Optional[Sequence[int]] = None,
               imu_stamps: Optional[Sequence[int]] = None, cam_yaml: bool = True) -> Path:
    """EuRoC folder ``root/mav0/...``; frames every 50 ms from T0; IMU at 200 Hz."""
    mav0 = root / "mav0"
    st = list(stamps) if stamps is not None else [T0 + i * 50_000_000 for i in range(n)]
    rows = ["#timestamp [ns],filename"]
    for i, s in enumerate(st):
        name = f"{s}.png" if stamps is None else f"{i}_{s}.png"  # given stamps may repeat
        write_png(mav0 / "cam0" / "data" / name, texture(i, color=color))
        rows.append(f"{s},{name}")
        if depth:
            (mav0 / "depth0" / "data").mkdir(parents=True, exist_ok=True)
            np.save(mav0 / "depth0" / "data" / f"{s}.npy", np.full((H, W), 1.0 + i, np.float32))
        if mask:
            m = np.zeros((H, W), np.uint8)
            m[10:20, 5:25] = 255
            write_png(mav0 / "mask0" / "data" / f"{s}.png", m)
    (mav0 / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
    if cam_yaml:
        (mav0 / "cam0" / "sensor.yaml").write_text(
            "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: "
            + str([float(v) for v in T_BC.reshape(-1)]) + "\nrate_hz: 20\nresolution: [64, 48]\n"
            f"camera_model: pinhole\nintrinsics: [{FX}, {FY}, {CX}, {CY}]\n"
            f"distortion_model: {model}\ndistortion_coefficients: "
            + str(list(distortion) if distortion is not None else [0.0, 0.0, 0.0, 0.0]) + "\n")
    if imu_n:
        ist, g, a = imu_series(imu_n)
        if imu_stamps is not None:
            ist = np.asarray(imu_stamps, dtype=np.int64)
            g, a = g[: len(ist)], a[: len(ist)]
        lines = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                 "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
        lines += [f"{s},{gg[0]!r},{gg[1]!r},{gg[2]!r},{aa[0]!r},{aa[1]!r},{aa[2]!r}"
                  for s, gg, aa in zip(ist.tolist(), g.tolist(), a.tolist())]
        (mav0 / "imu0").mkdir(parents=True, exist_ok=True)
        (mav0 / "imu0" / "data.csv").write_text("\n".join(lines) + "\n")
        (mav0 / "imu0" / "sensor.yaml").write_text(
            "%YAML:1.0\nsensor_type: imu\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, "
            "0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\nrate_hz: 200\n"
            "gyroscope_noise_density: 1.0e-4\ngyroscope_random_walk: 2.0e-5\n"
            "accelerometer_noise_density: 3.0e-3\naccelerometer_random_walk: 4.0e-3\n")
    if gt:
        gst, T = gt_series(max(n, 2))
        lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
                 "q_RS_z [], v_x, v_y, v_z"]
        for s, P in zip(gst.tolist(), T):
            q = quat_xyzw(P[:3, :3])
            v = [float(x) for x in (P[0, 3], P[1, 3], P[2, 3], q[3], q[0], q[1], q[2])]
            lines.append(f"{s}," + ",".join(repr(x) for x in v) + ",0,0,0")
        (mav0 / "state_groundtruth_estimate0").mkdir(parents=True, exist_ok=True)
        (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(lines) + "\n")
    return root


# ------------------------------------------------------------------------------------------ TUM


def make_tum(root: Path, n: int = 4, calib: bool = True, depth: bool = True,
             stamps_s: Optional[Sequence[str]] = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    st = list(stamps_s) if stamps_s is not None else [f"1305031102.{175304 + i * 33333:06d}" for i in range(n)]
    rgb = ["# color images", "# file: 'rgbd_dataset_test.bag'", "# timestamp filename"]
    dep = ["# depth maps", "# file", "# timestamp filename"]
    gtl = ["# ground truth trajectory", "# file", "# timestamp tx ty tz qx qy qz qw"]
    for i, s in enumerate(st):
        write_png(root / "rgb" / f"{s}.png", texture(i, color=True))
        rgb.append(f"{s} rgb/{s}.png")
        if depth:
            d = np.full((H, W), 5000 * (1 + i), np.uint16)  # (1 + i) metres
            write_png(root / "depth" / f"{s}.png", d)
            dep.append(f"{s} depth/{s}.png")
        gtl.append(f"{s} {0.1 * i} 0.2 0.3 0.0 0.0 0.0 1.0")
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    if depth:
        (root / "depth.txt").write_text("\n".join(dep) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gtl) + "\n")
    if calib:
        (root / "calib.yaml").write_text(yaml.safe_dump(
            {"image_width": W, "image_height": H, "camera_matrix": {"rows": 3, "cols": 3, "data":
             [FX, 0, CX, 0, FY, CY, 0, 0, 1]}, "distortion_model": "plumb_bob",
             "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0, 0, 0, 0, 0]}}))
    return root


# ---------------------------------------------------------------------------------------- KITTI


def make_kitti(root: Path, n: int = 4, image_dir: str = "image_0", labelled: bool = True,
               poses: str = "poses.txt", times: bool = True, color: bool = False) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        write_png(root / image_dir / f"{i:06d}.png", texture(i, color=color))
    P = [f"{FX} 0 {CX} 0 0 {FX} {CY} 0 0 0 1 0", f"{FX} 0 {CX} -20 0 {FX} {CY} 0 0 0 1 0",
         f"{FX} 0 {CX} 2.5 0 {FX} {CY} 0.1 0 0 1 0.005", f"{FX} 0 {CX} -17 0 {FX} {CY} 0 0 0 1 0"]
    lines = [f"P{i}: {p}" if labelled else p for i, p in enumerate(P)]
    (root / "calib.txt").write_text("\n".join(lines) + "\n")
    if times:
        (root / "times.txt").write_text("\n".join(f"{0.1 * i:.6e}" for i in range(n)) + "\n")
    rows = []
    for i in range(n):
        T = np.eye(4)
        T[2, 3] = 1.0 * i
        rows.append(" ".join(f"{v:.6e}" for v in T[:3].reshape(-1)))
    if poses == "poses.txt":
        (root / "poses.txt").write_text("\n".join(rows) + "\n")
    elif poses == "poses/NN":
        (root / "poses").mkdir()
        (root / "poses" / f"{root.name}.txt").write_text("\n".join(rows) + "\n")
    return root


# ------------------------------------------------------------------------------------------ bags


@dataclass
class BagSpec:
    """What :func:`make_bag` writes. Image stamps in ns; IMU stamps; encodings per image topic."""

    image_topics: dict = field(default_factory=lambda: {"/cam0/image_raw": "mono8"})
    image_stamps: Optional[Sequence[int]] = None
    n_images: int = 4
    imu_topics: Sequence[str] = ("/imu0",)
    imu_stamps: Optional[Sequence[int]] = None
    n_imu: int = 40
    camera_info: Optional[str] = "/cam0/camera_info"
    distortion_model: str = "plumb_bob"
    D: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    gt_topic: Optional[str] = None
    gt_type: str = "geometry_msgs/msg/PoseStamped"
    corrupt_image_index: Optional[int] = None   # JPEG bytes garbled / raw data truncated
    empty_topics: Sequence[str] = ()
    zero_header: bool = False
    gyro_cov0: float = 0.0          # -1 marks the gyro as unavailable
    info_scale: int = 1             # CameraInfo of a sensor this many times larger, binned by it
    R: Optional[Sequence[float]] = None   # CameraInfo rectification rotation (9 values; None = I)


def image_payload(i: int, encoding: str) -> tuple[np.ndarray, np.ndarray]:
    """(expected decoded array, raw buffer) for a test image in ``encoding``."""
    if encoding in ("mono8",):
        a = texture(i)
        return a, a.reshape(-1)
    if encoding == "rgb8":
        a = texture(i, color=True)
        return a, a.reshape(-1)
    if encoding == "bgr8":
        a = texture(i, color=True)
        return a, np.ascontiguousarray(a[..., ::-1]).reshape(-1)
    if encoding == "rgba8":
        a = texture(i, color=True)
        return a, np.concatenate([a, np.full((H, W, 1), 255, np.uint8)], 2).reshape(-1)
    if encoding == "bgra8":
        a = texture(i, color=True)
        return a, np.concatenate([a[..., ::-1], np.full((H, W, 1), 7, np.uint8)], 2).reshape(-1)
    if encoding == "16UC1":
        a = (texture(i).astype(np.uint16) * 256 + 3)
        return a, a.astype("<u2").view(np.uint8).reshape(-1)
    if encoding == "32FC1":
        a = texture(i).astype(np.float32) / 255.0
        return a, a.astype("<f4").view(np.uint8).reshape(-1)
    raise ValueError(encoding)


def make_bag(path: Path, spec: BagSpec, storage: str = "mcap") -> Path:
    """Write a bag: ``storage`` in ``mcap`` (ROS 2 folder), ``sqlite3`` (ROS 2 folder), ``plain``
    (one .mcap file; ``path`` must end in .mcap) or ``ros1`` (``path`` ends in .bag)."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = storage == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    T = ts.types
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr

    def hdr(s: int, frame: str):
        s = 0 if spec.zero_header else s
        kw = {"seq": 0} if ros1 else {}
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=s // 10**9, nanosec=s % 10**9), frame_id=frame, **kw)

    img_st = list(spec.image_stamps) if spec.image_stamps is not None else \
        [T0 + i * 50_000_000 for i in range(spec.n_images)]
    imu_st = list(spec.imu_stamps) if spec.imu_stamps is not None else \
        [T0 + i * 5_000_000 for i in range(spec.n_imu)]
    msgs = []  # (t, topic, type, bytes)
    for topic, enc in spec.image_topics.items():
        for i, s in enumerate(img_st):
            if enc.startswith("compressed-"):
                fmt = enc.split("-", 1)[1]
                ok, buf = cv2.imencode("." + fmt, cv2.cvtColor(texture(i, color=True), cv2.COLOR_RGB2BGR))
                data = buf.reshape(-1)
                if spec.corrupt_image_index == i:
                    data = np.frombuffer(b"\x00garbage" * 10, np.uint8)
                m = T["sensor_msgs/msg/CompressedImage"](header=hdr(s, "cam0"), format=fmt, data=data)
                msgs.append((s, topic, "sensor_msgs/msg/CompressedImage", ser(m, "sensor_msgs/msg/CompressedImage")))
                continue
            arr, raw = image_payload(i, enc)
            step = raw.size // H
            if spec.corrupt_image_index == i:
                raw = raw[: raw.size // 2]
            m = T["sensor_msgs/msg/Image"](header=hdr(s, "cam0"), height=H, width=W, encoding=enc,
                                           is_bigendian=0, step=step, data=raw)
            msgs.append((s, topic, "sensor_msgs/msg/Image", ser(m, "sensor_msgs/msg/Image")))
    for topic in spec.imu_topics:
        ist, g, a = imu_series(len(imu_st))
        for s, gg, aa in zip(imu_st, g, a):
            V3 = T["geometry_msgs/msg/Vector3"]
            m = T["sensor_msgs/msg/Imu"](
                header=hdr(s, "imu"), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.array([-1.0] + [0.0] * 8),
                angular_velocity=V3(x=gg[0], y=gg[1], z=gg[2]),
                angular_velocity_covariance=np.array([spec.gyro_cov0] + [0.0] * 8),
                linear_acceleration=V3(x=aa[0], y=aa[1], z=aa[2]),
                linear_acceleration_covariance=np.zeros(9))
            msgs.append((s, topic, "sensor_msgs/msg/Imu", ser(m, "sensor_msgs/msg/Imu")))
    if spec.camera_info:
        b = spec.info_scale
        K = np.array([FX * b, 0, CX * b, 0, FY * b, CY * b, 0, 0, 1.0])
        P = np.array([FX, 0, CX, 0, 0, FY, CY, 0, 0, 0, 1.0, 0])
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                     do_rectify=False)
        kw = dict(D=np.array(spec.D, float), K=K, R=np.eye(3).reshape(-1), P=P) if ros1 else \
            dict(d=np.array(spec.D, float), k=K, r=np.eye(3).reshape(-1) if spec.R is None else np.array(spec.R, float), p=P)
        for s in img_st[:2]:
            m = T["sensor_msgs/msg/CameraInfo"](header=hdr(s, "cam0"), height=H * b, width=W * b,
                                                distortion_model=spec.distortion_model,
                                                binning_x=0 if b == 1 else b,
                                                binning_y=0 if b == 1 else b, roi=roi, **kw)
            msgs.append((s, spec.camera_info, "sensor_msgs/msg/CameraInfo", ser(m, "sensor_msgs/msg/CameraInfo")))
    if spec.gt_topic:
        gst, TT = gt_series(len(img_st))
        for s, Pm in zip(gst, TT):
            q = quat_xyzw(Pm[:3, :3])
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=Pm[0, 3], y=Pm[1, 3], z=Pm[2, 3]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
            if spec.gt_type.endswith("Odometry"):
                m = T["nav_msgs/msg/Odometry"](
                    header=hdr(int(s), "world"), child_frame_id="base",
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                    twist=T["geometry_msgs/msg/TwistWithCovariance"](
                        twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                           angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                        covariance=np.zeros(36)))
            else:
                m = T["geometry_msgs/msg/PoseStamped"](header=hdr(int(s), "world"), pose=pose)
            msgs.append((int(s), spec.gt_topic, spec.gt_type, ser(m, spec.gt_type)))

    if ros1:
        from rosbags.rosbag1 import Writer as W1
        w = W1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer as W2
        plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
        w = W2(path if storage != "plain" else path.with_suffix(""), version=9, storage_plugin=plugin)
    with w:
        conns = {}
        types = {}
        for _, topic, typ, _ in msgs:
            types.setdefault(topic, typ)
        for topic in spec.empty_topics:
            types.setdefault(topic, "sensor_msgs/msg/Image")
        for topic, typ in types.items():
            conns[topic] = w.add_connection(topic, typ, typestore=ts)
        if spec.image_stamps is None:  # bag (log) time = the stamp the message was made for
            for t, topic, _, data in sorted(msgs, key=lambda x: x[0]):
                w.write(conns[topic], int(t), data)
        else:  # header stamps as given, written in list order with increasing log times
            for k, (t, topic, _, data) in enumerate(msgs):
                w.write(conns[topic], T0 + k * 1000, data)
    if storage == "plain":
        folder = path.with_suffix("")
        (folder / f"{folder.name}.mcap").rename(path)
        import shutil
        shutil.rmtree(folder)
    return path
