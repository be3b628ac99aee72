"""The skeleton of every VINGS node: :class:`StageNode`.

A node module subclasses it and keeps only what is its own::

    class LoopCloserNode(StageNode):
        spec = registry.node_spec("loop_closer_node")    # name, settings class, library sections
        STATUS_NAME = "vings/loop_closer"                # its /diagnostics status ("" = none)

        def setup(self) -> None:                         # library objects, subscriptions, publishers
            self.queue = self.input_queue(QueuePolicy.BACKPRESSURE, 1000)
            self.create_subscription(..., lambda m: self.queue.put(m), ...)

        def step(self) -> None:                          # one worker iteration (the library's work)
            item = self.queue.get(timeout=0.1)
            ...

        def diagnostics(self) -> NodeStatus:             # its /diagnostics values
            return NodeStatus(Level.OK, "running", {"queue_length": len(self.queue)})

    def main(args=None) -> int:
        return LoopCloserNode.main(args)

What the skeleton does: parameters -> config dataclasses (``self.ros``: the shared section,
``self.settings``: the node's own section, :meth:`config` for a library section), the input queues
(:meth:`input_queue`), one worker thread running :meth:`step` in a loop (when the subclass defines
it; an exception stops the node), periodic /diagnostics from :meth:`diagnostics`, checkpoints
(settings derived from :class:`~vings_ros.node_config.CheckpointSettings`: :meth:`write_checkpoint`,
:meth:`resume_file`, :meth:`save_checkpoint`, :meth:`maybe_checkpoint`, :meth:`mark_changed`),
the ordered :meth:`shutdown` (hooks :meth:`drain`, :meth:`finish`, :meth:`close`) and
:meth:`main` (ROS environment, parameter checks, one SingleThreadedExecutor, signals, exit code).
"""
from __future__ import annotations

import enum
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterable, Optional

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from msg_adapters import topics as T
from msg_adapters.diagnostics import diagnostic_array, make_status
from msg_adapters.exchange import exchange_topic, path_to_batch
from msg_adapters.keyframe import PART_TOPICS, KeyframeAssembler
from vings_core.config import LIBRARY_SECTIONS, config_class
from vings_core.errors import ConfigError, InputError, VingsError
from vings_core.exchange import IncrementBatch
from vings_core.types import Keyframe
from vings_core.util import check_output_file, remove_stale_temps

from .node_common import (InputQueue, Worker, check_parameters, graph_layout, node_sections,
                          param_rules, rss_mb, section_config, worth_reporting)
from .node_config import CheckpointSettings, QueuePolicy, RosConfig
from .registry import SHARED_SECTION, NodeSpec


class Level(str, enum.Enum):
    """Level of a node's /diagnostics status."""

    OK = "ok"
    WARN = "warn"
    ERROR = "error"


@dataclass
class NodeStatus:
    """What :meth:`StageNode.diagnostics` returns: level, one-line message, key/value pairs."""

    level: Level
    message: str
    values: dict[str, Any] = field(default_factory=dict)


class BatchInbox:
    """Pose-exchange batches of ``sources`` (``/vings/exchange/<source>``), received on the executor
    thread and taken by the worker (:meth:`take`); a malformed one is reported, counted (``bad``)
    and skipped."""

    def __init__(self, node: Node, sources: Iterable[str]) -> None:
        self._node = node
        self.bad = 0
        self._items: list[IncrementBatch] = []
        self._lock = threading.Lock()
        qos = T.sensor_qos(T.POSE_EXCHANGE_DEPTH)
        for source in sources:
            node.create_subscription(PathMsg, exchange_topic(source), lambda m, s=source: self._on(s, m), qos)

    def _on(self, source: str, msg: PathMsg) -> None:
        try:
            batch = path_to_batch(msg, source)
        except InputError as e:
            self.bad += 1
            self._node.get_logger().warning(f"ignored a malformed pose-exchange message ({self.bad} so far): {e}",
                                            throttle_duration_sec=5.0)
            return
        with self._lock:
            self._items.append(batch)

    def take(self) -> list[IncrementBatch]:
        """The batches received since the last call, in arrival order."""
        with self._lock:
            items, self._items = self._items, []
        return items


