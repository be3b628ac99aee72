"""Writers: a ROS 2 MCAP (or MCAP bag folder) and an EuRoC/ASL folder, both atomic.

* :func:`write_mcap` writes ``sensor_msgs/Image`` (``rgb8``/``mono8``), ``CameraInfo``, ``Imu`` and
  ``geometry_msgs/PoseStamped`` ground truth (of the body) with rosbags' MCAP storage, plus
  ``<stem>.calib.yaml`` beside it (T_bc, IMU noise), which :class:`~vings_core.io.bag.BagSource`
  finds by itself.
* :func:`write_euroc` writes the layout :class:`~vings_core.io.euroc.EurocSource` reads, including
  optional ``depth0`` (``.npy``) and ``mask0`` (``.png``) folders.
"""
from __future__ import annotations

import heapq
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterable, Mapping, Optional, Sequence, Union

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
    unknown = set(topics or {}) - set(DEFAULT_TOPICS)
    if unknown:
        raise ConfigError(f"write_mcap: unknown topic keys {sorted(unknown)}; expected "
                          f"{sorted(DEFAULT_TOPICS)}")
    names = {**DEFAULT_TOPICS, **(topics or {})}
    plain = path.suffix == ".mcap"
    if not plain and path.exists():
        raise InputError(f"{path}: output bag folder exists already")
    path.parent.mkdir(parents=True, exist_ok=True)

    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    calib = source.calibration
    cam = calib.camera if calib is not None else None

    def header(stamp: int, frame_id: str):
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=int(stamp // 1_000_000_000),
                                                   nanosec=int(stamp % 1_000_000_000)),
            frame_id=frame_id)

    def image_msg(f: Frame):
        img = f.image if f.image.ndim == 2 or f.image.shape[2] == 3 else f.image[..., :3]
        enc, step, data = encode_image(np.ascontiguousarray(img))
        return T["sensor_msgs/msg/Image"](header=header(f.stamp_ns, FRAME_IDS["image"]),
                                          height=img.shape[0], width=img.shape[1], encoding=enc,
                                          is_bigendian=0, step=step,
                                          data=np.frombuffer(data, dtype=np.uint8))

    def info_msg(f: Frame):
        c = f.camera
        model, d = _ros_distortion(c)
        K = c.K.reshape(-1)
        P = np.zeros((3, 4))
        P[:, :3] = c.K
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                     do_rectify=False)
        return T["sensor_msgs/msg/CameraInfo"](
            header=header(f.stamp_ns, FRAME_IDS["image"]), height=c.height, width=c.width,
            distortion_model=model, d=np.array(d, dtype=np.float64), k=K.astype(np.float64),
            r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi)

    gcov = (calib.gyro_noise_density ** 2 * calib.imu_rate_hz) if calib is not None else 0.0
    acov = (calib.accel_noise_density ** 2 * calib.imu_rate_hz) if calib is not None else 0.0

    def imu_msg(s: ImuSample):
        V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        oc = np.zeros(9)
        oc[0] = -1.0  # orientation not provided
        return T["sensor_msgs/msg/Imu"](
            header=header(s.stamp_ns, FRAME_IDS["imu"]), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=oc,
            angular_velocity=V3(x=float(s.gyro[0]), y=float(s.gyro[1]), z=float(s.gyro[2])),
            angular_velocity_covariance=(np.eye(3) * gcov).reshape(-1),
            linear_acceleration=V3(x=float(s.accel[0]), y=float(s.accel[1]), z=float(s.accel[2])),
            linear_acceleration_covariance=(np.eye(3) * acov).reshape(-1))

    def pose_msg(stamp: int, Twb: np.ndarray):
        q = np_rotmat_to_quat(Twb[:3, :3])
        P, Pt, Q = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
        return T["geometry_msgs/msg/PoseStamped"](
            header=header(stamp, FRAME_IDS["gt"]),
            pose=P(position=Pt(x=float(Twb[0, 3]), y=float(Twb[1, 3]), z=float(Twb[2, 3])),
                   orientation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))

    gt = source.ground_truth
    if gt is not None and source.gt_frame == "camera":
        if calib is None:
            gt = None
        else:
            gt = gt.right_multiply(np_pose_inverse(calib.T_bc))

    imu = source.imu_samples()
    streams = [
        ((s.stamp_ns, 0, i, "imu", s) for i, s in enumerate(imu)),
        ((int(st), 1, i, "gt", P) for i, (st, P) in enumerate(zip(gt.stamps_ns, gt.poses)))
        if gt is not None else iter(()),
        ((f.stamp_ns, 2, i, "frame", f) for i, f in enumerate(source.frames())),
    ]

    tmpdir = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    bagdir = tmpdir / (path.stem if plain else path.name)
    try:
        with Writer(bagdir, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conns = {}
            if cam is not None or len(source.frame_stamps()):
                conns["image"] = w.add_connection(names["image"], "sensor_msgs/msg/Image", typestore=ts)
                conns["camera_info"] = w.add_connection(names["camera_info"],
                                                        "sensor_msgs/msg/CameraInfo", typestore=ts)
            if imu:
                conns["imu"] = w.add_connection(names["imu"], "sensor_msgs/msg/Imu", typestore=ts)
            if gt is not None:
                conns["gt"] = w.add_connection(names["gt"], "geometry_msgs/msg/PoseStamped",
                                               typestore=ts)
            for stamp, _, _, what, item in heapq.merge(*streams, key=lambda x: (x[0], x[1], x[2])):
                stamp = int(stamp)
                if stamp < 0:
                    raise InputError(f"write_mcap: negative stamp {stamp} ns cannot be written")
                if what == "imu":
                    w.write(conns["imu"], stamp, ts.serialize_cdr(imu_msg(item), "sensor_msgs/msg/Imu"))
                elif what == "gt":
                    w.write(conns["gt"], stamp,
                            ts.serialize_cdr(pose_msg(stamp, item), "geometry_msgs/msg/PoseStamped"))
                else:
                    w.write(conns["image"], stamp,
                            ts.serialize_cdr(image_msg(item), "sensor_msgs/msg/Image"))
                    w.write(conns["camera_info"], stamp,
                            ts.serialize_cdr(info_msg(item), "sensor_msgs/msg/CameraInfo"))
        if plain:
            os.replace(bagdir / f"{bagdir.name}.mcap", path)
        else:
            os.replace(bagdir, path)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)

    ypath = calib_yaml_path(path)
    if cam is not None:
        atomic_write_text(ypath, format_calibration_yaml(calib))
    else:  # camera-less recording: T_bc and IMU noise only
        from .common import calibration_dict
        d = calibration_dict(calib) if calib is not None else {"T_bc": np.eye(4).tolist()}
        d.pop("camera", None)
        d["has_imu"] = bool(imu)
        atomic_write_text(ypath, "# VINGS-ROS calibration (no camera)\n" + yaml.safe_dump(d, sort_keys=False))


