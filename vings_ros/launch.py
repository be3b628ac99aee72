"""The launcher behind ``vings launch``: starts the node graph as processes, watches them, stops
them cleanly.

Order: mapper first (it may resume from a checkpoint), then the front end, then the recorder. A
node that exits on its own is reported and the rest of the graph is stopped (exit code 1). Ctrl-C /
SIGTERM stops the front end first (it flushes its last keyframes), then the mapper (it finishes its
queue and writes its checkpoint), then the recorder (it closes the MCAP). Fast DDS shared-memory
files left by the graph's processes are removed at the end.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, TextIO

from vings_core.config import config_from_dict
from vings_core.errors import ConfigError
from vings_core.util import check_output_file

from .node_common import NodeConfig, check_parameters
from .ros_env import cleanup_fastdds_shm, ros_environment, shm_snapshot

NODES = {"frontend_node": "vings_ros.frontend_node", "mapper_node": "vings_ros.mapper_node",
         "recorder_node": "vings_ros.recorder"}
#: seconds each node gets to stop after SIGINT before it is killed (the mapper: at least its
#: ``ros.shutdown_timeout_s`` to finish queued keyframes, plus MAPPER_SAVE_MARGIN_S to save)
STOP_TIMEOUT_S = {"frontend_node": 20.0, "mapper_node": 180.0, "recorder_node": 20.0}
MAPPER_SAVE_MARGIN_S = 60.0


@dataclass
class LaunchOptions:
    params_file: Optional[str] = None
    record: Optional[str] = None
    use_sim_time: bool = False
    domain_id: Optional[int] = None
    checkpoint: Optional[str] = None
    nodes: tuple = ("mapper_node", "frontend_node")
    extra_params: dict = field(default_factory=dict)   # "section.key" -> value (ROS -p overrides)
    log_dir: Optional[str] = None


def node_command(name: str, opt: LaunchOptions, extra: Optional[list] = None) -> list[str]:
    """The command line of one node process (``python -m module [args] --ros-args ...``)."""
    cmd = [sys.executable, "-m", NODES[name]] + list(extra or []) + ["--ros-args"]
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
    return str(v)


class Launcher:
    def __init__(self, opt: LaunchOptions, out: Optional[TextIO] = None) -> None:
        self.opt = opt
        self.out = out or sys.stderr
        self.procs: dict[str, subprocess.Popen] = {}
        self._stopping = False
        # every section as the nodes will see it (params file, then -p), checked before any node
        # starts; the ros section's shutdown_timeout_s sets how long the mapper may take to stop
        sections = check_parameters([opt.params_file] if opt.params_file else [],
                                    {k: _ros_value(v) for k, v in opt.extra_params.items()}, "vings launch")
        ncfg = config_from_dict(NodeConfig, sections["ros"], "vings launch: ros")
        self.stop_timeout = {**STOP_TIMEOUT_S, "mapper_node": max(
            STOP_TIMEOUT_S["mapper_node"], ncfg.shutdown_timeout_s + MAPPER_SAVE_MARGIN_S)}
        if opt.record and not str(opt.record).endswith(".mcap"):
            raise ConfigError(f"--record {opt.record}: the output must be a .mcap file")
        if opt.record:      # before any node starts, not when the recorder dies
            opt.record = str(check_output_file(opt.record, "--record", ConfigError))
        if opt.record and Path(opt.record).exists():
            raise ConfigError(f"--record {opt.record}: the file exists; recordings are never "
                              f"overwritten, choose a new name")
        if opt.checkpoint:
            opt.extra_params.setdefault("ros.checkpoint_path", str(Path(opt.checkpoint).resolve()))
        self.env = ros_environment(opt.domain_id, log_dir=opt.log_dir)

    def _say(self, text: str) -> None:
        print(f"vings launch: {text}", file=self.out, flush=True)

    def start(self) -> None:
        self.snapshot = shm_snapshot()
        names = list(self.opt.nodes) + (["recorder_node"] if self.opt.record else [])
        for name in names:
            extra = [str(Path(self.opt.record).resolve())] if name == "recorder_node" else []
            cmd = node_command(name, self.opt, extra)
            if name == "recorder_node":  # the recorder takes no stage parameters
                cmd = [sys.executable, "-m", NODES[name]] + extra + ["--ros-args"] + \
                    (["-p", "use_sim_time:=true"] if self.opt.use_sim_time else [])
            self.procs[name] = subprocess.Popen(cmd, env=self.env, start_new_session=True)
            self._say(f"started {name} (pid {self.procs[name].pid})")

    def poll(self) -> Optional[str]:
        """Name of a node that has exited, if any."""
        for name, p in self.procs.items():
            if p.poll() is not None:
                return name
        return None

    def stop(self) -> None:
        """Stop in order: front end, mapper, recorder; SIGINT, then SIGKILL after the timeout."""
        if self._stopping:
            return
        self._stopping = True
        for name in ("frontend_node", "mapper_node", "recorder_node"):
            p = self.procs.get(name)
            if p is None or p.poll() is not None:
                continue
            try:
                os.killpg(p.pid, signal.SIGINT)
            except ProcessLookupError:
                continue
            try:
                p.wait(self.stop_timeout[name])
            except subprocess.TimeoutExpired:
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
        """Start, watch until a node dies or SIGINT/SIGTERM/SIGHUP; returns the exit code."""
        stop_requested = []

        def _sig(signum, frame):  # noqa: ARG001
            stop_requested.append(signum)

        old = {s: signal.signal(s, _sig) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
        code = 0
        try:
            self.start()
            while not stop_requested:
                dead = self.poll()
                if dead is not None:
                    rc = self.procs[dead].returncode
                    self._say(f"{dead} exited with code {rc}; stopping the graph")
                    if dead == "recorder_node":
                        self._report_stranded_recording()
                    code = 1
                    break
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
