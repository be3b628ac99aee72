"""``loop_closer_node``: keyframe packets and the keeper's batches in; loop corrections, loop
constraints and ``loops.json`` out.

It runs :class:`vings_core.loop.LoopCloser`, the stage ``vings run`` uses, in its worker thread:
every keyframe the front end emits (the mapper's five-topic packet, assembled by stamp) goes to
``LoopCloser.add_keyframe`` (database, candidates, PnP, render check, pose graph). The render check
asks the mapper: a :class:`~msg_adapters.loop.RenderRequest` on ``/vings/render/request``, answered
by ``mapper_node`` on ``/vings/render/reply/{color,depth,alpha}`` with the same id; a reply that
does not come within ``loop_closer_node.render_timeout_s`` (or no mapper subscribed at all) is "no
map to render" and the candidate is rejected. A correction goes to the front end as a pose-exchange
batch on ``/vings/exchange/loop_closer`` (a jump writer: the front end moves its past and present),
the accepted loop as a ``nav_msgs/Path`` on ``/vings/loop/constraints``. It follows the front end's
batches (``/vings/exchange/frontend``) through the closer's own
:class:`~vings_core.exchange.PoseFollower`.

Whether the front end is metric (the ``auto`` pose graph is SE(3) then, Sim(3) before) is read
from the front end's ``/diagnostics`` (status ``vings/frontend``, key ``vi_state``):
``visual-inertial`` -> metric, ``visual-only`` / ``initialising`` -> not; the frame modes
``standstill`` / ``imu-only`` keep the last answer. Nothing waits on this node: tracking and
mapping go on without it. Settings: params sections ``loop_closer_node``
(node_config.LoopCloserNodeConfig), ``ros`` and ``loop``. Topics: docs/ros.md.
"""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path as FilePath
from typing import Any, Optional

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path

from msg_adapters import topics as T
from msg_adapters.diagnostics import parse_diagnostic_array
from msg_adapters.exchange import batch_to_path, exchange_topic
from msg_adapters.loop import LOOP_CONSTRAINTS_TOPIC, constraint_from_record, loop_constraint_to_path
from vings_core.errors import ConfigError, InputError
from vings_core.eval.output import RunOutput
from vings_core.exchange.config import KEEPER
from vings_core.keyframe_queue import KeyframeQueue
from vings_core.loop import LOOP_SOURCE, LoopCloser, LoopConfig
from vings_core.types import CameraModel, Keyframe
from vings_core.util import atomic_write, probe_writable_dir

from . import registry
from .node_base import BatchInbox, KeyframeInbox, Level, NodeStatus, StageNode
from .node_common import RateMeter, lower_priority
from .node_config import LoopCloserNodeConfig
from .render_client import RenderClient

#: the front end's /diagnostics status (vings_ros.frontend_node.FrontendNode.STATUS_NAME)
FRONTEND_STATUS = "vings/frontend"
#: vi_state values of the front end that say whether its poses are metric (others keep the last answer)
METRIC_STATES = {"visual-inertial": True, "visual-only": False, "initialising": False}
#: checkpoint file format
CHECKPOINT_FORMAT = "vings-loop-closer"
CHECKPOINT_VERSION = 1


# ------------------------------------------------------------------------------ checkpoint file


def save_loop_state(path: str | FilePath, state: dict, cfg: LoopConfig) -> None:
    """``LoopCloser.state_dict()`` -> one ``.npz`` file (no pickles), written atomically: the
    database's arrays, the loop edges' ``T_on``, the follower's keeper poses, and a JSON part
    (``meta``) with the rest."""
    arrays: dict[str, np.ndarray] = {f"db.{k}": np.asarray(v) for k, v in state["db"].items()}
    loops = state["loops"]
    arrays["loops.T_on"] = np.array([np.asarray(l["T_on"], np.float64) for l in loops], np.float64).reshape(-1, 4, 4)
    keeper = state["follower"]["keeper"]
    stamps = sorted(int(s) for s in keeper)
    arrays["follower.stamps"] = np.array(stamps, np.int64)
    arrays["follower.T"] = np.array([np.asarray(keeper[s], np.float64) for s in stamps], np.float64).reshape(-1, 4, 4)
    meta = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
            "features": str(cfg.features.value if hasattr(cfg.features, "value") else cfg.features),
            "loops": [{k: v for k, v in l.items() if k != "T_on"} for l in loops],
            "records": state["records"], "corrections": state.get("corrections", []),
            "stats": state.get("stats", {}),
            "follower": {"seq": int(state["follower"]["seq"]), "seen": int(state["follower"]["seen"])}}
    arrays["meta"] = np.frombuffer(json.dumps(meta, default=_json_default).encode("utf-8"), np.uint8)

    def _write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    atomic_write(path, _write)