# ------------------------------------------------------------------------------------------ EuRoC


def _lookup(src, stamp: int):
    if src is None:
        return None
    if callable(src):
        return src(stamp)
    return src.get(stamp)


def _asl_matrix(T: np.ndarray) -> dict:
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
    import cv2

    out = Path(out_dir)
    if out.exists() and not overwrite and any(out.iterdir()):
        raise InputError(f"{out}: output folder exists and is not empty (use overwrite=True)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        mav0 = tmp / "mav0"
        cam_dir = mav0 / "cam0" / "data"
        cam_dir.mkdir(parents=True)
        rows = ["#timestamp [ns],filename"]
        n_depth = n_mask = 0
        for f in frames_iter:
            name = f"{int(f.stamp_ns)}.png"
            img = f.image
            if img.dtype != np.uint8:
                raise InputError(f"write_euroc: frame {f.stamp_ns} is {img.dtype}, expected uint8")
            bgr = img if img.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(img[..., :3]),
                                                         cv2.COLOR_RGB2BGR)
            if not cv2.imwrite(str(cam_dir / name), bgr):
                raise InputError(f"{cam_dir / name}: could not write image")
            rows.append(f"{int(f.stamp_ns)},{name}")
            d = _lookup(depth, int(f.stamp_ns))
            if d is not None:
                (mav0 / "depth0" / "data").mkdir(parents=True, exist_ok=True)
                np.save(mav0 / "depth0" / "data" / f"{int(f.stamp_ns)}.npy",
                        np.asarray(d, dtype=np.float32))
                n_depth += 1
            m = _lookup(mask, int(f.stamp_ns))
            if m is not None:
                (mav0 / "mask0" / "data").mkdir(parents=True, exist_ok=True)
                m = np.asarray(m)
                m8 = (m.astype(bool) * 255).astype(np.uint8) if m.dtype == np.bool_ else m.astype(np.uint8)
                cv2.imwrite(str(mav0 / "mask0" / "data" / f"{int(f.stamp_ns)}.png"), m8)
                n_mask += 1
        (mav0 / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
        cam = calibration.camera
        model = {"none": "radial-tangential", "radtan": "radial-tangential",
                 "equidistant": "equidistant"}[cam.distortion_model]
        dist = [float(v) for v in cam.distortion] if cam.distortion_model != "none" else [0.0] * 4
        cam_yaml = {"sensor_type": "camera", "comment": "written by vings_core.io.write_euroc",
                    "T_BS": _asl_matrix(calibration.T_bc), "rate_hz": None,
                    "resolution": [cam.width, cam.height], "camera_model": "pinhole",
                    "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy], "distortion_model": model,
                    "distortion_coefficients": dist}
        if len(rows) > 2:
            st = np.array([int(r.split(",")[0]) for r in rows[1:]])
            cam_yaml["rate_hz"] = float(round(1e9 / np.median(np.diff(st)), 6))
        else:
            del cam_yaml["rate_hz"]
        (mav0 / "cam0" / "sensor.yaml").write_text(yaml.safe_dump(cam_yaml, sort_keys=False))

        if isinstance(imu, tuple):
            ist, ig, ia = (np.asarray(imu[0], dtype=np.int64), np.asarray(imu[1], dtype=np.float64),
                           np.asarray(imu[2], dtype=np.float64))
        else:
            ist = np.array([s.stamp_ns for s in imu], dtype=np.int64)
            ig = np.array([s.gyro for s in imu], dtype=np.float64).reshape(-1, 3)
            ia = np.array([s.accel for s in imu], dtype=np.float64).reshape(-1, 3)
        if len(ist):
            (mav0 / "imu0").mkdir()
            lines = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                     "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
            lines += [f"{int(s)},{g[0]!r},{g[1]!r},{g[2]!r},{a[0]!r},{a[1]!r},{a[2]!r}"
                      for s, g, a in zip(ist, ig.tolist(), ia.tolist())]
            (mav0 / "imu0" / "data.csv").write_text("\n".join(lines) + "\n")
            imu_yaml = {"sensor_type": "imu", "comment": "written by vings_core.io.write_euroc",
                        "T_BS": _asl_matrix(np.eye(4)), "rate_hz": float(calibration.imu_rate_hz),
                        "gyroscope_noise_density": calibration.gyro_noise_density,
                        "gyroscope_random_walk": calibration.gyro_random_walk,
                        "accelerometer_noise_density": calibration.accel_noise_density,
                        "accelerometer_random_walk": calibration.accel_random_walk}
            (mav0 / "imu0" / "sensor.yaml").write_text(yaml.safe_dump(imu_yaml, sort_keys=False))
        if gt_body is not None and len(gt_body):
            (mav0 / "state_groundtruth_estimate0").mkdir()
            q = np_rotmat_to_quat(gt_body.poses[:, :3, :3])
            lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
                     "q_RS_y [], q_RS_z []"]
            for s, P, qq in zip(gt_body.stamps_ns, gt_body.poses, q):
                v = [float(x) for x in (P[0, 3], P[1, 3], P[2, 3], qq[3], qq[0], qq[1], qq[2])]
                lines.append(f"{int(s)}," + ",".join(repr(x) for x in v))
            (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(lines) + "\n")
        (mav0 / "body.yaml").write_text("comment: VINGS-ROS body frame = IMU frame\n")

        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out
