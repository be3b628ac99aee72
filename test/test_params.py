"""The shipped params file matches the config dataclasses, and the nodes' section parsing."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from vings_core.config import ConfigError, load_section, params_layout, read_params_file
from vings_ros.node_common import check_params_file, graph_layout, section_classes
from vings_ros.params import default_params_file, default_sections

REPO = Path(__file__).resolve().parents[1]


def _load(cls, section, path):
    """``load_section`` with the graph's params layout (its node sections)."""
    layout = graph_layout()
    return load_section(cls, section, path, sections=layout.sections, nodes=layout.nodes)


def test_shipped_params_file_has_every_field_and_nothing_else():
    path = default_params_file()
    assert path == REPO / "params" / "vings.yaml"
    layout = graph_layout()
    shipped = read_params_file(path, layout.sections, nodes=layout.nodes)
    defaults = default_sections()
    assert set(shipped) == set(defaults) == set(layout.sections)
    for sec, vals in defaults.items():
        assert set(shipped[sec]) == set(vals), f"section {sec} drifted from its dataclass"


def test_every_section_loads_into_its_config():
    path = default_params_file()
    configs = check_params_file(path)
    assert set(configs) == set(section_classes())
    for sec, cls in section_classes().items():
        assert configs[sec] == cls(), sec
    # the library reads the graph's file: the installed graph declares its sections to it (entry
    # point vings.params_sections), which is the graph's layout
    from vings_core.config import LIBRARY_SECTIONS, ParamsLayout, installed_layout
    from vings_core.mapping import MapperConfig
    assert set(installed_layout().sections) == set(graph_layout().sections)
    assert load_section(MapperConfig, "mapping", path) == MapperConfig()
    with params_layout(ParamsLayout(tuple(LIBRARY_SECTIONS))):     # the library's sections alone
        with pytest.raises(ConfigError, match="unknown parameter section.*'frontend_node'"):
            load_section(MapperConfig, "mapping", path)


def test_params_writer_writes_enums_as_strings(tmp_path):
    from vings_ros.node_config import FrontendNodeConfig, QueuePolicy
    from vings_ros.params import format_params_file
    text = format_params_file(default_sections())
    assert "queue_policy: keep_newest" in text and "QueuePolicy" not in text and "!!python" not in text
    p = tmp_path / "p.yaml"
    p.write_text(text)
    assert _load(FrontendNodeConfig, "frontend_node", p).queue_policy is QueuePolicy.KEEP_NEWEST


def test_invalid_values_are_named(tmp_path):
    from vings_ros.node_config import FrontendNodeConfig
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"frontend_node": {"queue_policy": "newest"}}}}))
    with pytest.raises(ConfigError, match=r"frontend_node.queue_policy: expected one of 'keep_newest', "
                                          r"'backpressure', got 'newest'"):
        _load(FrontendNodeConfig, "frontend_node", p)
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"frontend_node": {"queue_polcy": "x"}}}}))
    with pytest.raises(ConfigError, match=r"p.yaml: frontend_node: unknown parameter 'queue_polcy'"):
        _load(FrontendNodeConfig, "frontend_node", p)


@pytest.mark.parametrize("old,new", [("ros.checkpoint_path", "mapper_node.checkpoint_path"),
                                     ("ros.mapper_nice", "mapper_node.nice"),
                                     ("ros.queue_policy", "frontend_node.queue_policy")])
def test_node_settings_in_the_shared_section_name_their_section(tmp_path, old, new):
    """The nodes' own settings live in their sections: an old ``ros.<key>`` names its new place,
    in a params file (vings run, vings launch, the nodes) and as a -p override."""
    from vings_ros.launch import Launcher, LaunchOptions
    from vings_ros.node_common import check_parameters, param_rules
    key = old.split(".")[1]
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"ros": {key: "x"}}}}))
    with pytest.raises(ConfigError, match=rf"p.yaml: {old} moved to {new}$"):
        check_params_file(p)
    with pytest.raises(ConfigError, match=rf"vings launch: {old} moved to {new}$"):
        Launcher(LaunchOptions(params_file=str(p)))
    with pytest.raises(ConfigError, match=rf"vings node: {old} moved to {new}$"):
        check_parameters(*param_rules(["n", "--ros-args", "-p", f"{old}:=x"]), "vings node")


