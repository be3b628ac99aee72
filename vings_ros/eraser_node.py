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

import threading
import time
from typing import Optional

from nav_msgs.msg import Path
from sensor_msgs.msg import Image

from msg_adapters import topics as T
from msg_adapters.eraser import mask_to_msg
from msg_adapters.stamps import header_ns
from vings_core.eraser import DynamicEraser, EraserConfig, EraserResult
from vings_core.errors import InputError
from vings_core.keyframe_queue import KeyframeQueue
from vings_core.types import Keyframe

from . import registry
from .node_base import KeyframeInbox, Level, NodeStatus, StageNode
from .node_common import RateMeter, lower_priority, worth_reporting
from .node_config import EraserNodeConfig
from .render_client import RenderClient

#: what happened to the last keyframe's render request (render_client.OUTCOMES) -> is it a warning
RENDER_OUTCOMES = {"answered": False, "empty": False, "timeout": True, "no_mapper": True, "mismatched": True}


class EraserNode(StageNode):
    spec = registry.node_spec("eraser_node")
    STATUS_NAME = "vings/eraser"
    WORKER_STOP_TIMEOUT_S = 30.0

    settings: EraserNodeConfig

    def setup(self) -> None:
        self.ecfg: EraserConfig = self.config("eraser")
        lower_priority(self.settings.nice, 0)      # tracking (and its keyframes) first
        self._abort = threading.Event()         # shutdown: a render wait ends at once
        self.eraser: Optional[DynamicEraser] = DynamicEraser(self.ecfg) if self.ecfg.enabled else None
        self.keyframes_done = 0
        self.masks_published = 0
        self.masks_dynamic = 0                  # masks with at least one dynamic pixel
        self.masks_distrusted = 0               # covered more than eraser.max_masked_fraction: sent empty
        self.without_render = 0                 # processed with render=None (motion cue only)
        self.renders_after_mapped = 0           # the mapper had mapped the keyframe before it answered
        self.bad_keyframes = 0
        self.last_render = ""                   # outcome of the last keyframe's request (RENDER_OUTCOMES)
        self.time_ms_sum = 0.0
        self.time_ms_max = 0.0
        self.latency_ms_sum = 0.0               # packet complete -> mask published
        self.fraction_sum = 0.0
        self.last: Optional[EraserResult] = None
        self.rate = RateMeter(30.0)
        self._arrived: dict[int, float] = {}    # stamp -> monotonic time its packet completed
        self._mapped_upto = -1                  # newest keyframe stamp on /vings/keyframes/refined
        # keyframes are not dropped: FIFO, bounded in memory, the rest in a private folder on disk
        self.queue = KeyframeQueue(self.settings.queue_memory_keyframes, None)
        on = self.ecfg.enabled      # off: no topics (no mask publisher: the mapper waits only while one exists)
        # one render request in flight at a time (the worker waits for it); ids follow the wall clock
        # (> 0, increasing): far from the loop closer's, which count up by one from its start time
        self.render_client = RenderClient(self, self._abort, ids="clock", connect=on,
                                          consequence="its mask uses the motion cue only")
        self.keyframes_in = KeyframeInbox(self, self._on_keyframe, connect=on)
        if not on:
            self.get_logger().warning("the dynamic eraser is off (eraser.enabled false): keyframes are ignored")
            return
        self.pub_mask = self.create_publisher(Image, T.DYNAMIC_MASK_TOPIC, T.sensor_qos(T.OUTPUT_DEPTH * 4))
        self.create_subscription(Path, T.REFINED_KEYFRAMES_TOPIC, self._on_refined, T.latched_qos(1))

    def ready_message(self) -> str:
        if self.eraser is None:
            return ""
        c = self.ecfg
        return (f"dynamic eraser ready: proposals {c.proposals}, cue {c.cue}; the mapper waits up to "
                f"{c.mask_timeout_s:g} s for each mask")

    # ------------------------------------------------------------------------------ callbacks

    def _on_keyframe(self, kf: Keyframe) -> None:
        self._arrived[int(kf.stamp_ns)] = time.monotonic()
        self.queue.put("kf", kf)

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
        res = self.render_client.request(kf.T_wc.detach().cpu().numpy(), kf.camera, stamp,
                                         self.settings.render_timeout_s, about=f"keyframe {stamp}")
        if res.outcome == "aborted":
            return None
        self.last_render = res.outcome
        if res.reply is not None and stamp <= self._mapped_upto:
            # the mapper did not wait for this mask (timeout): the render still leaves the
            # keyframe's own Gaussians out (older_than), and the mapper applies the mask late
            self.renders_after_mapped += 1
            if worth_reporting(self.renders_after_mapped):
                self.get_logger().warning(f"keyframe {stamp} was already mapped when its render came "
                                          f"({self.renders_after_mapped} so far): its mask is late for the mapper")
        return res.render

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
        assembler = self.keyframes_in.assembler
        values = {"keyframes": assembler.completed, "keyframes_processed": self.keyframes_done,
                  "masks_published": n, "masks_dynamic": self.masks_dynamic,
                  "masks_distrusted": self.masks_distrusted,
                  "masked_fraction_mean": self.fraction_sum / n if n else 0.0,
                  "masked_fraction_last": self.last.masked_fraction if self.last is not None else 0.0,
                  "eraser_ms_mean": self.time_ms_sum / n if n else 0.0, "eraser_ms_max": self.time_ms_max,
                  "latency_ms_mean": self.latency_ms_sum / n if n else 0.0,
                  "keyframe_rate_hz": self.rate.hz,
                  "processed_without_render": self.without_render,
                  **self.render_client.diagnostic_values(),
                  "renders_after_mapped": self.renders_after_mapped,
                  "queue_length": self.queue.keyframes, "queue_on_disk": self.queue.keyframes_on_disk,
                  "bad_keyframe_parts": self.keyframes_in.bad, "bad_keyframes": self.bad_keyframes,
                  "incomplete_packets": assembler.pending, "dropped_packets": assembler.dropped}
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
