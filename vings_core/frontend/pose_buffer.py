"""The front end's pose buffer: one record per processed frame, the keyframe poses, and a version
counter of keyframe-pose writes.

A keyframe's pose is stored as its ``T_cw`` (world-to-camera). A non-keyframe's pose is stored
relative to its reference keyframe (``T_c_kf``), so it follows later corrections of that keyframe
(window BA, or ``Frontend.set_poses`` from the mapper / loop closure); a frame without a reference
keyframe (waiting for initialisation) stores its ``T_cw``. Public accessors return ``T_wc``
(camera-to-world).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import InputError
from ..types import PoseEstimate, Trajectory, TrackState


@dataclass
class PoseRecord:
    """One processed frame: ``ref`` is its reference keyframe's stamp (``None``: absolute),
    ``T_rel`` is ``T_c_kf`` (frame from keyframe) with a reference, else ``T_cw``; ``state`` and
    ``covariance`` as in the frame's :class:`~vings_core.types.PoseEstimate`; ``segment``: the map
    segment its pose belongs to (its own world frame and scale)."""

    ref: Optional[int]
    T_rel: np.ndarray
    state: TrackState
    is_keyframe: bool = False
    covariance: Optional[np.ndarray] = None
    segment: int = 0


class PoseBuffer:
    """Poses of every processed frame, in processing order. ``version`` counts keyframe-pose
    writes (see :meth:`moved_since`)."""

    def __init__(self) -> None:
        self._kf_T_cw: dict[int, np.ndarray] = {}      # every keyframe ever: stamp -> T_cw
        self._records: dict[int, PoseRecord] = {}
        self._order: list[int] = []
        self.version = 0
        #: keyframe stamp -> ``version`` at its last write, in write order
        self._kf_written: dict[int, int] = {}
        self.segment = 0        #: the map segment that :meth:`record` assigns frames to
        #: map segment -> the earliest frame recorded in it
        self.segment_first: dict[int, int] = {}

    def __contains__(self, stamp: int) -> bool:
        return int(stamp) in self._records

    def is_keyframe(self, stamp: int) -> bool:
        return stamp in self._kf_T_cw

    def T_cw(self, stamp: int) -> np.ndarray:
        """Current ``T_cw`` (world-to-camera, 4x4 float64) of a processed frame."""
        if stamp in self._kf_T_cw:
            return self._kf_T_cw[stamp]
        rec = self._records[stamp]
        if rec.ref is None:
            return rec.T_rel
        return rec.T_rel @ self._kf_T_cw[rec.ref]

    def record(self, stamp: int, ref: Optional[int], T_cw: np.ndarray, state: TrackState,
               is_kf: bool = False, cov: Optional[np.ndarray] = None) -> PoseEstimate:
        """Store frame ``stamp``'s pose ``T_cw`` (relative to keyframe ``ref`` if given, which must
        have a pose) and return its estimate (``T_wc``)."""
        if ref is not None:
            T_rel = T_cw @ np.linalg.inv(self._kf_T_cw[ref])
        else:
            T_rel = T_cw
        if stamp not in self._records:
            self._order.append(stamp)
        self._records[stamp] = PoseRecord(ref, T_rel, state, is_kf, cov, self.segment)
        first = self.segment_first.get(self.segment)
        if first is None or stamp < first:
            self.segment_first[self.segment] = int(stamp)
        return PoseEstimate(stamp, np.linalg.inv(T_cw), cov, state, is_kf)

    def set_keyframe_pose(self, stamp: int, T_cw: np.ndarray) -> None:
        """Write keyframe ``stamp``'s ``T_cw`` (the array is kept, not copied) and count the write."""
        self._kf_T_cw[stamp] = T_cw
        self.version += 1
        self._kf_written.pop(stamp, None)          # re-insert: the dict stays in write order
        self._kf_written[stamp] = self.version

    def write_poses(self, poses_wc: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Overwrite the poses of processed frames (``stamp -> T_wc``, checked by the caller):
        keyframes first, then non-keyframes, which keep the given pose relative to their reference
        keyframe (its new pose). Returns the keyframes' new ``T_cw``."""
        kf_T_cw = {}
        for s, T in poses_wc.items():
            if s in self._kf_T_cw:
                T_cw = np.linalg.inv(np.asarray(T, np.float64))
                self.set_keyframe_pose(s, T_cw)
                kf_T_cw[s] = T_cw
        for s, T in poses_wc.items():
            rec = self._records[s]
            if s in self._kf_T_cw:
                continue
            T_cw = np.linalg.inv(np.asarray(T, np.float64))
            if rec.ref is not None and rec.ref in self._kf_T_cw:
                rec.T_rel = T_cw @ np.linalg.inv(self._kf_T_cw[rec.ref])
            else:
                rec.ref, rec.T_rel = None, T_cw
        return kf_T_cw

    def stamps_after(self, stamp_ns: int) -> list[int]:
        """Processed frames newer than ``stamp_ns`` whose pose does not follow a reference keyframe
        (keyframes, and frames without one), oldest first; the cost grows with their number only."""
        out = []
        for s in reversed(self._order):
            if s <= stamp_ns:
                break
            if s in self._kf_T_cw or self._records[s].ref is None:
                out.append(s)
        return out[::-1]

    def pose(self, stamp_ns: int) -> np.ndarray:
        """Current best ``T_wc`` of a processed frame (4x4 float64)."""
        if int(stamp_ns) not in self._records:
            raise InputError(f"frontend.pose: stamp {stamp_ns} was never processed by the front end")
        return np.linalg.inv(self.T_cw(int(stamp_ns)))

    def trajectory(self, states: tuple[str, ...], max_poses: Optional[int] = None,
                   segments: Optional[set[int]] = None) -> Trajectory:
        """Every processed frame's current ``T_wc`` whose latest state is in ``states`` (and whose
        segment is in ``segments``, if given); at most ``max_poses`` of them, evenly spread (first
        and last kept)."""
        st = [s for s in self._order if self._records[s].state in states
              and (segments is None or self._records[s].segment in segments)]
        if max_poses is not None and len(st) > max_poses:
            idx = np.linspace(0, len(st) - 1, max(int(max_poses), 2)).round().astype(int)
            st = [st[i] for i in idx]
        poses = np.stack([self.pose(s) for s in st]) if st else np.zeros((0, 4, 4))
        return Trajectory(np.asarray(st, np.int64), poses)

    def stamps_of_segment(self, segment: int) -> list[int]:
        """Every processed frame of map segment ``segment``, in processing order."""
        return [s for s in self._order if self._records[s].segment == segment]

    def keyframes_of_segment(self, segment: int) -> list[int]:
        """The keyframes of map segment ``segment``, in stamp order."""
        return sorted(s for s in self._kf_T_cw if s in self._records and self._records[s].segment == segment)

    def keyframe_trajectory(self) -> Trajectory:
        """``T_wc`` of every keyframe ever made, in stamp order."""
        st = sorted(self._kf_T_cw)
        poses = np.stack([self.pose(s) for s in st]) if st else np.zeros((0, 4, 4))
        return Trajectory(np.asarray(st, np.int64), poses)

    def segments(self) -> list[dict]:
        """Per map segment with tracked frames, in order: ``index``, ``first_stamp_ns``,
        ``last_stamp_ns``, ``frames`` (tracked), ``keyframes``. (Frames are processed in stamp
        order, so the first and last seen are the first and last stamps.)"""
        out: dict[int, dict] = {}
        for s in self._order:
            r = self._records[s]
            if r.state != TrackState.TRACKING:
                continue
            d = out.setdefault(r.segment, {"index": r.segment, "first_stamp_ns": s, "last_stamp_ns": s,
                                           "frames": 0, "keyframes": 0})
            d["last_stamp_ns"] = s
            d["frames"] += 1
            d["keyframes"] += int(r.is_keyframe)
        return [out[k] for k in sorted(out)]

    def frame_states(self) -> dict[int, TrackState]:
        """Latest state of every processed frame, in processing order."""
        return {s: self._records[s].state for s in self._order}

    def moved_since(self, version: int) -> list[int]:
        """Keyframes written after :attr:`version` had the value ``version``, newest write first;
        cost proportional to their number, not to the history."""
        out = []
        for s in reversed(self._kf_written):
            if self._kf_written[s] <= version:
                break
            out.append(s)
        return out
