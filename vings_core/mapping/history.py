"""History store: keyframes that left the mapper's local window, kept for history training.

A record is a keyframe in compact form (:func:`compact_keyframe`: RGB uint8, depth and
inverse-depth variance float16, validity and the dynamic mask bool; ~0.8 MB at 376x240), keyed by the keyframe's stamp.
Records live in host memory up to ``memory_budget_bytes``; beyond it the least recently used ones
are written to ``.npz`` files (once: records never change) and read back when training samples
them, so a long run's history costs disk, not memory. A file found missing or damaged is reported
and that keyframe is dropped from the history (training goes on without it).
"""
from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Iterable, Optional

import numpy as np
import torch

from ..errors import InputError, VingsError
from ..types import CameraModel, Keyframe
from ..util import log
from .storage import SpillFolder

FIELDS = ("image", "depth", "inv_depth_var", "valid", "dynamic")


def compact_keyframe(kf: Keyframe) -> dict:
    """``kf`` as a history record: RGB as uint8 (the inputs are 8-bit images), depth and
    inverse-depth variance as float16, validity and the dynamic mask (all False without one) as
    bool, plus its running ``index``."""
    return {"image": torch.round(kf.image.clamp(0, 1) * 255).to(torch.uint8),
            # (a depth beyond float16's range stays "far", not inf: inf / inf in the depth loss is NaN)
            "depth": kf.depth.clamp(max=65504.0).to(torch.float16),
            # float16 overflows above 65504 (the front end sends up to 1e10 for "unknown"): clamp, a
            # standard deviation of 256 1/m is as unusable as infinity
            "inv_depth_var": kf.inv_depth_var.clamp(0, 65504.0).to(torch.float16),
            "valid": kf.valid.clone(),
            "dynamic": (torch.zeros_like(kf.valid, dtype=torch.bool) if kf.dynamic is None else kf.dynamic.clone()),
            "index": int(kf.index)}


def scale_keyframe_depth(kf: Keyframe, k: float) -> None:
    """In place: ``kf``'s depth map follows a similarity of scale ``k`` (depth times ``k``,
    inverse-depth variance over ``k^2``); new tensors, so caches keyed on the old ones rebuild."""
    kf.depth = kf.depth * k
    kf.inv_depth_var = kf.inv_depth_var / (k * k)


def expand_keyframe(rec: dict, stamp: int, T_wc: np.ndarray, camera: CameraModel) -> Keyframe:
    """The :class:`Keyframe` of a history record at camera-to-world pose ``T_wc``."""
    return Keyframe(stamp_ns=int(stamp), image=rec["image"].to(torch.float32) / 255.0,
                    T_wc=torch.from_numpy(np.array(T_wc)), depth=rec["depth"].to(torch.float32),
                    inv_depth_var=rec["inv_depth_var"].to(torch.float32), valid=rec["valid"], camera=camera,
                    index=rec["index"], dynamic=rec["dynamic"] if bool(rec["dynamic"].any()) else None)


def _nbytes(rec: dict) -> int:
    return int(sum(rec[k].numel() * rec[k].element_size() for k in FIELDS))


