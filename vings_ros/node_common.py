"""What every VINGS node shares: parameters -> stage configs, the input queue policy, the worker
thread that runs the library, diagnostics, and a ``main`` that starts and stops cleanly.

Threads: each node spins ONE ``SingleThreadedExecutor`` (rclpy's MultiThreadedExecutor is unusably
slow in this version, see ../shared/STACK.md) for message I/O, and runs the heavy library work in one
worker thread fed by a :class:`InputQueue`. Publishing from the worker is safe (rcl publishers are
thread-safe); no callback ever blocks on the library.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Generic, Optional, TypeVar

from vings_core.config import KNOWN_SECTIONS, ConfigError, config_from_dict, read_params_file
from vings_core.errors import VingsError

log = logging.getLogger("vings.node")

T = TypeVar("T")
QUEUE_POLICIES = ("keep_newest", "backpressure")


@dataclass
class NodeConfig:
    """Node settings (params section ``ros``), shared by both nodes.

    ``queue_policy``: ``keep_newest`` (live: the worker takes the newest waiting input, older ones
    are dropped and counted) or ``backpressure`` (replay with ``--wait-for-graph``: nothing is
    dropped; the queue holds up to ``queue_size`` items and the replay waits for acknowledgements).
    ``calib_file``: calibration YAML used instead of the camera_info topic. ``width``/``height``:
    working resolution the front end resizes/undistorts to (0 = as published).
    ``calib_wait_s``: how long the front end holds an image that arrived before any calibration.
    ``checkpoint_path``: mapper checkpoint ("" = none); ``resume``: load it at start if it exists.
    The mapper writes it (atomically) after its first keyframe, every ``checkpoint_every_keyframes``
    keyframes, whenever ``checkpoint_period_s`` seconds passed since the last one and the map
    changed (also while it trains a keyframe), and on shutdown (0 switches a trigger off).
    ``shutdown_timeout_s``: how long the mapper may work through queued keyframes after SIGINT.
    ``mapper_nice``: niceness the mapper process adds to itself, so tracking wins the CPU (0 = off);
    ``mapper_threads``: torch / numba threads of the mapper (0 = library default).
    ``points_period_s``: throttle of /vings/map/points. ``diagnostics_period_s``: /diagnostics rate.
    """

    world_frame: str = "map"
    camera_frame: str = "camera_optical_frame"
    queue_policy: str = "keep_newest"
    queue_size: int = 64
    calib_file: str = ""
    calib_wait_s: float = 2.0
    width: int = 0
    height: int = 0
    path_max_poses: int = 10000
    checkpoint_path: str = ""
    resume: bool = True
    checkpoint_period_s: float = 30.0
    checkpoint_every_keyframes: int = 5
    shutdown_timeout_s: float = 120.0
    mapper_nice: int = 10
    mapper_threads: int = 0
    points_period_s: float = 2.0
    max_points: int = 200000
    diagnostics_period_s: float = 1.0
    render_every_keyframes: int = 1

    def validate(self) -> None:
        if self.queue_policy not in QUEUE_POLICIES:
            raise ValueError(f"queue_policy must be one of {QUEUE_POLICIES}, got {self.queue_policy!r}")
        if self.queue_size < 1:
            raise ValueError("queue_size must be >= 1")
        if self.width < 0 or self.height < 0:
            raise ValueError("width/height must be >= 0")
        if self.checkpoint_period_s < 0 or self.checkpoint_every_keyframes < 0:
            raise ValueError("checkpoint_period_s and checkpoint_every_keyframes must be >= 0")
        if not 0 <= self.mapper_nice <= 19:
            raise ValueError(f"mapper_nice must be in 0..19, got {self.mapper_nice}")
        if self.mapper_threads < 0:
            raise ValueError("mapper_threads must be >= 0")
        if self.calib_wait_s < 0 or self.shutdown_timeout_s < 0:
            raise ValueError("calib_wait_s and shutdown_timeout_s must be >= 0")
        if not self.diagnostics_period_s > 0:
            raise ValueError(f"diagnostics_period_s must be > 0, got {self.diagnostics_period_s}")
        if self.points_period_s < 0:
            raise ValueError("points_period_s must be >= 0")
        if self.max_points < 0 or self.path_max_poses < 1 or self.render_every_keyframes < 0:
            raise ValueError("max_points and render_every_keyframes must be >= 0, path_max_poses >= 1")
        for name in ("world_frame", "camera_frame"):
            v = getattr(self, name)
            if not v.strip() or v.startswith("/"):
                raise ValueError(f"{name} must be a frame id without a leading '/', got {v!r}")


#: parameters rclpy declares on every node
BUILTIN_PARAMETERS = ("use_sim_time", "start_type_description_service")


def _rcl_type(v: Any) -> str:
    if isinstance(v, bool):
        return "bool"
    if isinstance(v, int):
        return "integer"
    if isinstance(v, float):
        return "double"
    if isinstance(v, list):
        return f"{_rcl_type(v[0]) if v else 'empty'} array"
    return "string"


def section_classes() -> dict:
    """Params section -> config dataclass."""
    from vings_core.frontend.config import FrontendConfig
    from vings_core.mapping.config import MapperConfig
    from vings_core.pipeline import RunConfig
    return {"ros": NodeConfig, "frontend": FrontendConfig, "mapping": MapperConfig, "run": RunConfig}


def param_rules(argv: list[str]) -> tuple[list[str], dict[str, str]]:
    """``(params files, {name: raw value})`` of the ``--ros-args`` part of a node's argv."""
    files, rules = [], {}
    args = argv[argv.index("--ros-args") + 1:] if "--ros-args" in argv else []
    for flag, val in zip(args, args[1:]):
        if flag == "--params-file":
            files.append(val)
        elif flag in ("-p", "--param") and ":=" in val:
            name, _, raw = val.partition(":=")
            rules[name] = raw
    return files, rules


