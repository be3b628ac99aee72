"""Stage configuration: one dataclass per stage, loaded from ROS-format params YAML.

A params file is what ``--ros-args --params-file`` reads::

    /**:                      # every node (or a node name: that node's block)
      ros__parameters:
        frontend:             # stage section
          keyframe_flow_px: 2.4

``vings run --params FILE`` reads the same file: :func:`load_section` merges the ``/**`` block and
the blocks of the nodes the caller names, then picks one section. Which sections a file may hold
and which node blocks are read is a :class:`ParamsLayout`: the library's own sections
(:data:`LIBRARY_SECTIONS`) unless the caller (an application with its own sections, such as the ROS
node graph) gives one. Unknown sections and keys and values of the wrong type raise a
:class:`ConfigError` naming the file and key.
"""
from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import enum
import functools
import importlib
import importlib.metadata
import math
import os
import re
import typing
from pathlib import Path
from typing import Any, Iterable, Iterator, Optional, Type, TypeVar

import yaml

from .errors import ConfigError
from .util import describe_yaml_error, read_utf8_text

C = TypeVar("C")


#: the library's stage sections of ``ros__parameters`` -> their config dataclass ("module:Class")
LIBRARY_SECTIONS: dict[str, str] = {
    "frontend": "vings_core.frontend.config:FrontendConfig",
    "vio": "vings_core.vio.config:ViConfig",
    "mapping": "vings_core.mapping.config:MapperConfig",
    "run": "vings_core.pipeline:RunConfig",
    "exchange": "vings_core.exchange:ExchangeConfig",
    "loop": "vings_core.loop:LoopConfig",
    "eraser": "vings_core.eraser:EraserConfig",
}

#: parameters rclpy itself declares or reads (``qos_overrides.*`` too): not a VINGS section
ROS_BUILTIN_KEYS = ("use_sim_time", "start_type_description_service", "qos_overrides")


def config_class(ref: str) -> type:
    """The class a ``"module:Class"`` reference names (see :data:`LIBRARY_SECTIONS`)."""
    module, _, name = ref.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclasses.dataclass(frozen=True)
class ParamsLayout:
    """What a params file holds for its reader.

    ``sections``: the sections of ``ros__parameters`` (another one is a :class:`ConfigError`).
    ``nodes``: node names whose blocks are read besides ``/**``; the blocks of other nodes (RViz,
    a camera driver) are checked for their ``ros__parameters`` mapping and otherwise skipped."""

    sections: tuple[str, ...]
    nodes: tuple[str, ...] = ()


#: entry-point group through which an installed application (the ROS graph: vings_ros) names the
#: params sections and node blocks of its own that a params file may hold besides the library's
PARAMS_SECTIONS_GROUP = "vings.params_sections"


@functools.lru_cache(maxsize=1)
def installed_layout() -> ParamsLayout:
    """The library's sections plus those every installed application declares (entry points of
    :data:`PARAMS_SECTIONS_GROUP`: a callable returning ``{"sections": (...), "nodes": (...)}``)."""
    sections, nodes = list(LIBRARY_SECTIONS), []
    for ep in importlib.metadata.entry_points(group=PARAMS_SECTIONS_GROUP):
        try:
            more = ep.load()()
        except Exception as e:  # noqa: BLE001 - a broken plug-in names itself, it does not crash the reader
            raise ConfigError(f"params sections of {ep.value} ({PARAMS_SECTIONS_GROUP}) could not be "
                              f"loaded: {type(e).__name__}: {e}") from None
        sections += list(more.get("sections", ()))
        nodes += list(more.get("nodes", ()))
    return ParamsLayout(tuple(dict.fromkeys(sections)), tuple(dict.fromkeys(nodes)))


#: the layout a reader uses when its caller names none (None: :func:`installed_layout`); see
#: :func:`params_layout`
_LAYOUT: contextvars.ContextVar[Optional[ParamsLayout]] = contextvars.ContextVar("vings_params_layout",
                                                                                 default=None)


def _active_layout() -> ParamsLayout:
    layout = _LAYOUT.get()
    return installed_layout() if layout is None else layout


@contextlib.contextmanager
def params_layout(layout: ParamsLayout) -> Iterator[ParamsLayout]:
    """Within the block, :func:`read_params_file` and :func:`load_section` calls that name no
    ``sections`` / ``nodes`` use ``layout``: library code (``SlamRunner``) reading an
    application's file, e.g. the ROS graph's with its node sections."""
    token = _LAYOUT.set(layout)
    try:
        yield layout
    finally:
        _LAYOUT.reset(token)


