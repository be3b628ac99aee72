"""The node registry (vings_ros/registry.py) is the one list of nodes: setup.py's console scripts,
launch/vings.launch.py, `vings launch` and the params sections all follow it."""
from __future__ import annotations

import importlib
import os
import runpy
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest
import yaml

from vings_core.errors import ConfigError
from vings_ros import registry
from vings_ros.registry import Launch, NodeSpec

REPO = Path(__file__).resolve().parents[1]

#: an extra node with settings (the checkpoint ones), placed between the front end and the mapper
EXTRA = NodeSpec("extra_node", "stand_in_extra_node", "vings_ros.node_config:CheckpointSettings",
                 reads=("mapping",), stop_timeout_s=7.0)


def _with_extra() -> tuple[NodeSpec, ...]:
    fe, *rest = registry.NODES
    return (fe, EXTRA, *rest)


def _setup_py_kwargs() -> dict:
    import setuptools
    got: dict = {}
    real = setuptools.setup
    setuptools.setup = lambda **kw: got.update(kw)
    try:
        runpy.run_path(str(REPO / "setup.py"))
    finally:
        setuptools.setup = real
    return got


def _launch_file_nodes(monkeypatch) -> list[str]:
    """launch/vings.launch.py with stand-ins for launch / launch_ros / ament_index (not available as
    wheels): the executables of its Node actions, in order."""
    class Action:
        def __init__(self, *args, **kw):
            self.args, self.kw = args, kw

    class Node(Action):
        pass

    fake = {
        "launch": types.SimpleNamespace(LaunchDescription=lambda actions: list(actions)),
        "launch.actions": types.SimpleNamespace(DeclareLaunchArgument=Action, SetEnvironmentVariable=Action),
        "launch.substitutions": types.SimpleNamespace(LaunchConfiguration=Action),
        "launch_ros": types.SimpleNamespace(),
        "launch_ros.actions": types.SimpleNamespace(Node=Node),
        "ament_index_python": types.SimpleNamespace(),
        "ament_index_python.packages": types.SimpleNamespace(get_package_share_directory=lambda p: f"/share/{p}"),
    }
    for name, mod in fake.items():
        monkeypatch.setitem(sys.modules, name, mod)
    ns = runpy.run_path(str(REPO / "launch" / "vings.launch.py"))
    actions = ns["generate_launch_description"]()
    nodes = [a for a in actions if isinstance(a, Node)]
    assert all(a.kw["name"] == a.kw["executable"] for a in nodes)
    return [a.kw["executable"] for a in nodes]


def test_every_registry_node_has_a_console_script_and_a_launch_entry(monkeypatch):
    pytest.importorskip("rclpy")
    scripts = _setup_py_kwargs()["entry_points"]["console_scripts"]
    for spec in registry.NODES:
        assert f"{spec.name} = {spec.module}:main" in scripts, spec.name
        assert callable(importlib.import_module(spec.module).main), spec.module
    assert "vings = vings_ros.cli:main" in scripts
    # the launch file starts what `vings launch` starts by default, in the same order
    from vings_ros.launch import default_nodes
    assert _launch_file_nodes(monkeypatch) == list(reversed(default_nodes())) == ["eraser_node", "loop_closer_node",
                                                                                "mapper_node", "frontend_node"]