class KeyframeInbox:
    """The front end's keyframe packets (the five part topics of ``msg_adapters.keyframe``),
    assembled by stamp on the executor thread (:attr:`assembler`); each complete keyframe goes to
    ``on_keyframe``. A malformed part is reported (rate-limited), counted in :attr:`bad` and dropped.
    ``connect`` False: no subscriptions (a node that ignores keyframes keeps zero counts)."""

    PART_TYPES = (("image", Image), ("depth", Image), ("inv_depth_var", Image), ("pose", PoseStamped),
                  ("camera_info", CameraInfo))

    def __init__(self, node: Node, on_keyframe: Callable[[Keyframe], None], connect: bool = True) -> None:
        self._node = node
        self._on_keyframe = on_keyframe
        self.assembler = KeyframeAssembler(max_pending=16)
        self.bad = 0
        if connect:
            qos = T.sensor_qos(T.OUTPUT_DEPTH * 4)
            for part, type_ in self.PART_TYPES:
                node.create_subscription(type_, PART_TOPICS[part], lambda m, p=part: self.add(p, m), qos)

    def add(self, part: str, msg: Any) -> None:
        """One part (a callback; tests call it directly)."""
        try:
            kf = self.assembler.add(part, msg)
        except InputError as e:
            self.bad += 1
            if worth_reporting(self.bad):
                self._node.get_logger().warning(f"dropped a malformed keyframe part ({self.bad} so far): {e}")
            return
        if kf is not None:
            self._on_keyframe(kf)


