"""Writers: a ROS 2 MCAP (or MCAP bag folder) and an EuRoC/ASL folder, both atomic.

* :func:`write_mcap` writes ``sensor_msgs/Image`` (``rgb8``/``mono8``), ``CameraInfo``, ``Imu`` and
  ``geometry_msgs/PoseStamped`` ground truth (of the body) with rosbags' MCAP storage, plus
  ``<stem>.calib.yaml`` beside it (T_bc, IMU noise), which :class:`~vings_core.io.bag.BagSource`
  finds by itself.
* :func:`write_euroc` writes the layout :class:`~vings_core.io.euroc.EurocSource` reads, including
  optional ``depth0`` (``.npy``) and ``mask0`` (``.png``) folders.
"""
from __future__ import annotations

import contextlib
import heapq
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterable, Iterator, Mapping, Optional, Sequence, Union

import numpy as np
import yaml

from ..errors import ConfigError, InputError
from ..geometry import np_pose_inverse, np_rotmat_to_quat
from ..types import Calibration, CameraModel, Frame, ImuSample, Trajectory
from ..util import atomic_write_text
from .base import Source
from .calib_yaml import format_calibration_yaml
from .image_codec import encode_image

DEFAULT_TOPICS = {"image": "/cam0/image_raw", "camera_info": "/cam0/camera_info", "imu": "/imu0",
                  "gt": "/ground_truth/pose"}
FRAME_IDS = {"image": "cam0", "imu": "imu0", "gt": "world"}


def calib_yaml_path(path: Union[str, os.PathLike]) -> Path:
    """``<stem>.calib.yaml`` beside an MCAP file (or beside a bag folder)."""
    p = Path(path)
    stem = p.stem if p.suffix == ".mcap" else p.name
    return p.parent / f"{stem}.calib.yaml"


def _ros_distortion(cam: CameraModel) -> tuple[str, list[float]]:
    if cam.distortion_model == "equidistant":
        return "equidistant", [float(v) for v in cam.distortion[:4]]
    if cam.distortion_model == "radtan" and cam.distortion.size > 5:
        d = list(cam.distortion[:8]) + [0.0] * (8 - min(8, cam.distortion.size))
        return "rational_polynomial", [float(v) for v in d]
    d = list(cam.distortion[:5]) + [0.0] * (5 - min(5, cam.distortion.size))
    return "plumb_bob", [float(v) for v in d]


def write_mcap(path: Union[str, os.PathLike], source: Source, topics: Optional[dict] = None) -> None:
    """Write ``source`` as ROS 2 messages with rosbags' MCAP storage.

    ``path`` ending in ``.mcap``: one plain MCAP file; otherwise a ROS 2 bag folder (``metadata.yaml``
    + ``<name>.mcap``) that ``ros2 bag play`` accepts. ``topics`` overrides the names of
    ``image`` (``/cam0/image_raw``), ``camera_info`` (``/cam0/camera_info``), ``imu`` (``/imu0``)
    and ``gt`` (``/ground_truth/pose``). Header stamps and log times are the source stamps (ns).
    Frames are written as delivered by ``source.frames()`` (undistorted, working resolution), so
    the CameraInfo carries ``source.calibration.camera``. Ground truth is written as the body pose
    ``T_wb`` (camera ground truth is mapped with ``T_bc``). The calibration YAML goes to
    :func:`calib_yaml_path`. Both outputs are written to a temporary name and renamed.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    names = _topic_names(topics)
    plain = path.suffix == ".mcap"
    if not plain and path.exists():
        raise InputError(f"{path}: output bag folder exists already")
    path.parent.mkdir(parents=True, exist_ok=True)

    calib = source.calibration
    has_camera = calib is not None and calib.camera is not None
    messages = _RosMessages(get_typestore(Stores.ROS2_JAZZY), calib)
    gt = _body_ground_truth(source.ground_truth, source.gt_frame, calib)
    imu = source.imu_samples()
    stream = _time_ordered(imu, gt, source.frames())

    with _staging_dir(path) as tmpdir:
        bagdir = tmpdir / (path.stem if plain else path.name)
        with Writer(bagdir, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            has_frames = has_camera or len(source.frame_stamps()) > 0
            conns = _add_connections(w, messages.ts, names, has_frames, bool(imu), gt is not None)
            _write_messages(w, conns, messages, stream)
        if plain:
            os.replace(bagdir / f"{bagdir.name}.mcap", path)
        else:
            os.replace(bagdir, path)
    _write_mcap_calibration(calib_yaml_path(path), calib, has_camera, bool(imu))


def _topic_names(topics: Optional[dict]) -> dict[str, str]:
    """:data:`DEFAULT_TOPICS` with the overrides of ``topics`` (unknown keys are an error)."""
    unknown = set(topics or {}) - set(DEFAULT_TOPICS)
    if unknown:
        raise ConfigError(f"write_mcap: unknown topic keys {sorted(unknown)}; expected "
                          f"{sorted(DEFAULT_TOPICS)}")
    return {**DEFAULT_TOPICS, **(topics or {})}


@contextlib.contextmanager
def _staging_dir(target: Path) -> Iterator[Path]:
    """A new temporary folder ``.<name>.XXXX`` beside ``target`` (whose parent must exist); it is
    removed, with whatever is still in it, on leaving the block."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