class _RosYamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2 floats, as rcl reads them: ``1e-4`` is a number (YAML
    1.1, PyYAML's default, makes it a string unless written ``1.0e-4``)."""


_RosYamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"""),
    list("-+0123456789."))


def ros_yaml_load(text: str) -> Any:
    """Parse a params file or a ``-p name:=value`` value the way rcl types it."""
    return yaml.load(text, Loader=_RosYamlLoader)  # noqa: S506 - a SafeLoader subclass


def read_params_file(path: str | os.PathLike, sections: Optional[Iterable[str]] = None,
                     strict: bool = True, nodes: Optional[Iterable[str]] = None) -> dict:
    """Merged ``ros__parameters`` of the ``/**`` block and the blocks of ``nodes`` of a ROS 2
    params YAML (``/**`` first).

    Dotted names (``mapping.window_size: 4``, valid ROS 2 params syntax) are expanded into their
    sections; a section other than ``sections`` (e.g. a misspelt ``mappping``) is a
    :class:`ConfigError`, as the nodes treat it; with ``strict=False`` other keys (rclpy's
    ``use_sim_time``, ``qos_overrides``) are left out instead. ``sections`` / ``nodes`` default to
    the active :class:`ParamsLayout` (:func:`params_layout`; the library's sections and ``/**``
    alone otherwise). Every block must have a ``ros__parameters`` mapping. Lists rcl cannot hold
    (mixed types, empty) are refused in either case."""
    layout = _active_layout()
    sections = tuple(layout.sections if sections is None else sections)
    ours = ("**", *(layout.nodes if nodes is None else nodes))
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: params file not found")
    text = read_utf8_text(path, "params file", ConfigError)
    try:
        doc = ros_yaml_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: {describe_yaml_error(e)}") from None
    if doc is None:     # empty or comments only: most likely the wrong file, never "all defaults"
        raise ConfigError(f"{path}: the params file is empty (or only comments); give a file with "
                          f"'/**: {{ros__parameters: ...}}', or no params file for the defaults")
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: top level must be a mapping of node names")
    merged: dict = {}
    keys = sorted(doc, key=lambda k: k != "/**")
    for node in keys:
        block = doc[node]
        if not isinstance(block, dict) or "ros__parameters" not in block:
            raise ConfigError(f"{path}: node block {node!r} has no 'ros__parameters' mapping")
        params = block["ros__parameters"] or {}
        if not isinstance(params, dict):
            raise ConfigError(f"{path}: node block {node!r}: 'ros__parameters' must be a mapping of "
                              f"sections, got {params!r}")
        if str(node).rstrip("/").split("/")[-1] not in ours:
            continue                  # another node's block (rviz, a camera driver): not ours
        _deep_merge(merged, _expand_dotted(params, f"{path}: node block {node!r}"))
    _check_ros_lists(merged, f"{path}")
    for k in ROS_BUILTIN_KEYS:        # rclpy's own: the nodes accept them, so does vings run
        merged.pop(k, None)
    unknown = [k for k in merged if k not in sections]
    if unknown and not strict:      # rclpy's own (use_sim_time, qos_overrides) or other nodes' keys
        return {k: v for k, v in merged.items() if k in sections}
    if unknown:
        raise ConfigError(f"{path}: unknown parameter section(s) {', '.join(map(repr, unknown))}; "
                          f"parameters live in the sections {', '.join(sections)} "
                          f"(e.g. mapping: {{window_size: 8}} or mapping.window_size: 8)")
    return merged


def _check_ros_lists(d: dict, where: str, prefix: str = "") -> None:
    """Lists as ROS 2 parameters can hold them: non-empty, one scalar type (rcl refuses ``[0, 0.5]``
    and ``[]`` when a node starts, so ``vings run --params`` refuses them too: one file, one meaning)."""
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            _check_ros_lists(v, where, name + ".")
        elif isinstance(v, list):
            if not v:
                raise ConfigError(f"{where}: {name}: an empty list is not a valid ROS 2 parameter; "
                                  f"leave the key out for the default")
            kinds = {type(x) for x in v}
            if len(kinds) > 1 or not kinds <= {bool, int, float, str}:
                raise ConfigError(f"{where}: {name}: ROS 2 list parameters hold one scalar type, got "
                                  f"{v!r} ({', '.join(sorted(t.__name__ for t in kinds))}); write "
                                  f"floats as 0.0, not 0")


def _expand_dotted(d: dict, where: str) -> dict:
    """``{'mapping.window_size': 4, 'mapping': {'k': 1}} -> {'mapping': {'window_size': 4, 'k': 1}}``."""
    out: dict = {}
    for k, v in d.items():
        v = _expand_dotted(v, where) if isinstance(v, dict) else v
        parts = str(k).split(".")
        for name in reversed(parts[1:]):
            v = {name: v}
        if parts[0] in out and isinstance(out[parts[0]], dict) and isinstance(v, dict):
            _merge_new(out[parts[0]], v, f"{where}: parameter {k!r}")
        elif parts[0] in out:
            raise ConfigError(f"{where}: parameter {k!r} is given twice")
        else:
            out[parts[0]] = v
    return out


def _merge_new(dst: dict, src: dict, what: str) -> None:
    """Merge ``src`` into ``dst`` where a value given twice (``run.x: 1`` beside ``run: {x: 2}``)
    is an error, not a silent override."""
    for k, v in src.items():
        if isinstance(v, dict) and isinstance(dst.get(k), dict):
            _merge_new(dst[k], v, what)
        elif k in dst:
            raise ConfigError(f"{what}: {k!r} is given twice")
        else:
            dst[k] = v


def _deep_merge(dst: dict, src: dict) -> None:
    for k, v in src.items():
        if isinstance(v, dict) and isinstance(dst.get(k), dict):
            _deep_merge(dst[k], v)
        else:
            dst[k] = v


def flatten(d: dict, prefix: str = "") -> dict:
    """``{'a': {'b': 1}} -> {'a.b': 1}`` (ROS parameter names use dots)."""
    out = {}
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, name + "."))
        else:
            out[name] = v
    return out


def config_from_dict(cls: Type[C], values: dict, where: str = "params") -> C:
    """Build dataclass ``cls`` from ``values`` with type checks; unknown keys are errors."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls} is not a dataclass")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, val in (values or {}).items():
        if key not in fields:
            renamed = getattr(cls, "RENAMED", {}).get(key)
            if renamed:
                raise ConfigError(f"{where}: parameter {key!r} was replaced by {renamed}")
            raise ConfigError(f"{where}: unknown parameter {key!r}; known: {', '.join(sorted(fields))}")
        kwargs[key] = _coerce(hints[key], val, f"{where}.{key}")
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {e}") from None
    validate = getattr(obj, "validate", None)
    if callable(validate):
        try:
            validate()
        except ValueError as e:
            raise ConfigError(f"{where}: {e}") from None
    return obj


def _coerce(tp: Any, val: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Union:
        if val is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(inner[0], val, where)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        if isinstance(val, tp):
            return val
        allowed = [m.value for m in tp]
        if val in allowed:
            return tp(val)
        raise ConfigError(f"{where}: expected one of {', '.join(map(repr, allowed))}, got {val!r}")
    if tp is bool:
        if isinstance(val, bool):
            return val
        raise ConfigError(f"{where}: expected true/false, got {val!r}")
    if tp is int:
        if isinstance(val, int) and not isinstance(val, bool):
            return val
        raise ConfigError(f"{where}: expected an integer, got {val!r}")
    if tp is float:
        if isinstance(val, (int, float)) and not isinstance(val, bool):
            if not math.isfinite(val):
                raise ConfigError(f"{where}: expected a finite number, got {val!r}")
            return float(val)
        raise ConfigError(f"{where}: expected a number, got {val!r}")
    if tp is str:
        if isinstance(val, str):
            return val
        raise ConfigError(f"{where}: expected a string, got {val!r}")
    if origin in (list, tuple):
        if not isinstance(val, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {val!r}")
        el = args[0] if args else Any
        items = [_coerce(el, v, f"{where}[{i}]") if el is not Any and el is not Ellipsis else v
                 for i, v in enumerate(val)]
        return tuple(items) if origin is tuple else items
    return val


def load_section(cls: Type[C], section: str, params_file: str | os.PathLike | None = None,
                 overrides: dict | None = None, sections: Optional[Iterable[str]] = None,
                 nodes: Optional[Iterable[str]] = None) -> C:
    """Config dataclass ``cls`` from section ``section`` of ``params_file`` (defaults if None);
    ``sections`` / ``nodes``: what the file holds for this reader (:func:`read_params_file`)."""
    values: dict = {}
    where = section
    if params_file is not None:
        merged = read_params_file(params_file, sections, nodes=nodes)
        sec = merged.get(section, {})
        if not isinstance(sec, dict):
            raise ConfigError(f"{params_file}: section {section!r} must be a mapping")
        values.update(sec)
        where = f"{params_file}: {section}"
    if overrides:
        values.update(overrides)
    return config_from_dict(cls, values, where)