class StageNode(Node):
    """One VINGS node: see the module docstring. Subclasses set :attr:`spec` and override hooks."""

    #: the node's registry entry (vings_ros/registry.py)
    spec: ClassVar[NodeSpec]
    #: name of its DiagnosticStatus on /diagnostics ("" = it publishes none)
    STATUS_NAME: ClassVar[str] = ""
    #: how long :meth:`shutdown` waits for the worker's current step
    WORKER_STOP_TIMEOUT_S: ClassVar[float] = 60.0

    def __init__(self) -> None:
        name = self.spec.name
        super().__init__(name, automatically_declare_parameters_from_overrides=True)
        self.error: Optional[BaseException] = None
        self.hurried = False            # a second stop request: see hurry()
        self.worker: Optional[Worker] = None
        self._queues: list[InputQueue] = []
        sections = node_sections(self, graph_layout([self.spec]))
        self.ros: RosConfig = section_config(RosConfig, SHARED_SECTION, sections[SHARED_SECTION], name)
        self.settings: Any = None
        if self.spec.config:
            self.settings = section_config(config_class(self.spec.config), name, sections[name], name)
        self._configs = {sec: section_config(_library_class(sec), sec, sections[sec], name)
                         for sec in self.spec.reads}
        self._init_checkpoints()
        self.setup()
        if type(self).step is not StageNode.step:
            self.worker = Worker(f"vings-{name}", self.step, self._fail)
            self.worker.start()
        if self.STATUS_NAME:
            self.pub_diag = self.create_publisher(DiagnosticArray, T.DIAGNOSTICS_TOPIC, T.sensor_qos(10))
            # on the steady (wall) clock: /diagnostics goes on when /clock stops (a replay ended)
            from rclpy.clock import Clock, ClockType
            self.create_timer(self.ros.diagnostics_period_s, self.publish_diagnostics,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))
        ready = self.ready_message()
        if ready:
            self.get_logger().info(ready)

    # ---------------------------------------------------------------------------------- hooks

    def setup(self) -> None:
        """Build the library objects, queues, subscriptions and publishers (before the worker
        starts)."""

    def step(self) -> None:
        """One iteration of the worker thread (e.g. take one queued input, run the library on
        it). A node that leaves it out has no worker."""

    def diagnostics(self) -> NodeStatus:
        """The node's /diagnostics status (with :attr:`STATUS_NAME`); ``rss_mb`` is added, and a
        failed node reports ``error``."""
        return NodeStatus(Level.OK, "running")

    def ready_message(self) -> str:
        """Logged once the node is up ("" = nothing)."""
        return ""

    def drain(self) -> None:
        """Shutdown, first step (the inputs are still open): finish what must not be lost."""

    def finish(self) -> None:
        """Shutdown, after the worker has stopped: flush the last outputs."""

    def close(self) -> None:
        """Shutdown, last step (after the final checkpoint): release library resources."""

    def write_checkpoint(self, path: Path) -> str:
        """Write the node's state to ``path`` (atomically); returns a summary for the log."""
        raise NotImplementedError(f"{type(self).__name__} has checkpoint settings but no write_checkpoint")

    def checkpoint_ready(self) -> bool:
        """Whether the node has state worth a checkpoint."""
        return True

    # ------------------------------------------------------------------------------- services

    def config(self, section: str) -> Any:
        """The config of library section ``section`` (one of ``spec.reads``)."""
        return self._configs[section]

    def input_queue(self, policy: QueuePolicy, maxsize: int) -> InputQueue:
        """A new input queue of this node; :meth:`shutdown` closes it."""
        q: InputQueue = InputQueue(policy, maxsize)
        self._queues.append(q)
        return q

    def _fail(self, e: BaseException) -> None:
        self.get_logger().error(f"{self.get_name()} failed: {e}")
        self.error = e

    def publish_diagnostics(self) -> None:
        st = self.diagnostics()
        level, message = st.level, st.message
        if self.error is not None:
            level, message = Level.ERROR, f"failed: {self.error}"
        values = {k: (v.value if isinstance(v, enum.Enum) else v) for k, v in st.values.items()}
        values["rss_mb"] = rss_mb()
        self.pub_diag.publish(diagnostic_array(self.get_clock().now().nanoseconds,
                                               [make_status(self.STATUS_NAME, Level(level).value,
                                                            message, values)]))

    # ---------------------------------------------------------------------------- checkpoints

    def _init_checkpoints(self) -> None:
        self.checkpoint_file: Optional[Path] = None
        self.checkpoints = 0
        self._changed = False
        self._last_checkpoint = time.monotonic()
        s = self.settings
        if isinstance(s, CheckpointSettings) and s.checkpoint_path:
            # found unwritable now, not when the first checkpoint is due
            self.checkpoint_file = check_output_file(s.checkpoint_path, f"{self.spec.name}.checkpoint_path",
                                                     ConfigError)
            remove_stale_temps(self.checkpoint_file)

    def resume_file(self) -> Optional[Path]:
        """The checkpoint to resume from: set, ``resume`` on, and the file exists."""
        f = self.checkpoint_file
        return f if f is not None and self.settings.resume and f.exists() else None

    def mark_changed(self) -> None:
        """The state changed since the last checkpoint (a periodic one becomes due)."""
        self._changed = True

    def maybe_checkpoint(self, idle: bool) -> None:
        """Periodic checkpoint (``checkpoint_period_s``) when the state changed since the last."""
        p = self.settings.checkpoint_period_s if self.checkpoint_file is not None else 0.0
        if p <= 0 or not self._changed or not self.checkpoint_ready():
            return
        if time.monotonic() - self._last_checkpoint >= p:
            self.save_checkpoint("periodic" + (" (idle)" if idle else ""))

    def save_checkpoint(self, why: str) -> None:
        """Write the checkpoint now (no file set: nothing). Worker thread only, or after the
        worker has stopped."""
        if self.checkpoint_file is None:
            return
        t0 = time.perf_counter()
        summary = self.write_checkpoint(self.checkpoint_file)
        self._last_checkpoint = time.monotonic()
        self._changed = False
        self.checkpoints += 1
        self.get_logger().info(f"checkpoint ({why}): {summary}, {time.perf_counter() - t0:.2f} s")

    # -------------------------------------------------------------------------------- shutdown

    def hurry(self) -> None:
        """A second stop request (a second Ctrl-C) while stopping: :meth:`drain` ends at once and
        the stop goes straight to the final checkpoint (:attr:`hurried`)."""
        self.hurried = True
        self.get_logger().warning("stop requested again: skipping the remaining work, writing the "
                                  "final checkpoint")

    def shutdown(self, executor: Any = None) -> None:
        """Ordered stop: :meth:`drain`, close the input queues, stop the worker (its current step
        ends), :meth:`finish`, the final checkpoint, :meth:`close`. Everything after the worker
        runs only once it has ended, so nothing races with the library. With ``executor`` (the
        one spinning this node, stopped by now) a helper thread spins it while :meth:`drain`
        runs, so the inputs are open in fact: the callbacks a draining worker relies on still run
        (the mapper's queue waits for the eraser's masks and answers render requests)."""
        spinner = _DrainSpinner(executor) if executor is not None else None
        try:
            self.drain()
        finally:
            if spinner is not None:
                spinner.stop()
        for q in self._queues:
            q.close()
        if self.worker is not None and not self.worker.stop(timeout=self.WORKER_STOP_TIMEOUT_S):
            ckpt = "; no final checkpoint" if self.checkpoint_file is not None else ""
            self.get_logger().error(f"{self.get_name()} worker did not stop within "
                                    f"{self.WORKER_STOP_TIMEOUT_S:.0f} s{ckpt}")
            self.error = self.error or RuntimeError(f"{self.get_name()} worker did not stop")
            return
        self.finish()
        if self.checkpoint_file is not None and self.error is None and self.checkpoint_ready():
            self.save_checkpoint("shutdown")
        self.close()

    # ------------------------------------------------------------------------------------ main

    @classmethod
    def from_args(cls, args: list[str]) -> "StageNode":
        """The node from its command-line arguments before ``--ros-args`` (none by default)."""
        if args:
            raise ConfigError(f"{cls.spec.name} takes no arguments before --ros-args, got {' '.join(args)}")
        return cls()

    @classmethod
    def main(cls, args: Optional[list[str]] = None) -> int:
        """Console script / ``python -m``: run the node until SIGINT/SIGTERM/SIGHUP or an error."""
        argv = list(sys.argv if args is None else args)
        end = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
        return run_node(lambda: cls.from_args(argv[1:end]), argv, [cls.spec])


