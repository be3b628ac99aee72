"""``eraser_node``: keyframe packets in; each keyframe's dynamic mask out.

It runs :class:`vings_core.eraser.DynamicEraser`, the stage ``vings run`` uses, in its worker
thread, on every keyframe the front end emits (the mapper's five-topic packet, assembled by stamp),
in keyframe order. The re-render cue needs the map rendered at the keyframe's pose before the
keyframe's Gaussians are added: the node asks the mapper with a
:class:`~msg_adapters.loop.RenderRequest` on ``/vings/render/request`` (the keyframe's pose and
camera, ``older_than`` = the keyframe's stamp, so the render holds only the Gaussians of earlier
keyframes even when the mapper has already added this one), answered by ``mapper_node`` on
``/vings/render/reply/{color,depth,alpha}``. Without a reply within
``eraser_node.render_timeout_s`` (or without a mapper) the keyframe is processed with
``render=None``: the motion cue only. The mask goes out on ``/vings/keyframe/dynamic_mask``
(``sensor_msgs/Image`` mono8, 255 = dynamic, stamped with the keyframe's stamp;
msg_adapters/eraser.py), also when it is empty: the mapper waits for it (at most
``eraser.mask_timeout_s``) before it adds the keyframe's Gaussians, the front end gives the masked
pixels weight 0 while the keyframe is in its window.

Nothing waits on this node beyond that timeout: the mapper waits only while a publisher of the mask
topic exists, so tracking and mapping go on without it (``vings launch --no-eraser`` leaves it out).
A keyframe whose content the eraser refuses is dropped with a warning; any other failure of the
eraser stops the node (the graph goes on without masks, as ``vings run`` does). Settings: params
sections ``eraser_node`` (node_config.EraserNodeConfig), ``ros`` and ``eraser``. Topics:
docs/ros.md.
"""
from __future__ import annotations

import os
import threading
import time
from typing import Optional

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, Image

from msg_adapters import topics as T
from msg_adapters.eraser import mask_to_msg
from msg_adapters.keyframe import PART_TOPICS, KeyframeAssembler
from msg_adapters.loop import (RENDER_REQUEST_TOPIC, REPLY_TOPICS, RenderReply, RenderReplyAssembler,
                               RenderRequest, render_request_to_msg)
from msg_adapters.stamps import header_ns
from vings_core.eraser import DynamicEraser, EraserConfig, EraserResult
from vings_core.errors import InputError
from vings_core.keyframe_queue import KeyframeQueue
from vings_core.types import Keyframe

from . import registry
from .node_base import Level, NodeStatus, StageNode
from .node_common import RateMeter, worth_reporting
from .node_config import EraserNodeConfig

#: what happened to the last keyframe's render request -> is it a warning
RENDER_OUTCOMES = {"answered": False, "empty": False, "timeout": True, "no_mapper": True, "mismatched": True}