def check_parameters(files: list[str], rules: dict[str, str], where: str) -> dict[str, dict]:
    """The sections the nodes will see (params files, then ``-p`` rules), checked before rclpy
    starts: every section through its config dataclass, and every ``-p`` value against the type the
    params file gives the same parameter. rcl keeps the FILE's value when the two types differ (an
    override ``-p mapping.points_per_keyframe:=1e4`` over the file's ``20000`` is silently
    ignored), so such an override is a :class:`ConfigError` here. Returns ``{section: {key: value}}``."""
    from vings_core.config import ros_yaml_load
    sections: dict[str, dict] = {s: {} for s in KNOWN_SECTIONS}
    for f in files:
        for sec, vals in read_params_file(f, strict=False).items():
            sections.setdefault(sec, {}).update(vals)
    for name, raw in rules.items():
        sec, _, key = name.partition(".")
        if name in BUILTIN_PARAMETERS or name.startswith("qos_overrides.") or sec not in sections:
            continue    # rclpy's own, or a section the node itself reports as unknown
        try:
            val = ros_yaml_load(raw) if raw.strip() else raw
        except Exception:  # noqa: BLE001 - rcl takes what YAML cannot parse as a string
            val = raw
        if key in sections[sec] and _rcl_type(sections[sec][key]) != _rcl_type(val):
            old = sections[sec][key]
            raise ConfigError(f"{where}: -p {name}:={raw} is {'an' if _rcl_type(val)[0] in 'aeiou' else 'a'} "
                              f"{_rcl_type(val)}, but the params file gives {name} as {_rcl_type(old)} "
                              f"{old!r}: rcl would silently keep the file's value; write it as {_rcl_type(old)} "
                              f"(e.g. {'1.0 for 1' if _rcl_type(old) == 'double' else 'without a decimal point'})")
        sections[sec][key] = val
    for sec, cls in section_classes().items():
        config_from_dict(cls, sections.get(sec, {}), f"{where}: {sec}")
    return sections


def worth_reporting(count: int) -> bool:
    """Rate limit for repeated warnings: the 1st, the 20th, then every 200th occurrence."""
    return count in (1, 20) or count % 200 == 0


def node_sections(node) -> dict[str, dict]:
    """The node's parameters (declared from the params file overrides) grouped by section:
    ``{'frontend': {'window': 8, ...}, ...}``. Unknown sections are a :class:`ConfigError`."""
    out: dict[str, dict] = {s: {} for s in KNOWN_SECTIONS}
    for name, param in node._parameters.items():  # rclpy keeps declared parameters here
        if name in BUILTIN_PARAMETERS or name.startswith("qos_overrides."):
            continue
        sec, _, key = name.partition(".")
        if sec not in out or not key:
            raise ConfigError(f"node {node.get_name()}: unknown parameter {name!r}; parameters live "
                              f"in the sections {', '.join(KNOWN_SECTIONS)} (e.g. frontend.window)")
        if "." in key:
            raise ConfigError(f"node {node.get_name()}: parameter {name!r} is nested too deeply")
        out[sec][key] = param.value
    return out


