"""ROS 1 bags, ROS 2 bags (sqlite3 or mcap storage) and plain ``.mcap`` files, via rosbags' AnyReader.

Messages read: ``sensor_msgs/Image`` (any encoding of :mod:`image_codec`), ``CompressedImage``
(JPEG/PNG), ``Imu``, ``CameraInfo``; ground truth from a ``PoseStamped``,
``PoseWithCovarianceStamped``, ``Odometry`` or ``TransformStamped`` topic (the body pose).

Topics: chosen by ``SourceOptions.image_topic``/``imu_topic``/``camera_info_topic``/``gt_topic``, or
detected by message type: one non-empty topic of the type is used; several are an error listing them
(camera info: the one sharing the image topic's namespace). Ground truth is read from ``gt_topic``
or, by default, ``/ground_truth/pose`` when present.

Stamps are the message ``header.stamp``; a zero header stamp falls back to the bag's receive time
(with a warning). Calibration: ``SourceOptions.calib_file``, else ``<stem>.calib.yaml`` beside the
file/folder (what :func:`vings_core.io.write_mcap` writes), else the CameraInfo topic; a calibration
YAML may add ``T_bc`` and IMU noise to a CameraInfo.

Memory: the constructor reads the bag once keeping only stamps, IMU, camera info and ground truth
(and decodes the first image for its size); :meth:`frames` reads the image topic again.
"""
from __future__ import annotations

import contextlib
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from ..errors import InputError
from ..geometry import np_project_rotation, np_quat_to_rotmat, rotation_angle_deg
from ..trajectory_io import sec_nsec_to_ns
from ..types import CameraModel, Frame
from .base import SourceOptions
from .calib_yaml import (CalibParts, camera_info_intrinsics, camera_topic, distortion_model_name,
                         is_rectified_topic, make_camera, read_calibration_parts, rectified_camera_matrix,
                         topic_namespace)
from .common import LoaderSource, check_size, late_entries, order_stamps
from .image_codec import decode_compressed, decode_image

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED)
IMU = "sensor_msgs/msg/Imu"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
GT_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
            "nav_msgs/msg/Odometry", "geometry_msgs/msg/TransformStamped")
DEFAULT_GT_TOPIC = "/ground_truth/pose"


def calib_yaml_beside(path: Path) -> Optional[Path]:
    """``<stem>.calib.yaml`` beside a bag file/folder, or ``calib.yaml`` inside a bag folder; for a
    symbolic link, also beside the file it points to."""
    path = Path(path)
    cands = []
    for p in dict.fromkeys((path, path.resolve())):     # the link first, then its target
        stem = p.name if p.is_dir() else p.stem
        cands.append(p.parent / f"{stem}.calib.yaml")
        if p.is_dir():
            cands += [p / "calib.yaml", p / f"{stem}.calib.yaml"]
    return next((c for c in cands if c.is_file()), None)


def header_stamp_ns(raw: bytes, ros1: bool, where: str) -> int:
    """``header.stamp`` of a serialized message whose first field is a std_msgs/Header."""
    if len(raw) < 12:
        raise InputError(f"{where}: message of {len(raw)} bytes is too short to hold a header")
    if ros1:  # uint32 seq, uint32 sec, uint32 nsec
        sec, nsec = struct.unpack_from("<II", raw, 4)
    else:  # CDR: 4-byte encapsulation (byte 1: 1 = little endian), int32 sec, uint32 nanosec
        e = "<" if raw[1] == 1 else ">"
        sec, nsec = struct.unpack_from(e + "iI", raw, 4)
    return sec_nsec_to_ns(sec, nsec, f"{where}: header stamp")


def _stamp_of(msg, where: str) -> int:
    st = msg.header.stamp
    return sec_nsec_to_ns(st.sec, getattr(st, "nanosec", getattr(st, "nsec", 0)), f"{where}: header stamp")


def _field(msg, *names):
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


