"""Where the shipped params file is, in a source checkout, a pip install or a ROS 2 install."""
from __future__ import annotations

import sys
from pathlib import Path

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
    """Every stage's defaults, as the params file's sections (``ros``, ``frontend``, ``mapping``,
    ``run``)."""
    import dataclasses

    from .node_common import section_classes
    return {name: dataclasses.asdict(cls()) for name, cls in section_classes().items()}


def format_params_file(sections: dict) -> str:
    """A ROS 2 params YAML applying ``sections`` to every node (``/**``)."""
    import yaml
    head = ("# VINGS-ROS parameters: read by frontend_node / mapper_node (--ros-args --params-file)\n"
            "# and by `vings run --params`. One section per stage; see docs/ros.md and the config\n"
            "# dataclasses (vings_core/*/config.py, vings_core/pipeline.py RunConfig,\n"
            "# vings_ros/node_common.py NodeConfig) for units and meanings.\n")
    return head + yaml.safe_dump({"/**": {"ros__parameters": sections}}, sort_keys=False)
