"""What every VINGS node shares besides its ROS skeleton (vings_ros/node_base.py): parameters ->
config dataclasses (the params layout of the graph, the section -> config class table, the checks
run before rclpy starts), the input queue, the worker thread that runs the library, rate meters.

Threads: each node spins ONE ``SingleThreadedExecutor`` (rclpy's MultiThreadedExecutor is unusably
slow in this version, see ../shared/STACK.md) for message I/O, and runs the heavy library work in one
worker thread fed by a :class:`InputQueue`. Publishing from the worker is safe (rcl publishers are
thread-safe); no callback ever blocks on the library.

No rclpy import here: ``vings run --params`` and ``vings launch`` check params files with it.
"""
from __future__ import annotations

import collections
import os
import threading
import time
from typing import Any, Callable, Generic, Iterable, Optional, TypeVar

from vings_core.config import (LIBRARY_SECTIONS, ParamsLayout, config_class, config_from_dict,
                               read_params_file, ros_yaml_load)
from vings_core.errors import ConfigError

from . import registry
from .node_config import MOVED_PARAMETERS, QueuePolicy
from .registry import NodeSpec

T = TypeVar("T")

#: parameters rclpy declares on every node
BUILTIN_PARAMETERS = ("use_sim_time", "start_type_description_service")


def _node_specs(extra: Iterable[NodeSpec] = ()) -> list[NodeSpec]:
    specs = list(registry.NODES)
    specs += [s for s in extra if s.name not in {n.name for n in specs}]
    return specs


def graph_layout(extra: Iterable[NodeSpec] = ()) -> ParamsLayout:
    """What the graph's params file holds: the shared section ``ros``, one section per node with
    settings (named after the node), the library sections; the node blocks of every registry node
    (and of ``extra``) are read besides ``/**``."""
    own = registry.params_sections()
    more = [s for s in extra if s.name not in own["nodes"]]
    return ParamsLayout(sections=(*own["sections"], *(s.name for s in more if s.config), *LIBRARY_SECTIONS),
                        nodes=(*own["nodes"], *(s.name for s in more)))


def section_classes(extra: Iterable[NodeSpec] = ()) -> dict[str, type]:
    """Params section -> config dataclass, for every section of :func:`graph_layout`."""
    refs = {registry.SHARED_SECTION: registry.SHARED_CONFIG,
            **{s.name: s.config for s in _node_specs(extra) if s.config}, **LIBRARY_SECTIONS}
    return {name: config_class(ref) for name, ref in refs.items()}


def section_config(cls: type, section: str, values: dict, origin: str) -> Any:
    """Config dataclass ``cls`` of params section ``section``; errors start with ``origin`` (a
    file, a node). A key that lives in another section is named there (``ros.checkpoint_path
    moved to mapper_node.checkpoint_path``); ROS arrays (YAML lists) become lists."""
    for key in values:
        moved = MOVED_PARAMETERS.get(f"{section}.{key}")
        if moved:
            raise ConfigError(f"{origin}: {section}.{key} moved to {moved}")
    fixed = {k: (list(v) if not isinstance(v, (str, bytes, bool, int, float)) and v is not None
                 and hasattr(v, "__iter__") else v) for k, v in values.items()}
    return config_from_dict(cls, fixed, f"{origin}: {section}")


def check_params_file(path: str | os.PathLike) -> dict[str, Any]:
    """Every section of the graph's params file through its config dataclass (as the nodes will
    read it): ``{section: config}``; a :class:`ConfigError` names the file and key."""
    layout = graph_layout()
    merged = read_params_file(path, layout.sections, nodes=layout.nodes)
    return {sec: section_config(cls, sec, merged.get(sec, {}), str(path))
            for sec, cls in section_classes().items()}


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


def check_parameters(files: list[str], rules: dict[str, str], where: str,
                     extra: Iterable[NodeSpec] = ()) -> dict[str, dict]:
    """The sections the nodes will see (params files, then ``-p`` rules), checked before rclpy
    starts: every section through its config dataclass, and every ``-p`` value against the type the
    params file gives the same parameter. rcl keeps the FILE's value when the two types differ (an
    override ``-p mapping.points_per_keyframe:=1e4`` over the file's ``20000`` is silently
    ignored), so such an override is a :class:`ConfigError` here. Returns ``{section: {key: value}}``."""
    layout = graph_layout(extra)
    sections: dict[str, dict] = {s: {} for s in layout.sections}
    for f in files:
        for sec, vals in read_params_file(f, layout.sections, strict=False, nodes=layout.nodes).items():
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
    for sec, cls in section_classes(extra).items():
        section_config(cls, sec, sections.get(sec, {}), where)
    return sections