def camera_from_camera_info(msg, where: str, rectified: bool = False) -> Optional[CameraModel]:
    """A CameraInfo message (ROS 1 or 2 field names) -> raw CameraModel of the recorded image
    (region of interest and binning applied, :func:`camera_info_intrinsics`), or None if
    uncalibrated (K = 0). ``rectified``: the image topic carries rectified images (``image_rect``);
    its camera is then the projection matrix ``P[:3, :3]`` without distortion (ROS convention:
    ``K``/``D`` describe the raw sensor, which would undistort the images a second time)."""
    if rectified:
        K, D = rectified_camera_matrix(_field(msg, "p", "P"), where), np.zeros(0)
    else:
        K = np.asarray(_field(msg, "k", "K"), dtype=np.float64).reshape(3, 3)
        D = np.asarray(_field(msg, "d", "D"), dtype=np.float64).reshape(-1)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return None
    name = "none" if rectified else (msg.distortion_model or ("plumb_bob" if np.any(D) else "none"))
    model = distortion_model_name(name, f"{where}: distortion_model")
    if model == "equidistant":
        D = D[:4]
    roi = msg.roi
    w, h, fx, fy, cx, cy = camera_info_intrinsics(
        K, int(msg.width), int(msg.height), (roi.x_offset, roi.y_offset, roi.width, roi.height),
        (msg.binning_x, msg.binning_y), where)
    return make_camera(w, h, fx, fy, cx, cy, model, D, where)


def pose_of(msg, msgtype: str) -> np.ndarray:
    if msgtype.endswith("TransformStamped"):
        t, q = msg.transform.translation, msg.transform.rotation
    else:
        p = msg.pose.pose if msgtype.endswith(("Odometry", "PoseWithCovarianceStamped")) else msg.pose
        t, q = p.position, p.orientation
    T = np.eye(4)
    qq = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    n = np.linalg.norm(qq)
    T[:3, :3] = np_quat_to_rotmat(qq / n) if n > 1e-9 else np.full((3, 3), np.nan)
    T[:3, 3] = [t.x, t.y, t.z]
    return T


# images whose header stamps are out of recording order wait in a buffer of at most this many
# (raw messages, counting the one just read) to be delivered in time order; a later image is dropped, warned
REORDER_WINDOW = 256


def _non_ros_mcap_channels(path: Path) -> list[str]:
    """``'topic' (encoding)`` of the channels of an MCAP file (or of the ``.mcap`` files of a
    rosbag2 folder) whose messages are not ROS 1/ROS 2 encoded (JSON, protobuf, ...): rosbags
    cannot open a file holding any. Empty when there are none or the file cannot be read."""
    files = [path] if path.is_file() else sorted(path.glob("*.mcap")) if path.is_dir() else []
    out = []
    for f in files:
        if f.suffix != ".mcap":
            continue
        try:
            from mcap.reader import make_reader
            with open(f, "rb") as fh:
                summary = make_reader(fh).get_summary()
        except Exception:  # noqa: BLE001 - only a better message is at stake
            continue
        if summary is None:
            continue
        out += [f"{c.topic!r} ({c.message_encoding})" for c in summary.channels.values()
                if c.message_encoding not in ("cdr", "ros1")]
    return out


@dataclass
class _Scan:
    """What :meth:`BagSource._first_pass` keeps of one read: image stamps (ns) and the first image,
    IMU stamps (ns) and values (gyro rad/s, accel m/s^2), the first usable CameraInfo, ground-truth
    stamps (ns) and poses, how many messages per topic fell back to the receive time, and how many
    IMU messages marked gyro / accel unavailable."""

    img_st: list[int] = field(default_factory=list)
    img_zero: int = 0
    first_img: Optional[np.ndarray] = None
    imu_st: list[int] = field(default_factory=list)
    imu_v: list[tuple] = field(default_factory=list)
    imu_missing: dict[str, int] = field(default_factory=lambda: {"gyro": 0, "accel": 0})
    imu_zero: int = 0
    cam_msg: object = None
    gt_st: list[int] = field(default_factory=list)
    gt_T: list[np.ndarray] = field(default_factory=list)
    gt_zero: int = 0


