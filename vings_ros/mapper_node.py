"""``mapper_node``: keyframe packets in; renders, map points, refined keyframe poses, markers out.

It assembles the five keyframe parts by stamp (``msg_adapters.keyframe.KeyframeAssembler``) and
runs :func:`vings_core.pipeline.map_keyframe` on :class:`vings_core.mapping.Mapper`, the step
``vings run`` uses, with the same pose exchange (:class:`vings_core.pipeline.MapperPoseLink`). It
checkpoints the map after its first keyframe, every N keyframes, every T seconds while the map
changes, and on shutdown, atomically, and resumes from the checkpoint at start
(``ros.checkpoint_path``, ``ros.resume``) in the same world frame. Topics and parameters: docs/ros.md.
"""
from __future__ import annotations

import os
import threading
import time
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
from msg_adapters.stamps import header_ns
from vings_core.errors import ConfigError, InputError
from vings_core.mapping import Mapper, MapperConfig
from vings_core.pipeline import MapperPoseLink, PoseUpdates, map_keyframe
from vings_core.types import Keyframe, Trajectory
from vings_core.util import check_output_file, remove_stale_temps
from .node_common import (InputQueue, NodeConfig, RateMeter, Worker, node_sections, rss_mb,
                          run_node, section_config, worth_reporting)

#: training iterations between two checks for shutdown / a due checkpoint
TRAIN_CHUNK = 5


def lower_priority(nice: int, threads: int) -> None:
    """Make the mapper yield the CPU to tracking: add ``nice`` to this process's niceness and use
    ``threads`` torch / numba threads (0 = leave)."""
    if nice > 0:
        try:
            os.nice(nice)
        except OSError:
            pass
    if threads > 0:
        import torch
        torch.set_num_threads(threads)
        try:
            import numba
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        except Exception:  # noqa: BLE001 - numba absent or threading layer fixed
            pass