class _RosMessages:
    """ROS 2 messages (types of the typestore ``ts``) of frames, IMU samples and body poses.

    Stamps are ns; the IMU covariances are ``density^2 * rate`` of ``calib`` (zero without one).
    """

    def __init__(self, ts, calib: Optional[Calibration]) -> None:
        self.ts = ts
        self.T = ts.types
        self.gcov = (calib.gyro_noise_density ** 2 * calib.imu_rate_hz) if calib is not None else 0.0
        self.acov = (calib.accel_noise_density ** 2 * calib.imu_rate_hz) if calib is not None else 0.0

    def header(self, stamp: int, frame_id: str):
        """``std_msgs/Header`` at ``stamp`` (ns)."""
        return self.T["std_msgs/msg/Header"](
            stamp=self.T["builtin_interfaces/msg/Time"](sec=int(stamp // 1_000_000_000),
                                                        nanosec=int(stamp % 1_000_000_000)),
            frame_id=frame_id)

    def image(self, f: Frame):
        """``sensor_msgs/Image`` of a frame (an alpha channel is dropped)."""
        img = f.image if f.image.ndim == 2 or f.image.shape[2] == 3 else f.image[..., :3]
        enc, step, data = encode_image(np.ascontiguousarray(img))
        return self.T["sensor_msgs/msg/Image"](header=self.header(f.stamp_ns, FRAME_IDS["image"]),
                                               height=img.shape[0], width=img.shape[1], encoding=enc,
                                               is_bigendian=0, step=step,
                                               data=np.frombuffer(data, dtype=np.uint8))

    def camera_info(self, f: Frame):
        """``sensor_msgs/CameraInfo`` of the frame's camera (``R = I``, ``P = [K | 0]``)."""
        T = self.T
        c = f.camera
        model, d = _ros_distortion(c)
        K = c.K.reshape(-1)
        P = np.zeros((3, 4))
        P[:, :3] = c.K
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                     do_rectify=False)
        return T["sensor_msgs/msg/CameraInfo"](
            header=self.header(f.stamp_ns, FRAME_IDS["image"]), height=c.height, width=c.width,
            distortion_model=model, d=np.array(d, dtype=np.float64), k=K.astype(np.float64),
            r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi)

    def imu(self, s: ImuSample):
        """``sensor_msgs/Imu`` of a sample (body frame; orientation marked as not provided)."""
        T = self.T
        V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        oc = np.zeros(9)
        oc[0] = -1.0  # orientation not provided
        return T["sensor_msgs/msg/Imu"](
            header=self.header(s.stamp_ns, FRAME_IDS["imu"]), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=oc,
            angular_velocity=V3(x=float(s.gyro[0]), y=float(s.gyro[1]), z=float(s.gyro[2])),
            angular_velocity_covariance=(np.eye(3) * self.gcov).reshape(-1),
            linear_acceleration=V3(x=float(s.accel[0]), y=float(s.accel[1]), z=float(s.accel[2])),
            linear_acceleration_covariance=(np.eye(3) * self.acov).reshape(-1))

    def pose(self, stamp: int, Twb: np.ndarray):
        """``geometry_msgs/PoseStamped`` of the body pose ``T_wb`` (world frame) at ``stamp`` (ns)."""
        T = self.T
        q = np_rotmat_to_quat(Twb[:3, :3])
        P, Pt, Q = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
        return T["geometry_msgs/msg/PoseStamped"](
            header=self.header(stamp, FRAME_IDS["gt"]),
            pose=P(position=Pt(x=float(Twb[0, 3]), y=float(Twb[1, 3]), z=float(Twb[2, 3])),
                   orientation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))


