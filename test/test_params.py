"""The shipped params file matches the config dataclasses, and the nodes' section parsing."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from vings_core.config import ConfigError, load_section, read_params_file
from vings_ros.params import default_params_file, default_sections

REPO = Path(__file__).resolve().parents[1]


def test_shipped_params_file_has_every_field_and_nothing_else():
    path = default_params_file()
    assert path == REPO / "params" / "vings.yaml"
    shipped = read_params_file(path)
    defaults = default_sections()
    assert set(shipped) == set(defaults)
    for sec, vals in defaults.items():
        assert set(shipped[sec]) == set(vals), f"section {sec} drifted from its dataclass"


def test_every_section_loads_into_its_config():
    from vings_core.frontend import FrontendConfig
    from vings_core.mapping import MapperConfig
    from vings_core.pipeline import RunConfig
    from vings_ros.node_common import NodeConfig
    path = default_params_file()
    for cls, sec in ((FrontendConfig, "frontend"), (MapperConfig, "mapping"), (RunConfig, "run"),
                     (NodeConfig, "ros")):
        assert load_section(cls, sec, path) == cls()


def test_invalid_values_are_named(tmp_path):
    from vings_ros.node_common import NodeConfig
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"ros": {"queue_policy": "newest"}}}}))
    with pytest.raises(ConfigError, match="queue_policy must be one of"):
        load_section(NodeConfig, "ros", p)
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"ros": {"queue_polcy": "x"}}}}))
    with pytest.raises(ConfigError, match=r"p.yaml: ros: unknown parameter 'queue_polcy'"):
        load_section(NodeConfig, "ros", p)


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
    q = InputQueue("keep_newest")
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


@pytest.mark.parametrize("key,value,match", [
    ("diagnostics_period_s", 0.0, "diagnostics_period_s must be > 0"),
    ("diagnostics_period_s", -1.0, "diagnostics_period_s must be > 0"),
    ("max_points", -1, "max_points"),
    ("world_frame", "", "world_frame must be a frame id"),
    ("camera_frame", "/cam", "camera_frame must be a frame id"),
])
def test_node_settings_that_fail_later_are_refused_at_start(tmp_path, key, value, match):
    from vings_ros.node_common import NodeConfig
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"ros": {key: value}}}}))
    with pytest.raises(ConfigError, match=match):
        load_section(NodeConfig, "ros", p)


def test_lenient_reading_keeps_what_rclpy_and_other_nodes_own(tmp_path):
    """What launch_ros writes (use_sim_time), qos_overrides and other nodes' blocks are valid for
    the nodes (rclpy takes them): the nodes' pre-check and the launcher read leniently."""
    from vings_ros.launch import Launcher, LaunchOptions
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n    ros:\n      shutdown_timeout_s: 30.0\n"
                 "    qos_overrides:\n      /clock:\n        subscription:\n          depth: 5\n"
                 "other_node:\n  ros__parameters:\n    gain: [1.0, 2.0]\n")
    with pytest.raises(ConfigError, match="unknown parameter section"):
        read_params_file(p)                                  # `vings run --params`: strict
    assert read_params_file(p, strict=False) == {"ros": {"shutdown_timeout_s": 30.0}}
    assert Launcher(LaunchOptions(params_file=str(p))).stop_timeout["mapper_node"] == 180.0
    p.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n    mapping.background: [0, 1, 1.0]\n")
    with pytest.raises(ConfigError, match="mapping.background: ROS 2 list parameters hold one"):
        read_params_file(p, strict=False)                    # rcl would refuse it anyway
