"""The mapper's input queue: FIFO, bounded in memory, spilling keyframes to disk, losing none.

Tracking must never wait for mapping, so the keyframes the mapper has not reached yet wait here.
At most ``memory_keyframes`` of them are held in memory; every later one is written to
``spill_dir`` (one ``kf-<seq>-<stamp>.pt`` file, written under a temporary name and renamed, so a
killed process leaves only whole files) and read back when its turn comes. Small messages (pose
batches) always stay in memory, in order with the keyframes. A spill file that a killed process
left behind is found again by :meth:`KeyframeQueue.recover` (the mapper node re-queues them when
it resumes).

Spill file format (``torch.save`` of a dict, read with ``weights_only=True``):

| key | type | content |
| --- | --- | --- |
| ``version`` | int | 1 |
| ``stamp_ns``, ``index`` | int | the keyframe's identity and running number |
| ``image`` | float32 (H, W, 3) | RGB in [0, 1] |
| ``T_wc`` | float64 (4, 4) | camera-to-world |
| ``depth``, ``inv_depth_var`` | float32 (H, W) | metric z-depth (m, 0 = invalid), 1/m^2 |
| ``valid`` | bool (H, W) | depth usable for mapping |
| ``camera`` | dict | :class:`~vings_core.types.CameraModel` fields (distortion as a list) |
"""
from __future__ import annotations

import collections
import os
import re
import tempfile
import threading
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from .errors import VingsError
from .types import CameraModel, Keyframe
from .util import atomic_write

SPILL_VERSION = 1
_NAME = re.compile(r"^kf-(\d{9})-(\d+)\.pt$")


def keyframe_to_dict(kf: Keyframe) -> dict:
    """The spill-file dict of ``kf`` (table in the module docstring)."""
    cam = kf.camera
    return {"version": SPILL_VERSION, "stamp_ns": int(kf.stamp_ns), "index": int(kf.index),
            "image": kf.image.detach().cpu().contiguous(), "T_wc": kf.T_wc.detach().cpu().contiguous(),
            "depth": kf.depth.detach().cpu().contiguous(),
            "inv_depth_var": kf.inv_depth_var.detach().cpu().contiguous(),
            "valid": kf.valid.detach().cpu().contiguous(),
            "camera": {"width": int(cam.width), "height": int(cam.height), "fx": float(cam.fx),
                       "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy),
                       "distortion_model": cam.distortion_model,
                       "distortion": [float(v) for v in cam.distortion]}}


def keyframe_from_dict(d: dict, source: str = "spill file") -> Keyframe:
    """Inverse of :func:`keyframe_to_dict`; a missing or malformed field is a :class:`VingsError`
    naming ``source`` and the field."""
    if d.get("version") != SPILL_VERSION:
        raise VingsError(f"{source}: unsupported keyframe spill version {d.get('version')!r} "
                         f"(expected {SPILL_VERSION})")
    try:
        c = dict(d["camera"])
        c["distortion"] = np.asarray(c.get("distortion", []), dtype=np.float64)
        return Keyframe(stamp_ns=d["stamp_ns"], image=d["image"], T_wc=d["T_wc"], depth=d["depth"],
                        inv_depth_var=d["inv_depth_var"], valid=d["valid"], camera=CameraModel(**c),
                        index=d["index"])
    except (KeyError, TypeError, ValueError) as e:
        raise VingsError(f"{source}: malformed keyframe ({type(e).__name__}: {e})") from e


class _Spilled:
    """A queue entry whose keyframe waits on disk."""

    __slots__ = ("path", "stamp_ns")

    def __init__(self, path: Path, stamp_ns: int) -> None:
        self.path = path
        self.stamp_ns = stamp_ns


class _Held:
    """A queue entry whose keyframe waits in memory (``seq``: its place, kept if it is spilled)."""

    __slots__ = ("kf", "seq")

    def __init__(self, kf: Keyframe, seq: int) -> None:
        self.kf = kf
        self.seq = seq