def _body_ground_truth(gt: Optional[Trajectory], gt_frame: str, calib: Optional[Calibration]
                       ) -> Optional[Trajectory]:
    """Ground truth as body poses ``T_wb``: camera poses (``gt_frame == 'camera'``) are mapped with
    ``T_bc``, or dropped when there is no calibration to map them."""
    if gt is not None and gt_frame == "camera":
        if calib is None:
            return None
        return gt.right_multiply(np_pose_inverse(calib.T_bc))
    return gt


def _time_ordered(imu: list[ImuSample], gt: Optional[Trajectory], frames: Iterable[Frame]
                  ) -> Iterator[tuple[int, str, object]]:
    """``(stamp ns, kind, item)`` of IMU samples (``imu``), ground-truth poses (``gt``: the 4x4
    pose) and frames (``frame``) merged in time order; on equal stamps IMU first, then ground
    truth, then the frame, each stream keeping its own order."""
    streams = [
        ((s.stamp_ns, 0, i, "imu", s) for i, s in enumerate(imu)),
        ((int(st), 1, i, "gt", P) for i, (st, P) in enumerate(zip(gt.stamps_ns, gt.poses)))
        if gt is not None else iter(()),
        ((f.stamp_ns, 2, i, "frame", f) for i, f in enumerate(frames)),
    ]
    for stamp, _, _, what, item in heapq.merge(*streams, key=lambda x: (x[0], x[1], x[2])):
        yield stamp, what, item


def _add_connections(w, ts, names: dict[str, str], has_frames: bool, has_imu: bool,
                     has_gt: bool) -> dict:
    """The writer ``w``'s connections by role: ``image`` and ``camera_info``, ``imu``, ``gt`` (those
    present, added in this order)."""
    conns = {}
    if has_frames:
        conns["image"] = w.add_connection(names["image"], "sensor_msgs/msg/Image", typestore=ts)
        conns["camera_info"] = w.add_connection(names["camera_info"],
                                                "sensor_msgs/msg/CameraInfo", typestore=ts)
    if has_imu:
        conns["imu"] = w.add_connection(names["imu"], "sensor_msgs/msg/Imu", typestore=ts)
    if has_gt:
        conns["gt"] = w.add_connection(names["gt"], "geometry_msgs/msg/PoseStamped", typestore=ts)
    return conns


def _write_messages(w, conns: dict, messages: _RosMessages,
                    stream: Iterable[tuple[int, str, object]]) -> None:
    """Serialize (CDR) and write each item of ``stream`` at its stamp (ns, the log time; a negative
    one is an error); a frame gives an Image and a CameraInfo."""
    ser = messages.ts.serialize_cdr
    for stamp, what, item in stream:
        stamp = int(stamp)
        if stamp < 0:
            raise InputError(f"write_mcap: negative stamp {stamp} ns cannot be written")
        if what == "imu":
            w.write(conns["imu"], stamp, ser(messages.imu(item), "sensor_msgs/msg/Imu"))
        elif what == "gt":
            w.write(conns["gt"], stamp, ser(messages.pose(stamp, item), "geometry_msgs/msg/PoseStamped"))
        else:
            w.write(conns["image"], stamp, ser(messages.image(item), "sensor_msgs/msg/Image"))
            w.write(conns["camera_info"], stamp,
                    ser(messages.camera_info(item), "sensor_msgs/msg/CameraInfo"))


def _write_mcap_calibration(ypath: Path, calib: Optional[Calibration], has_camera: bool,
                            has_imu: bool) -> None:
    """The calibration YAML beside an MCAP; a camera-less recording gets ``T_bc`` and IMU noise only."""
    if has_camera:
        atomic_write_text(ypath, format_calibration_yaml(calib))
        return
    from .common import calibration_dict
    d = calibration_dict(calib) if calib is not None else {"T_bc": np.eye(4).tolist()}
    d.pop("camera", None)
    d["has_imu"] = has_imu
    atomic_write_text(ypath, "# VINGS-ROS calibration (no camera)\n" + yaml.safe_dump(d, sort_keys=False))


# ------------------------------------------------------------------------------------------ EuRoC


def _lookup(src, stamp: int):
    """The array a mapping or callable ``src`` (or None) gives for ``stamp`` (ns), or None."""
    if src is None:
        return None
    if callable(src):
        return src(stamp)
    return src.get(stamp)


