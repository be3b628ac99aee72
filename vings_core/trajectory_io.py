"""TUM trajectory files: ``stamp tx ty tz qx qy qz qw`` per line, stamps in seconds written with
9 decimals so that nanosecond stamps survive a round trip. Writes are atomic."""
from __future__ import annotations

import os
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from .errors import InputError
from .geometry import np_quat_to_rotmat, np_rotmat_to_quat
from .types import Trajectory
from .util import atomic_write_text, read_utf8_text


def stamp_ns_to_str(stamp_ns: int) -> str:
    """Nanoseconds -> seconds string with exactly 9 decimals (exact, no float rounding)."""
    s = int(stamp_ns)
    sign = "-" if s < 0 else ""
    s = abs(s)
    return f"{sign}{s // 1_000_000_000}.{s % 1_000_000_000:09d}"


def sec_nsec_to_ns(sec: int, nsec: int, where: str) -> int:
    """ROS time ``(sec, nanosec)`` -> int nanoseconds; ``nanosec`` outside ``[0, 1e9)`` (a corrupt
    message or a writer bug) is an :class:`InputError` naming ``where``."""
    sec, nsec = int(sec), int(nsec)
    if not 0 <= nsec < 1_000_000_000:
        raise InputError(f"{where} nanoseconds {nsec} outside [0, 1e9) (sec {sec}): corrupt message "
                         f"or a writer bug")
    return sec * 1_000_000_000 + nsec


def str_to_stamp_ns(text: str) -> int:
    """Seconds string (any number of decimals, or exponent form) -> int nanoseconds, exact.

    Stamps must be seconds within int64 nanoseconds (|t| < ~292 years); a larger number is
    most likely a stamp in ns / us / ms and is a ValueError saying so."""
    try:
        d = Decimal(text)
    except InvalidOperation as e:
        raise ValueError(f"not a time stamp: {text!r}") from e
    if not d.is_finite():
        raise ValueError(f"not a finite time stamp: {text!r}")
    ns = int((d * 1_000_000_000).to_integral_value())
    if abs(ns) >= 2 ** 63:
        raise ValueError(f"time stamp {text} is out of range for seconds; stamps must be in seconds "
                         f"(this looks like nanoseconds, microseconds or milliseconds)")
    return ns


def format_tum(traj: Trajectory) -> str:
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    q = np_rotmat_to_quat(traj.poses[:, :3, :3]) if len(traj) else np.zeros((0, 4))
    for s, T, qq in zip(traj.stamps_ns, traj.poses, q):
        t = T[:3, 3]
        lines.append(f"{stamp_ns_to_str(int(s))} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} "
                     f"{qq[0]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f}")
    return "\n".join(lines) + "\n"


def write_tum(path: str | os.PathLike, traj: Trajectory) -> None:
    """Write a TUM file atomically (temp file + rename)."""
    atomic_write_text(path, format_tum(traj))


def read_tum(path: str | os.PathLike) -> Trajectory:
    """Read a TUM trajectory; raises :class:`InputError` naming the file and line on bad content."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: trajectory file not found")
    text = read_utf8_text(path, "trajectory file", InputError)
    stamps, poses = [], []
    for ln, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(f"{path}:{ln}: expected 8 columns 'stamp tx ty tz qx qy qz qw', "
                             f"got {len(parts)}")
        try:
            stamp = str_to_stamp_ns(parts[0])
            vals = np.array([float(v) for v in parts[1:]])
        except ValueError as e:
            raise InputError(f"{path}:{ln}: {e}") from None
        if not np.all(np.isfinite(vals)):
            raise InputError(f"{path}:{ln}: non-finite value")
        qn = np.linalg.norm(vals[3:])
        if qn < 1e-6:
            raise InputError(f"{path}:{ln}: zero quaternion")
        T = np.eye(4)
        T[:3, :3] = np_quat_to_rotmat(vals[3:] / qn)
        T[:3, 3] = vals[:3]
        stamps.append(stamp)
        poses.append(T)
    if not stamps:
        raise InputError(f"{path}: no poses in trajectory file")
    stamps = np.array(stamps, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    if np.any(np.diff(stamps[order]) == 0):
        raise InputError(f"{path}: duplicated time stamps")
    return Trajectory(stamps[order], np.stack(poses)[order])
