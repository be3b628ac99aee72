"""The launcher behind ``vings launch``: starts the node graph as processes, watches them, stops
them cleanly.

The nodes are the registry's (vings_ros/registry.py): those with ``launch=ALWAYS`` unless
``LaunchOptions.nodes`` names others, plus the recorder with ``record``. They start in the reverse
of the registry order (mapper first: it may resume from a checkpoint; then the front end) and stop
in the registry order on Ctrl-C / SIGTERM / SIGHUP: the front end first (it flushes its last
keyframes), then the mapper (it finishes its queue and writes its checkpoint), then the recorder
(it closes the MCAP). A node that exits on its own is handled by its exit policy (its settings'
``on_exit``, :class:`~vings_ros.node_config.ExitPolicy`): respawned after a back-off (the default;
it resumes from its checkpoint; at most ``respawn_max`` times), left out (the graph goes on), or
the graph is stopped (exit code 1). Every node gets SIGTERM from the kernel if the launcher dies,
whatever killed it. Fast DDS shared-memory files of dead processes are removed at the start and
those left by the graph's processes at the end.
"""
from __future__ import annotations

import enum
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, TextIO

from vings_core.errors import ConfigError
from vings_core.util import check_output_file

from . import registry
from .node_common import check_parameters, section_classes, section_config
from .node_config import ExitPolicy
from .ros_env import cleanup_fastdds_shm, ros_environment, shm_snapshot

#: the node ``--record`` starts (its one argument: the output file)
RECORDER = "recorder_node"
#: the node ``--rerun`` starts (its one argument: the .rrd file)
RERUN = "rerun_node"
#: a node whose settings have ``shutdown_timeout_s`` (the mapper: time to finish queued keyframes)
#: gets that plus SAVE_MARGIN_S (to write its checkpoint) before it is killed, at least its
#: registry ``stop_timeout_s``
SAVE_MARGIN_S = 60.0


def default_nodes() -> tuple[str, ...]:
    """The nodes ``vings launch`` starts without options (``launch=ALWAYS`` in the registry)."""
    return tuple(n.name for n in registry.NODES if n.launch is registry.Launch.ALWAYS)


@dataclass
class LaunchOptions:
    params_file: Optional[str] = None
    record: Optional[str] = None
    rerun: Optional[str] = None
    use_sim_time: bool = False
    domain_id: Optional[int] = None
    checkpoint: Optional[str] = None
    nodes: Optional[tuple] = None          # registry node names (None: default_nodes())
    extra_params: dict = field(default_factory=dict)   # "section.key" -> value (ROS -p overrides)
    log_dir: Optional[str] = None


def node_command(name: str, opt: LaunchOptions, extra: Optional[list] = None) -> list[str]:
    """The command line of one node process (``python -m module [args] --ros-args ...``)."""
    cmd = [sys.executable, "-m", registry.node_spec(name).module] + list(extra or []) + ["--ros-args"]
    if opt.params_file:
        cmd += ["--params-file", str(opt.params_file)]
    if opt.use_sim_time:
        cmd += ["-p", "use_sim_time:=true"]
    for k, v in opt.extra_params.items():
        cmd += ["-p", f"{k}:={_ros_value(v)}"]
    return cmd


def _ros_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, enum.Enum):
        return str(v.value)
    return str(v)


def _stop_with_launcher(launcher_pid: int):
    """``preexec_fn`` of a node process: the kernel sends it SIGTERM when the launcher dies,
    whatever killed it (Linux ``PR_SET_PDEATHSIG``), so no node is left orphaned; a launcher that
    died before the node got there is caught by the parent check."""
    def pre() -> None:
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)     # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            return                                          # not Linux: the nodes' own checks remain
        if os.getppid() != launcher_pid:
            os.kill(os.getpid(), signal.SIGTERM)
    return pre


