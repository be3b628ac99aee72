"""Where the shipped params file is, in a source checkout, a pip install or a ROS 2 install."""
from __future__ import annotations

import enum
import sys
from pathlib import Path
from typing import Any

PARAMS_NAME = "vings.yaml"


def default_params_file() -> Path:
    """``params/vings.yaml``: the checkout's copy, else ``share/vings_ros/params`` of the install
    (found through the ament index when available)."""
    here = Path(__file__).resolve().parents[1] / "params" / PARAMS_NAME
    if here.is_file():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory
        p = Path(get_package_share_directory("vings_ros")) / "params" / PARAMS_NAME
        if p.is_file():
            return p
    except Exception:  # noqa: BLE001 - not in an ament environment
        pass
    p = Path(sys.prefix) / "share" / "vings_ros" / "params" / PARAMS_NAME
    return p


def default_sections() -> dict:
    """Every section's defaults, as the params file holds them: ``ros``, one per node with
    settings (``frontend_node``, ``mapper_node``), the library stages (``frontend``, ``mapping``,
    ``run``, ``exchange``, ...). Enum values are their plain strings; a field whose default is an
    empty list is left out (a ROS 2 parameter cannot hold ``[]``)."""
    import dataclasses

    from .node_common import section_classes
    return {name: {k: _plain(v) for k, v in dataclasses.asdict(cls()).items() if v != []}
            for name, cls in section_classes().items()}


def _plain(v: Any) -> Any:
    """A value as YAML / ROS parameters hold it (an Enum member as its value)."""
    if isinstance(v, enum.Enum):
        return v.value
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def format_params_file(sections: dict) -> str:
    """A ROS 2 params YAML applying ``sections`` to every node (``/**``)."""
    import yaml
    head = ("# VINGS-ROS parameters: read by every node of the graph (--ros-args --params-file) and by\n"
            "# `vings run --params`. Section ros: shared by the nodes; one section per node (its name);\n"
            "# one per library stage. Units and meanings: docs/ros.md and the config dataclasses\n"
            "# (vings_ros/node_config.py, vings_core/*/config.py, vings_core/pipeline.py RunConfig).\n")
    return head + yaml.safe_dump({"/**": {"ros__parameters": sections}}, sort_keys=False)