class MapperNode(Node):
    def __init__(self) -> None:
        super().__init__("mapper_node", automatically_declare_parameters_from_overrides=True)
        secs = node_sections(self)
        self.ncfg: NodeConfig = section_config(NodeConfig, secs["ros"], "mapper_node: ros")
        self.mcfg: MapperConfig = section_config(MapperConfig, secs["mapping"], "mapper_node: mapping")
        self.error: Optional[BaseException] = None
        self.ckpt = None
        if self.ncfg.checkpoint_path:
            # found unwritable now, not when the first checkpoint is due (that ended the mapper)
            self.ckpt = check_output_file(self.ncfg.checkpoint_path, "ros.checkpoint_path", ConfigError)
            remove_stale_temps(self.ckpt)
        lower_priority(self.ncfg.mapper_nice, self.ncfg.mapper_threads)
        self.link = MapperPoseLink()
        self.mapper = self._load_or_new()
        self.assembler = KeyframeAssembler(max_pending=16)
        # keyframes are never dropped: the queue is FIFO whatever the input policy
        self.queue: InputQueue = InputQueue("backpressure", 10 ** 6)
        self._moved: list[dict[int, np.ndarray]] = []
        self._lock = threading.Lock()
        self._abort = threading.Event()     # shutdown: stop training early
        self._busy = False
        self.rate = RateMeter(30.0)
        self.last_train: dict = {}
        self._last_points = 0.0
        self._last_ckpt = time.monotonic()
        self._dirty = False                 # map changed since the last checkpoint
        self.checkpoints = 0
        self.keyframes_mapped = 0
        self.bad_parts = 0

        sq = T.sensor_qos
        for part, type_ in (("image", Image), ("depth", Image), ("inv_depth_var", Image),
                            ("pose", PoseStamped), ("camera_info", CameraInfo)):
            self.create_subscription(type_, PART_TOPICS[part],
                                     lambda m, p=part: self._on_part(p, m), sq(T.OUTPUT_DEPTH * 4))
        self.create_subscription(Path, T.FRONTEND_KEYFRAMES_TOPIC, self._on_moved, sq(T.POSE_EXCHANGE_DEPTH))
        self.pub_color = self.create_publisher(Image, T.RENDER_COLOR_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_depth = self.create_publisher(Image, T.RENDER_DEPTH_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_normal = self.create_publisher(Image, T.RENDER_NORMAL_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_points = self.create_publisher(PointCloud2, T.MAP_POINTS_TOPIC, T.latched_qos(1))
        self.pub_refined = self.create_publisher(Path, T.REFINED_KEYFRAMES_TOPIC, T.latched_qos(1))
        self.pub_corr = self.create_publisher(Path, T.KEYFRAME_CORRECTIONS_TOPIC, sq(T.POSE_EXCHANGE_DEPTH))
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
            self.link.resumed(m.keyframe_poses())
            self.get_logger().info(f"resumed from checkpoint {self.ckpt}: "
                                   f"{len(m.keyframe_poses())} keyframes, {m.num_gaussians} Gaussians")
            return m
        return Mapper(self.mcfg)

    # ------------------------------------------------------------------------------ callbacks

    def _fail(self, e: BaseException) -> None:
        self.get_logger().error(f"mapper failed: {e}")
        self.error = e

    def _on_part(self, part: str, msg) -> None:
        try:
            kf = self.assembler.add(part, msg)
        except InputError as e:  # a malformed keyframe part is reported and dropped
            self.bad_parts += 1
            if worth_reporting(self.bad_parts):
                self.get_logger().warning(f"dropped a malformed keyframe part ({self.bad_parts} so "
                                          f"far): {e}")
            return
        if kf is not None:
            self.queue.put(kf)

    def _on_moved(self, msg: Path) -> None:
        try:
            traj = path_to_trajectory(msg, T.FRONTEND_KEYFRAMES_TOPIC)
            ack = header_ns(msg.header, T.FRONTEND_KEYFRAMES_TOPIC)   # last correction batch it had seen
        except Exception as e:  # noqa: BLE001 - a bad message is reported, the node keeps running
            self.get_logger().warning(f"ignored a malformed keyframe-pose message: {e}")
            return
        with self._lock:
            self._moved.append(PoseUpdates(zip(traj.stamps_ns.tolist(), traj.poses), ack=ack))

    # ----------------------------------------------------------------------------- the worker

    def _apply_moved(self) -> None:
        with self._lock:
            pending, self._moved = self._moved, []
        for moved in pending:
            if self.link.apply_frontend_poses(self.mapper, moved):
                self._dirty = True

    def _step(self) -> None:
        kf: Optional[Keyframe] = self.queue.get(timeout=0.1)
        self._apply_moved()
        if kf is None:
            self._maybe_checkpoint(idle=True)
            return
        if int(kf.stamp_ns) in self.mapper.keyframe_poses():
            return  # resumed graph: the front end re-sent a keyframe the checkpoint already holds
        self._busy = True
        try:
            self._map(kf)
        except InputError as e:
            if int(kf.stamp_ns) in self.mapper.keyframe_poses():
                raise            # the keyframe was taken: not a refusal of its content
            # refused before anything changed (bad image range, shapes, pose): drop it, keep mapping
            self.bad_parts += 1
            self.get_logger().warning(f"dropped keyframe {kf.stamp_ns}: {e}")
        finally:
            self._busy = False

    def _map(self, kf: Keyframe) -> None:
        def stop() -> bool:
            # between training chunks: front-end updates, a due periodic checkpoint, shutdown
            self._apply_moved()
            self._maybe_checkpoint(idle=False)
            return self._abort.is_set()

        self.last_train, corrections = map_keyframe(self.mapper, self.link, kf, refine=True,
                                                    chunk=TRAIN_CHUNK, stop=stop)
        self._dirty = True
        self.keyframes_mapped += 1
        self.rate.tick()
        stamp = int(kf.stamp_ns)
        if corrections:
            # header stamp: the batch number (the mapped keyframe's stamp), echoed by the front end
            self.pub_corr.publish(trajectory_to_path(Trajectory.from_poses(corrections), self.ncfg.world_frame,
                                                     stamp_ns=corrections.batch))
        self._publish_refined(stamp)
        if self.ncfg.render_every_keyframes and self.keyframes_mapped % self.ncfg.render_every_keyframes == 0:
            self._publish_render(stamp, kf)
        self._publish_markers(stamp, kf)
        now = time.monotonic()
        if now - self._last_points >= self.ncfg.points_period_s:
            self._publish_points(stamp)
            self._last_points = now
        n = self.ncfg.checkpoint_every_keyframes
        if self.keyframes_mapped == 1 or (n and self.keyframes_mapped % n == 0):
            self._save_checkpoint(f"keyframe {self.keyframes_mapped}")
        else:
            self._maybe_checkpoint(idle=False)

    def _maybe_checkpoint(self, idle: bool) -> None:
        """Periodic checkpoint (``checkpoint_period_s``) when the map changed since the last."""
        p = self.ncfg.checkpoint_period_s
        if self.ckpt is None or p <= 0 or not self._dirty or not self.mapper.keyframe_poses():
            return
        if time.monotonic() - self._last_ckpt >= p:
            self._save_checkpoint("periodic" + (" (idle)" if idle else ""))

    def _save_checkpoint(self, why: str) -> None:
        """Write the checkpoint (atomic: a crash leaves the previous one intact). Worker thread
        only, or after the worker has stopped."""
        if self.ckpt is None:
            return
        t0 = time.perf_counter()
        self.mapper.save_checkpoint(self.ckpt)
        self._last_ckpt = time.monotonic()
        self._dirty = False
        self.checkpoints += 1
        self.get_logger().info(f"checkpoint ({why}): {len(self.mapper.keyframe_poses())} keyframes, "
                               f"{self.mapper.num_gaussians} Gaussians, {time.perf_counter() - t0:.2f} s")

    def _kf_traj(self) -> Trajectory:
        return Trajectory.from_poses(self.mapper.keyframe_poses())

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
        if self.mapper.num_gaussians == 0:
            return
        xyz, rgb = self.mapper.point_sample(self.ncfg.max_points)
        self.pub_points.publish(points_to_pointcloud2(xyz, (rgb * 255).astype(np.uint8), stamp,
                                                      self.ncfg.world_frame))

    def _publish_markers(self, stamp: int, kf: Keyframe) -> None:
        traj = self._kf_traj()
        ma = marker_array([keyframe_frustums_marker(traj.poses, kf.camera, stamp, self.ncfg.world_frame),
                           trajectory_marker(traj.positions, stamp, self.ncfg.world_frame)])
        self.pub_markers.publish(ma)

    def _publish_diagnostics(self) -> None:
        values = {"keyframes": len(self.mapper.keyframe_poses()), "keyframes_mapped": self.keyframes_mapped,
                  "bad_keyframe_parts": self.bad_parts,
                  "gaussians_total": self.mapper.num_gaussians, "gaussians_active": self.mapper.num_active,
                  "gaussians_passive": self.mapper.num_passive, "queue_length": len(self.queue),
                  "keyframe_rate_hz": self.rate.hz, "incomplete_packets": self.assembler.pending,
                  "dropped_packets": self.assembler.dropped, "checkpoints": self.checkpoints,
                  "rss_mb": rss_mb()}
        level = "ok" if self.error is None else "error"
        msg = "mapping" if self.error is None else f"failed: {self.error}"
        self.pub_diag.publish(diagnostic_array(self.get_clock().now().nanoseconds,
                                               [make_status("vings/mapper", level, msg, values)]))

    # -------------------------------------------------------------------------------- shutdown

    def shutdown(self) -> None:
        """Finish the keyframes already received (up to ``shutdown_timeout_s``), stop the worker,
        then write the final checkpoint: only once the worker has ended, so the checkpoint never
        races with training."""
        deadline = time.monotonic() + self.ncfg.shutdown_timeout_s
        while (len(self.queue) or self._busy) and self.error is None and \
                self.worker.thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        if len(self.queue) or self._busy:
            self.get_logger().warning(f"shutdown: {len(self.queue)} queued keyframes not mapped "
                                      f"after {self.ncfg.shutdown_timeout_s:.0f} s")
        self._abort.set()
        self.queue.close()
        if not self.worker.stop(timeout=120.0):
            self.get_logger().error("mapper worker did not stop within 120 s; no final checkpoint")
            self.error = self.error or RuntimeError("mapper worker did not stop")
            return
        self._apply_moved()
        if self.ckpt is not None and self.error is None and self.mapper.keyframe_poses():
            self._save_checkpoint("shutdown")
        self.mapper.close()


def main(args: Optional[list] = None) -> int:
    return run_node(MapperNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
