"""The requester's side of the mapper's render service, shared by ``loop_closer_node`` and
``eraser_node``: :class:`RenderClient`.

A request (:class:`~msg_adapters.loop.RenderRequest`: id, pose, optional ``older_than`` bound and
camera) goes out on ``/vings/render/request``; ``mapper_node`` answers on
``/vings/render/reply/{color,depth,alpha}`` with the same id (docs/ros.md, *Render request and
reply*). One request is in flight at a time: the worker thread sends it and waits (at most the
timeout, or until the node's abort event is set) while the executor thread pairs the reply parts
and hands over the reply with the awaited id; replies to other ids (the other requester's, or an
older request's) are ignored.

Request ids (> 0, ``header.stamp`` of the request), per requester: ``clock`` follows the wall clock
(``max(last + 1, time.time_ns())``, the eraser); ``counter`` counts up by one from the client's start
time (the loop closer). No rclpy import here beyond what the node hands in.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import Image

from msg_adapters import topics as T
from msg_adapters.loop import (RENDER_REQUEST_TOPIC, REPLY_TOPICS, RenderReply, RenderReplyAssembler,
                               RenderRequest, render_request_to_msg)
from vings_core.errors import InputError
from vings_core.types import CameraModel

from .node_common import worth_reporting

#: request-id schemes (module docstring)
ID_SCHEMES = ("clock", "counter")
#: the outcomes of :meth:`RenderClient.request`; all but ``answered`` give no render. ``aborted``:
#: the node was shutting down before the request went out (nothing sent, nothing counted)
OUTCOMES = ("answered", "empty", "timeout", "no_mapper", "mismatched", "aborted")
#: outcome -> its key in :attr:`RenderClient.counts` (``aborted`` is not counted)
_COUNT_KEY = {"answered": "answered", "empty": "empty", "timeout": "timeouts", "no_mapper": "no_mapper",
              "mismatched": "mismatched"}
#: seconds between two looks at the abort event while waiting
_POLL_S = 0.02


@dataclass
class RenderOutcome:
    """What became of one request: ``outcome`` (:data:`OUTCOMES`), the request id (0 when nothing
    was sent) and the reply (any reply that came: also an empty or mismatched one; None without)."""

    outcome: str
    request_id: int = 0
    reply: Optional[RenderReply] = None

    @property
    def render(self) -> Optional[dict]:
        """``{"color", "depth", "alpha"}`` as ``Mapper.render`` gives them, for ``answered`` only."""
        return self.reply.as_dict() if self.outcome == "answered" and self.reply is not None else None


class RenderClient:
    """Render requests of ``node`` to the mapper and the wait for their replies (module docstring).

    ``connect``: create the request publisher and the reply subscriptions (a node that never asks
    passes False and keeps zero counts). ``abort``: the node's shutdown event; a wait ends at once
    when it is set. ``ids``: the request-id scheme (:data:`ID_SCHEMES`). ``consequence``: what the
    node does without a render, appended to the warnings (``the candidate is rejected``).

    :meth:`request` runs on the worker thread; the replies arrive on the executor's. Counters:
    :attr:`counts` (``requests``, ``answered``, ``empty``, ``timeouts``, ``no_mapper``,
    ``mismatched``), :attr:`bad_replies`; :meth:`diagnostic_values` gives them under the nodes'
    /diagnostics keys (``render_*``, ``bad_render_replies``)."""

    def __init__(self, node: Any, abort: threading.Event, ids: str, consequence: str,
                 connect: bool = True) -> None:
        if ids not in ID_SCHEMES:
            raise ValueError(f"request-id scheme {ids!r}: expected one of {ID_SCHEMES}")
        self._node = node
        self._abort = abort
        self._follow_clock = ids == "clock"
        self._last_id = 0 if self._follow_clock else time.time_ns()
        self.consequence = consequence
        self.counts = dict(requests=0, answered=0, empty=0, timeouts=0, no_mapper=0, mismatched=0)
        self.bad_replies = 0
        self.replies = RenderReplyAssembler(max_pending=16)
        self._lock = threading.Lock()
        self._event = threading.Event()
        self._waiting: Optional[int] = None
        self._reply: Optional[RenderReply] = None
        self._pub = None
        self._subs: list = []
        if connect:
            qos = T.sensor_qos(T.OUTPUT_DEPTH)
            self._pub = node.create_publisher(PoseStamped, RENDER_REQUEST_TOPIC, qos)
            self._subs = [node.create_subscription(Image, topic, lambda m, p=part: self.on_reply(p, m), qos)
                          for part, topic in REPLY_TOPICS.items()]

    def disconnect(self) -> None:
        """Remove the request publisher and the reply subscriptions (a client needed only for a
        while: replies to others then no longer reach this node). Worker thread, no request in
        flight."""
        for sub in self._subs:
            self._node.destroy_subscription(sub)
        if self._pub is not None:
            self._node.destroy_publisher(self._pub)
        self._subs, self._pub = [], None

    # ------------------------------------------------------------------------- executor thread

    def on_reply(self, part: str, msg: Image) -> None:
        """One reply part; the complete reply is handed to the waiting request when the ids agree."""
        try:
            reply = self.replies.add(part, msg)
        except InputError as e:
            self.bad_replies += 1
            if worth_reporting(self.bad_replies):
                self._node.get_logger().warning(f"ignored a malformed render reply ({self.bad_replies} so far): {e}")
            return
        if reply is None:
            return
        with self._lock:
            if reply.request_id == self._waiting:       # the other requester's replies are not ours
                self._reply = reply
                self._event.set()

    # --------------------------------------------------------------------------- worker thread

    def _next_id(self) -> int:
        if self._follow_clock:
            self._last_id = max(self._last_id + 1, time.time_ns())
        else:
            self._last_id += 1
        return self._last_id

    def _count(self, outcome: str) -> int:
        key = _COUNT_KEY[outcome]
        self.counts[key] += 1
        return self.counts[key]

    def request(self, T_wc: np.ndarray, camera: CameraModel, older_than: Optional[int], timeout_s: float,
                about: str = "") -> RenderOutcome:
        """Ask the mapper for the map at ``T_wc`` rendered with ``camera`` (from the Gaussians of
        keyframes older than ``older_than``; None: all) and wait at most ``timeout_s`` for the
        reply. Without a mapper subscribed nothing is sent (``no_mapper``); a reply whose size is
        not ``camera``'s is ``mismatched``. ``about`` names the request in warnings (``keyframe
        <stamp>``)."""
        if self._abort.is_set() or self._pub is None:
            return RenderOutcome("aborted")
        if self._node.count_subscribers(RENDER_REQUEST_TOPIC) == 0:
            self._count("no_mapper")
            return RenderOutcome("no_mapper")
        rid = self._next_id()
        with self._lock:
            self._waiting, self._reply = rid, None
            self._event.clear()
        req = RenderRequest(rid, T_wc, older_than=older_than, camera=camera)
        self._pub.publish(render_request_to_msg(req, self._node.ros.world_frame))
        self.counts["requests"] += 1
        deadline = time.monotonic() + timeout_s
        while not self._event.wait(min(_POLL_S, max(deadline - time.monotonic(), 0.0))):
            if self._abort.is_set() or time.monotonic() >= deadline:
                break
        with self._lock:
            reply, self._waiting, self._reply = self._reply, None, None
        what = f"render request {rid}" + (f" ({about})" if about else "")
        if reply is None:
            n = self._count("timeout")
            if worth_reporting(n):
                self._node.get_logger().warning(f"{what}: no reply within {timeout_s:g} s ({n} so far); "
                                                f"{self.consequence}")
            return RenderOutcome("timeout", rid)
        self.counts["answered"] += 1
        if reply.empty:
            self._count("empty")
            return RenderOutcome("empty", rid, reply)
        if reply.color.shape[:2] != (camera.height, camera.width):
            n = self._count("mismatched")
            if worth_reporting(n):
                self._node.get_logger().warning(
                    f"{what}: the reply is {reply.color.shape[1]}x{reply.color.shape[0]} but the camera "
                    f"is {camera.width}x{camera.height} ({n} so far); {self.consequence}")
            return RenderOutcome("mismatched", rid, reply)
        return RenderOutcome("answered", rid, reply)

    # ------------------------------------------------------------------------------ diagnostics

    def diagnostic_values(self) -> dict[str, int]:
        """``render_requests`` / ``_answered`` / ``_empty`` / ``_timeouts`` / ``_no_mapper`` /
        ``_mismatched`` and ``bad_render_replies``."""
        return {**{f"render_{k}": v for k, v in self.counts.items()}, "bad_render_replies": self.bad_replies}