def test_a_parameter_given_twice_is_an_error(tmp_path):
    from vings_core.pipeline import RunConfig
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    run.eval_keyframes: 3\n    run:\n      eval_keyframes: 4\n")
    with pytest.raises(ConfigError, match="'eval_keyframes' is given twice"):
        load_section(RunConfig, "run", p)
    # different keys of one section, dotted and nested, merge
    p.write_text("/**:\n  ros__parameters:\n    run.eval_keyframes: 3\n    run:\n      eval_novel: 4\n")
    c = load_section(RunConfig, "run", p)
    assert (c.eval_keyframes, c.eval_novel) == (3, 4)


def test_replaced_parameter_names_its_successor(tmp_path):
    from vings_core.mapping import MapperConfig
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"mapping": {"refine_lr_trans": 1e-3}}}}))
    with pytest.raises(ConfigError, match=r"p.yaml: mapping: parameter 'refine_lr_trans' was replaced by "
                                          r"'refine_lr_trans_rel'"):
        load_section(MapperConfig, "mapping", p)


def test_input_queue_policies():
    from vings_ros.node_common import InputQueue
    from vings_ros.node_config import QueuePolicy
    q = InputQueue(QueuePolicy.KEEP_NEWEST)
    for i in range(5):
        q.put(i)
    assert q.get(0) == 4 and q.dropped == 4 and q.get(0) is None
    b = InputQueue("backpressure", maxsize=3)
    for i in range(4):
        b.put(i)
    assert [b.get(0) for _ in range(3)] == [1, 2, 3] and b.dropped == 1


def test_lists_rcl_cannot_hold_are_refused_with_the_key(tmp_path):
    """rcl refuses mixed-type and empty lists when a node starts; `vings run --params` and the
    launcher read the same file, so they refuse it too (one file, one meaning)."""
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      background: [0, 0.5, 0]\n")
    with pytest.raises(ConfigError, match=r"p.yaml: mapping.background: ROS 2 list parameters hold one "
                                          r"scalar type.*write floats as 0.0"):
        read_params_file(p)
    p.write_text("/**:\n  ros__parameters:\n    mapping.background: []\n")
    with pytest.raises(ConfigError, match=r"mapping.background: an empty list"):
        read_params_file(p)
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      background: [0.0, 0.5, 0.0]\n")
    assert read_params_file(p)["mapping"]["background"] == [0.0, 0.5, 0.0]


@pytest.mark.parametrize("section,key,value,match", [
    ("ros", "diagnostics_period_s", 0.0, "diagnostics_period_s must be > 0"),
    ("ros", "diagnostics_period_s", -1.0, "diagnostics_period_s must be > 0"),
    ("mapper_node", "max_points", -1, "max_points"),
    ("mapper_node", "nice", 20, "nice must be in 0..19"),
    ("frontend_node", "queue_size", 0, "queue_size must be >= 1"),
    ("ros", "world_frame", "", "world_frame must be a frame id"),
    ("ros", "camera_frame", "/cam", "camera_frame must be a frame id"),
])
def test_node_settings_that_fail_later_are_refused_at_start(tmp_path, section, key, value, match):
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {section: {key: value}}}}))
    with pytest.raises(ConfigError, match=rf"p.yaml: {section}: {match}"):
        check_params_file(p)


def test_lenient_reading_keeps_what_rclpy_and_other_nodes_own(tmp_path):
    """What launch_ros writes (use_sim_time), qos_overrides and other nodes' blocks are valid for
    the nodes (rclpy takes them): the nodes' pre-check and the launcher read leniently."""
    from vings_ros.launch import Launcher, LaunchOptions
    p = tmp_path / "p.yaml"
    layout = graph_layout()

    def read(strict: bool = True) -> dict:
        return read_params_file(p, layout.sections, strict, layout.nodes)

    p.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n    mapper_node:\n      shutdown_timeout_s: 30.0\n"
                 "    qos_overrides:\n      /clock:\n        subscription:\n          depth: 5\n"
                 "other_node:\n  ros__parameters:\n    gain: [1.0, 2.0]\n")
    # `vings run --params` reads the same file as the nodes: rclpy's keys and blocks for other
    # nodes are not VINGS sections
    assert read() == read(strict=False) == {"mapper_node": {"shutdown_timeout_s": 30.0}}
    p.write_text(p.read_text() + "mapper_node:\n  ros__parameters:\n    mappping: {window_size: 4}\n")
    with pytest.raises(ConfigError, match="unknown parameter section.*'mappping'"):
        read()                                               # a misspelt section of ours: strict
    assert read(strict=False) == {"mapper_node": {"shutdown_timeout_s": 30.0}}
    assert Launcher(LaunchOptions(params_file=str(p))).stop_timeout["mapper_node"] == 180.0
    p.write_text("/**:\n  ros__parameters:\n    mapper_node: {shutdown_timeout_s: 300.0}\n")
    assert Launcher(LaunchOptions(params_file=str(p))).stop_timeout["mapper_node"] == 360.0
    p.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n    mapping.background: [0, 1, 1.0]\n")
    with pytest.raises(ConfigError, match="mapping.background: ROS 2 list parameters hold one"):
        read(strict=False)                                   # rcl would refuse it anyway