class HistoryStore:
    """Compact keyframe records by stamp, in memory up to a budget, spilled to disk beyond it.

    ``memory_budget_bytes``: in-memory size above which the least recently used records go to
    disk; ``spill_dir``: parent folder of the store's private spill folder (None = a temporary
    folder). :meth:`close` deletes the files.
    """

    def __init__(self, memory_budget_bytes: int, spill_dir: Optional[str] = None):
        self.memory_budget_bytes = int(memory_budget_bytes)
        self._mem: "OrderedDict[int, dict]" = OrderedDict()   # stamp -> record, least recent first
        self._files: dict[int, Path] = {}                      # stamp -> spilled file
        self._index: dict[int, int] = {}                       # stamp -> keyframe index, insertion order
        self._mem_bytes = 0
        self._folder = SpillFolder(spill_dir, "vings_history_")
        self.spilled_total = 0
        self.loaded_total = 0
        self.lost_total = 0

    def __len__(self) -> int:
        return len(self._index)

    def __contains__(self, stamp: int) -> bool:
        return int(stamp) in self._index

    def stamps(self) -> list[int]:
        """Stamps in the order they were added."""
        return list(self._index)

    @property
    def memory_bytes(self) -> int:
        return self._mem_bytes

    @property
    def num_spilled(self) -> int:
        return sum(1 for s in self._index if s not in self._mem)

    def put(self, stamp: int, rec: dict) -> None:
        """Add (or replace) the record of keyframe ``stamp``."""
        s = int(stamp)
        self.remove(s)
        self._mem[s] = {k: rec[k] for k in FIELDS}
        self._index[s] = int(rec["index"])
        self._mem_bytes += _nbytes(rec)
        self._spill_if_needed()

    def get(self, stamp: int) -> Optional[dict]:
        """The record of ``stamp`` (read back from disk if spilled, and kept in memory as the most
        recently used); None when its file is missing or damaged (reported, counted in
        ``lost_total``, and the keyframe leaves the history)."""
        s = int(stamp)
        rec = self._mem.get(s)
        if rec is None:
            rec = self._read(s)
            if rec is None:
                return None
            self._mem[s] = rec
            self._mem_bytes += _nbytes(rec)
        self._mem.move_to_end(s)
        self._spill_if_needed(keep=s)
        return {**rec, "index": self._index[s]}

    def peek(self, stamp: int) -> Optional[dict]:
        """Like :meth:`get`, but a spilled record is read without entering memory and the
        least-recently-used order is left as it is (checkpoints read every record once)."""
        s = int(stamp)
        rec = self._mem.get(s)
        if rec is None:
            rec = self._read(s)
        return None if rec is None else {**rec, "index": self._index[s]}

    def _read(self, s: int) -> Optional[dict]:
        if s not in self._files:
            raise KeyError(s)
        try:
            arrays = SpillFolder.read(self._files[s], FIELDS, f"history keyframe {s}")
        except InputError as e:
            log.error("%s: the keyframe is dropped from history training", e)
            self.lost_total += 1
            self.remove(s)
            return None
        self.loaded_total += 1
        return {k: torch.from_numpy(arrays[k]) for k in FIELDS}

    def remove(self, stamp: int) -> None:
        s = int(stamp)
        if s not in self._index:
            return
        rec = self._mem.pop(s, None)
        if rec is not None:
            self._mem_bytes -= _nbytes(rec)
        path = self._files.pop(s, None)
        if path is not None and path.exists():
            path.unlink()
        del self._index[s]

    def items(self) -> Iterable[tuple[int, dict]]:
        """``(stamp, record)`` in insertion order, one at a time through :meth:`peek` (memory stays
        bounded, the in-memory set unchanged); records found lost are skipped."""
        for s in list(self._index):
            rec = self.peek(s)
            if rec is not None:
                yield s, rec

    def close(self) -> None:
        """Forget every record and delete the spill files."""
        self._mem.clear()
        self._files.clear()
        self._index.clear()
        self._mem_bytes = 0
        self._folder.close()

    def _spill_if_needed(self, keep: Optional[int] = None) -> None:
        while self._mem_bytes > self.memory_budget_bytes and self._mem:
            s = next(iter(self._mem))
            if s == keep:
                break     # the record just asked for stays, even over the budget
            if s not in self._files:     # records never change: a file once written stays valid
                rec = self._mem[s]        # written before it leaves memory: a failed write loses nothing
                try:
                    self._files[s] = self._folder.write(f"kf_{s}.npz", {k: rec[k].numpy() for k in FIELDS})
                except VingsError as e:     # disk full, folder gone (SpillFolder.write)
                    log.warning("history keyframes: cannot spill to disk (%s); kept in memory over "
                                "history_memory_mb", e)
                    return
                self.spilled_total += 1
            self._mem_bytes -= _nbytes(self._mem.pop(s))

    def __del__(self) -> None:  # best effort: private temp folders do not outlive the store
        try:
            self._folder.close()
        except Exception:
            pass