class EraserNode(StageNode):
    spec = registry.node_spec("eraser_node")
    STATUS_NAME = "vings/eraser"
    WORKER_STOP_TIMEOUT_S = 30.0

    settings: EraserNodeConfig

    def setup(self) -> None:
        self.ecfg: EraserConfig = self.config("eraser")
        if self.settings.nice > 0:      # tracking (and its keyframes) first
            try:
                os.nice(self.settings.nice)
            except OSError:
                pass
        self._abort = threading.Event()         # shutdown: a render wait ends at once
        self.eraser: Optional[DynamicEraser] = DynamicEraser(self.ecfg) if self.ecfg.enabled else None
        self.keyframes_done = 0
        self.masks_published = 0
        self.masks_dynamic = 0                  # masks with at least one dynamic pixel
        self.masks_distrusted = 0               # covered more than eraser.max_masked_fraction: sent empty
        self.without_render = 0                 # processed with render=None (motion cue only)
        self.renders_after_mapped = 0           # the mapper had mapped the keyframe before it answered
        self.bad_parts = 0
        self.bad_replies = 0
        self.bad_keyframes = 0
        self.renders = dict(requests=0, answered=0, empty=0, timeouts=0, no_mapper=0, mismatched=0)
        self.last_render = ""                   # outcome of the last keyframe's request (RENDER_OUTCOMES)
        self.time_ms_sum = 0.0
        self.time_ms_max = 0.0
        self.latency_ms_sum = 0.0               # packet complete -> mask published
        self.fraction_sum = 0.0
        self.last: Optional[EraserResult] = None
        self.rate = RateMeter(30.0)
        self._arrived: dict[int, float] = {}    # stamp -> monotonic time its packet completed
        self._mapped_upto = -1                  # newest keyframe stamp on /vings/keyframes/refined
        # one render request in flight at a time (the worker waits for it)
        self._reply_lock = threading.Lock()
        self._reply_event = threading.Event()
        self._waiting: Optional[int] = None
        self._reply: Optional[RenderReply] = None
        self._last_id = 0
        self.assembler = KeyframeAssembler(max_pending=16)
        self.replies = RenderReplyAssembler(max_pending=16)
        # keyframes are not dropped: FIFO, bounded in memory, the rest in a private folder on disk
        self.queue = KeyframeQueue(self.settings.queue_memory_keyframes, None)

        sq = T.sensor_qos
        if not self.ecfg.enabled:
            # no mask publisher either: the mapper waits only while one exists
            self.get_logger().warning("the dynamic eraser is off (eraser.enabled false): keyframes are ignored")
            return
        self.pub_mask = self.create_publisher(Image, T.DYNAMIC_MASK_TOPIC, sq(T.OUTPUT_DEPTH * 4))
        self.pub_request = self.create_publisher(PoseStamped, RENDER_REQUEST_TOPIC, sq(T.OUTPUT_DEPTH))
        for part, topic in REPLY_TOPICS.items():
            self.create_subscription(Image, topic, lambda m, p=part: self._on_reply(p, m), sq(T.OUTPUT_DEPTH))
        self.create_subscription(Path, T.REFINED_KEYFRAMES_TOPIC, self._on_refined, T.latched_qos(1))
        for part, type_ in (("image", Image), ("depth", Image), ("inv_depth_var", Image),
                            ("pose", PoseStamped), ("camera_info", CameraInfo)):
            self.create_subscription(type_, PART_TOPICS[part], lambda m, p=part: self._on_part(p, m),
                                     sq(T.OUTPUT_DEPTH * 4))

    def ready_message(self) -> str:
        if self.eraser is None:
            return ""
        c = self.ecfg
        return (f"dynamic eraser ready: proposals {c.proposals}, cue {c.cue}; the mapper waits up to "
                f"{c.mask_timeout_s:g} s for each mask")

    # ------------------------------------------------------------------------------ callbacks

    def _on_part(self, part: str, msg) -> None:
        try:
            kf = self.assembler.add(part, msg)
        except InputError as e:
            self.bad_parts += 1
            if worth_reporting(self.bad_parts):
                self.get_logger().warning(f"dropped a malformed keyframe part ({self.bad_parts} so far): {e}")
            return
        if kf is not None:
            self._arrived[int(kf.stamp_ns)] = time.monotonic()
            self.queue.put("kf", kf)

    def _on_reply(self, part: str, msg: Image) -> None:
        try:
            reply = self.replies.add(part, msg)
        except InputError as e:
            self.bad_replies += 1
            if worth_reporting(self.bad_replies):
                self.get_logger().warning(f"ignored a malformed render reply ({self.bad_replies} so far): {e}")
            return
        if reply is None:
            return
        with self._reply_lock:
            if reply.request_id == self._waiting:       # the loop closer's replies are not ours
                self._reply = reply
                self._reply_event.set()

    def _on_refined(self, msg: Path) -> None:
        """The mapper's keyframes (``/vings/keyframes/refined``): which ones it has mapped."""
        try:
            stamps = [header_ns(p.header, f"{T.REFINED_KEYFRAMES_TOPIC}.poses.header") for p in msg.poses]
        except InputError:
            return
        if stamps:
            self._mapped_upto = max(self._mapped_upto, max(stamps))

    # ----------------------------------------------------------------------------- the render

    def render_keyframe(self, kf: Keyframe) -> Optional[dict]:
        """The map at ``kf``'s pose with its camera, from the Gaussians of keyframes older than it
        (a request to the mapper and a wait of at most ``render_timeout_s``); None when no mapper
        subscribes, no reply comes, the map is empty or the reply does not fit the camera. Worker
        thread (the replies arrive on the executor's)."""
        stamp = int(kf.stamp_ns)
        if self._abort.is_set():
            return None
        if self.count_subscribers(RENDER_REQUEST_TOPIC) == 0:
            self.renders["no_mapper"] += 1
            self.last_render = "no_mapper"
            return None
        # ids follow the wall clock (> 0, increasing): far from the loop closer's, which count up by
        # one from its start time
        rid = self._last_id = max(self._last_id + 1, time.time_ns())
        with self._reply_lock:
            self._waiting, self._reply = rid, None
            self._reply_event.clear()
        req = RenderRequest(rid, kf.T_wc.detach().cpu().numpy(), older_than=stamp, camera=kf.camera)
        self.pub_request.publish(render_request_to_msg(req, self.ros.world_frame))
        self.renders["requests"] += 1
        timeout = self.settings.render_timeout_s
        deadline = time.monotonic() + timeout
        while not self._reply_event.wait(0.02):
            if self._abort.is_set() or time.monotonic() >= deadline:
                break
        with self._reply_lock:
            reply, self._waiting, self._reply = self._reply, None, None
        if reply is None:
            self.renders["timeouts"] += 1
            self.last_render = "timeout"
            if worth_reporting(self.renders["timeouts"]):
                self.get_logger().warning(f"keyframe {stamp}: no render from the mapper within {timeout:g} s "
                                          f"({self.renders['timeouts']} so far); its mask uses the motion cue only")
            return None
        self.renders["answered"] += 1
        if stamp <= self._mapped_upto:
            # the mapper did not wait for this mask (timeout): the render still leaves the
            # keyframe's own Gaussians out (older_than), and the mapper applies the mask late
            self.renders_after_mapped += 1
            if worth_reporting(self.renders_after_mapped):
                self.get_logger().warning(f"keyframe {stamp} was already mapped when its render came "
                                          f"({self.renders_after_mapped} so far): its mask is late for the mapper")
        if reply.empty:
            self.renders["empty"] += 1
            self.last_render = "empty"
            return None
        if reply.color.shape[:2] != (kf.camera.height, kf.camera.width):
            self.renders["mismatched"] += 1
            self.last_render = "mismatched"
            if worth_reporting(self.renders["mismatched"]):
                self.get_logger().warning(f"render reply {rid} is {reply.color.shape[1]}x{reply.color.shape[0]} "
                                          f"but keyframe {stamp} is {kf.camera.width}x{kf.camera.height}")
            return None
        self.last_render = "answered"
        return reply.as_dict()

    # ----------------------------------------------------------------------------- the worker

    def step(self) -> None:
        msg = self.queue.get(timeout=0.1)
        if msg is None:
            return
        kf: Keyframe = msg[1]
        stamp = int(kf.stamp_ns)
        arrived = self._arrived.pop(stamp, time.monotonic())
        if self.eraser is None or self._abort.is_set():
            return
        render = self.render_keyframe(kf)
        if render is None:
            self.without_render += 1
        try:
            res = self.eraser.process(kf, render)
        except InputError as e:
            self.bad_keyframes += 1
            self.get_logger().warning(f"dropped keyframe {stamp}: {e}")
            return
        self.pub_mask.publish(mask_to_msg(res.mask, stamp, self.ros.camera_frame))
        self.keyframes_done += 1
        self.masks_published += 1
        self.masks_dynamic += int(bool(res.mask.any()))
        self.masks_distrusted += int(bool(res.note))
        self.time_ms_sum += res.time_ms
        self.time_ms_max = max(self.time_ms_max, res.time_ms)
        self.fraction_sum += res.masked_fraction
        self.latency_ms_sum += 1e3 * (time.monotonic() - arrived)
        self.last = res
        self.rate.tick()

    def diagnostics(self) -> NodeStatus:
        n = self.masks_published
        values = {"keyframes": self.assembler.completed, "keyframes_processed": self.keyframes_done,
                  "masks_published": n, "masks_dynamic": self.masks_dynamic,
                  "masks_distrusted": self.masks_distrusted,
                  "masked_fraction_mean": self.fraction_sum / n if n else 0.0,
                  "masked_fraction_last": self.last.masked_fraction if self.last is not None else 0.0,
                  "eraser_ms_mean": self.time_ms_sum / n if n else 0.0, "eraser_ms_max": self.time_ms_max,
                  "latency_ms_mean": self.latency_ms_sum / n if n else 0.0,
                  "keyframe_rate_hz": self.rate.hz,
                  "processed_without_render": self.without_render,
                  **{f"render_{k}": v for k, v in self.renders.items()},
                  "renders_after_mapped": self.renders_after_mapped,
                  "queue_length": self.queue.keyframes, "queue_on_disk": self.queue.keyframes_on_disk,
                  "bad_keyframe_parts": self.bad_parts, "bad_keyframes": self.bad_keyframes,
                  "bad_render_replies": self.bad_replies, "incomplete_packets": self.assembler.pending,
                  "dropped_packets": self.assembler.dropped}
        if self.eraser is None:
            return NodeStatus(Level.WARN, "dynamic eraser off (eraser.enabled false)", values)
        if RENDER_OUTCOMES.get(self.last_render, False):
            why = {"timeout": f"no reply within {self.settings.render_timeout_s:g} s",
                   "no_mapper": "no mapper subscribes to render requests",
                   "mismatched": "the reply's size is not the keyframe's"}[self.last_render]
            return NodeStatus(Level.WARN, f"no render from the mapper for the last keyframe ({why}): "
                                          f"its mask used the motion cue only", values)
        return NodeStatus(Level.OK, f"{n} masks, mean masked fraction {values['masked_fraction_mean']:.3f}",
                          values)

    # -------------------------------------------------------------------------------- shutdown

    def drain(self) -> None:
        """Keyframes still queued are not processed (the mapper, stopped before this node, waits
        for no mask); a render wait ends at once."""
        self._abort.set()
        if self.queue.keyframes:
            self.get_logger().info(f"shutdown: {self.queue.keyframes} queued keyframe(s) not processed")

    def close(self) -> None:
        self.queue.close()


def main(args: Optional[list[str]] = None) -> int:
    return EraserNode.main(args)


if __name__ == "__main__":
    raise SystemExit(main())
