"""``mapper_node``: keyframe packets in; renders, map points, refined keyframe poses, markers out.

It assembles the five keyframe parts by stamp (``msg_adapters.keyframe.KeyframeAssembler``) and
runs :func:`vings_core.stages.map_keyframe` on :class:`vings_core.mapping.Mapper`, the step
``vings run`` uses, following the same pose exchange (:class:`vings_core.exchange.PoseFollower`). It
checkpoints the map after its first keyframe, every N keyframes, every T seconds while the map
changes, and on shutdown, atomically, and resumes from the checkpoint at start
(``mapper_node.checkpoint_path``, ``mapper_node.resume``) in the same world frame. It answers the
loop closer's render requests (``/vings/render/request`` -> ``/vings/render/reply/*``,
msg_adapters/loop.py) in its worker thread, between keyframes and between training chunks (never
while training), and after a keeper batch that first acknowledges a new loop correction it retrains
the revisited region (:func:`vings_core.stages.retrain_after_loop`, section ``loop``). The same
render requests come from ``eraser_node``, for the pose of a keyframe before its Gaussians are
added: while a publisher of ``/vings/keyframe/dynamic_mask`` exists (and ``eraser.enabled``), each
keyframe waits up to ``eraser.mask_timeout_s`` for its mask in the worker thread (which answers
render requests meanwhile; the executor never waits), then is mapped with the mask
(``Keyframe.dynamic``) or, when none came, without one (counted, WARN on /diagnostics); a mask that
comes later goes through :meth:`~vings_core.mapping.Mapper.set_dynamic_mask`. Settings: params
sections ``mapper_node`` (node_config.MapperNodeConfig), ``ros``, ``mapping``, ``loop`` and
``eraser``. Topics and parameters: docs/ros.md.
"""
from __future__ import annotations

import threading
import time
from dataclasses import replace
from pathlib import Path as FilePath
from typing import Optional

import numpy as np
import torch
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from visualization_msgs.msg import MarkerArray

from msg_adapters import topics as T
from msg_adapters.eraser import msg_to_mask
from msg_adapters.image import float_image_to_msg, image_to_msg, rgb_float_to_uint8
from msg_adapters.keyframe import PART_TOPICS, KeyframeAssembler
from msg_adapters.loop import (RENDER_REQUEST_TOPIC, REPLY_TOPICS, RenderRequest, msg_to_render_request,
                               render_reply_to_msgs)
from msg_adapters.markers import keyframe_frustums_marker, marker_array, trajectory_marker
from msg_adapters.pointcloud import points_to_pointcloud2
from msg_adapters.exchange import batch_to_path, exchange_topic
from msg_adapters.pose import trajectory_to_path
from vings_core.eraser import EraserConfig
from vings_core.errors import InputError, VingsError
from vings_core.exchange import IncrementBatch, PoseFollower
from vings_core.exchange.config import KEEPER
from vings_core.keyframe_queue import KeyframeQueue
from vings_core.mapping import Mapper, MapperConfig
from vings_core.loop import LOOP_SOURCE, LoopConfig
from vings_core.stages import MAPPER_SOURCE, map_keyframe, retrain_after_loop
from vings_core.types import Keyframe, Trajectory

from . import registry
from .node_base import BatchInbox, Level, NodeStatus, StageNode
from .node_common import RateMeter, lower_priority, worth_reporting
from .node_config import MapperNodeConfig, QueuePolicy, StopPolicy

#: training iterations between two checks for shutdown / a due checkpoint / render requests
TRAIN_CHUNK = 5
#: render requests waiting for the worker (older ones are dropped: their requester has moved on)
RENDER_QUEUE = 8
#: dynamic masks waiting for their keyframe (a mapper far behind the eraser); more are refused
MASK_BUFFER = 256


def _unpack(packed: tuple[tuple[int, int], np.ndarray]) -> np.ndarray:
    """A buffered mask ``(shape, np.packbits(mask))`` -> ``(H, W)`` bool."""
    shape, bits = packed
    return np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape).astype(bool)