class BagSource(LoaderSource):
    """ROS 1 ``.bag``, ROS 2 bag folder (``metadata.yaml``), ``.db3`` or plain ``.mcap`` (module doc)."""

    def __init__(self, path: str | Path, options: Optional[SourceOptions] = None) -> None:
        path = Path(path)
        if path.is_dir() and not (path / "metadata.yaml").is_file():
            inner = sorted(list(path.glob("*.mcap")) + list(path.glob("*.db3")))
            if len(inner) == 1:
                path = inner[0]
        suffix = path.suffix.lower()
        super().__init__(path, "mcap" if suffix == ".mcap" else "bag", options)
        if not self.path.exists():
            raise InputError(f"{self.path}: bag not found")
        if suffix in (".mcap", ".bag", ".db3") and path.suffix != suffix:
            raise InputError(f"{self.path}: the bag reader (rosbags) recognises only the lower-case "
                             f"suffix {suffix!r}; rename the file (or link it) with that suffix")
        self._ros1 = suffix == ".bag"
        self.format = ("ROS 1 bag" if self._ros1 else "MCAP file" if suffix == ".mcap"
                       else "ROS 2 bag folder" if self.path.is_dir() else "ROS 2 sqlite3 file")
        o = self.options
        with self._open() as r:
            self.topic_table = {n: {"type": i.msgtype, "count": int(i.msgcount)}
                                for n, i in r.topics.items()}
            self.image_topic = self._pick("image", o.image_topic, IMAGE_TYPES)
            self.imu_topic = self._pick("IMU", o.imu_topic, (IMU,))
            self._camera_info_note = ""
            self.camera_info_topic = self._pick_camera_info(o.camera_info_topic)
            self.gt_topic = self._pick("ground-truth", o.gt_topic, GT_TYPES) if o.gt_topic else None
            if not o.gt_topic and DEFAULT_GT_TOPIC in self.topic_table:
                # the default topic only when usable: nobody asked for it, so never a hard error
                info = self.topic_table[DEFAULT_GT_TOPIC]
                if info["type"] in GT_TYPES and info["count"] > 0:
                    self.gt_topic = DEFAULT_GT_TOPIC
                else:
                    self._warn(f"{self.path}: {DEFAULT_GT_TOPIC} ({info['type']}, {info['count']} "
                               f"msgs) is not a usable ground-truth topic; no ground truth")
            self._first_pass(r)

    # -- reader --------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _open(self):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
        store = get_typestore(Stores.ROS1_NOETIC if self._ros1 else Stores.ROS2_JAZZY)
        try:
            r = AnyReader([self.path], default_typestore=store)
            r.open()
        except Exception as e:  # noqa: BLE001 - rosbags raises many kinds; report them uniformly
            foreign = _non_ros_mcap_channels(self.path)
            if foreign:
                raise InputError(f"{self.path}: cannot open {self.format}: it has channels that are not "
                                 f"ROS messages ({', '.join(foreign)}); VINGS reads ROS 1/ROS 2 messages "
                                 f"only: drop those channels, e.g. `mcap filter -n '<their topics>'`"
                                 ) from None
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise InputError(f"{self.path}: cannot open {self.format}: {first}") from None
        try:
            yield r
        finally:
            with contextlib.suppress(Exception):
                r.close()

    def _conns(self, r, topic: Optional[str]) -> list:
        return [c for c in r.connections if c.topic == topic] if topic else []

    def _deser(self, r, raw, conn, where: str):
        try:
            return r.deserialize(raw, conn.msgtype)
        except Exception as e:  # noqa: BLE001
            raise InputError(f"{where}: cannot deserialize {conn.msgtype}: {e}") from None

    # -- topic choice ----------------------------------------------------------------------------
    def _topics_of(self, types) -> list[str]:
        return sorted(t for t, i in self.topic_table.items() if i["type"] in types)

    def _describe(self) -> str:
        return ", ".join(f"{t} ({i['type']}, {i['count']} msgs)" for t, i in
                         sorted(self.topic_table.items())) or "none"

    def _pick(self, role: str, requested: Optional[str], types) -> Optional[str]:
        if requested:
            if requested not in self.topic_table:
                raise InputError(f"{self.path}: {role} topic {requested!r} not found; topics in the "
                                 f"bag: {self._describe()}")
            info = self.topic_table[requested]
            if info["type"] not in types:
                raise InputError(f"{self.path}: {role} topic {requested!r} has type {info['type']}, "
                                 f"expected {' or '.join(types)}")
            if info["count"] == 0:
                raise InputError(f"{self.path}: {role} topic {requested!r} is empty (0 messages)")
            return requested
        cands = self._topics_of(types)
        full = [t for t in cands if self.topic_table[t]["count"] > 0]
        if len(cands) > len(full):
            self._warn(f"{self.path}: empty {role} topic(s) ignored: "
                       f"{', '.join(t for t in cands if t not in full)}")
        if len(full) > 1:
            opt = {"image": "--image-topic", "IMU": "--imu-topic"}.get(role, "the topic option")
            raise InputError(f"{self.path}: several {role} topics: {', '.join(full)}; choose one with "
                             f"{opt}")
        return full[0] if full else None

    def _pick_camera_info(self, requested: Optional[str]) -> Optional[str]:
        """The CameraInfo topic of the image topic's camera: the one in its namespace
        (``/cam0/image_raw`` -> ``/cam0/camera_info``). Another camera's calibration is never taken
        silently: with CameraInfo topics only in other namespaces there is none (and, without a
        calibration YAML, the error says why)."""
        if requested:
            return self._pick("camera-info", requested, (CAMERA_INFO,))
        cands = [t for t in self._topics_of((CAMERA_INFO,)) if self.topic_table[t]["count"] > 0]
        if not self.image_topic:
            return cands[0] if len(cands) == 1 else None
        ns = topic_namespace(self.image_topic)
        mine = [t for t in cands if topic_namespace(t) == ns]
        if len(mine) == 1:
            return mine[0]
        if not cands:
            return None
        # the bag's cameras: image topics without their transport (raw + compressed is one camera)
        cameras = {camera_topic(t) for t in self._topics_of(IMAGE_TYPES) if self.topic_table[t]["count"] > 0}
        if len(cands) == 1 and cameras == {camera_topic(self.image_topic)}:
            # one camera in the bag, its CameraInfo named differently: no other camera to mix up
            self._warn(f"{self.path}: using {cands[0]} for the image topic {self.image_topic} (the only "
                       f"camera-info and image topics, in different namespaces)")
            return cands[0]
        # not an error yet: a calibration YAML may give the camera (else reported with this note)
        self._camera_info_note = (f"the camera-info topic(s) {', '.join(cands)} are not in the namespace "
                                  f"{ns} of the image topic (another camera's?)")
        return None

    # -- first pass ------------------------------------------------------------------------------
    def _first_pass(self, r) -> None:
        """Read the chosen topics once: frame stamps, IMU, ground truth and calibration."""
        scan = self._scan(r)
        for topic, n, what in ((self.image_topic, scan.img_zero, "image(s)"),
                               (self.imu_topic, scan.imu_zero, "IMU sample(s)"),
                               (self.gt_topic, scan.gt_zero, "ground-truth pose(s)")):
            if n:
                self._warn(f"{self.path}:{topic}: {n} {what} with a zero header stamp; used the bag "
                           f"receive time")
        self._set_frame_stamps(scan.img_st)
        if self.imu_topic:
            self._set_bag_imu(scan.imu_st, scan.imu_v, scan.imu_missing)
        if self.gt_topic and scan.gt_st:
            self._set_bag_gt(scan.gt_st, scan.gt_T)
        self._set_calibration(scan.cam_msg, scan.first_img)
        if scan.first_img is not None:
            self._first_img_dtype = str(scan.first_img.dtype)

    def _scan(self, r) -> _Scan:
        """One read of the image, IMU, camera-info and ground-truth topics (module doc, Memory)."""
        topics = [t for t in (self.image_topic, self.imu_topic, self.camera_info_topic, self.gt_topic)
                  if t]
        conns = [c for c in r.connections if c.topic in topics]
        scan = _Scan()
        for conn, t, raw in (r.messages(connections=conns) if conns else ()):
            topic = conn.topic
            if topic == self.image_topic:
                s = header_stamp_ns(raw, self._ros1, f"{self.path}:{topic}")
                if s == 0:
                    s, scan.img_zero = int(t), scan.img_zero + (1 if t else 0)
                scan.img_st.append(s)
                if scan.first_img is None:
                    scan.first_img = self._decode(r, conn, raw, s)
            elif topic == self.imu_topic:
                m, s, zero = self._stamped(r, conn, t, raw)
                scan.imu_zero += int(zero)
                if m.angular_velocity_covariance[0] == -1:
                    scan.imu_missing["gyro"] += 1
                if m.linear_acceleration_covariance[0] == -1:
                    scan.imu_missing["accel"] += 1
                w, a = m.angular_velocity, m.linear_acceleration
                scan.imu_st.append(s)
                scan.imu_v.append((w.x, w.y, w.z, a.x, a.y, a.z))
            elif topic == self.camera_info_topic:
                if scan.cam_msg is None:
                    m = self._deser(r, raw, conn, f"{self.path}:{topic}")
                    if camera_from_camera_info(m, f"{self.path}:{topic}",
                                               is_rectified_topic(self.image_topic)) is not None:
                        scan.cam_msg = m
            elif topic == self.gt_topic:
                m, s, zero = self._stamped(r, conn, t, raw)
                scan.gt_zero += int(zero)
                scan.gt_st.append(s)
                scan.gt_T.append(pose_of(m, conn.msgtype))
        return scan

    def _stamped(self, r, conn, t: int, raw: bytes) -> tuple[object, int, bool]:
        """The message, its header stamp (ns) and whether that stamp was zero and replaced by the
        bag receive time ``t`` (ns)."""
        m = self._deser(r, raw, conn, f"{self.path}:{conn.topic}")
        s = _stamp_of(m, f"{self.path}:{conn.topic}")
        return (m, int(t), True) if s == 0 else (m, s, False)

    def _set_frame_stamps(self, img_st: list[int]) -> None:
        """Frame stamps (ns): sorted, de-duplicated, images too far out of order dropped, limited."""
        st = np.asarray(img_st, dtype=np.int64)
        idx = order_stamps(st, f"{self.path}:{self.image_topic}", self._warn)
        # frames() inserts an arriving image before delivering, so REORDER_WINDOW - 1 may wait
        late = late_entries(idx, max(REORDER_WINDOW - 1, 0))
        if late.any():
            self._warn(f"{self.path}:{self.image_topic}: {int(late.sum())} image(s) recorded more than "
                       f"{REORDER_WINDOW} images after later-stamped ones (header stamps far out of "
                       f"order); dropped, e.g. the one stamped {int(st[idx[late][0]])} ns")
            idx = idx[~late]
        idx = idx[: self._limit(len(idx))]
        self._stamps = st[idx]
        self._pos = {int(s): i for i, s in enumerate(self._stamps)}

    def _set_bag_imu(self, imu_st: list[int], imu_v: list[tuple], missing: dict[str, int]) -> None:
        """IMU samples (stamps ns; gyro rad/s, accel m/s^2 in ``imu_v`` rows): none when the
        messages mark gyro or accel unavailable, samples with non-finite values dropped."""
        v = np.asarray(imu_v, dtype=np.float64).reshape(-1, 6)
        bad = [k for k, n in missing.items() if n]
        if bad:
            self._warn(f"{self.path}:{self.imu_topic}: messages mark {' and '.join(bad)} as "
                       f"unavailable (covariance[0] = -1); IMU not used")
            v = v[:0]
            imu_st = []
        elif not np.all(np.isfinite(v)):
            keep = np.all(np.isfinite(v), axis=1)
            self._warn(f"{self.path}:{self.imu_topic}: {int((~keep).sum())} IMU sample(s) with "
                       f"non-finite values dropped")
            v = v[keep]
            imu_st = list(np.asarray(imu_st)[keep])
        self._set_imu(np.asarray(imu_st, dtype=np.int64), v[:, :3], v[:, 3:],
                      f"{self.path}:{self.imu_topic}")

    def _set_bag_gt(self, gt_st: list[int], gt_T: list[np.ndarray]) -> None:
        """Body ground truth (stamps ns, ``T_wb``), poses with a zero quaternion or non-finite
        values dropped."""
        T = np.stack(gt_T)
        ok = np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
        if not ok.all():
            self._warn(f"{self.path}:{self.gt_topic}: {int((~ok).sum())} pose(s) with a zero "
                       f"quaternion or non-finite values dropped")
        self._set_gt(np.asarray(gt_st, dtype=np.int64)[ok], T[ok], f"{self.path}:{self.gt_topic}",
                     "body")

    def _set_calibration(self, cam_msg, first_img: Optional[np.ndarray]) -> None:
        """Camera and rig calibration (module doc: YAML, else CameraInfo), checked against the first
        image's size; missing extrinsic or IMU noise warned. Needs the IMU set."""
        parts, camera = self._calibration_parts(cam_msg, first_img)
        has_imu = len(self._imu_st) > 0
        parts.has_imu = has_imu
        parts.imu_rate_hz = self._imu_rate() or parts.imu_rate_hz
        if first_img is not None:
            h, w = first_img.shape[:2]
            if camera is None:
                stem = self.path.name if self.path.is_dir() else self.path.stem
                note = f" ({self._camera_info_note})" if self._camera_info_note else ""
                raise InputError(
                    f"{self.path}: no calibration for image topic {self.image_topic}: no usable "
                    f"CameraInfo topic{note} and no calibration YAML (looked for "
                    f"{self.path.parent / (stem + '.calib.yaml')}); pass --calib FILE or "
                    f"--camera-info-topic")
            camera = check_size(camera, w, h, f"{self.path}:{self.image_topic}", self._warn)
        if has_imu and not parts.noise:
            self._warn(f"{self.path}: IMU noise parameters unknown; using the defaults (EuRoC "
                       f"ADIS16448)")
        if camera is not None:
            if has_imu and parts.T_bc is None:
                self._warn(f"{self.path}: camera-to-IMU extrinsic T_bc unknown; assuming identity "
                           f"(give it in a calibration YAML with --calib)")
            self._set_camera(camera, parts.to_calibration(camera))
        else:  # no camera in this recording: IMU (and GT) only
            self.calibration = parts.to_calibration(None)

    def _calibration_parts(self, cam_msg, first_img: Optional[np.ndarray]
                           ) -> tuple[CalibParts, Optional[CameraModel]]:
        """The calibration YAML's parts and the raw camera: the YAML's, else the CameraInfo's (None
        when neither gives one); sets ``calib_source``."""
        parts = CalibParts()
        yaml_path = self.options.calib_file or calib_yaml_beside(self.path)
        self.calib_source = None
        if yaml_path:
            parts = read_calibration_parts(yaml_path, self.image_topic)
            self.calib_source = str(yaml_path)
        camera = parts.camera
        if camera is None and cam_msg is not None:
            rectified = is_rectified_topic(self.image_topic)
            camera = camera_from_camera_info(cam_msg, f"{self.path}:{self.camera_info_topic}", rectified)
            self.calib_source = f"{self.camera_info_topic} (CameraInfo)"
            if camera is not None and (camera.width == 0 or camera.height == 0) and first_img is not None:
                camera = None
            if camera is not None and rectified:
                self._rectified_extrinsic(parts, cam_msg)
        return parts, camera

    def _rectified_extrinsic(self, parts: CalibParts, cam_msg) -> None:
        """Rectified images (``image_rect``) live in the rectified frame, turned by CameraInfo's R
        against the raw camera (``x_rect = R x_raw``) that an extrinsic ``T_bc`` describes; the
        camera frame of the output (and of ground truth mapped through ``T_bc``) is the rectified
        one, so ``T_bc`` becomes ``T_bc @ [R^T | 0]``."""
        where = f"{self.path}:{self.camera_info_topic}: field r"
        try:
            R = np.asarray(_field(cam_msg, "r", "R"), dtype=np.float64).reshape(3, 3)
        except (AttributeError, ValueError):
            return
        if not np.any(R) or np.allclose(R, np.eye(3), atol=1e-12):
            return      # unset (all zeros) or identity: nothing to turn
        # calibration files print R with a few decimals: accept 1e-4, then make it exactly orthonormal
        if not (np.all(np.isfinite(R)) and np.allclose(R @ R.T, np.eye(3), atol=1e-4)
                and np.linalg.det(R) > 0):
            raise InputError(f"{where}: the rectification matrix is not a rotation: {R.tolist()}")
        T_raw_rect = np.eye(4)
        T_raw_rect[:3, :3] = np_project_rotation(R).T
        if parts.T_bc is None:
            self._warn(f"{where}: rectified images turned by {float(rotation_angle_deg(R)):.2f} deg against "
                       f"the raw camera, and no extrinsic T_bc to apply it to: outputs are in the rectified "
                       f"camera frame")
            return
        parts.T_bc = np.asarray(parts.T_bc, dtype=np.float64) @ T_raw_rect

    # -- decoding --------------------------------------------------------------------------------
    def _decode(self, r, conn, raw, stamp: int) -> np.ndarray:
        where = f"{self.path}:{conn.topic} @ {stamp} ns"
        m = self._deser(r, raw, conn, where)
        if conn.msgtype == COMPRESSED:
            return decode_compressed(m.data, m.format, where)
        return decode_image(m.data, m.encoding, m.width, m.height, m.step, where,
                            is_bigendian=bool(m.is_bigendian))

    # -- Source API ------------------------------------------------------------------------------
    def frame_stamps(self) -> np.ndarray:
        return self._stamps.copy()

    def frames(self) -> Iterator[Frame]:
        n = len(self._stamps)
        if n == 0:
            return
        with self._open() as r:
            conns = self._conns(r, self.image_topic)
            pending: dict[int, tuple[np.ndarray, int]] = {}
            done = np.zeros(n, dtype=bool)
            nxt = 0
            for conn, t, raw in r.messages(connections=conns):
                s = header_stamp_ns(raw, self._ros1, f"{self.path}:{conn.topic}") or int(t)
                i = self._pos.get(s)
                if i is None or done[i]:
                    continue  # dropped duplicate, or beyond max_frames
                done[i] = True
                # kept raw until its turn (images that arrive early wait, at most REORDER_WINDOW:
                # the first read dropped the ones that would need more)
                pending[i] = (conn, raw, s)
                while nxt in pending:
                    c2, raw2, s2 = pending.pop(nxt)
                    fr = self._frame(lambda: self._decode(r, c2, raw2, s2), s2, f"{self.path}:{c2.topic} @ {s2} ns")
                    if fr is not None:
                        yield fr
                    nxt += 1
                if nxt >= n:
                    return
        if nxt < n:
            raise InputError(f"{self.path}:{self.image_topic}: {n - nxt} image(s) seen on the first "
                             f"read were not found again (bag changed while reading?)")

    def _extra_info(self) -> dict:
        return {"format": self.format,
                "topics_used": {"image": self.image_topic, "imu": self.imu_topic,
                                "camera_info": self.camera_info_topic, "ground_truth": self.gt_topic},
                "calibration_from": self.calib_source,
                "topics": self.topic_table}
