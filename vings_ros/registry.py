"""The nodes of the VINGS graph: one :class:`NodeSpec` line per node.

Everything that lists nodes reads :data:`NODES`: ``vings launch`` (vings_ros/launch.py), the console
scripts of setup.py (``ros2 run vings_ros <name>``), launch/vings.launch.py (``ros2 launch``) and the
params file check (every node's settings section; vings_ros/node_common.py). Plain data and the
standard library only: setup.py loads this file by path, before anything is installed.

Order: :data:`NODES` follows the data flow (producers first). ``vings launch`` stops the nodes in
this order (the front end flushes its last keyframes before the mapper finishes its queue and saves,
then the loop closer saves its database; the eraser, which the mapper asks for masks while it
works through its queue, stops after it; the recorder closes its file last) and starts them in the
reverse order (every consumer listens before its producer sends).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass


class Launch(str, enum.Enum):
    """When ``vings launch`` starts a node."""

    ALWAYS = "always"           # part of the graph (``--no-mapper`` leaves the mapper out)
    ON_REQUEST = "on_request"   # only when an option asks for it (``--record`` starts the recorder)


@dataclass(frozen=True)
class NodeSpec:
    """One node of the graph.

    ``name``: the ROS node name, its console script (``ros2 run vings_ros NAME``) and the params
    section of its settings. ``module``: ``python -m MODULE`` starts it and ``MODULE:main`` is the
    console script. ``config``: ``"module:Class"`` of its settings dataclass (params section
    ``name``; keep the module free of rclpy so ``vings run --params`` checks it without ROS); ``""``
    = no settings. ``reads``: the library sections it builds configs from (``frontend``,
    ``mapping``, ``run``, ...). ``stop_timeout_s``: how long ``vings launch`` waits after SIGINT
    before it kills the node (settings with ``shutdown_timeout_s`` extend it, see launch.py).
    ``optional``: the graph goes on without it when it exits (``vings launch`` reports the exit and
    keeps the other nodes running), as tracking and mapping do without the loop closer.
    """

    name: str
    module: str
    config: str = ""
    reads: tuple[str, ...] = ()
    stop_timeout_s: float = 20.0
    launch: Launch = Launch.ALWAYS
    optional: bool = False


NODES: tuple[NodeSpec, ...] = (
    NodeSpec("frontend_node", "vings_ros.frontend_node", "vings_ros.node_config:FrontendNodeConfig",
             reads=("frontend", "vio", "exchange", "loop")),
    NodeSpec("mapper_node", "vings_ros.mapper_node", "vings_ros.node_config:MapperNodeConfig",
             reads=("mapping", "loop", "eraser"), stop_timeout_s=180.0),
    NodeSpec("loop_closer_node", "vings_ros.loop_closer_node", "vings_ros.node_config:LoopCloserNodeConfig",
             reads=("loop",), stop_timeout_s=60.0, optional=True),
    NodeSpec("eraser_node", "vings_ros.eraser_node", "vings_ros.node_config:EraserNodeConfig",
             reads=("eraser",), stop_timeout_s=30.0, optional=True),
    NodeSpec("recorder_node", "vings_ros.recorder", launch=Launch.ON_REQUEST),
    NodeSpec("rerun_node", "vings_ros.rerun_node", launch=Launch.ON_REQUEST, optional=True),
)

#: the shared settings section of every node (frames, diagnostics rate): vings_ros.node_config.RosConfig
SHARED_SECTION = "ros"
SHARED_CONFIG = "vings_ros.node_config:RosConfig"


def node_spec(name: str) -> NodeSpec:
    """The registry entry of node ``name`` (``KeyError`` naming the known nodes otherwise)."""
    for spec in NODES:
        if spec.name == name:
            return spec
    raise KeyError(f"no VINGS node {name!r}; known: {', '.join(n.name for n in NODES)}")


def node_names() -> tuple[str, ...]:
    return tuple(n.name for n in NODES)


def console_scripts() -> list[str]:
    """``setup.py`` console scripts of the nodes: ``NAME = MODULE:main``."""
    return [f"{n.name} = {n.module}:main" for n in NODES]


def params_sections() -> dict[str, tuple[str, ...]]:
    """The graph's own params sections and node blocks, for the library's params reader: the
    ``vings.params_sections`` entry point of setup.py, so that ``vings_core`` (which knows no node)
    accepts the shipped params file: ``sections``: the shared section and every node's settings
    section; ``nodes``: the node blocks read besides ``/**``."""
    return {"sections": (SHARED_SECTION, *(n.name for n in NODES if n.config)), "nodes": node_names()}

