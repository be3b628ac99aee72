"""``diagnostic_msgs/DiagnosticArray`` from plain dicts, and back.

A node publishes one DiagnosticStatus per stage (``name`` like ``vings/frontend``) with a level,
a one-line message and key/value pairs (rates, queue lengths, drop counts, Gaussian counts,
memory). Values are strings on the wire: floats with 6 significant digits, bools as true/false.
"""
from __future__ import annotations

from typing import Any, Iterable, Mapping, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from vings_core.errors import InputError

from .stamps import header_ns, make_header

LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN,
          "error": DiagnosticStatus.ERROR, "stale": DiagnosticStatus.STALE}
_LEVEL_NAMES = {v: k for k, v in LEVELS.items()}

#: diagnostic level of each front-end tracking state
TRACKING_STATE_LEVEL = {"waiting": "warn", "tracking": "ok", "lost": "error", "inertial": "warn"}


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.6g}"
    if hasattr(v, "item") and getattr(v, "ndim", 1) == 0:  # numpy / torch scalar
        return _fmt(v.item())
    return str(v)


def make_status(name: str, level: str, message: str, values: Optional[Mapping[str, Any]] = None,
                hardware_id: str = "vings") -> DiagnosticStatus:
    """One DiagnosticStatus; ``level`` is ``ok``, ``warn``, ``error`` or ``stale``."""
    if level not in LEVELS:
        raise InputError(f"diagnostics {name!r}: unknown level {level!r}; expected one of "
                         f"{', '.join(LEVELS)}")
    return DiagnosticStatus(level=LEVELS[level], name=str(name), message=str(message),
                            hardware_id=str(hardware_id),
                            values=[KeyValue(key=str(k), value=_fmt(v))
                                    for k, v in (values or {}).items()])


def tracking_status(name: str, state: str, values: Optional[Mapping[str, Any]] = None,
                    message: Optional[str] = None) -> DiagnosticStatus:
    """Status for a tracking state (``waiting`` -> warn, ``tracking`` -> ok, ``lost`` -> error);
    the state is also stored under the key ``state``."""
    if state not in TRACKING_STATE_LEVEL:
        raise InputError(f"diagnostics {name!r}: unknown tracking state {state!r}; expected one "
                         f"of {', '.join(TRACKING_STATE_LEVEL)}")
    vals = {"state": state}
    vals.update(values or {})
    return make_status(name, TRACKING_STATE_LEVEL[state], message or state, vals)


def diagnostic_array(stamp_ns: int, statuses: Iterable[DiagnosticStatus]) -> DiagnosticArray:
    return DiagnosticArray(header=make_header(stamp_ns, "", "diagnostics"), status=list(statuses))


def parse_diagnostic_array(msg: DiagnosticArray, where: str = "diagnostics") -> dict:
    """DiagnosticArray -> ``{"stamp_ns": int, "status": {name: {"level", "message",
    "hardware_id", "values": {key: str}}}}``."""
    out: dict = {"stamp_ns": header_ns(msg.header, f"{where}.header"), "status": {}}
    for st in msg.status:
        lvl = bytes(st.level)
        if lvl not in _LEVEL_NAMES:
            raise InputError(f"{where}: status {st.name!r} has unknown level {lvl!r}")
        out["status"][st.name] = {"level": _LEVEL_NAMES[lvl], "message": st.message,
                                  "hardware_id": st.hardware_id,
                                  "values": {kv.key: kv.value for kv in st.values}}
    return out


__all__ = ["LEVELS", "TRACKING_STATE_LEVEL", "make_status", "tracking_status",
           "diagnostic_array", "parse_diagnostic_array"]
