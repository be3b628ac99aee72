"""Small shared helpers: atomic file writes, logging set-up."""
from __future__ import annotations

import json
import logging
import os
import tempfile
import threading
import zipfile
from glob import escape as glob_escape
from pathlib import Path
from typing import Any, Callable

from .errors import VingsError

log = logging.getLogger("vings")

#: what reading a missing, truncated or foreign ``.npz`` (np.load) can raise
NPZ_READ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


def _process_umask() -> int:
    old = os.umask(0o022)   # read at import (single-threaded): os.umask can only be read by setting
    os.umask(old)
    return old


_FILE_MODE = 0o666 & ~_process_umask()


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a file's data (or a folder's entries, after a rename in it) to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Call ``write(tmp_path)`` then rename ``tmp_path`` onto ``path`` (same folder, atomic on POSIX).

    A crash leaves either the old file or the new one, never a half-written one. The file gets the
    mode a plain ``open`` would give it (``0666`` less the umask; temporary files are ``0600``). An
    ``OSError`` (folder not writable, disk full) becomes a :class:`VingsError` naming ``path``.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
        write(tmp)
        fsync_path(tmp)
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException as e:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise VingsError(f"{path}: cannot write ({e.strerror or e})") from e
        raise


def remove_stale_temps(path: str | os.PathLike) -> int:
    """Delete the temporary files :func:`atomic_write` left beside ``path`` when its process was
    killed mid-write (``.<name>.*.tmp``); call it before a process starts writing ``path``.
    Returns how many were removed."""
    path = Path(path)
    n = 0
    for tmp in path.parent.glob(f".{glob_escape(path.name)}.*.tmp"):
        try:
            tmp.unlink()
            n += 1
        except OSError:
            pass
    return n


def read_utf8_text(path: str | os.PathLike, kind: str, error: type = VingsError) -> str:
    """The text of ``path`` (UTF-8). A binary / non-UTF-8 or unreadable file raises ``error`` (a
    :class:`VingsError` subclass) naming the file and ``kind`` (e.g. "params file"), one line."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not UTF-8 text (byte {e.start}); is this a {kind}?") from None
    except OSError as e:
        raise error(f"{path}: cannot read the {kind} ({e.strerror or e})") from None


def describe_yaml_error(e: Exception) -> str:
    """One line for a PyYAML error: where (line, column) and what, without its multi-line excerpt."""
    mark = getattr(e, "problem_mark", None)
    at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    why = getattr(e, "problem", None) or (str(e).splitlines() or [type(e).__name__])[0]
    return f"not valid YAML{at}: {why}"


def _write_test(d: Path) -> None:
    """Make and remove a temporary file in folder ``d``; raises ``OSError``. (``os.access`` is not
    enough: it says yes to root where a write fails.)"""
    fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=d)
    os.close(fd)
    os.unlink(probe)


def probe_writable_dir(d: str | os.PathLike) -> None:
    """Create folder ``d`` if needed and write-test it; raises ``OSError``."""
    d = Path(d)
    d.mkdir(parents=True, exist_ok=True)
    _write_test(d)


def check_output_file(path: str | os.PathLike, what: str, error: type = VingsError) -> Path:
    """Before a long job: ``path`` (``~`` expanded; the returned path) can be written as a file: not
    a folder, and its nearest existing folder is write-tested (missing folders are created only
    when the file is written). Raises ``error`` (a :class:`VingsError` subclass) naming ``what``
    (e.g. the option)."""
    path = Path(path).expanduser().absolute()
    if path.is_dir():
        raise error(f"{what} {path}: is a folder; give a file name")
    base = path.parent
    while not base.exists() and base != base.parent:
        base = base.parent
    try:
        if not base.is_dir():
            raise NotADirectoryError(20, f"{base} is not a folder")
        _write_test(base)
    except OSError as e:
        raise error(f"{what} {path}: cannot write there ({e.strerror or e})") from None
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    def _w(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text)
    atomic_write(path, _w)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    def _w(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)
    atomic_write(path, _w)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    import numpy as np
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="[vings] %(levelname)s %(message)s")


def nice_current_thread(increment: int) -> bool:
    """Add ``increment`` (0-19) to the niceness of the calling thread alone (Linux: a thread is a
    task with its own priority), so that a background stage yields the CPU to tracking. Threads it
    starts later inherit it. Returns False where the platform does not allow it."""
    if increment <= 0:
        return True
    try:
        tid = threading.get_native_id()
        cur = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, cur + increment))
        return True
    except (AttributeError, OSError):
        return False