def test_an_extra_registry_entry_is_listed_everywhere_without_editing_them(monkeypatch, tmp_path):
    from vings_ros.launch import Launcher, LaunchOptions, default_nodes, node_command
    from vings_ros.node_common import check_parameters, graph_layout, param_rules
    from vings_ros.params import default_sections
    monkeypatch.setattr(registry, "NODES", _with_extra())
    assert default_nodes() == ("frontend_node", "extra_node", "mapper_node", "loop_closer_node", "eraser_node")
    assert _launch_file_nodes(monkeypatch) == ["eraser_node", "loop_closer_node", "mapper_node", "extra_node",
                                               "frontend_node"]
    assert "extra_node = stand_in_extra_node:main" in registry.console_scripts()
    # its settings section is part of the params layout, the defaults dump and the checks
    assert "extra_node" in graph_layout().sections and "extra_node" in graph_layout().nodes
    assert default_sections()["extra_node"] == {"checkpoint_path": "", "resume": True, "checkpoint_period_s": 30.0}
    assert check_parameters(*param_rules(["n", "--ros-args", "-p", "extra_node.checkpoint_period_s:=5.0"]),
                            "n")["extra_node"] == {"checkpoint_period_s": 5.0}
    with pytest.raises(ConfigError, match="n: extra_node: unknown parameter 'bogus'"):
        check_parameters(*param_rules(["n", "--ros-args", "-p", "extra_node.bogus:=1"]), "n")
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"extra_node": {"ros__parameters": {"extra_node": {"resume": False}}}}))
    launcher = Launcher(LaunchOptions(params_file=str(p)))
    assert launcher.nodes == ["frontend_node", "extra_node", "mapper_node", "loop_closer_node", "eraser_node"]
    assert launcher.stop_timeout["extra_node"] == 7.0
    assert node_command("extra_node", launcher.opt)[:3] == [sys.executable, "-m", "stand_in_extra_node"]
    # an on-request node is left out unless asked for
    monkeypatch.setattr(registry, "NODES", (*_with_extra(), NodeSpec("later_node", "m", launch=Launch.ON_REQUEST)))
    assert "later_node" not in default_nodes()


LAUNCH_CHILD = """
import dataclasses
from vings_ros import launch as L, registry
from vings_ros.registry import NodeSpec
fe, *rest = registry.NODES
nodes = (fe, NodeSpec("extra_node", "stand_in_extra_node"), *rest)
registry.NODES = tuple(dataclasses.replace(n, module=f"stand_in_{n.name}") for n in nodes)
print("rc", L.Launcher(L.LaunchOptions()).run(), flush=True)
"""


