"""A recording of ``vings launch --record`` (MCAP) as an output folder the report can draw.

:func:`recording_to_folder` reads (rosbags, no ROS install needed) the graph's output topics
(defaults of docs/ros.md) and writes what a `vings run` folder would hold of them:

=============================  =========================================================
topic                          written
=============================  =========================================================
``/vings/odometry``            ``trajectory.tum`` (every posed frame, cam0 ``T_wc``)
``/vings/keyframes/refined``   ``keyframes.tum`` (the last message: every keyframe's final
                               pose); without it ``/vings/keyframe/pose``
``/vings/keyframe/image``      ``views/kf_<stamp>_input.png`` of keyframes that have renders
``/vings/render/{color,depth,  ``renders/kf_<stamp>.png``, ``views/kf_<stamp>_{depth,normal}.png``
normal}``                      (at most 6 keyframes, evenly spread; PSNR against the input)
``/vings/keyframe/dynamic_mask``  ``masks/kf_<stamp>.png``
``/vings/map/points``          ``map_points.ply`` is not written; the last cloud's points give the
                               bird's-eye view (``bev.png``) as one-pixel surfels
=============================  =========================================================

plus ``metrics.json`` (frames, keyframes; the rest null: a recording holds no evaluation) and
``run.json`` (the recording's path). Nothing is written over an existing ``metrics.json``.
"""
from __future__ import annotations

import json
from pathlib import Path
import numpy as np

from ..errors import InputError
from ..trajectory_io import write_tum
from ..types import Trajectory
from ..util import atomic_write_bytes, atomic_write_text
from .bev import Surfels, splat_bev, write_bev
from .build import BEV_FILE, RUN_INFO_FILE, VIEWS_DIR, VIEWS_INDEX

ODOMETRY = "/vings/odometry"
REFINED = "/vings/keyframes/refined"
KF_POSE = "/vings/keyframe/pose"
KF_IMAGE = "/vings/keyframe/image"
RENDER = {"color": "/vings/render/color", "depth": "/vings/render/depth", "normal": "/vings/render/normal"}
MASK = "/vings/keyframe/dynamic_mask"
POINTS = "/vings/map/points"
MAX_VIEWS = 6


def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _pose(p) -> np.ndarray:
    from ..geometry import np_quat_to_rotmat
    T = np.eye(4)
    q = p.orientation
    T[:3, :3] = np_quat_to_rotmat(np.array([q.x, q.y, q.z, q.w], np.float64))
    T[:3, 3] = [p.position.x, p.position.y, p.position.z]
    return T


def _image(msg, where: str) -> np.ndarray:
    from ..io.image_codec import decode_image
    return decode_image(np.asarray(msg.data, np.uint8), msg.encoding, msg.width, msg.height, msg.step, where,
                        bool(msg.is_bigendian))


def _cloud_points(msg) -> tuple[np.ndarray, np.ndarray]:
    """``x, y, z`` (FLOAT32) and packed ``rgb`` of a PointCloud2 as written by the mapper node."""
    fields = {f.name: f for f in msg.fields}
    if not all(k in fields for k in ("x", "y", "z")):
        raise InputError(f"{POINTS}: point cloud without x, y, z fields")
    buf = np.asarray(msg.data, np.uint8)
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    rows = buf[: n * step].reshape(n, step)
    end = ">" if msg.is_bigendian else "<"
    col = lambda k, dt: rows[:, fields[k].offset:fields[k].offset + 4].copy().view(end + dt).ravel()  # noqa: E731
    xyz = np.stack([col("x", "f4"), col("y", "f4"), col("z", "f4")], 1).astype(np.float64)
    if "rgb" in fields:
        p = col("rgb", "u4")
        rgb = np.stack([(p >> 16) & 255, (p >> 8) & 255, p & 255], 1) / 255.0
    else:
        rgb = np.full((n, 3), 0.5)
    ok = np.isfinite(xyz).all(1)
    return xyz[ok], rgb[ok]