def publisher_ids(node: Any, topic: str) -> set[tuple]:
    """Endpoint ids of the publishers of ``topic`` now: a restarted node shows up as a new id even
    while the killed process's endpoint still lingers in discovery (empty while shutting down)."""
    try:
        return {tuple(i.endpoint_gid) for i in node.get_publishers_info_by_topic(topic)}
    except Exception:  # noqa: BLE001 - graph queries fail only while shutting down
        return set()


def wait_all_acked(publishers: Iterable[Any], timeout_s: float) -> Optional[str]:
    """Wait (at most ``timeout_s`` for all together) until every reliable reader of each of
    ``publishers`` confirmed what was published: a writer that goes away drops what its readers
    had not fetched. Returns the topic of the first publisher not confirmed in time (or whose
    wait failed, e.g. while shutting down), None when all were."""
    from rclpy.duration import Duration         # lazy: no rclpy import at module load
    deadline = time.monotonic() + timeout_s
    for pub in publishers:
        left = max(0.0, deadline - time.monotonic())
        try:
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                return pub.topic_name
        except Exception:  # noqa: BLE001 - best effort while stopping
            return pub.topic_name
    return None


def spin_in_background(node: Any, period_s: float = 0.02) -> Callable[[], None]:
    """Spin ``node`` in a daemon thread with its own ``SingleThreadedExecutor`` (probes, tools and
    benchmarks that wait in their main thread); returns the function that stops it."""
    from rclpy.executors import SingleThreadedExecutor   # lazy: no rclpy import at module load
    stop = threading.Event()

    def spin() -> None:
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        while not stop.is_set():
            ex.spin_once(timeout_sec=period_s)
        ex.shutdown()

    th = threading.Thread(target=spin, name=f"spin-{node.get_name()}", daemon=True)
    th.start()

    def stop_spinning() -> None:
        stop.set()
        th.join(5.0)
    return stop_spinning


def worth_reporting(count: int) -> bool:
    """Rate limit for repeated warnings: the 1st, the 20th, then every 200th occurrence."""
    return count in (1, 20) or count % 200 == 0


def node_sections(node: Any, layout: ParamsLayout) -> dict[str, dict]:
    """The node's parameters (declared from the params file overrides) grouped by section:
    ``{'frontend': {'window': 8, ...}, ...}``. A section outside ``layout`` is a :class:`ConfigError`."""
    out: dict[str, dict] = {s: {} for s in layout.sections}
    for name, param in node._parameters.items():  # rclpy keeps declared parameters here
        if name in BUILTIN_PARAMETERS or name.startswith("qos_overrides."):
            continue
        sec, _, key = name.partition(".")
        if sec not in out or not key:
            raise ConfigError(f"node {node.get_name()}: unknown parameter {name!r}; parameters live "
                              f"in the sections {', '.join(layout.sections)} (e.g. frontend.window)")
        if "." in key:
            raise ConfigError(f"node {node.get_name()}: parameter {name!r} is nested too deeply")
        out[sec][key] = param.value
    return out


class InputQueue(Generic[T]):
    """Thread-safe input queue with the node's drop policy.

    ``keep_newest``: ``get`` returns the newest item and drops (counts) every older one waiting.
    ``backpressure``: FIFO, nothing dropped unless more than ``maxsize`` items wait (then the oldest
    is dropped and counted: the sender ignored the back-pressure protocol).
    """

    def __init__(self, policy: QueuePolicy | str, maxsize: int = 64) -> None:
        self.policy = QueuePolicy(policy)
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
            if self.policy is QueuePolicy.KEEP_NEWEST:
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


def lower_priority(nice: int, threads: int) -> None:
    """Make a node yield the CPU to tracking: add ``nice`` to this process's niceness (0 = leave; not
    allowed: ignored) and use ``threads`` torch / numba threads (0 = leave)."""
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


def rss_mb() -> float:
    """Current resident set size of this process (MiB)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except OSError:
        return float("nan")