class KeyframeQueue:
    """Thread-safe FIFO of ``(kind, item)`` messages; ``kind == "kf"`` items are :class:`Keyframe`\\ s.

    * ``memory_keyframes``: keyframes held in memory at most (>= 1); later ones spill to disk.
    * ``spill_dir``: folder of the spill files (created on the first spill); ``None``: a private
      temporary folder. ``remove_dir``: :meth:`close` deletes the folder with what still waits
      in it (default: only a private folder); a kept folder is what :meth:`recover` reads.

    One producer thread (``put``) and one consumer thread (``get``).

    ``put`` never blocks. ``get`` returns the oldest message (reading a spilled keyframe back) or
    ``None`` after ``timeout`` seconds without one. A ``put(None)`` is an end marker that ``get``
    returns as ``None`` too; :meth:`closed` tells the two apart.
    """

    def __init__(self, memory_keyframes: int = 8, spill_dir: Optional[str | os.PathLike] = None,
                 remove_dir: Optional[bool] = None) -> None:
        if memory_keyframes < 1:
            raise ValueError(f"memory_keyframes must be >= 1, got {memory_keyframes}")
        self.memory_keyframes = int(memory_keyframes)
        private = spill_dir is None or str(spill_dir) == ""
        self._own_dir = private if remove_dir is None else bool(remove_dir)
        self._dir: Optional[Path] = None if private else Path(spill_dir)
        self._dq: collections.deque = collections.deque()
        self._cv = threading.Condition()
        self._seq = 0
        self._in_memory = 0         # keyframes held in memory now
        self._keyframes = 0         # keyframes waiting now (memory and disk)
        self._ended = False
        self.spilled = 0            # keyframes written to disk so far
        self.peak_keyframes = 0     # most keyframes waiting at once
        self.peak_spilled_mb = 0.0  # most disk used at once (MiB)
        self._disk_bytes = 0

    # ------------------------------------------------------------------------------ producer

    def put(self, kind: Optional[str], item: Any = None) -> None:
        """Append a message (``kind`` None: the end marker)."""
        if kind is None:
            with self._cv:
                self._ended = True
                self._dq.append(None)
                self._cv.notify_all()
            return
        entry: Any = item
        with self._cv:
            spill = kind == "kf" and self._in_memory >= self.memory_keyframes
            seq = self._seq
            self._seq += 1
        if spill:
            entry = self._write(seq, item)
        elif kind == "kf":
            entry = _Held(item, seq)
        with self._cv:
            if kind == "kf":
                self._keyframes += 1
                self.peak_keyframes = max(self.peak_keyframes, self._keyframes)
                if spill:
                    self.spilled += 1
                else:
                    self._in_memory += 1
            self._dq.append((kind, entry))
            self._cv.notify()

    def _spill_dir(self) -> Path:
        if self._dir is None:
            self._dir = Path(tempfile.mkdtemp(prefix="vings-kfqueue-"))
        try:
            self._dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise VingsError(f"{self._dir}: cannot create the keyframe spill folder ({e.strerror or e})") from e
        return self._dir

    def _write(self, seq: int, kf: Keyframe) -> _Spilled:
        d = self._spill_dir()
        path = d / f"kf-{seq:09d}-{int(kf.stamp_ns)}.pt"
        tmp = d / f".{path.name}.tmp"
        try:
            torch.save(keyframe_to_dict(kf), tmp)
            os.replace(tmp, path)
            size = path.stat().st_size
        except OSError as e:
            tmp.unlink(missing_ok=True)
            raise VingsError(f"{path}: cannot spill a queued keyframe to disk ({e.strerror or e}); "
                             f"free space or set the spill folder elsewhere") from e
        with self._cv:
            self._disk_bytes += size
            self.peak_spilled_mb = max(self.peak_spilled_mb, self._disk_bytes / 2 ** 20)
        return _Spilled(path, int(kf.stamp_ns))

    # ------------------------------------------------------------------------------ consumer

    def get(self, timeout: Optional[float] = None) -> Optional[tuple[str, Any]]:
        """The oldest message, or None (end marker, or nothing within ``timeout`` s)."""
        with self._cv:
            if not self._dq:
                self._cv.wait(timeout)
            if not self._dq:
                return None
            msg = self._dq.popleft()
            if msg is None:
                return None
            kind, entry = msg
            if isinstance(entry, _Held):
                self._in_memory -= 1
        if kind != "kf":
            return kind, entry
        try:
            kf = self._read(entry) if isinstance(entry, _Spilled) else entry.kf
        finally:
            with self._cv:
                self._keyframes -= 1
        return kind, kf

    def _read(self, s: _Spilled) -> Keyframe:
        try:
            size = s.path.stat().st_size
            d = torch.load(s.path, weights_only=True)
        except FileNotFoundError as e:
            raise VingsError(f"{s.path}: a spilled keyframe (stamp {s.stamp_ns}) is gone from disk") from e
        except (OSError, RuntimeError, EOFError) as e:
            raise VingsError(f"{s.path}: cannot read a spilled keyframe back ({e})") from e
        kf = keyframe_from_dict(d, str(s.path))
        s.path.unlink(missing_ok=True)
        with self._cv:
            self._disk_bytes -= size
        return kf

    # ------------------------------------------------------------------------------ state

    @property
    def keyframes(self) -> int:
        """Keyframes waiting (in memory and on disk)."""
        with self._cv:
            return self._keyframes

    @property
    def keyframes_on_disk(self) -> int:
        with self._cv:
            return self._keyframes - self._in_memory

    @property
    def spill_dir(self) -> Optional[Path]:
        return self._dir

    @property
    def keeps_files(self) -> bool:
        """True when :meth:`close` keeps the spill folder (a named one, for :meth:`recover`)."""
        return not self._own_dir and self._dir is not None

    def closed(self) -> bool:
        """True once the end marker was put."""
        return self._ended

    def __len__(self) -> int:
        with self._cv:
            return sum(1 for m in self._dq if m is not None)

    def stats(self) -> dict:
        """Counters for metrics and diagnostics."""
        with self._cv:
            return {"queue_keyframes": self._keyframes, "queue_keyframes_on_disk": self._keyframes - self._in_memory,
                    "queue_spilled": self.spilled, "queue_peak_keyframes": self.peak_keyframes,
                    "queue_peak_spilled_mb": round(self.peak_spilled_mb, 2)}

    def clear(self) -> int:
        """Drop every waiting message (an aborted run) and delete its spill files; returns the
        number of keyframes dropped."""
        with self._cv:
            msgs = list(self._dq)
            self._dq.clear()
            n = self._keyframes
            self._keyframes = self._in_memory = 0
            self._disk_bytes = 0
        for m in msgs:
            if m is not None and isinstance(m[1], _Spilled):
                m[1].path.unlink(missing_ok=True)
        return n

    def close(self) -> None:
        """End of use: a private spill folder is removed (a named one keeps what still waits)."""
        if self._own_dir and self._dir is not None:
            self.clear()
            for p in self._dir.glob(".*.tmp"):
                p.unlink(missing_ok=True)
            try:
                self._dir.rmdir()
            except OSError:
                pass

    def persist(self) -> int:
        """Write every keyframe still waiting in memory to disk, in its place (a node that stops
        before its queue is empty: :meth:`recover` finds them all when it resumes). Returns how
        many were written."""
        with self._cv:
            held = [(i, m[1]) for i, m in enumerate(self._dq) if m is not None and isinstance(m[1], _Held)]
        done = {}
        for i, h in held:
            done[id(h)] = self._write(h.seq, h.kf)
        with self._cv:
            for i, m in enumerate(self._dq):
                if m is not None and id(m[1]) in done:
                    self._dq[i] = (m[0], done[id(m[1])])
                    self._in_memory -= 1
        return len(done)

    def discard_leftovers(self) -> int:
        """Delete the spill files a killed earlier process left in ``spill_dir`` (a new run that
        does not resume them); returns how many."""
        if self._dir is None or not self._dir.is_dir():
            return 0
        n = 0
        for p in list(self._dir.iterdir()):
            if _NAME.match(p.name) or (p.name.startswith(".kf-") and p.name.endswith(".tmp")):
                p.unlink(missing_ok=True)
                n += 1
        return n

    def recover(self) -> int:
        """Queue the spill files a killed process left in ``spill_dir`` (in their original order,
        before anything put later); half-written temporaries are deleted. Returns how many."""
        if self._dir is None or not self._dir.is_dir():
            return 0
        for p in self._dir.glob(".kf-*.pt.tmp"):
            p.unlink(missing_ok=True)
        found = sorted((int(m.group(1)), int(m.group(2)), p) for p in self._dir.iterdir()
                       if (m := _NAME.match(p.name)))
        with self._cv:
            for seq, stamp, p in reversed(found):
                self._dq.appendleft(("kf", _Spilled(p, stamp)))
                self._disk_bytes += p.stat().st_size
            self._keyframes += len(found)
            self.spilled += len(found)
            self._seq = max(self._seq, (found[-1][0] + 1) if found else 0)
            self.peak_keyframes = max(self.peak_keyframes, self._keyframes)
            self._cv.notify_all()
        return len(found)


