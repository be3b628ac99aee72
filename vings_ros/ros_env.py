"""The process environment every VINGS ROS process runs in, and shared-memory clean-up.

:func:`ros_environment` returns the environment for a node / replay / launcher process:

* ``FASTRTPS_DEFAULT_PROFILES_FILE`` -> the shipped profile ``vings_ros/config/fastdds_shm.xml``:
  shared-memory transport with a 64 MiB segment (752x480 rgb8 at 20 Hz passes between processes
  without loss) plus UDPv4 (stock ROS tools and other hosts still see the graph).
  ``VINGS_DDS=udp`` (or ``use_shm=False``) leaves the profile out: Fast DDS built-in transports.
  With ``use_shm=None`` the profile is also left out, with a warning, when ``/dev/shm`` has less
  than :data:`MIN_SHM_FREE` bytes free (Docker's default 64 MiB). A profile file the user already
  set is left alone.
* ``ROS_LOG_DIR``: kept if set, else ``~/.ros/log`` when writable, else a per-user temp folder.
* ``AMENT_PREFIX_PATH`` includes ``sys.prefix`` so ``ament_index_python`` finds this package when
  it was pip-installed into a venv.
* ``ROS_DOMAIN_ID`` when ``domain_id`` is given.

It must be applied before ``rclpy.init()`` (Fast DDS reads it when the participant is created):
pass it as ``env=`` to child processes, or call :func:`apply_ros_environment` in-process.

Fast DDS leaves ``/dev/shm/fastrtps_*`` files behind when a process dies uncleanly.
:func:`cleanup_fastdds_shm` removes only files that (a) appeared after a snapshot / time the caller
took before starting its processes and (b) no live process holds: each segment and port has a lock
file (``_el`` exclusive / ``_sl`` shared) that Fast DDS keeps ``flock``-ed while its owner lives.
"""
from __future__ import annotations

import fcntl
import logging
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, Optional, Union

from vings_core.errors import ConfigError

log = logging.getLogger("vings.ros_env")

SHM_DIR = Path("/dev/shm")
PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
TRANSPORT_ENV = "VINGS_DDS"
#: ROS 2 Jazzy's discovery range; ros_environment() sets LOCALHOST unless the user set it
DISCOVERY_RANGE_ENV = "ROS_AUTOMATIC_DISCOVERY_RANGE"
TRANSPORTS = ("shm", "udp")
SEGMENT_BYTES = 64 * 2 ** 20                  # keep equal to segment_size in fastdds_shm.xml
MIN_SHM_FREE = 4 * (SEGMENT_BYTES + 2 ** 22)  # a few processes' segments must fit in /dev/shm
_PROFILE_ENVS = (PROFILE_ENV, "FASTDDS_DEFAULT_PROFILES_FILE")


def shm_profile_path() -> Path:
    """Absolute path of the shipped shared-memory Fast DDS profile."""
    return Path(__file__).resolve().parent / "config" / "fastdds_shm.xml"


def dds_transport(env: Optional[Mapping[str, str]] = None) -> str:
    """``shm`` (default) or ``udp``, from ``VINGS_DDS`` in ``env`` (``os.environ`` if None)."""
    env = os.environ if env is None else env
    val = env.get(TRANSPORT_ENV, "shm").strip().lower() or "shm"
    if val not in TRANSPORTS:
        raise ConfigError(f"{TRANSPORT_ENV}={env.get(TRANSPORT_ENV)!r}: expected one of "
                          f"{', '.join(TRANSPORTS)}")
    return val


def default_log_dir() -> Path:
    """``~/.ros/log`` if it is (or can be made) writable, else ``<tmp>/vings-ros-log-<uid>``."""
    home = Path(os.path.expanduser("~")) / ".ros" / "log"
    try:
        home.mkdir(parents=True, exist_ok=True)
        if os.access(home, os.W_OK):
            return home
    except OSError:
        pass
    return Path(tempfile.gettempdir()) / f"vings-ros-log-{os.getuid()}"


def _shm_has_room() -> bool:
    try:
        free = shutil.disk_usage(SHM_DIR).free
    except OSError:
        log.warning("%s is not available: using Fast DDS built-in transports (UDP)", SHM_DIR)
        return False
    if free < MIN_SHM_FREE:
        log.warning("%s has only %.0f MiB free (< %.0f MiB): not using the shared-memory DDS "
                    "profile; images go over UDP (enlarge /dev/shm, e.g. docker --shm-size=1g)",
                    SHM_DIR, free / 2 ** 20, MIN_SHM_FREE / 2 ** 20)
        return False
    return True