def _asl_matrix(T: np.ndarray) -> dict:
    """A 4x4 matrix in the ASL sensor.yaml form (``cols``, ``rows``, row-major ``data``)."""
    return {"cols": 4, "rows": 4, "data": [float(v) for v in np.asarray(T).reshape(-1)]}


def write_euroc(out_dir: Union[str, os.PathLike], frames_iter: Iterable[Frame],
                imu: Union[Sequence[ImuSample], tuple], calibration: Calibration,
                gt_body: Optional[Trajectory] = None,
                depth: Union[Mapping[int, np.ndarray], Callable[[int], Optional[np.ndarray]], None] = None,
                mask: Union[Mapping[int, np.ndarray], Callable[[int], Optional[np.ndarray]], None] = None,
                overwrite: bool = False) -> Path:
    """Write an EuRoC/ASL folder ``out_dir/mav0/...`` that :class:`EurocSource` reads back.

    ``frames_iter``: frames (uint8 mono or RGB, described by ``calibration.camera``). ``imu``: IMU
    samples, or a tuple ``(stamps_ns, gyro (N,3), accel (N,3))``. ``gt_body``: body poses ``T_wb``.
    ``depth``/``mask``: per-stamp float32 z-depth (m) / bool or uint8 masks (255 = dynamic), given as
    a mapping or a callable ``stamp -> array | None``. The folder is built under a temporary name and
    renamed; an existing ``out_dir`` is an error unless ``overwrite``.
    """
    out = Path(out_dir)
    if out.exists() and not overwrite and any(out.iterdir()):
        raise InputError(f"{out}: output folder exists and is not empty (use overwrite=True)")
    out.parent.mkdir(parents=True, exist_ok=True)
    with _staging_dir(out) as tmp:
        mav0 = tmp / "mav0"
        stamps = _write_euroc_frames(mav0, frames_iter, depth, mask)
        _write_yaml(mav0 / "cam0" / "sensor.yaml", _camera_sensor(calibration, stamps))
        ist, ig, ia = _imu_arrays(imu)
        if len(ist):
            _write_euroc_imu(mav0 / "imu0", ist, ig, ia, calibration)
        if gt_body is not None and len(gt_body):
            _write_euroc_gt(mav0 / "state_groundtruth_estimate0", gt_body)
        (mav0 / "body.yaml").write_text("comment: VINGS-ROS body frame = IMU frame\n")
        _replace_folder(tmp, out)
    return out


def _write_lines(path: Path, lines: list[str]) -> None:
    """A text file of ``lines``, each ended by a newline."""
    path.write_text("\n".join(lines) + "\n")


def _write_yaml(path: Path, d: dict) -> None:
    """``d`` as block YAML in its key order."""
    path.write_text(yaml.safe_dump(d, sort_keys=False))


def _write_euroc_frames(mav0: Path, frames: Iterable[Frame], depth, mask) -> list[int]:
    """``cam0/data/<ns>.png`` and ``cam0/data.csv`` of ``frames``, with the ``depth0``/``mask0`` maps
    that :func:`write_euroc`'s ``depth``/``mask`` give for their stamps. Returns the stamps (ns)."""
    import cv2

    cam_dir = mav0 / "cam0" / "data"
    cam_dir.mkdir(parents=True)
    rows = ["#timestamp [ns],filename"]
    stamps = []
    for f in frames:
        stamp = int(f.stamp_ns)
        name = f"{stamp}.png"
        img = f.image
        if img.dtype != np.uint8:
            raise InputError(f"write_euroc: frame {f.stamp_ns} is {img.dtype}, expected uint8")
        bgr = img if img.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2BGR)
        if not cv2.imwrite(str(cam_dir / name), bgr):
            raise InputError(f"{cam_dir / name}: could not write image")
        rows.append(f"{stamp},{name}")
        stamps.append(stamp)
        d = _lookup(depth, stamp)
        if d is not None:
            (mav0 / "depth0" / "data").mkdir(parents=True, exist_ok=True)
            np.save(mav0 / "depth0" / "data" / f"{stamp}.npy", np.asarray(d, dtype=np.float32))
        m = _lookup(mask, stamp)
        if m is not None:
            (mav0 / "mask0" / "data").mkdir(parents=True, exist_ok=True)
            m = np.asarray(m)
            m8 = (m.astype(bool) * 255).astype(np.uint8) if m.dtype == np.bool_ else m.astype(np.uint8)
            cv2.imwrite(str(mav0 / "mask0" / "data" / f"{stamp}.png"), m8)
    _write_lines(mav0 / "cam0" / "data.csv", rows)
    return stamps