class UnackedKeyframes:
    """Keyframes the front end sent to the mapper and the mapper has not acknowledged yet (the
    mapper acknowledges a keyframe by listing its stamp among its keyframes: the refined
    keyframes path), oldest first, bounded in memory (later ones on disk: a
    :class:`KeyframeQueue`), so that a mapper that was down can be given them again.

    ``sent(kf)``: one more; ``acknowledged(stamps)``: the mapper holds these (returns how many
    were released); ``pending()``: the unacknowledged keyframes, oldest first (they stay held;
    those acknowledged out of order are not among them, nor counted by ``len``);
    ``overdue(now, timeout_s)``: whether the oldest waited longer than ``timeout_s``. Stamps are
    released in the order they were sent (the mapper maps in that order); a stamp acknowledged
    out of order is remembered until the older ones are released. One thread.

    ``keep_dir``: every keyframe held is also written there (``kf-<stamp>.pt``, the spill format,
    written atomically) until it is acknowledged, so that a front end restarted after a crash gets
    them back with :meth:`restore`."""

    def __init__(self, memory_keyframes: int = 8, spill_dir: Optional[str | os.PathLike] = None,
                 keep_dir: Optional[str | os.PathLike] = None) -> None:
        self._q = KeyframeQueue(memory_keyframes, spill_dir)
        self._order: collections.deque = collections.deque()     # (stamp, time sent)
        self._acked: set[int] = set()
        self.released = 0
        self.keep_dir = Path(keep_dir) if keep_dir is not None else None

    def _kept(self, stamp: int) -> Path:
        return self.keep_dir / f"kf-{int(stamp)}.pt"

    def restore(self) -> list[Keyframe]:
        """The keyframes ``keep_dir`` holds (left by a process that held them), oldest first, held
        again as sent at time 0; unreadable files are removed and skipped."""
        if self.keep_dir is None or not self.keep_dir.is_dir():
            return []
        out = []
        for f in sorted(self.keep_dir.glob("kf-*.pt"), key=lambda f: int(f.stem.split("-")[1])):
            try:
                kf = keyframe_from_dict(torch.load(f, weights_only=True), str(f))
            except Exception:  # noqa: BLE001 - a torn or foreign file (any unpickling error)
                f.unlink(missing_ok=True)
                continue
            self._q.put("kf", kf)
            self._order.append((int(kf.stamp_ns), 0.0))
            out.append(kf)
        return out

    def __len__(self) -> int:
        """Keyframes not acknowledged yet (those acknowledged out of order are not counted)."""
        return sum(1 for s, _ in self._order if s not in self._acked)

    def sent(self, kf: Keyframe, now: float) -> None:
        s = int(kf.stamp_ns)
        if s in self._acked or any(s == o for o, _ in self._order):
            return                      # sent again (a re-send): held once
        self._q.put("kf", kf)
        self._order.append((s, float(now)))
        if self.keep_dir is not None:
            atomic_write(self._kept(s), lambda tmp: torch.save(keyframe_to_dict(kf), tmp))

    def acknowledged(self, stamps) -> int:
        self._acked.update(int(s) for s in stamps)
        n = 0
        while self._order and self._order[0][0] in self._acked:
            self._q.get(0)
            s, _ = self._order.popleft()
            if self.keep_dir is not None:
                self._kept(s).unlink(missing_ok=True)
            n += 1
        oldest = self._order[0][0] if self._order else None
        # acknowledgements older than what is still held can no longer matter
        self._acked = {s for s in self._acked if oldest is not None and s > oldest}
        self.released += n
        return n

    def pending(self) -> list[Keyframe]:
        kfs = []
        for _ in range(len(self._order)):
            msg = self._q.get(0)
            if msg is None:
                break
            kfs.append(msg[1])
        for kf in kfs:                  # back in, in the same order
            self._q.put("kf", kf)
        return [kf for kf in kfs if int(kf.stamp_ns) not in self._acked]

    def overdue(self, now: float, timeout_s: float) -> bool:
        return bool(self._order) and now - self._order[0][1] > timeout_s

    def restamp(self, now: float) -> None:
        """Count the waiting time of what is held from ``now`` (after a re-send)."""
        self._order = collections.deque((s, float(now)) for s, _ in self._order)

    def discard(self) -> None:
        """Forget every keyframe held (they belong to another run), ``keep_dir``'s files too."""
        self.acknowledged([s for s, _ in self._order])

    def close(self) -> None:
        """Free the memory and the private spill folder (``keep_dir`` stays: the next process)."""
        self._q.close()