def recording_to_folder(path: str | Path, folder: str | Path) -> str:
    """Write ``folder`` from the recording ``path`` (module doc); returns a one-line summary."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from ..eraser.mask_io import encode_mask_png
    from ..eval.output import RunOutput, metrics_template
    from .run_files import depth_png, rgb_png
    path, folder = Path(path), Path(folder)
    if (folder / "metrics.json").exists():
        raise InputError(f"{folder}: holds a run's outputs already; give another --out-dir")
    odo, kf_pose, refined, images, masks, renders, cloud = {}, {}, None, {}, {}, {k: {} for k in RENDER}, None
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
            topics = {c.topic for c in r.connections}
            if ODOMETRY not in topics and KF_POSE not in topics:
                raise InputError(f"{path}: no {ODOMETRY} or {KF_POSE}: not a recording of `vings launch --record`")
            for conn, _, raw in r.messages():
                t = conn.topic
                if t not in (ODOMETRY, REFINED, KF_POSE, KF_IMAGE, MASK, POINTS, *RENDER.values()):
                    continue
                msg = r.deserialize(raw, conn.msgtype)
                if t == ODOMETRY:
                    odo[_stamp(msg.header)] = _pose(msg.pose.pose)
                elif t == KF_POSE:
                    kf_pose[_stamp(msg.header)] = _pose(msg.pose)
                elif t == REFINED:
                    refined = {_stamp(p.header): _pose(p.pose) for p in msg.poses}
                elif t == KF_IMAGE:
                    images[_stamp(msg.header)] = msg
                elif t == MASK:
                    masks[_stamp(msg.header)] = msg
                elif t == POINTS:
                    cloud = msg
                else:
                    kind = next(k for k, v in RENDER.items() if v == t)
                    renders[kind][_stamp(msg.header)] = msg
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - rosbags raises many kinds; one line naming the file
        raise InputError(f"{path}: cannot read the recording: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    out = RunOutput(folder)
    out.prepare()
    traj = Trajectory.from_poses(odo)
    kfs = Trajectory.from_poses(refined if refined else kf_pose)
    write_tum(out.trajectory_path, traj)
    write_tum(out.keyframes_path, kfs)
    for s, msg in masks.items():
        out.write_mask(s, encode_mask_png(_image(msg, MASK) > 127))
    both = sorted(set(images) & set(renders["color"]))
    pick = [both[i] for i in np.linspace(0, len(both) - 1, min(MAX_VIEWS, len(both))).round().astype(int)] if both else []
    index = []
    from ..eval.image import psnr
    for s in pick:
        inp = _image(images[s], KF_IMAGE)
        col = _image(renders["color"][s], RENDER["color"])
        atomic_write_bytes(folder / VIEWS_DIR / f"kf_{s}_input.png", rgb_png(inp))
        out.save_render(f"kf_{s}.png", col)
        if s in renders["depth"]:
            atomic_write_bytes(folder / VIEWS_DIR / f"kf_{s}_depth.png", depth_png(_image(renders["depth"][s], RENDER["depth"])))
        if s in renders["normal"]:
            atomic_write_bytes(folder / VIEWS_DIR / f"kf_{s}_normal.png", rgb_png(_image(renders["normal"][s], RENDER["normal"])))
        p = psnr(col.astype(np.float32) / 255, inp.astype(np.float32) / 255) if col.shape == inp.shape else None
        index.append({"stamp_ns": int(s), "psnr_db": float(p) if p is not None and np.isfinite(p) else None})
    if index:
        atomic_write_text(folder / VIEWS_DIR / VIEWS_INDEX, json.dumps({"views": index}, indent=1) + "\n")
    if cloud is not None and len(kfs):
        xyz, rgb = _cloud_points(cloud)
        if len(xyz):
            s = Surfels(xyz, rgb, np.ones(len(xyz)), np.zeros(len(xyz)))
            write_bev(folder / BEV_FILE, splat_bev(s, kfs.poses, False))
    atomic_write_text(folder / RUN_INFO_FILE, json.dumps({"source": str(path), "format": "MCAP recording of vings launch",
                                                          "metric": False, "gravity_aligned": False}, indent=1) + "\n")
    m = metrics_template()
    m.update(frames=len(traj), frames_tracked=len(traj), keyframes=len(kfs))
    out.write_metrics(m)
    return (f"{len(traj)} poses, {len(kfs)} keyframes, {len(pick)} views, {len(masks)} masks"
            f"{', map points' if cloud is not None else ''} -> {folder}")
