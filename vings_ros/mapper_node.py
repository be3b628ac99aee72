"""``mapper_node``: keyframe packets in; renders, map points, refined keyframe poses, markers out.

It assembles the five keyframe parts by stamp (``msg_adapters.keyframe.KeyframeAssembler``) and
calls :class:`vings_core.mapping.Mapper`, the class ``vings run`` uses. It checkpoints the map
periodically and on shutdown, and resumes from the checkpoint at start (``ros.checkpoint_path``,
``ros.resume``) in the same world frame. Topics and parameters: docs/ros.md.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path as FsPath
from typing import Optional

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from visualization_msgs.msg import MarkerArray

from msg_adapters import topics as T
from msg_adapters.diagnostics import diagnostic_array, make_status
from msg_adapters.image import float_image_to_msg, image_to_msg, rgb_float_to_uint8
from msg_adapters.keyframe import PART_TOPICS, KeyframeAssembler
from msg_adapters.markers import keyframe_frustums_marker, marker_array, trajectory_marker
from msg_adapters.pointcloud import points_to_pointcloud2
from msg_adapters.pose import path_to_trajectory, trajectory_to_path
from vings_core.mapping import Mapper, MapperConfig
from vings_core.types import Keyframe, Trajectory

from .frontend_node import FRONTEND_KEYFRAMES_TOPIC
from .node_common import (InputQueue, NodeConfig, RateMeter, Worker, node_sections, rss_mb,
                          run_node, section_config)


class MapperNode(Node):
    def __init__(self) -> None:
        super().__init__("mapper_node", automatically_declare_parameters_from_overrides=True)
        secs = node_sections(self)
        self.ncfg: NodeConfig = section_config(NodeConfig, secs["ros"], "mapper_node: ros")
        self.mcfg: MapperConfig = section_config(MapperConfig, secs["mapping"], "mapper_node: mapping")
        self.error: Optional[BaseException] = None
        self.ckpt = FsPath(self.ncfg.checkpoint_path) if self.ncfg.checkpoint_path else None
        self.mapper = self._load_or_new()
        self.assembler = KeyframeAssembler(max_pending=16)
        # keyframes are never dropped: the queue is FIFO whatever the input policy
        self.queue: InputQueue = InputQueue("backpressure", 10 ** 6)
        self._moved: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()
        self.rate = RateMeter(30.0)
        self.last_train: dict = {}
        self._last_points = 0.0
        self._last_ckpt = time.monotonic()
        self.keyframes_mapped = 0

        sq = T.sensor_qos
        for part, type_ in (("image", Image), ("depth", Image), ("inv_depth_var", Image),
                            ("pose", PoseStamped), ("camera_info", CameraInfo)):
            self.create_subscription(type_, PART_TOPICS[part],
                                     lambda m, p=part: self._on_part(p, m), sq(T.OUTPUT_DEPTH * 4))
        self.create_subscription(Path, FRONTEND_KEYFRAMES_TOPIC, self._on_moved, T.latched_qos(1))
        self.pub_color = self.create_publisher(Image, T.RENDER_COLOR_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_depth = self.create_publisher(Image, T.RENDER_DEPTH_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_normal = self.create_publisher(Image, T.RENDER_NORMAL_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_points = self.create_publisher(PointCloud2, T.MAP_POINTS_TOPIC, T.latched_qos(1))
        self.pub_refined = self.create_publisher(Path, T.REFINED_KEYFRAMES_TOPIC, T.latched_qos(1))
        self.pub_markers = self.create_publisher(MarkerArray, T.MARKERS_TOPIC, T.latched_qos(1))
        self.pub_diag = self.create_publisher(DiagnosticArray, T.DIAGNOSTICS_TOPIC, sq(10))
        self.create_timer(self.ncfg.diagnostics_period_s, self._publish_diagnostics)
        self.worker = Worker("vings-mapper", self._step, self._fail)
        self.worker.start()
        self.get_logger().info(f"mapper ready: {len(self.mapper.keyframe_poses())} keyframes, "
                               f"{self.mapper.num_gaussians} Gaussians")

    def _load_or_new(self) -> Mapper:
        if self.ckpt is not None and self.ncfg.resume and self.ckpt.exists():
            m = Mapper.load_checkpoint(self.ckpt, self.mcfg)
            self.get_logger().info(f"resumed from checkpoint {self.ckpt}: "
                                   f"{len(m.keyframe_poses())} keyframes, {m.num_gaussians} Gaussians")
            return m
        return Mapper(self.mcfg)

    # ------------------------------------------------------------------------------ callbacks

    def _fail(self, e: BaseException) -> None:
        self.get_logger().error(f"mapper failed: {e}")
        self.error = e

    def _on_part(self, part: str, msg) -> None:
        kf = self.assembler.add(part, msg)
        if kf is not None:
            self.queue.put(kf)

    def _on_moved(self, msg: Path) -> None:
        traj = path_to_trajectory(msg, FRONTEND_KEYFRAMES_TOPIC)
        with self._lock:
            self._moved.update({int(s): P for s, P in zip(traj.stamps_ns, traj.poses)})

    # ----------------------------------------------------------------------------- the worker

    def _apply_moved(self) -> None:
        with self._lock:
            moved, self._moved = self._moved, {}
        known = set(self.mapper.keyframe_poses())
        moved = {s: P for s, P in moved.items() if s in known}
        if moved:
            self.mapper.set_keyframe_poses(moved)

    def _step(self) -> None:
        kf: Optional[Keyframe] = self.queue.get(timeout=0.1)
        self._apply_moved()
        if kf is None:
            return
        if int(kf.stamp_ns) in self.mapper.keyframe_poses():
            return  # resumed graph: the front end re-sent a keyframe the checkpoint already holds
        self.mapper.add_keyframe(kf)
        self.last_train = self.mapper.train()
        self.mapper.refine_poses()
        self.keyframes_mapped += 1
        self.rate.tick()
        stamp = int(kf.stamp_ns)
        self._publish_refined(stamp)
        if self.ncfg.render_every_keyframes and self.keyframes_mapped % self.ncfg.render_every_keyframes == 0:
            self._publish_render(stamp, kf)
        self._publish_markers(stamp, kf)
        now = time.monotonic()
        if now - self._last_points >= self.ncfg.points_period_s:
            self._publish_points(stamp)
            self._last_points = now
        if self.ckpt is not None and self.ncfg.checkpoint_period_s > 0 and \
                now - self._last_ckpt >= self.ncfg.checkpoint_period_s:
            self.mapper.save_checkpoint(self.ckpt)
            self._last_ckpt = now

    def _kf_traj(self) -> Trajectory:
        poses = self.mapper.keyframe_poses()
        st = sorted(poses)
        return Trajectory(np.array(st, np.int64), np.stack([poses[s] for s in st]))

    def _publish_refined(self, stamp: int) -> None:
        self.pub_refined.publish(trajectory_to_path(self._kf_traj(), self.ncfg.world_frame))

    def _publish_render(self, stamp: int, kf: Keyframe) -> None:
        T_wc = self.mapper.keyframe_poses()[stamp]
        out = self.mapper.render(T_wc, kf.camera)
        frame = self.ncfg.camera_frame
        self.pub_color.publish(image_to_msg(rgb_float_to_uint8(out["color"]), stamp, frame,
                                            T.RENDER_COLOR_TOPIC))
        self.pub_depth.publish(float_image_to_msg(out["depth"], stamp, frame, T.RENDER_DEPTH_TOPIC))
        nrm = rgb_float_to_uint8(np.clip(out["normal"] * 0.5 + 0.5, 0, 1))
        self.pub_normal.publish(image_to_msg(nrm, stamp, frame, T.RENDER_NORMAL_TOPIC))

    def _publish_points(self, stamp: int) -> None:
        gm = self.mapper.all_gaussians()
        n = len(gm)
        if n == 0:
            return
        idx = np.arange(n)
        if n > self.ncfg.max_points:
            idx = np.linspace(0, n - 1, self.ncfg.max_points).round().astype(int)
        xyz = gm.means.detach()[idx].cpu().numpy()
        rgb = np.clip(gm.sh.detach()[idx, 0, :].cpu().numpy() * 0.28209479177387814 + 0.5, 0, 1)
        self.pub_points.publish(points_to_pointcloud2(xyz, (rgb * 255).astype(np.uint8), stamp,
                                                      self.ncfg.world_frame))

    def _publish_markers(self, stamp: int, kf: Keyframe) -> None:
        traj = self._kf_traj()
        ma = marker_array([keyframe_frustums_marker(traj.poses, kf.camera, stamp, self.ncfg.world_frame),
                           trajectory_marker(traj.positions, stamp, self.ncfg.world_frame)])
        self.pub_markers.publish(ma)

    def _publish_diagnostics(self) -> None:
        values = {"keyframes": len(self.mapper.keyframe_poses()), "keyframes_mapped": self.keyframes_mapped,
                  "gaussians_total": self.mapper.num_gaussians, "gaussians_active": self.mapper.num_active,
                  "gaussians_passive": self.mapper.num_passive, "queue_length": len(self.queue),
                  "keyframe_rate_hz": self.rate.hz, "incomplete_packets": self.assembler.pending,
                  "dropped_packets": self.assembler.dropped, "rss_mb": rss_mb()}
        level = "ok" if self.error is None else "error"
        msg = "mapping" if self.error is None else f"failed: {self.error}"
        self.pub_diag.publish(diagnostic_array(self.get_clock().now().nanoseconds,
                                               [make_status("vings/mapper", level, msg, values)]))

    # -------------------------------------------------------------------------------- shutdown

    def shutdown(self) -> None:
        """Finish the keyframes already received, then write the final checkpoint."""
        deadline = time.monotonic() + 120.0
        while len(self.queue) and self.error is None and time.monotonic() < deadline:
            time.sleep(0.1)
        self.queue.close()
        self.worker.stop()
        if self.ckpt is not None and self.error is None and self.mapper.keyframe_poses():
            self.mapper.save_checkpoint(self.ckpt)
            self.get_logger().info(f"checkpoint written: {self.ckpt}")
        self.mapper.close()


def main(args: Optional[list] = None) -> int:
    return run_node(MapperNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