def _camera_sensor(calibration: Calibration, stamps: list[int]) -> dict:
    """``cam0/sensor.yaml`` content: pinhole intrinsics (px), distortion, ``T_BS = T_bc`` and the
    median frame rate (Hz) of ``stamps`` (ns; left out for fewer than two frames)."""
    cam = calibration.camera
    model = {"none": "radial-tangential", "radtan": "radial-tangential",
             "equidistant": "equidistant"}[cam.distortion_model]
    dist = [float(v) for v in cam.distortion] if cam.distortion_model != "none" else [0.0] * 4
    cam_yaml = {"sensor_type": "camera", "comment": "written by vings_core.io.write_euroc",
                "T_BS": _asl_matrix(calibration.T_bc), "rate_hz": None,
                "resolution": [cam.width, cam.height], "camera_model": "pinhole",
                "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy], "distortion_model": model,
                "distortion_coefficients": dist}
    if len(stamps) > 1:
        st = np.array(stamps)
        cam_yaml["rate_hz"] = float(round(1e9 / np.median(np.diff(st)), 6))
    else:
        del cam_yaml["rate_hz"]
    return cam_yaml


def _imu_arrays(imu: Union[Sequence[ImuSample], tuple]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMU samples, or a tuple ``(stamps, gyro, accel)``, as int64 stamps (N,) ns and float64 gyro
    (N, 3) rad/s and accel (N, 3) m/s^2 (body frame)."""
    if isinstance(imu, tuple):
        return (np.asarray(imu[0], dtype=np.int64), np.asarray(imu[1], dtype=np.float64),
                np.asarray(imu[2], dtype=np.float64))
    return (np.array([s.stamp_ns for s in imu], dtype=np.int64),
            np.array([s.gyro for s in imu], dtype=np.float64).reshape(-1, 3),
            np.array([s.accel for s in imu], dtype=np.float64).reshape(-1, 3))


def _write_euroc_imu(imu_dir: Path, ist: np.ndarray, ig: np.ndarray, ia: np.ndarray,
                     calibration: Calibration) -> None:
    """``imu0/data.csv`` (stamps ns, gyro rad/s, accel m/s^2) and ``imu0/sensor.yaml`` (noise of
    ``calibration``, ``T_BS = I``: the body frame is the IMU frame)."""
    imu_dir.mkdir()
    lines = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
             "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
    lines += [f"{int(s)},{g[0]!r},{g[1]!r},{g[2]!r},{a[0]!r},{a[1]!r},{a[2]!r}"
              for s, g, a in zip(ist, ig.tolist(), ia.tolist())]
    _write_lines(imu_dir / "data.csv", lines)
    _write_yaml(imu_dir / "sensor.yaml",
                {"sensor_type": "imu", "comment": "written by vings_core.io.write_euroc",
                 "T_BS": _asl_matrix(np.eye(4)), "rate_hz": float(calibration.imu_rate_hz),
                 "gyroscope_noise_density": calibration.gyro_noise_density,
                 "gyroscope_random_walk": calibration.gyro_random_walk,
                 "accelerometer_noise_density": calibration.accel_noise_density,
                 "accelerometer_random_walk": calibration.accel_random_walk})


def _write_euroc_gt(gt_dir: Path, gt_body: Trajectory) -> None:
    """``state_groundtruth_estimate0/data.csv``: stamp (ns), body position (m, world) and
    orientation quaternion (w, x, y, z) of ``T_wb``."""
    gt_dir.mkdir()
    q = np_rotmat_to_quat(gt_body.poses[:, :3, :3])
    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
             "q_RS_y [], q_RS_z []"]
    for s, P, qq in zip(gt_body.stamps_ns, gt_body.poses, q):
        v = [float(x) for x in (P[0, 3], P[1, 3], P[2, 3], qq[3], qq[0], qq[1], qq[2])]
        lines.append(f"{int(s)}," + ",".join(repr(x) for x in v))
    _write_lines(gt_dir / "data.csv", lines)


def _replace_folder(tmp: Path, out: Path) -> None:
    """Rename ``tmp`` onto ``out``; an existing ``out`` is moved aside first, then deleted."""
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
        os.replace(out, old / out.name)
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)
