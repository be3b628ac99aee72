"""``recorder_node``: records every VINGS output topic (serialized, as received) to one MCAP file.

Messages are taken raw (CDR bytes, no deserialisation) and written with rosbags' rosbag2 writer
(MCAP storage) into a temporary bag folder beside the target; on shutdown the ``.mcap`` is moved onto
the target path atomically. ``vings launch --record OUT.mcap`` starts it.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Optional

from msg_adapters import topics as T
from msg_adapters.loop import LOOP_CONSTRAINTS_TOPIC
from vings_core.errors import ConfigError, VingsError
from vings_core.util import fsync_path

from . import registry
from .node_base import StageNode

#: (topic, ROS 2 type name, durability-latched?) of everything the graph publishes
OUTPUT_TOPICS = [
    (T.ODOMETRY_TOPIC, "nav_msgs/msg/Odometry", False),
    (T.PATH_TOPIC, "nav_msgs/msg/Path", True),
    (T.KEYFRAME_IMAGE_TOPIC, "sensor_msgs/msg/Image", False),
    (T.KEYFRAME_DEPTH_TOPIC, "sensor_msgs/msg/Image", False),
    (T.KEYFRAME_VAR_TOPIC, "sensor_msgs/msg/Image", False),
    (T.KEYFRAME_POSE_TOPIC, "geometry_msgs/msg/PoseStamped", False),
    (T.KEYFRAME_INFO_TOPIC, "sensor_msgs/msg/CameraInfo", False),
    (T.EXCHANGE_TOPIC_PREFIX + "frontend", "nav_msgs/msg/Path", False),
    (T.RENDER_COLOR_TOPIC, "sensor_msgs/msg/Image", False),
    (T.RENDER_DEPTH_TOPIC, "sensor_msgs/msg/Image", False),
    (T.RENDER_NORMAL_TOPIC, "sensor_msgs/msg/Image", False),
    (T.MAP_POINTS_TOPIC, "sensor_msgs/msg/PointCloud2", True),
    (T.REFINED_KEYFRAMES_TOPIC, "nav_msgs/msg/Path", True),
    (T.EXCHANGE_TOPIC_PREFIX + "mapper", "nav_msgs/msg/Path", False),
    (T.EXCHANGE_TOPIC_PREFIX + "loop_closer", "nav_msgs/msg/Path", False),
    (T.MARKERS_TOPIC, "visualization_msgs/msg/MarkerArray", True),
    (LOOP_CONSTRAINTS_TOPIC, "nav_msgs/msg/Path", True),
    (T.DYNAMIC_MASK_TOPIC, "sensor_msgs/msg/Image", False),
    (T.DIAGNOSTICS_TOPIC, "diagnostic_msgs/msg/DiagnosticArray", False),
]


def _msg_class(type_name: str):
    pkg, _, name = type_name.split("/")
    mod = __import__(f"{pkg}.msg", fromlist=[name])
    return getattr(mod, name)


class RecorderNode(StageNode):
    spec = registry.node_spec("recorder_node")

    def __init__(self, out_path: str) -> None:
        self.out = Path(out_path).resolve()
        self._out_arg = out_path
        super().__init__()

    def setup(self) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        out_path = self._out_arg
        if self.out.suffix != ".mcap":
            raise ValueError(f"--record {out_path}: the output must be a .mcap file")
        if self.out.exists():
            raise ValueError(f"--record {out_path}: the file exists; recordings are never overwritten")
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.", dir=self.out.parent))
        self.bagdir = self.tmpdir / self.out.stem
        ts = get_typestore(Stores.ROS2_JAZZY)
        self.writer = Writer(self.bagdir, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.lock = threading.Lock()
        self.counts: dict[str, int] = {}
        for topic, type_name, latched in OUTPUT_TOPICS:
            conn = self.writer.add_connection(topic, type_name, typestore=ts)
            qos = T.latched_qos(1) if latched else T.sensor_qos(100)
            self.create_subscription(_msg_class(type_name), topic,
                                     lambda data, c=conn, t=topic: self._write(c, t, data), qos, raw=True)

    def ready_message(self) -> str:
        return f"recording {len(OUTPUT_TOPICS)} topics to {self.out}"

    @classmethod
    def from_args(cls, args: list[str]) -> "RecorderNode":
        if len(args) != 1:
            raise ConfigError("usage: recorder_node OUT.mcap [--ros-args ...]")
        return cls(args[0])

    def _write(self, conn, topic: str, data: bytes) -> None:
        stamp = self.get_clock().now().nanoseconds
        with self.lock:
            if self.error is not None:
                return
            try:
                self.writer.write(conn, stamp, data)
            except OSError as e:      # disk full, file size limit, folder gone: stop, say where
                self.error = VingsError(f"{self.out}: cannot write the recording ({e.strerror or e}); "
                                        f"what was written so far is in {self.bagdir}")
                return
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        """Close the bag and move its ``.mcap`` onto the target (after the inputs stopped)."""
        part = self.bagdir / f"{self.bagdir.name}.mcap"
        with self.lock:
            try:
                self.writer.close()
            except OSError as e:
                # the file lacks its summary: `mcap recover` (the MCAP CLI) rebuilds one
                raise VingsError(f"{self.out}: cannot finish the recording ({e.strerror or e}); the "
                                 f"partial file stays at {part} (`mcap recover` can repair it)") from None
        if self.out.exists():   # appeared while recording: keep both, never overwrite
            self.get_logger().error(f"{self.out} appeared while recording; the recording stays in "
                                    f"{self.bagdir}")
            return
        fsync_path(part)          # the data is on disk before the name points at it
        os.replace(part, self.out)
        fsync_path(self.out.parent)
        shutil.rmtree(self.tmpdir, ignore_errors=True)
        total = sum(self.counts.values())
        self.get_logger().info(f"recorded {total} messages on {len(self.counts)} topics to {self.out}")


def main(args: Optional[list[str]] = None) -> int:
    return RecorderNode.main(args)


if __name__ == "__main__":
    raise SystemExit(main())