def test_params_read_like_rcl_types_them(tmp_path):
    """rcl reads `1e-4` as a double (YAML 1.2); PyYAML's YAML 1.1 made it a string, so a file the
    nodes took was refused by `vings run`. Non-finite numbers are refused everywhere."""
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    frontend:\n      lm_lambda: 1e-4\n    mapping:\n      lr_means: 2E-5\n")
    from vings_core.frontend import FrontendConfig
    from vings_core.mapping import MapperConfig
    assert load_section(FrontendConfig, "frontend", p).lm_lambda == 1e-4
    assert load_section(MapperConfig, "mapping", p).lr_means == 2e-5
    for bad in (".nan", ".inf", "-.inf"):
        p.write_text(f"/**:\n  ros__parameters:\n    mapping:\n      lr_means: {bad}\n")
        with pytest.raises(ConfigError, match="mapping.lr_means: expected a finite number"):
            load_section(MapperConfig, "mapping", p)


def test_overrides_rcl_would_ignore_are_refused_before_any_node_starts(tmp_path):
    """With a params file, rcl keeps the FILE's value when a -p override has another type
    (`-p mapping.points_per_keyframe:=1e4` over 20000): the launcher and every node refuse it."""
    from vings_ros.launch import Launcher, LaunchOptions
    from vings_ros.node_base import run_node
    from vings_ros.node_common import check_parameters, param_rules
    f = str(default_params_file())
    for name, raw, msg in (("mapping.points_per_keyframe", "1e4", "is a double, but the params file gives "
                            "mapping.points_per_keyframe as integer 20000"),
                           ("mapper_node.resume", "0", "is an integer, but the params file gives "
                            "mapper_node.resume as bool"),
                           ("frontend_node.queue_size", "abc", "is a string"),
                           ("frontend.window", "8.0", "is a double")):
        with pytest.raises(ConfigError, match=msg):
            Launcher(LaunchOptions(params_file=f, extra_params={name: raw}))
        argv = ["node", "--ros-args", "--params-file", f, "-p", f"{name}:={raw}"]
        with pytest.raises(ConfigError, match=msg):
            check_parameters(*param_rules(argv), "vings node")
    # the same types pass, and a wrong value is still named through the stage's config
    assert check_parameters(*param_rules(["n", "--ros-args", "--params-file", f, "-p",
                                          "mapping.points_per_keyframe:=10000"]), "n")["mapping"][
        "points_per_keyframe"] == 10000
    with pytest.raises(ConfigError, match="mapping.iters_per_keyframe: expected an integer"):
        check_parameters(*param_rules(["n", "--ros-args", "-p", "mapping.iters_per_keyframe:=20.5"]), "n")
    # a node started as `ros2 run` would start it exits with one line, code 2
    assert run_node(lambda: None, ["frontend_node", "--ros-args", "--params-file", f, "-p",
                                   "mapping.points_per_keyframe:=1e4"]) == 2


LAUNCH_CHILD = """
import dataclasses
from vings_ros import launch as L, registry
registry.NODES = tuple(dataclasses.replace(n, module=f"stand_in_{n.name}") for n in registry.NODES)
print("rc", L.Launcher(L.LaunchOptions(nodes=["frontend_node", "mapper_node"])).run(), flush=True)
"""


def test_launcher_stops_the_graph_in_order_when_its_terminal_closes(tmp_path):
    """SIGHUP (terminal or SSH session closed) stops the graph like Ctrl-C: the nodes, each in its
    own session, must not outlive the launcher."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from stand_in_nodes import write_stand_in_nodes
    logs = write_stand_in_nodes(tmp_path, ("frontend_node", "mapper_node"))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(Path(__file__).parents[1])]))
    p = subprocess.Popen([sys.executable, "-c", LAUNCH_CHILD], env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    t_end = time.monotonic() + 60
    while not all(f.exists() for f in logs) and time.monotonic() < t_end:
        time.sleep(0.1)
    p.send_signal(signal.SIGHUP)
    out, err = p.communicate(timeout=60)
    assert "rc 0" in out, err
    got = [float(f.read_text().splitlines()[-1].split()[0]) for f in logs]
    assert got[0] < got[1], "the front end stops before the mapper"