def ros_environment(domain_id: Optional[int] = None, use_shm: Optional[bool] = None,
                    log_dir: Optional[Union[str, os.PathLike]] = None,
                    base: Optional[Mapping[str, str]] = None) -> dict:
    """Environment (a new dict: ``base`` or ``os.environ`` plus the ROS settings) for a VINGS ROS
    process. ``use_shm=None`` follows ``VINGS_DDS`` (default shared memory). Discovery stays on
    this host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) unless the variable is set already
    (``SUBNET``: nodes on separate hosts)."""
    env = dict(os.environ if base is None else base)
    ours = str(shm_profile_path())
    if use_shm is None:
        use_shm = dds_transport(env) == "shm" and _shm_has_room()
    user_profile = next((env[k] for k in _PROFILE_ENVS if env.get(k) and env[k] != ours), None)
    if use_shm:
        if user_profile is None:
            if not Path(ours).is_file():
                raise ConfigError(f"{ours}: shipped Fast DDS profile is missing (broken install)")
            env[PROFILE_ENV] = ours
    else:
        for k in _PROFILE_ENVS:  # inherited from a parent vings process: drop ours only
            if env.get(k) == ours:
                del env[k]
    if domain_id is not None:
        d = int(domain_id)
        if not 0 <= d <= 232:
            raise ConfigError(f"ROS_DOMAIN_ID {d} is outside 0..232")
        env["ROS_DOMAIN_ID"] = str(d)
    elif env.get("ROS_DOMAIN_ID", "").strip():
        # an inherited value rcl cannot use fails deep inside rclpy.init(): say it here
        v = env["ROS_DOMAIN_ID"].strip()
        if not (v.isdigit() and 0 <= int(v) <= 232):
            raise ConfigError(f"environment variable ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']!r} is not an "
                              f"integer in 0..232 (unset it or give --domain-id)")
    if not env.get(DISCOVERY_RANGE_ENV, "").strip():
        # the graph stays on this host unless asked (docs/ros.md "Hosts apart": SUBNET)
        env[DISCOVERY_RANGE_ENV] = "LOCALHOST"
    if log_dir is not None:
        env["ROS_LOG_DIR"] = str(log_dir)
    elif not env.get("ROS_LOG_DIR"):
        env["ROS_LOG_DIR"] = str(default_log_dir())
    prefixes = [p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if sys.prefix not in prefixes:
        prefixes.append(sys.prefix)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(prefixes)
    return env


def apply_ros_environment(domain_id: Optional[int] = None, use_shm: Optional[bool] = None,
                          log_dir: Optional[Union[str, os.PathLike]] = None) -> dict:
    """Apply :func:`ros_environment` to ``os.environ`` (call before ``rclpy.init()``); returns
    the variables that changed ``{name: new value or None if removed}``."""
    new = ros_environment(domain_id, use_shm, log_dir)
    changed = {k: v for k, v in new.items() if os.environ.get(k) != v}
    changed.update({k: None for k in os.environ if k not in new})
    for k, v in changed.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    Path(new["ROS_LOG_DIR"]).mkdir(parents=True, exist_ok=True)
    return changed


# ------------------------------------------------------------------------ shared-memory clean-up


@dataclass(frozen=True)
class ShmSnapshot:
    """Names under the shm folder at a moment (take it before starting processes)."""

    taken_at: float
    names: frozenset


def shm_snapshot(shm_dir: Union[str, os.PathLike] = SHM_DIR) -> ShmSnapshot:
    try:
        names = frozenset(os.listdir(shm_dir))
    except FileNotFoundError:
        names = frozenset()
    return ShmSnapshot(time.time(), names)


@dataclass
class ShmGroup:
    """One Fast DDS segment or port: its data file, lock file and (ports) named semaphore.

    ``lock`` is None for an orphaned port: its owner closed it (removing the lock file) but could
    not unlink it because a process that had it open as a sender was killed."""

    name: str               # fastrtps_<16 hex> or fastrtps_port<N>
    lock: Optional[str]     # name of the _el / _sl lock file
    files: list             # existing file names of the group


def _is_fastdds(name: str) -> bool:
    return name.startswith("fastrtps_") or name.startswith("fastdds_")


def fastdds_shm_groups(shm_dir: Union[str, os.PathLike] = SHM_DIR) -> list:
    """Fast DDS segments and ports under ``shm_dir``, grouped by their lock file (plus orphaned
    ports, which have none)."""
    try:
        names = set(os.listdir(shm_dir))
    except FileNotFoundError:
        return []
    groups = []
    grouped: set = set()
    for n in sorted(names):
        if _is_fastdds(n) and n.endswith(("_el", "_sl")):
            base = n[:-3]
            files = [f for f in (base, n, f"sem.{base}_mutex") if f in names]
            groups.append(ShmGroup(base, n, files))
            grouped.add(base)
    for n in sorted(names):
        if _is_fastdds(n) and "_port" in n and n[-1].isdigit() and n not in grouped \
                and f"{n}_el" not in names and f"{n}_sl" not in names:
            groups.append(ShmGroup(n, None, [f for f in (n, f"sem.{n}_mutex") if f in names]))
    return groups


def _lock_is_free(path: Path) -> bool:
    """True if nobody holds a flock on ``path`` (probe with a non-blocking exclusive lock)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return True
    finally:
        os.close(fd)


def shm_files_of(pid: int, shm_dir: Union[str, os.PathLike] = SHM_DIR) -> set:
    """Fast DDS files of a live process: the groups (data file, lock, semaphore) whose lock file it
    holds open, i.e. its own segment and ports plus the shared multicast ports (``_sl``) it
    listens on. Peers' segments it merely maps are not included. Empty if the process is gone or
    unreadable. Record them while a child runs to attribute its files exactly."""
    prefix = str(Path(shm_dir)) + "/"
    out: set = set()
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return out
    for fd in fds:
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if not target.startswith(prefix):
            continue
        name = target[len(prefix):]
        if ("fastrtps_" in name or "fastdds_" in name) and name.endswith(("_el", "_sl")):
            base = name[:-3]
            out.update((base, name, f"sem.{base}_mutex") if "_port" in base else (base, name))
    return out


def cleanup_fastdds_shm(since: Union[ShmSnapshot, float, None] = None,
                        shm_dir: Union[str, os.PathLike] = SHM_DIR, min_age_s: float = 0.5,
                        dry_run: bool = False, names: Optional[Iterable[str]] = None) -> list:
    """Remove Fast DDS shared-memory files left by dead processes.

    Which files are candidates: with ``since`` a :class:`ShmSnapshot` (groups whose lock file is
    not in it) or a ``time.time()`` value (lock file modified at or after it); with ``names``
    (e.g. collected by :func:`shm_files_of` while the processes lived) only groups with a file in
    it; at least one of the two is required, both must hold when both are given. A candidate is
    removed only if its lock file is older than ``min_age_s`` (a starting process creates, then
    locks it) and no process holds a lock on it; an orphaned port (no lock file: its owner closed
    it but a killed peer kept it referenced) only needs the age. Files of live processes, and
    files that existed before, are never touched. Returns the removed (``dry_run``: removable)
    file names.
    """
    if since is None and names is None:
        raise ValueError("cleanup_fastdds_shm needs `since` or `names` to attribute files")
    wanted = None if names is None else set(names)
    shm_dir = Path(shm_dir)
    now = time.time()
    removed = []
    for g in fastdds_shm_groups(shm_dir):
        key = g.lock if g.lock is not None else g.name  # the file whose age attributes the group
        try:
            mtime = (shm_dir / key).stat().st_mtime
        except FileNotFoundError:
            continue
        if wanted is not None and not wanted.intersection(g.files + [g.name]):
            continue
        if isinstance(since, ShmSnapshot):
            if key in since.names:
                continue
        elif since is not None and mtime < float(since):
            continue
        if now - mtime < min_age_s:
            continue
        if g.lock is not None and not _lock_is_free(shm_dir / g.lock):
            continue
        for f in g.files:
            if dry_run:
                removed.append(f)
                continue
            try:
                (shm_dir / f).unlink()
                removed.append(f)
            except FileNotFoundError:
                pass
            except OSError as e:
                log.warning("could not remove %s: %s", shm_dir / f, e)
    return removed


def fastdds_files_since(since: Union[ShmSnapshot, float],
                        shm_dir: Union[str, os.PathLike] = SHM_DIR) -> list:
    """Fast DDS file names present now that were not there at ``since`` (for tests' assertions)."""
    try:
        names = os.listdir(shm_dir)
    except FileNotFoundError:
        return []
    out = []
    for n in sorted(names):
        if not ("fastrtps_" in n or "fastdds_" in n):
            continue
        if isinstance(since, ShmSnapshot):
            if n not in since.names:
                out.append(n)
        else:
            try:
                if (Path(shm_dir) / n).stat().st_mtime >= float(since):
                    out.append(n)
            except FileNotFoundError:
                pass
    return out