def load_loop_state(path: str | FilePath, cfg: LoopConfig) -> dict:
    """The state :func:`save_loop_state` wrote, for ``LoopCloser.load_state_dict``. A damaged or
    foreign file, or one made with other features than ``cfg``'s, raises :class:`ConfigError`
    naming the file."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        meta = json.loads(bytes(arrays.pop("meta")).decode("utf-8"))
    except Exception as e:  # noqa: BLE001 - any failure to read is the same error for the user
        raise ConfigError(f"{path}: not a loop closer checkpoint ({type(e).__name__}: {e})") from None
    if meta.get("format") != CHECKPOINT_FORMAT or meta.get("version") != CHECKPOINT_VERSION:
        raise ConfigError(f"{path}: not a loop closer checkpoint of version {CHECKPOINT_VERSION} "
                          f"(format {meta.get('format')!r}, version {meta.get('version')!r})")
    want = str(cfg.features.value if hasattr(cfg.features, "value") else cfg.features)
    if meta.get("features") != want:
        raise ConfigError(f"{path}: the database holds {meta.get('features')} features but loop.features "
                          f"is {want}; use the same features or start without the checkpoint")
    db = {k[3:]: v for k, v in arrays.items() if k.startswith("db.")}
    T_on = arrays["loops.T_on"]
    loops = [dict(l, T_on=T_on[i]) for i, l in enumerate(meta["loops"])]
    keeper = {int(s): arrays["follower.T"][i] for i, s in enumerate(arrays["follower.stamps"])}
    return {"db": db, "loops": loops, "records": meta["records"], "corrections": meta["corrections"],
            "stats": meta["stats"], "follower": dict(meta["follower"], keeper=keeper)}


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# ------------------------------------------------------------------------------------- the node


class LoopCloserNode(StageNode):
    spec = registry.node_spec("loop_closer_node")
    STATUS_NAME = "vings/loop_closer"
    WORKER_STOP_TIMEOUT_S = 60.0

    settings: LoopCloserNodeConfig

    def setup(self) -> None:
        self.lcfg: LoopConfig = self.config("loop")
        lower_priority(self.settings.nice, 0)      # tracking (and its keyframes) first
        self._abort = threading.Event()         # shutdown: a render wait ends at once
        self._metric = False
        self.vi_state = "unknown"
        self.keyframes_done = 0
        self.keyframes_skipped = 0              # already in a resumed database
        self.bad_keyframes = 0
        self.rate = RateMeter(30.0)
        self._last_report = 0.0
        self._reported_records = -1
        self._segment_starts: set[int] = set()     # first frames of the front end's later map segments
        self.closer = LoopCloser(self.lcfg, render=self.render_map, metric=self.metric)
        resume = self.resume_file()
        if resume is not None:
            self.closer.load_state_dict(load_loop_state(resume, self.lcfg))
            self.get_logger().info(f"resumed from checkpoint {resume}: {len(self.closer.db)} keyframes, "
                                   f"{len(self.closer.loops)} loops")
        self.output: Optional[RunOutput] = None
        if self.settings.output_dir:
            try:
                probe_writable_dir(self.settings.output_dir)
            except OSError as e:
                raise ConfigError(f"loop_closer_node.output_dir {self.settings.output_dir}: cannot write "
                                  f"there ({e.strerror or e})") from None
            self.output = RunOutput(self.settings.output_dir)
        # keyframes are not dropped: FIFO, bounded in memory, the rest in a private folder on disk
        self.queue = KeyframeQueue(self.settings.queue_memory_keyframes, None)

        sq = T.sensor_qos
        self.inbox = BatchInbox(self, (KEEPER,))
        self.pub_exchange = self.create_publisher(Path, exchange_topic(LOOP_SOURCE), sq(T.POSE_EXCHANGE_DEPTH))
        # one render request in flight at a time (the worker waits for it); request ids count up by
        # one from the start time
        self.render_client = RenderClient(self, self._abort, ids="counter",
                                          consequence="the candidate is rejected")
        self.pub_constraints = self.create_publisher(Path, LOOP_CONSTRAINTS_TOPIC, T.latched_qos(100))
        self.create_subscription(DiagnosticArray, T.DIAGNOSTICS_TOPIC, self._on_diagnostics, sq(10))
        self.keyframes_in = KeyframeInbox(self, lambda kf: self.queue.put("kf", kf), connect=self.lcfg.enabled)
        if not self.lcfg.enabled:
            self.get_logger().warning("loop closure is off (loop.enabled false): keyframes are ignored")

    def ready_message(self) -> str:
        return f"loop closer ready: {len(self.closer.db)} keyframes, {len(self.closer.loops)} loops"

    # ------------------------------------------------------------------------------ callbacks

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        try:
            st = parse_diagnostic_array(msg, T.DIAGNOSTICS_TOPIC)["status"].get(FRONTEND_STATUS)
        except InputError:
            return
        if st is None:
            return
        seg, first = st["values"].get("segment", "0"), st["values"].get("segment_first_stamp_ns", "0")
        if str(seg).isdigit() and int(seg) > 0 and str(first).isdigit() and int(first) > 0:
            self._segment_starts.add(int(first))       # taken by the worker (step)
        vi = st["values"].get("vi_state")
        if vi is None:
            return
        self.vi_state = vi
        if vi in METRIC_STATES:
            self._metric = METRIC_STATES[vi]

    # --------------------------------------------------------------------- the closer's callbacks

    def metric(self) -> bool:
        """Whether the front end's poses are metric (its last ``vi_state`` on /diagnostics)."""
        return self._metric

    def render_map(self, T_wc: np.ndarray, camera: CameraModel, older_than: Optional[int]) -> Optional[dict]:
        """The closer's ``render``: a request to the mapper (pose, bound, ``camera``: the check's
        camera, at ``loop.render_downscale``) and a wait (at most ``render_timeout_s``) for its
        reply. None (no map to render) when no mapper subscribes, the reply does not come, says the
        map is empty, or does not fit ``camera``. Worker thread (never the executor's: the replies
        arrive there)."""
        return self.render_client.request(T_wc, camera, older_than, self.settings.render_timeout_s).render

    # ----------------------------------------------------------------------------- the worker

    def step(self) -> None:
        msg = self.queue.get(timeout=0.1)
        self._exchange_receive()
        if msg is None:
            self._report(force=False)
            self.maybe_checkpoint(idle=True)
            return
        kf: Keyframe = msg[1]
        if int(kf.stamp_ns) in self.closer.db:
            self.keyframes_skipped += 1   # resumed graph: the database already holds it
            return
        for s in sorted(self._segment_starts - self.closer.segment_starts):
            self.closer.segment_started(s)      # the front end's new map segments (its /diagnostics)
        try:
            rec = self.closer.add_keyframe(kf)
        except InputError as e:
            if int(kf.stamp_ns) in self.closer.db:
                raise
            self.bad_keyframes += 1
            self.get_logger().warning(f"dropped keyframe {kf.stamp_ns}: {e}")
            return
        self.keyframes_done += 1
        self.rate.tick()
        self.mark_changed()
        self._exchange_send()
        if rec is not None:
            self._publish_constraint(rec)
            c = rec["correction"]
            self.get_logger().info(f"loop {c['older']} -> {c['newer']} accepted: {c['graph']} graph over "
                                   f"{c['keyframes']} keyframes moved {c['moved']}, newer shifted "
                                   f"{c['newer_shift']:.4g}")
            self.save_checkpoint(f"loop {c['older']} -> {c['newer']}")
        self._report(force=rec is not None)
        self.maybe_checkpoint(idle=False)

    def _publish_constraint(self, rec: dict) -> None:
        loop = self.closer.loops[-1]
        T_wo = self.closer.db.get(loop.older).T_wc
        c = constraint_from_record(loop.older, loop.newer, loop.T_on, T_wo, rec)
        self.pub_constraints.publish(loop_constraint_to_path(c, self.ros.world_frame))

    def loop_report(self) -> dict:
        """``loops.json``'s content: as ``SlamRunner.loop_report()`` without ``retrains`` (the
        mapper retrains)."""
        return {"candidates": self.closer.records, "corrections": self.closer.corrections,
                "summary": self.closer.summary()}

    def _report(self, force: bool) -> None:
        """Rewrite ``loops.json`` when the records changed: at once after a loop (``force``),
        else at most every ``report_period_s``."""
        if self.output is None or len(self.closer.records) == self._reported_records:
            return
        if not force and time.monotonic() - self._last_report < self.settings.report_period_s:
            return
        self.output.write_loops(self.loop_report())
        self._reported_records = len(self.closer.records)
        self._last_report = time.monotonic()

    def diagnostics(self) -> NodeStatus:
        values = {"keyframes": len(self.closer.db), "keyframes_processed": self.keyframes_done,
                  "keyframe_rate_hz": self.rate.hz, "queue_length": self.queue.keyframes,
                  "queue_on_disk": self.queue.keyframes_on_disk, "loops": len(self.closer.loops),
                  **self.closer.summary(), "vi_state": self.vi_state, "metric": self._metric,
                  **self.render_client.diagnostic_values(), "bad_keyframe_parts": self.keyframes_in.bad,
                  "incomplete_packets": self.keyframes_in.assembler.pending,
                  "dropped_packets": self.keyframes_in.assembler.dropped,
                  "checkpoints": self.checkpoints, "bad_exchange_messages": self.inbox.bad}
        if not self.lcfg.enabled:
            return NodeStatus(Level.WARN, "loop closure off (loop.enabled false)", values)
        renders = self.render_client.counts
        if renders["requests"] + renders["no_mapper"] and not renders["answered"]:
            return NodeStatus(Level.WARN, "no mapper answers render requests: every candidate is rejected",
                              values)
        return NodeStatus(Level.OK, f"{len(self.closer.loops)} loops closed", values)

    # ---------------------------------------------------------------------------- checkpoints

    def write_checkpoint(self, path: FilePath) -> str:
        save_loop_state(path, self.closer.state_dict(), self.lcfg)
        return f"{len(self.closer.db)} keyframes, {len(self.closer.loops)} loops"

    def checkpoint_ready(self) -> bool:
        return len(self.closer.db) > 0

    # ----------------------------------------------------------------------- pose exchange

    def _exchange_receive(self) -> None:
        for batch in self.inbox.take():
            self.closer.receive(batch)
            self.mark_changed()         # the follower's view of the keeper is in the checkpoint

    def _exchange_send(self) -> None:
        while True:
            batch = self.closer.poll()
            if batch is None:
                return
            self.pub_exchange.publish(batch_to_path(batch, self.ros.world_frame))

    # -------------------------------------------------------------------------------- shutdown

    def drain(self) -> None:
        """The keyframes still queued are not added (the mapper, stopped before this node, would
        answer no render); a render wait ends at once."""
        self._abort.set()
        if self.queue.keyframes:
            self.get_logger().info(f"shutdown: {self.queue.keyframes} queued keyframe(s) not added")

    def finish(self) -> None:
        self._exchange_receive()
        if self.count_publishers(exchange_topic(KEEPER)) == 0:
            # the front end has stopped: corrections it never answered are not in the trajectory
            n = self.closer.follower.abandon()
            if n:
                self.mark_changed()
                self.get_logger().info(f"undid the unanswered correction of {n} keyframe(s): the front end "
                                       f"stopped before it answered")
        if self.output is not None:
            self._reported_records = -1
            self._report(force=True)

    def close(self) -> None:
        self.queue.close()


def main(args: Optional[list[str]] = None) -> int:
    return LoopCloserNode.main(args)


if __name__ == "__main__":
    raise SystemExit(main())