class _DrainSpinner:
    """Spins an executor on a helper thread until :meth:`stop` (during :meth:`StageNode.drain`);
    ends quietly when the context goes away (rclpy shut down by a signal)."""

    def __init__(self, executor: Any) -> None:
        self._ex = executor
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="vings-drain-spin", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._ex.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - context shut down, executor gone: stop spinning
                return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)


def _library_class(section: str) -> type:
    if section not in LIBRARY_SECTIONS:
        raise ConfigError(f"no library section {section!r}; known: {', '.join(LIBRARY_SECTIONS)}")
    return config_class(LIBRARY_SECTIONS[section])


def run_node(make_node: Callable[[], Any], args: Optional[list[str]] = None,
             specs: tuple | list = ()) -> int:
    """Run one node: ROS environment, parameter checks, rclpy init, one SingleThreadedExecutor,
    clean shutdown on SIGINT/SIGTERM/SIGHUP (the node's ``shutdown()`` runs: final checkpoint
    etc.). ``specs``: nodes outside the registry whose sections are valid too. Returns the exit
    code: 0 clean, 2 configuration/input error, 1 crash."""
    import logging

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    from .ros_env import apply_ros_environment

    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(levelname)s %(message)s")
    argv = list(sys.argv if args is None else args)
    try:
        apply_ros_environment()
        # rcl parses the files in init (a traceback for a bad one) and ignores a -p override whose
        # type differs from the file's value: both are checked here first
        check_parameters(*param_rules(argv), "vings node", specs)
        rclpy.init(args=argv, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    except VingsError as e:
        print(f"vings node: error: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:    # rclpy's RCLError: arguments or a params file rcl cannot parse
        why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        print(f"vings node: error: rcl cannot parse the ROS arguments or params files "
              f"({' '.join(argv[1:])}): {why}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def _sig(signum, frame):  # noqa: ARG001
        if stop.is_set() and node is not None:     # a second request while stopping: hurry
            node.hurry()
        stop.set()

    signal.signal(signal.SIGINT, _sig)
    signal.signal(signal.SIGTERM, _sig)
    signal.signal(signal.SIGHUP, _sig)     # the terminal closed: stop cleanly (final checkpoint)
    node = None
    ex = None
    code = 0
    try:
        try:
            node = make_node()
        except OSError as e:       # an output the node cannot create (recording, checkpoint folder)
            raise VingsError(str(e)) from None
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        while not stop.is_set() and rclpy.ok() and node.error is None:
            ex.spin_once(timeout_sec=0.1)
        if node.error is not None:
            err = node.error
            code = 2 if isinstance(err, VingsError) else 1
            print(f"{node.get_name()}: error: {err}", file=sys.stderr)
    except (VingsError, ValueError) as e:
        print(f"vings node: error: {e}", file=sys.stderr)
        code = 2
    except ExternalShutdownException:
        pass
    finally:
        # order: the node's shutdown (stops its worker thread, final checkpoint), then the
        # executor, the node, and rclpy
        worker_alive = False
        if node is not None:
            try:
                # the executor goes on spinning while the node drains (its inputs are still open)
                node.shutdown(executor=ex if ex is not None and rclpy.ok() else None)
            except Exception as e:  # noqa: BLE001
                print(f"{node.get_name()}: error during shutdown: {e}", file=sys.stderr)
                code = code or 1
            w = getattr(node, "worker", None)
            worker_alive = w is not None and w.thread.is_alive()
            if ex is not None:
                ex.shutdown(timeout_sec=1.0)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
        if worker_alive:
            # a thread stuck in native code would abort the interpreter at exit; leave at once
            print(f"{node.get_name()}: worker thread did not stop; exiting hard", file=sys.stderr)
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code or 1)
    return code
