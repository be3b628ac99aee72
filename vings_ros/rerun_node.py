"""``rerun_node``: logs the graph's outputs for the rerun viewer into one ``.rrd`` file.

``vings launch --rerun FILE.rrd`` starts it (``ros2 run vings_ros rerun_node FILE.rrd``; the rerun
SDK is the optional extra ``pip install '.[viz]'``). It subscribes, translates with the message
adapters and writes through :class:`vings_core.report.rerun_log.RerunLog` (the entities of
``vings run --rerun``):

=================================  ================================================
topic                              logged as
=================================  ================================================
``/vings/odometry``                ``world/camera`` pose (every tracked frame)
``/vings/keyframe/camera_info``    ``world/camera/image`` pinhole (once)
``/vings/keyframe/image``          ``world/camera/image/rgb`` (keyframes)
``/vings/render/color``, ``depth``  ``world/keyframes/render``, ``world/keyframes/depth``
``/vings/keyframes/refined``       ``world/trajectory`` (the keyframe path)
``/vings/map/points``              ``world/map``
=================================  ================================================

A message it cannot translate is counted and skipped (``/diagnostics`` has no status of its own:
the log is a viewer's aid, never part of the graph's work).
"""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Optional

import numpy as np
from nav_msgs.msg import Odometry, Path as PathMsg
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from msg_adapters import topics as T
from msg_adapters.camera_info import camera_info_to_camera
from msg_adapters.image import msg_to_float_image, msg_to_image, stamp_of
from msg_adapters.pointcloud import pointcloud2_to_points
from msg_adapters.pose import odometry_to_estimate, path_to_trajectory
from msg_adapters.stamps import header_ns
from vings_core.errors import ConfigError

from . import registry
from .node_base import StageNode


class RerunNode(StageNode):
    spec = registry.node_spec("rerun_node")

    def __init__(self, out_path: str) -> None:
        self._out_arg = out_path
        super().__init__()

    def setup(self) -> None:
        from vings_core.report.rerun_log import RerunLog
        self.log_ = RerunLog(self._out_arg)
        self.lock = threading.Lock()
        self.counts: dict[str, int] = {}
        self.skipped = 0
        self._renders: dict[int, dict] = {}
        q = T.sensor_qos(100)
        self.create_subscription(Odometry, T.ODOMETRY_TOPIC, self._odometry, q)
        self.create_subscription(CameraInfo, T.KEYFRAME_INFO_TOPIC, self._camera_info, q)
        self.create_subscription(Image, T.KEYFRAME_IMAGE_TOPIC, self._image, q)
        self.create_subscription(Image, T.RENDER_COLOR_TOPIC, lambda m: self._render("color", m), q)
        self.create_subscription(Image, T.RENDER_DEPTH_TOPIC, lambda m: self._render("depth", m), q)
        self.create_subscription(PathMsg, T.REFINED_KEYFRAMES_TOPIC, self._keyframes, T.latched_qos(1))
        self.create_subscription(PointCloud2, T.MAP_POINTS_TOPIC, self._points, T.latched_qos(1))

    def ready_message(self) -> str:
        return f"logging the graph's outputs to {Path(self._out_arg).resolve()} (rerun)"

    @classmethod
    def from_args(cls, args: list[str]) -> "RerunNode":
        if len(args) != 1:
            raise ConfigError("usage: rerun_node OUT.rrd [--ros-args ...]")
        return cls(args[0])

    def _do(self, topic: str, fn) -> None:
        with self.lock:
            try:
                fn()
            except Exception as e:  # noqa: BLE001 - a bad message is skipped, never a crash
                self.skipped += 1
                self.get_logger().warning(f"{topic}: message not logged: {e}", throttle_duration_sec=10.0)
                return
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def _odometry(self, msg: Odometry) -> None:
        def go():
            est = odometry_to_estimate(msg, T.ODOMETRY_TOPIC)
            self.log_.pose(est.stamp_ns, est.T_wc)
        self._do(T.ODOMETRY_TOPIC, go)

    def _camera_info(self, msg: CameraInfo) -> None:
        self._do(T.KEYFRAME_INFO_TOPIC, lambda: self.log_.set_camera(camera_info_to_camera(msg, T.KEYFRAME_INFO_TOPIC)))

    def _image(self, msg: Image) -> None:
        self._do(T.KEYFRAME_IMAGE_TOPIC, lambda: self.log_.image(stamp_of(msg), msg_to_image(msg, T.KEYFRAME_IMAGE_TOPIC)))

    def _render(self, kind: str, msg: Image) -> None:
        topic = T.RENDER_COLOR_TOPIC if kind == "color" else T.RENDER_DEPTH_TOPIC

        def go():
            s = stamp_of(msg, topic)
            img = msg_to_image(msg, topic) if kind == "color" else msg_to_float_image(msg, topic)
            r = self._renders.setdefault(s, {})
            r[kind] = img
            if "color" in r and "depth" in r:
                self.log_.render(s, r["color"], r["depth"])
                del self._renders[s]
            while len(self._renders) > 20:        # a half pair that never completes
                self._renders.pop(min(self._renders))
        self._do(topic, go)

    def _keyframes(self, msg: PathMsg) -> None:
        def go():
            tr = path_to_trajectory(msg, T.REFINED_KEYFRAMES_TOPIC)
            if len(tr):
                self.log_.keyframe_path(int(tr.stamps_ns[-1]), tr.positions)
        self._do(T.REFINED_KEYFRAMES_TOPIC, go)

    def _points(self, msg: PointCloud2) -> None:
        def go():
            xyz, rgb = pointcloud2_to_points(msg, T.MAP_POINTS_TOPIC)
            stamp = header_ns(msg.header, f"{T.MAP_POINTS_TOPIC}.header")
            self.log_.points(stamp, xyz, rgb if rgb is not None else np.full(xyz.shape, 0.5))
        self._do(T.MAP_POINTS_TOPIC, go)

    def close(self) -> None:
        with self.lock:
            self.log_.close()
        total = sum(self.counts.values())
        self.get_logger().info(f"logged {total} messages on {len(self.counts)} topics to {self.log_.path}"
                               + (f" ({self.skipped} skipped)" if self.skipped else ""))


def main(args: Optional[list[str]] = None) -> int:
    return RerunNode.main(args)


if __name__ == "__main__":
    raise SystemExit(main())