class MapperNode(StageNode):
    spec = registry.node_spec("mapper_node")
    STATUS_NAME = "vings/mapper"
    WORKER_STOP_TIMEOUT_S = 120.0

    settings: MapperNodeConfig

    def setup(self) -> None:
        self.mcfg: MapperConfig = self.config("mapping")
        self.lcfg: LoopConfig = self.config("loop")
        self.ecfg: EraserConfig = self.config("eraser")
        lower_priority(self.settings.nice, self.settings.threads)
        self._exchange_setup()
        self.mapper = self._load_or_new()
        self.assembler = KeyframeAssembler(max_pending=16)
        # keyframes are never dropped: FIFO whatever the input policy, bounded in memory, the rest on disk
        self.queue = self._keyframe_queue()
        self._abort = threading.Event()     # shutdown: stop training early
        self._stored = threading.Event()    # shutdown with on_stop store: take no more keyframes
        self._busy = False
        self.rate = RateMeter(30.0)
        self._last_points = 0.0
        self.keyframes_mapped = 0
        self.light_keyframes = 0        # trained lightly to catch up (mapping.catch_up_backlog)
        self.bad_parts = 0
        self._loop_ack = 0              # the last loop-closer batch the keeper acknowledged
        self.retrains: list[dict] = []
        self.renders_answered = 0
        self.bad_render_requests = 0
        # render requests of the loop closer and the eraser: answered by the worker between its steps
        self.render_requests = self.input_queue(QueuePolicy.BACKPRESSURE, RENDER_QUEUE)
        # dynamic masks of the eraser: stamp -> (shape, bits packed), taken by the worker
        self._masks: dict[int, tuple[tuple[int, int], np.ndarray]] = {}
        self._mask_lock = threading.Lock()
        self._wake = threading.Event()      # a mask or a render request arrived (the mask wait)
        self.masks_received = 0
        self.masks_late = 0                 # came after their keyframe was mapped: set_dynamic_mask
        self.masks_unused = 0               # for a keyframe the mapper never mapped (dropped)
        self.masks_refused = 0              # buffer full
        self.bad_masks = 0
        self.keyframes_with_mask = 0        # mapped with the mask that came within the timeout
        self.keyframes_without_mask = 0     # waited eraser.mask_timeout_s, mapped without one
        self.erased_late = 0                # Gaussians erased by late masks
        self._mask_missing: Optional[int] = None   # the last keyframe that waited in vain (None: it came)
        self.mask_wait_s_sum = 0.0
        self.mask_wait_s_max = 0.0
        self.mask_waits = 0

        sq = T.sensor_qos
        for part, type_ in (("image", Image), ("depth", Image), ("inv_depth_var", Image),
                            ("pose", PoseStamped), ("camera_info", CameraInfo)):
            self.create_subscription(type_, PART_TOPICS[part],
                                     lambda m, p=part: self._on_part(p, m), sq(T.OUTPUT_DEPTH * 4))
        self.pub_color = self.create_publisher(Image, T.RENDER_COLOR_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_depth = self.create_publisher(Image, T.RENDER_DEPTH_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_normal = self.create_publisher(Image, T.RENDER_NORMAL_TOPIC, sq(T.OUTPUT_DEPTH))
        self.pub_points = self.create_publisher(PointCloud2, T.MAP_POINTS_TOPIC, T.latched_qos(1))
        self.pub_refined = self.create_publisher(Path, T.REFINED_KEYFRAMES_TOPIC, T.latched_qos(1))
        # with a checkpoint: which keyframes it holds (the front end releases only those)
        self.pub_checkpointed = (self.create_publisher(Path, T.CHECKPOINTED_KEYFRAMES_TOPIC, T.latched_qos(1))
                                 if self.checkpoint_file is not None else None)
        self._publish_checkpointed()        # resumed: the checkpoint holds these
        self.pub_markers = self.create_publisher(MarkerArray, T.MARKERS_TOPIC, T.latched_qos(1))
        self.pub_reply = {p: self.create_publisher(Image, topic, sq(T.OUTPUT_DEPTH)) for p, topic in REPLY_TOPICS.items()}
        self.create_subscription(PoseStamped, RENDER_REQUEST_TOPIC, self._on_render_request, sq(T.OUTPUT_DEPTH))
        self.create_subscription(Image, T.DYNAMIC_MASK_TOPIC, self._on_mask, sq(T.OUTPUT_DEPTH * 4))

    def ready_message(self) -> str:
        return (f"mapper ready: {len(self.mapper.keyframe_poses())} keyframes, "
                f"{self.mapper.num_gaussians} Gaussians")

    def _keyframe_queue(self) -> KeyframeQueue:
        s = self.settings
        spill = s.queue_spill_dir or (f"{self.checkpoint_file}.queue" if self.checkpoint_file is not None else "")
        q = KeyframeQueue(s.queue_memory_keyframes, spill or None, remove_dir=not spill)
        if spill and s.resume:
            n = q.recover()
            if n:
                self.get_logger().info(f"resumed {n} queued keyframe(s) from {spill}")
        elif spill:
            q.discard_leftovers()
        return q

    def _load_or_new(self) -> Mapper:
        resume = self.resume_file()
        if resume is not None:
            m = Mapper.load_checkpoint(resume, self.mcfg)
            self._exchange_resumed(m)
            self.get_logger().info(f"resumed from checkpoint {resume}: "
                                   f"{len(m.keyframe_poses())} keyframes, {m.num_gaussians} Gaussians")
            return m
        return Mapper(self.mcfg)

    # ------------------------------------------------------------------------------ callbacks

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
            self.queue.put("kf", kf)

    def _on_render_request(self, msg: PoseStamped) -> None:
        try:
            req = msg_to_render_request(msg, RENDER_REQUEST_TOPIC)
        except InputError as e:
            self.bad_render_requests += 1
            if worth_reporting(self.bad_render_requests):
                self.get_logger().warning(f"ignored a malformed render request ({self.bad_render_requests} so "
                                          f"far): {e}")
            return
        self.render_requests.put(req)
        self._wake.set()

    def _on_mask(self, msg: Image) -> None:
        try:
            stamp, mask = msg_to_mask(msg, T.DYNAMIC_MASK_TOPIC)
        except InputError as e:
            self.bad_masks += 1
            if worth_reporting(self.bad_masks):
                self.get_logger().warning(f"ignored a malformed dynamic mask ({self.bad_masks} so far): {e}")
            return
        with self._mask_lock:
            self.masks_received += 1
            if len(self._masks) >= MASK_BUFFER and stamp not in self._masks:
                self.masks_refused += 1
                return
            self._masks[stamp] = (mask.shape, np.packbits(mask, axis=None))
        self._wake.set()

    # ----------------------------------------------------------------------------- the worker

    def step(self) -> None:
        if self._stored.is_set():       # stopping: what is queued stays queued (stored)
            time.sleep(0.05)
            return
        msg = self.queue.get(timeout=0.1)
        kf: Optional[Keyframe] = None if msg is None else msg[1]
        self._exchange_receive()
        self._answer_renders()
        self._apply_late_masks()
        if kf is None:
            self.maybe_checkpoint(idle=True)
            return
        if int(kf.stamp_ns) in self.mapper.keyframe_poses():
            return  # resumed graph: the front end re-sent a keyframe the checkpoint already holds
        self._busy = True
        try:
            kf = self._with_mask(kf)
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
            # between training chunks: front-end updates, render requests, a due periodic
            # checkpoint, shutdown
            self._exchange_receive()
            self._answer_renders()
            self._apply_late_masks()
            self.maybe_checkpoint(idle=False)
            return self._abort.is_set()

        # no refinement once the front end has stopped: nobody would answer it
        keeper_up = self.count_publishers(exchange_topic(KEEPER)) > 0
        stats, batch = map_keyframe(self.mapper, self.follower, kf, refine=keeper_up, chunk=TRAIN_CHUNK, stop=stop,
                                    backlog=self.queue.keyframes)
        self.light_keyframes += int(stats["light"])
        self.mark_changed()
        self.keyframes_mapped += 1
        self.rate.tick()
        stamp = int(kf.stamp_ns)
        self._exchange_send(batch)
        self._publish_refined(stamp)
        n_render = self.settings.render_every_keyframes
        if n_render and self.keyframes_mapped % n_render == 0:
            self._publish_render(stamp, kf)
        self._publish_markers(stamp, kf)
        now = time.monotonic()
        if now - self._last_points >= self.settings.points_period_s:
            self._publish_points(stamp)
            self._last_points = now
        n = self.settings.checkpoint_every_keyframes
        if self.keyframes_mapped == 1 or (n and self.keyframes_mapped % n == 0):
            self.save_checkpoint(f"keyframe {self.keyframes_mapped}")
        else:
            self.maybe_checkpoint(idle=False)

    # ------------------------------------------------------------------------- dynamic masks

    def _eraser_running(self) -> bool:
        """Whether to wait for masks: the eraser is on and someone publishes them (an eraser
        that stopped, or a graph launched with ``--no-eraser``, costs no wait)."""
        return bool(self.ecfg.enabled) and self.count_publishers(T.DYNAMIC_MASK_TOPIC) > 0

    def _take_mask(self, stamp: int) -> Optional[np.ndarray]:
        with self._mask_lock:
            packed = self._masks.pop(stamp, None)
        return None if packed is None else _unpack(packed)

    def _with_mask(self, kf: Keyframe) -> Keyframe:
        """Keyframe ``kf`` with its dynamic mask: wait (worker thread, at most
        ``eraser.mask_timeout_s``, answering render requests meanwhile: the eraser asks for this
        keyframe's render first) while an eraser runs; without one, a mask already here is used."""
        stamp = int(kf.stamp_ns)
        mask = self._take_mask(stamp)
        if mask is None and self._eraser_running():
            t0 = time.monotonic()
            deadline = t0 + float(self.ecfg.mask_timeout_s)
            while mask is None and not self._abort.is_set():
                self._answer_renders()
                self._apply_late_masks()
                mask = self._take_mask(stamp)
                left = deadline - time.monotonic()
                if mask is not None or left <= 0:
                    break
                self._wake.wait(min(left, 0.05))
                self._wake.clear()
            waited = time.monotonic() - t0
            self.mask_waits += 1
            self.mask_wait_s_sum += waited
            self.mask_wait_s_max = max(self.mask_wait_s_max, waited)
            if mask is None:
                self.keyframes_without_mask += 1
                self._mask_missing = stamp
                if worth_reporting(self.keyframes_without_mask):
                    self.get_logger().warning(
                        f"keyframe {stamp}: the eraser's mask did not come within eraser.mask_timeout_s = "
                        f"{self.ecfg.mask_timeout_s:g} s; mapped without it ({self.keyframes_without_mask} "
                        f"so far; a mask that comes later is applied then)")
                return kf
        if mask is None:
            return kf
        self._mask_missing = None
        if mask.shape != (kf.camera.height, kf.camera.width):
            self.bad_masks += 1
            self.get_logger().warning(f"keyframe {stamp}: dynamic mask is {mask.shape[1]}x{mask.shape[0]} but the "
                                      f"keyframe is {kf.camera.width}x{kf.camera.height}; mapped without it")
            return kf
        self.keyframes_with_mask += 1
        if not mask.any():
            return kf
        return replace(kf, dynamic=torch.from_numpy(mask))

    def _apply_late_masks(self) -> None:
        """Masks of keyframes already mapped (they came after the timeout):
        :meth:`Mapper.set_dynamic_mask`; masks of keyframes older than the newest mapped one that
        the mapper does not hold (dropped) are discarded. Worker thread."""
        st = self.mapper.state
        if not self._masks or not st.order:
            return
        newest = st.order[-1]
        with self._mask_lock:
            done = {s: m for s, m in self._masks.items() if s in st.poses or s < newest}
            for s in done:
                del self._masks[s]
        for s, packed in sorted(done.items()):
            if s not in st.poses:
                self.masks_unused += 1
                continue
            try:
                self.erased_late += self.mapper.set_dynamic_mask(s, _unpack(packed))
            except ValueError as e:     # a mask of another size
                self.bad_masks += 1
                self.get_logger().warning(f"ignored the late dynamic mask of keyframe {s}: {e}")
                continue
            self.masks_late += 1
            self.mark_changed()

    def _answer_renders(self) -> None:
        """The loop closer's render requests (worker thread, between training chunks): the map from
        the request's pose with its camera (none given: the mapper's keyframe camera), the
        Gaussians of keyframes older than the request's bound; three 0 x 0 images when there is no
        map yet."""
        while True:
            req: Optional[RenderRequest] = self.render_requests.get(timeout=0)
            if req is None:
                return
            out = None
            cam = req.camera or self.mapper.state.camera
            if cam is not None and self.mapper.num_gaussians:
                try:
                    out = self.mapper.render(req.T_wc, cam, owners_before=req.older_than)
                except VingsError as e:     # a pose the renderer refuses: answered as "no map"
                    self.bad_render_requests += 1
                    self.get_logger().warning(f"render request {req.request_id}: {e}")
            for part, m in render_reply_to_msgs(req.request_id, out, self.ros.camera_frame).items():
                self.pub_reply[part].publish(m)
            self.renders_answered += 1

    def _kf_traj(self) -> Trajectory:
        return Trajectory.from_poses(self.mapper.keyframe_poses())

    def _publish_refined(self, stamp: int) -> None:
        self.pub_refined.publish(trajectory_to_path(self._kf_traj(), self.ros.world_frame))

    def _publish_render(self, stamp: int, kf: Keyframe) -> None:
        T_wc = self.mapper.keyframe_poses()[stamp]
        out = self.mapper.render(T_wc, kf.camera)
        frame = self.ros.camera_frame
        self.pub_color.publish(image_to_msg(rgb_float_to_uint8(out["color"]), stamp, frame,
                                            T.RENDER_COLOR_TOPIC))
        self.pub_depth.publish(float_image_to_msg(out["depth"], stamp, frame, T.RENDER_DEPTH_TOPIC))
        nrm = rgb_float_to_uint8(np.clip(out["normal"] * 0.5 + 0.5, 0, 1))
        self.pub_normal.publish(image_to_msg(nrm, stamp, frame, T.RENDER_NORMAL_TOPIC))

    def _publish_points(self, stamp: int) -> None:
        if self.mapper.num_gaussians == 0:
            return
        xyz, rgb = self.mapper.point_sample(self.settings.max_points)
        self.pub_points.publish(points_to_pointcloud2(xyz, (rgb * 255).astype(np.uint8), stamp,
                                                      self.ros.world_frame))

    def _publish_markers(self, stamp: int, kf: Keyframe) -> None:
        traj = self._kf_traj()
        world = self.ros.world_frame
        ma = marker_array([keyframe_frustums_marker(traj.poses, kf.camera, stamp, world),
                           trajectory_marker(traj.positions, stamp, world)])
        self.pub_markers.publish(ma)

    def diagnostics(self) -> NodeStatus:
        values = {"keyframes": len(self.mapper.keyframe_poses()), "keyframes_mapped": self.keyframes_mapped,
                  "keyframes_light": self.light_keyframes,
                  "bad_keyframe_parts": self.bad_parts,
                  "gaussians_total": self.mapper.num_gaussians, "gaussians_active": self.mapper.num_active,
                  "gaussians_passive": self.mapper.num_passive, "queue_length": self.queue.keyframes,
                  "queue_on_disk": self.queue.keyframes_on_disk,
                  "keyframe_rate_hz": self.rate.hz, "incomplete_packets": self.assembler.pending,
                  "dropped_packets": self.assembler.dropped, "checkpoints": self.checkpoints,
                  "renders_answered": self.renders_answered, "bad_render_requests": self.bad_render_requests,
                  "loop_retrains": len(self.retrains),
                  "eraser_wait": self.ecfg.enabled and self.count_publishers(T.DYNAMIC_MASK_TOPIC) > 0,
                  "keyframes_with_mask": self.keyframes_with_mask,
                  "keyframes_without_mask": self.keyframes_without_mask,
                  "mask_wait_ms_mean": 1e3 * self.mask_wait_s_sum / self.mask_waits if self.mask_waits else 0.0,
                  "mask_wait_ms_max": 1e3 * self.mask_wait_s_max,
                  "masks_received": self.masks_received, "masks_late": self.masks_late,
                  "masks_unused": self.masks_unused, "masks_refused": self.masks_refused,
                  "bad_masks": self.bad_masks,
                  "gaussians_erased_dynamic": int(self.mapper.state.counters.get("erased_dynamic", 0)),
                  "gaussians_erased_late": self.erased_late, "bad_exchange_messages": self.inbox.bad}
        if self._mask_missing is not None:
            return NodeStatus(Level.WARN, f"{self.keyframes_without_mask} keyframe(s) mapped without a dynamic "
                                          f"mask: the eraser's mask did not come within eraser.mask_timeout_s = "
                                          f"{self.ecfg.mask_timeout_s:g} s (last: keyframe {self._mask_missing})",
                              values)
        return NodeStatus(Level.OK, "mapping", values)

    # ---------------------------------------------------------------------------- checkpoints

    def write_checkpoint(self, path: FilePath) -> str:
        self.mapper.save_checkpoint(path)
        self._publish_checkpointed()
        return f"{len(self.mapper.keyframe_poses())} keyframes, {self.mapper.num_gaussians} Gaussians"

    def _publish_checkpointed(self) -> None:
        """With a checkpoint: the keyframes it holds (as written last, or resumed from)."""
        if self.pub_checkpointed is not None and self.mapper.keyframe_poses():
            self.pub_checkpointed.publish(trajectory_to_path(self._kf_traj(), self.ros.world_frame))

    def checkpoint_ready(self) -> bool:
        return bool(self.mapper.keyframe_poses())

    # ----------------------------------------------------------------------- pose exchange
    # The mapper follows the front end's batches (/vings/exchange/frontend: window BA moves, what it
    # did with the mapper's increments) and sends its refinements (/vings/exchange/mapper), through
    # vings_core.exchange.PoseFollower.

    def _exchange_setup(self) -> None:
        self.follower = PoseFollower(MAPPER_SOURCE, self)
        self.inbox = BatchInbox(self, (KEEPER,))
        self.pub_exchange = self.create_publisher(Path, exchange_topic(MAPPER_SOURCE),
                                                  T.sensor_qos(T.POSE_EXCHANGE_DEPTH))

    def apply_increments(self, increments: dict[int, np.ndarray]) -> None:
        """The follower's moves, applied to the map (it is the follower's pose owner)."""
        if self.mapper.apply_increments(increments):
            self.mark_changed()

    def _exchange_resumed(self, mapper: Mapper) -> None:
        self.follower.resumed(mapper.keyframe_poses())

    def _exchange_receive(self) -> None:
        for batch in self.inbox.take():
            self.follower.receive(batch)
            self._retrain_after_loop(batch)

    def _retrain_after_loop(self, batch: IncrementBatch) -> None:
        """As ``vings run`` after each keeper batch: when it first acknowledges a new loop-closer
        batch, a short retrain of the revisited region and a prune (section ``loop``)."""
        if not self.lcfg.enabled:
            return
        lc = self.lcfg
        self._loop_ack, re = retrain_after_loop(self.mapper, batch, self._loop_ack, lc.retrain_iters,
                                                lc.retrain_max_s, lc.prune_after, source=LOOP_SOURCE)
        if re is not None:
            self.retrains.append(re)
            self.mark_changed()
            self.get_logger().info(f"loop correction: map retrained {re['retrain_iters']} iterations over "
                                   f"{re['retrain_views']} views in {re.get('retrain_s', 0.0):.2f} s, "
                                   f"{re['loop_pruned']} pruned")

    def _exchange_send(self, batch: Optional[IncrementBatch]) -> None:
        if batch is not None:
            self.pub_exchange.publish(batch_to_path(batch, self.ros.world_frame))

    # -------------------------------------------------------------------------------- shutdown

    def drain(self) -> None:
        """Finish the keyframes already received (up to ``shutdown_timeout_s``), then make the
        current training stop early; the final checkpoint follows once the worker has ended, so
        it never races with training."""
        n = self.queue.keyframes
        if self.settings.on_stop is StopPolicy.STORE and self.queue.keeps_files:
            self._stored.set()
            self._abort.set()           # the keyframe in training ends at its next chunk
            deadline = time.monotonic() + STOP_WAIT_S
            while self._busy and self.worker.thread.is_alive() and time.monotonic() < deadline \
                    and not self.hurried:
                time.sleep(0.02)
            self.get_logger().info(f"stopping: {self.queue.keyframes} keyframe(s) not mapped yet are stored in "
                                   f"{self.queue.spill_dir} with the checkpoint; the mapper maps them when it "
                                   f"resumes")
            return
        timeout = self.settings.shutdown_timeout_s
        if n or self._busy:
            self.get_logger().info(f"stopping: mapping the {n} queued keyframe(s) first (at most {timeout:.0f} s"
                                   + ("" if self.queue.keeps_files else "; no checkpoint_path to store them")
                                   + ")")
        deadline = time.monotonic() + timeout
        while (self.queue.keyframes or self._busy) and self.error is None and \
                self.worker.thread.is_alive() and time.monotonic() < deadline and not self.hurried:
            time.sleep(0.05)
        if self.queue.keyframes or self._busy:
            kept = (f"; they wait in {self.queue.spill_dir} for the next start (resume)"
                    if self.queue.keeps_files else "")
            self.get_logger().warning(f"shutdown: {self.queue.keyframes} queued keyframes not mapped "
                                      f"after {timeout:.0f} s{kept}")
        self._abort.set()

    def finish(self) -> None:
        self._exchange_receive()
        if self.count_publishers(exchange_topic(KEEPER)) == 0:
            # the front end has stopped: refinements it never answered are not in the trajectory
            n = self.follower.abandon()
            if n:
                self.mark_changed()
                self.get_logger().info(f"undid the unanswered refinement of {n} keyframe(s): the front end "
                                       f"stopped before it answered")

    def close(self) -> None:
        if self.queue.keeps_files:
            self.queue.persist()        # what was not mapped waits on disk for the resumed node
        else:
            self.queue.close()
        self.mapper.close()


#: with on_stop store: how long the stop waits for the keyframe in training to reach its next chunk
STOP_WAIT_S = 8.0


def main(args: Optional[list[str]] = None) -> int:
    return MapperNode.main(args)


if __name__ == "__main__":
    raise SystemExit(main())