def section_config(cls, values: dict, where: str):
    """Config dataclass from a params section; ROS turns YAML lists into arrays, undo that."""
    fixed = {k: (list(v) if not isinstance(v, (str, bytes, bool, int, float)) and v is not None
                 and hasattr(v, "__iter__") else v) for k, v in values.items()}
    return config_from_dict(cls, fixed, where)


class InputQueue(Generic[T]):
    """Thread-safe input queue with the node's drop policy.

    ``keep_newest``: ``get`` returns the newest item and drops (counts) every older one waiting.
    ``backpressure``: FIFO, nothing dropped unless more than ``maxsize`` items wait (then the oldest
    is dropped and counted: the sender ignored the back-pressure protocol).
    """

    def __init__(self, policy: str, maxsize: int = 64) -> None:
        self.policy = policy
        self._dq: collections.deque = collections.deque()
        self._cv = threading.Condition()
        self.maxsize = maxsize
        self.dropped = 0
        self.received = 0
        self._closed = False

    def put(self, item: T) -> None:
        with self._cv:
            self.received += 1
            self._dq.append(item)
            while len(self._dq) > self.maxsize:
                self._dq.popleft()
                self.dropped += 1
            self._cv.notify()

    def get(self, timeout: float = 0.1) -> Optional[T]:
        with self._cv:
            if not self._dq and not self._closed:
                self._cv.wait(timeout)
            if not self._dq:
                return None
            if self.policy == "keep_newest":
                self.dropped += len(self._dq) - 1
                item = self._dq.pop()
                self._dq.clear()
                return item
            return self._dq.popleft()

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()

    def __len__(self) -> int:
        with self._cv:
            return len(self._dq)


class Worker:
    """Runs ``step()`` in a loop on its own thread until stopped; an exception stops the node."""

    def __init__(self, name: str, step: Callable[[], None], on_error: Callable[[BaseException], None]):
        self._step, self._on_error = step, on_error
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                self._step()
        except BaseException as e:  # noqa: BLE001 - reported to the node, which exits non-zero
            self._on_error(e)

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def stop(self, timeout: Optional[float] = None) -> bool:
        """Let the current step finish, end the loop and wait for the thread (``None`` = as long
        as it takes). Returns True when the thread has ended: only then may the caller touch
        what the worker was using, and only then may the process exit cleanly (a thread still
        inside torch at interpreter exit aborts the process: "terminate called without an
        active exception")."""
        self._stop.set()
        if self.thread.is_alive() and threading.current_thread() is not self.thread:
            self.thread.join(timeout)
        return not self.thread.is_alive()


class RateMeter:
    """Events per second over a sliding window of ``window_s`` seconds."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._t: collections.deque = collections.deque()

    def tick(self) -> None:
        now = time.monotonic()
        self._t.append(now)
        while self._t and now - self._t[0] > self.window_s:
            self._t.popleft()

    @property
    def hz(self) -> float:
        if len(self._t) < 2:
            return 0.0
        return (len(self._t) - 1) / max(self._t[-1] - self._t[0], 1e-9)


def rss_mb() -> float:
    """Current resident set size of this process (MiB)."""
    try:
        with open("/proc/self/statm") as f:
            import os
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except OSError:
        return float("nan")


def run_node(make_node: Callable[[], Any], args: Optional[list[str]] = None) -> int:
    """Common ``main``: ROS environment, rclpy init, one SingleThreadedExecutor, clean shutdown on
    SIGINT/SIGTERM (the node's ``shutdown()`` runs: final checkpoint etc.). Returns the exit code:
    0 clean, 2 configuration/input error, 1 crash."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    from .ros_env import apply_ros_environment

    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(levelname)s %(message)s")
    argv = list(sys.argv if args is None else args)
    try:
        apply_ros_environment()
        # rcl parses the files in init (a traceback for a bad one) and ignores a -p override whose
        # type differs from the file's value: both are checked here first
        check_parameters(*param_rules(argv), "vings node")
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
                node.shutdown()
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


def config_summary(cfg: Any) -> str:
    return ", ".join(f"{k}={v}" for k, v in dataclasses.asdict(cfg).items())
