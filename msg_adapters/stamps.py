"""Exact conversions between ``int`` nanosecond stamps and ``builtin_interfaces/Time``.

ROS time is ``sec`` (int32, any sign) plus ``nanosec`` in ``[0, 1e9)``; ``divmod`` keeps it exact for
every stamp (no float rounding), including negative ones.
"""
from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from std_msgs.msg import Header

from vings_core.errors import InputError
from vings_core.trajectory_io import sec_nsec_to_ns

NS_PER_S = 1_000_000_000
_INT32_MIN, _INT32_MAX = -(2 ** 31), 2 ** 31 - 1


def ns_to_time(stamp_ns: int, where: str = "stamp") -> Time:
    """``int`` nanoseconds -> ``builtin_interfaces/Time`` (exact)."""
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, (int, np.integer)):
        # a float would be taken at face value: 1.7e9 (seconds) as 1.7 s of nanoseconds
        raise InputError(f"{where}: stamp must be an integer number of nanoseconds, "
                         f"got {stamp_ns!r}")
    ns = int(stamp_ns)
    sec, nanosec = divmod(ns, NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise InputError(f"{where}: stamp {ns} ns does not fit builtin_interfaces/Time "
                         f"(int32 seconds)")
    return Time(sec=sec, nanosec=nanosec)


def time_to_ns(t: Time, where: str = "stamp") -> int:
    """``builtin_interfaces/Time`` (or anything with ``sec``/``nanosec``) -> ``int`` nanoseconds."""
    return sec_nsec_to_ns(t.sec, t.nanosec, where)


def make_header(stamp_ns: int, frame_id: str, where: str = "header") -> Header:
    """``std_msgs/Header`` with an exact stamp."""
    return Header(stamp=ns_to_time(stamp_ns, f"{where}.stamp"), frame_id=str(frame_id))


def header_ns(header: Header, where: str = "header") -> int:
    """Stamp of a ``std_msgs/Header`` in nanoseconds."""
    return time_to_ns(header.stamp, f"{where}.stamp")