class Launcher:
    def __init__(self, opt: LaunchOptions, out: Optional[TextIO] = None) -> None:
        self.opt = opt
        self.out = out or sys.stderr
        self.procs: dict[str, subprocess.Popen] = {}
        self._stopping = False
        self._gone: set[str] = set()        # optional nodes that exited; the graph went on
        if opt.checkpoint:
            opt.extra_params.setdefault("mapper_node.checkpoint_path", str(Path(opt.checkpoint).resolve()))
        names = list(default_nodes() if opt.nodes is None else opt.nodes)
        if opt.record and RECORDER not in names:
            names.append(RECORDER)
        if opt.rerun and RERUN not in names:
            names.append(RERUN)
        for name in names:
            registry.node_spec(name)    # a KeyError naming the known nodes
        order = [n.name for n in registry.NODES]
        #: the nodes in stop order (the registry's); they start in the reverse order
        self.nodes = sorted(names, key=order.index)
        # every section as the nodes will see it (params file, then -p), checked before any node
        # starts; a node's shutdown_timeout_s sets how long it may take to stop
        sections = check_parameters([opt.params_file] if opt.params_file else [],
                                    {k: _ros_value(v) for k, v in opt.extra_params.items()}, "vings launch")
        classes = section_classes()
        self.stop_timeout: dict[str, float] = {}
        #: per node: (exit policy, restarts at most, first back-off s); nodes without settings:
        #: an optional one is left out when it exits, another stops the graph
        self.exit_policy: dict[str, tuple[ExitPolicy, int, float]] = {}
        for spec in registry.NODES:
            timeout = spec.stop_timeout_s
            policy = (ExitPolicy.CONTINUE if spec.optional else ExitPolicy.STOP, 0, 0.0)
            if spec.config:
                cfg = section_config(classes[spec.name], spec.name, sections[spec.name], "vings launch")
                work = getattr(cfg, "shutdown_timeout_s", None)
                if work is not None:
                    timeout = max(timeout, work + SAVE_MARGIN_S)
                if hasattr(cfg, "on_exit"):
                    policy = (ExitPolicy(cfg.on_exit), int(cfg.respawn_max), float(cfg.respawn_backoff_s))
            self.stop_timeout[spec.name] = timeout
            self.exit_policy[spec.name] = policy
        self.respawns: dict[str, int] = {}
        self._signals: list[int] = []       # stop requests received (a second one hurries the stop)
        self._restart_at: dict[str, float] = {}
        if opt.record and not str(opt.record).endswith(".mcap"):
            raise ConfigError(f"--record {opt.record}: the output must be a .mcap file")
        if opt.record:      # before any node starts, not when the recorder dies
            opt.record = str(check_output_file(opt.record, "--record", ConfigError))
        if opt.rerun:
            if not str(opt.rerun).endswith(".rrd"):
                raise ConfigError(f"--rerun {opt.rerun}: the output must be a .rrd file")
            opt.rerun = str(check_output_file(opt.rerun, "--rerun", ConfigError))
            try:
                import rerun  # noqa: F401 - the optional extra, checked before any node starts
            except ImportError:
                raise ConfigError("--rerun needs the rerun SDK, an optional extra: pip install '.[viz]'") from None
        if opt.record and Path(opt.record).exists():
            raise ConfigError(f"--record {opt.record}: the file exists; recordings are never "
                              f"overwritten, choose a new name")
        self.env = ros_environment(opt.domain_id, log_dir=opt.log_dir)

    def _say(self, text: str) -> None:
        print(f"vings launch: {text}", file=self.out, flush=True)

    def _spawn(self, name: str) -> None:
        extra = ([str(Path(self.opt.record).resolve())] if name == RECORDER else
                 [str(Path(self.opt.rerun).resolve())] if name == RERUN else [])
        self.procs[name] = subprocess.Popen(node_command(name, self.opt, extra), env=self.env,
                                            start_new_session=True, preexec_fn=_stop_with_launcher(os.getpid()))

    def _node_exited(self, dead: str) -> Optional[int]:
        """Apply ``dead``'s exit policy; returns the launcher's exit code when the graph must stop."""
        rc = self.procs[dead].returncode
        policy, most, backoff = self.exit_policy.get(dead, (ExitPolicy.STOP, 0, 0.0))
        optional = registry.node_spec(dead).optional
        k = self.respawns.get(dead, 0)
        if policy is ExitPolicy.RESPAWN and k < most:
            wait = backoff * 2 ** k
            self._restart_at[dead] = time.monotonic() + wait
            self._gone.add(dead)
            self._say(f"{dead} exited with code {rc}; respawning it in {wait:.1f} s ({k + 1} of {most}); "
                      f"the other nodes keep working")
            return None
        if policy is ExitPolicy.CONTINUE or (policy is ExitPolicy.RESPAWN and optional):
            self._gone.add(dead)
            more = f" after {k} respawn(s)" if k else ""
            self._say(f"{dead} exited with code {rc}{more}; the graph goes on without it")
            return None
        more = f" after {k} respawn(s)" if k else ""
        self._say(f"{dead} exited with code {rc}{more}; stopping the graph")
        if dead == RECORDER:
            self._report_stranded_recording()
        return 1

    def _respawn_due(self) -> None:
        now = time.monotonic()
        for name, at in list(self._restart_at.items()):
            if now >= at:
                del self._restart_at[name]
                self.respawns[name] = self.respawns.get(name, 0) + 1
                self._spawn(name)
                self._gone.discard(name)
                self._say(f"respawned {name} (pid {self.procs[name].pid})")

    def start(self) -> None:
        # shared-memory files of processes that died uncleanly earlier (their locks are free)
        stale = cleanup_fastdds_shm(0.0)
        if stale:
            self._say(f"removed {len(stale)} Fast DDS shared-memory files of dead processes")
        self.snapshot = shm_snapshot()
        for name in reversed(self.nodes):
            self._spawn(name)
            self._say(f"started {name} (pid {self.procs[name].pid})")

    def poll(self) -> Optional[str]:
        """Name of a node that has exited, if any."""
        for name, p in self.procs.items():
            if name not in self._gone and p.poll() is not None:
                return name
        return None

    def stop(self) -> None:
        """Stop in the registry order (front end, mapper, recorder); SIGINT, then SIGKILL after
        the node's timeout."""
        if self._stopping:
            return
        self._stopping = True
        for name in self.nodes:
            p = self.procs.get(name)
            if p is None or p.poll() is not None:
                continue
            try:
                os.killpg(p.pid, signal.SIGINT)
            except ProcessLookupError:
                continue
            self._say(f"stopping {name} (pid {p.pid}; at most {self.stop_timeout[name]:.0f} s; Ctrl-C again "
                      f"to skip its remaining work)")
            deadline = time.monotonic() + self.stop_timeout[name]
            hurried = len(self._signals)
            while p.poll() is None and time.monotonic() < deadline:
                if len(self._signals) > hurried:        # Ctrl-C again: the node skips to its checkpoint
                    hurried = len(self._signals)
                    self._say(f"asking {name} again to stop now")
                    try:
                        os.killpg(p.pid, signal.SIGINT)
                    except ProcessLookupError:
                        break
                time.sleep(0.05)
            if p.poll() is None:
                self._say(f"{name} did not stop within {self.stop_timeout[name]:.0f} s; killing it")
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        removed = cleanup_fastdds_shm(self.snapshot)
        if removed:
            self._say(f"removed {len(removed)} stale Fast DDS shared-memory files")

    def _report_stranded_recording(self) -> None:
        """A recorder that died keeps what it wrote in its hidden working folder: say where."""
        out = Path(str(self.opt.record)).resolve()
        for d in sorted(out.parent.glob(f".{out.name}.*")):
            for f in d.rglob("*.mcap"):
                self._say(f"the recorder's partial recording is in {f} (not moved to {out})")

    def run(self) -> int:
        """Start, watch until a node dies (an optional one's exit is reported and the others go on)
        or SIGINT/SIGTERM/SIGHUP; returns the exit code."""
        stop_requested = self._signals

        def _sig(signum, frame):  # noqa: ARG001
            stop_requested.append(signum)

        old = {s: signal.signal(s, _sig) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
        code = 0
        try:
            self.start()
            while not stop_requested:
                dead = self.poll()
                if dead is not None:
                    rc = self._node_exited(dead)
                    if rc is not None:
                        code = rc
                        break
                    continue
                self._respawn_due()
                time.sleep(0.2)
            if stop_requested:
                self._say("shutting down")
        finally:
            self.stop()
            for s, h in old.items():
                signal.signal(s, h)
        bad = {n: p.returncode for n, p in self.procs.items() if p.returncode not in (0, -2, 130)}
        if bad and code == 0:
            self._say(f"nodes exited with errors: {bad}")
            code = 1
        return code