def test_vings_launch_starts_and_stops_an_extra_registry_node_in_order(tmp_path):
    """A node added to the registry (between front end and mapper) is started by the launcher
    (consumers first) and stopped after the front end, before the mapper."""
    names = ("frontend_node", "extra_node", "mapper_node", "loop_closer_node", "eraser_node")
    from stand_in_nodes import write_stand_in_nodes
    logs = write_stand_in_nodes(tmp_path, names)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]))
    p = subprocess.Popen([sys.executable, "-c", LAUNCH_CHILD], env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    t_end = time.monotonic() + 60
    while not all(f.exists() for f in logs) and time.monotonic() < t_end:
        time.sleep(0.1)
    time.sleep(0.3)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    assert "rc 0" in out, err
    started = [err.find(f"started {name} ") for name in names]
    assert min(started) >= 0 and started == sorted(started, reverse=True), f"consumers start first:\n{err}"
    stopped = [float(f.read_text().splitlines()[-1].split()[0]) for f in logs]
    assert stopped == sorted(stopped), "stopped in the registry order"


def test_ament_install_registers_the_package_and_its_node_executables(tmp_path, monkeypatch):
    import os
    import subprocess

    from vings_ros.ament_install import install
    pytest.importorskip("ament_index_python")
    prefix = tmp_path / "prefix"
    install(prefix)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    from ament_index_python.packages import get_package_prefix, get_package_share_directory
    assert Path(get_package_prefix("vings_ros")) == prefix.resolve()
    assert (Path(get_package_share_directory("vings_ros")) / "package.xml").is_file()
    for spec in registry.NODES:
        exe = prefix / "lib" / "vings_ros" / spec.name
        assert exe.is_file() and os.access(exe, os.X_OK), spec.name
    # an executable starts its node's code: a bad argument is its one-line usage error
    r = subprocess.run([str(prefix / "lib" / "vings_ros" / "recorder_node")], capture_output=True, text=True,
                       timeout=60, env=dict(os.environ, ROS_DOMAIN_ID="231", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert r.returncode != 0 and "usage: recorder_node OUT.mcap" in (r.stderr + r.stdout)


def test_nodes_stop_when_the_launcher_is_killed(tmp_path):
    """`kill -9` of the launcher: every node gets SIGTERM from the kernel and exits (no orphans)."""
    names = ("frontend_node", "mapper_node", "loop_closer_node", "eraser_node")
    from stand_in_nodes import write_stand_in_nodes
    logs = write_stand_in_nodes(tmp_path, names)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]))
    child = LAUNCH_CHILD.replace('nodes = (fe, NodeSpec("extra_node", "stand_in_extra_node"), *rest)',
                                 "nodes = (fe, *rest)")
    p = subprocess.Popen([sys.executable, "-c", child], env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    t_end = time.monotonic() + 60
    while not all(f.exists() for f in logs) and time.monotonic() < t_end:
        time.sleep(0.1)
    assert all(f.exists() for f in logs), p.stderr.read() if p.poll() is not None else "nodes did not start"
    time.sleep(0.3)
    t_kill = time.monotonic()
    os.kill(p.pid, signal.SIGKILL)
    p.communicate(timeout=30)
    while time.monotonic() < t_kill + 10 and not all("got" in f.read_text() for f in logs):
        time.sleep(0.05)
    for f in logs:
        last = f.read_text().splitlines()[-1]
        assert f"got {int(signal.SIGTERM)}" in last, f"{f.name}: {last}"
        assert float(last.split()[0]) - t_kill < 5.0


RESPAWN_CHILD = """
import dataclasses, sys
from vings_ros import launch as L, registry
registry.NODES = tuple(dataclasses.replace(n, module=f"stand_in_{n.name}") for n in registry.NODES)
extra = dict(a.split("=", 1) for a in sys.argv[1:])
print("rc", L.Launcher(L.LaunchOptions(extra_params=extra)).run(), flush=True)
"""


def _pids(log: Path) -> list[int]:
    return [int(ln.split()[2]) for ln in log.read_text().splitlines() if " started " in ln] if log.exists() else []


def _launch_stand_ins(tmp_path, *params):
    names = ("frontend_node", "mapper_node", "loop_closer_node", "eraser_node")
    from stand_in_nodes import write_stand_in_nodes
    logs = dict(zip(names, write_stand_in_nodes(tmp_path, names)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]))
    p = subprocess.Popen([sys.executable, "-c", RESPAWN_CHILD, *params], env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    t_end = time.monotonic() + 60
    while not all(_pids(f) for f in logs.values()) and time.monotonic() < t_end:
        time.sleep(0.1)
    return p, logs


def test_launcher_respawns_a_node_that_dies_and_the_others_keep_working(tmp_path):
    p, logs = _launch_stand_ins(tmp_path, "mapper_node.respawn_backoff_s=0.2", "mapper_node.respawn_max=1")
    first = _pids(logs["mapper_node"])[0]
    others = {n: _pids(f) for n, f in logs.items() if n != "mapper_node"}
    os.kill(first, signal.SIGKILL)
    t_end = time.monotonic() + 30
    while len(_pids(logs["mapper_node"])) < 2 and time.monotonic() < t_end:
        time.sleep(0.05)
    assert len(_pids(logs["mapper_node"])) == 2, "the mapper was not respawned"
    assert {n: _pids(f) for n, f in logs.items() if n != "mapper_node"} == others   # untouched
    # the second death exhausts respawn_max: the mapper is needed, the graph stops (exit 1)
    os.kill(_pids(logs["mapper_node"])[1], signal.SIGKILL)
    out, err = p.communicate(timeout=60)
    assert "rc 1" in out, err
    assert "mapper_node exited with code -9; respawning it in 0.2 s (1 of 1)" in err
    assert "mapper_node exited with code -9 after 1 respawn(s); stopping the graph" in err


def test_launcher_exit_policy_continue_and_stop(tmp_path):
    p, logs = _launch_stand_ins(tmp_path, "eraser_node.on_exit=continue", "loop_closer_node.on_exit=stop")
    os.kill(_pids(logs["eraser_node"])[0], signal.SIGKILL)
    time.sleep(1.0)
    assert p.poll() is None and len(_pids(logs["eraser_node"])) == 1       # left out, not respawned
    os.kill(_pids(logs["loop_closer_node"])[0], signal.SIGKILL)
    out, err = p.communicate(timeout=60)
    assert "rc 1" in out and "eraser_node exited with code -9; the graph goes on without it" in err
    assert "loop_closer_node exited with code -9; stopping the graph" in err


def test_vings_launch_nodes_names_unknown_nodes_in_one_line():
    import subprocess
    import sys
    p = subprocess.run([sys.executable, "-m", "vings_ros.cli", "launch", "--nodes", "mapper_node,bogus_node"],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert p.returncode != 0 and "Traceback" not in p.stderr
    assert "--nodes: unknown node(s) bogus_node; known: frontend_node, mapper_node" in p.stderr
