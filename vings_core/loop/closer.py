"""The loop closer stage (the paper's "NVS Loop Closure"): a keyframe database, candidates by
radius and bag of words, verification by PnP and a render of the map, and the correction of every
keyframe by a pose graph, sent through the pose exchange as increments (the keeper moves the
trajectory, the mapper moves each Gaussian with its keyframe ID(g)).

The stage is synchronous and owns no thread: ``vings run`` calls it in the mapper's thread after a
keyframe is mapped (so its renders see the map as trained), ``loop_closer_node`` in its worker.
"""
from __future__ import annotations

import bisect
import logging
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ..exchange import IncrementBatch, PoseFollower
from ..geometry import sim3_scale
from ..profiling import timed
from ..types import Keyframe
from .config import GraphChoice, LoopConfig, Verdict
from .database import KeyframeDatabase, extract
from .pose_graph import GraphMode, LoopEdge, optimize_pose_graph
from .verify import Check, RenderFn, decide, find_candidates, match_descriptors, render_check, solve_loop_pnp

log = logging.getLogger(__name__)

#: the loop closer's source name in the pose exchange
LOOP_SOURCE = "loop_closer"


@dataclass
class AcceptedLoop:
    """A loop edge kept for every later pose graph (its measurement ``T_on``, see
    :class:`~vings_core.loop.pose_graph.LoopEdge`)."""

    older: int
    newer: int
    older_index: int
    newer_index: int
    T_on: np.ndarray
    sigma_pos: float
    sigma_rot: float
    sigma_scale: float


#: information (per tangent component) of the odometry edge across a map-segment break: next to
#: nothing, so the pose graph is solvable but the break bends nothing
BREAK_INFO = 1e-6


class LoopCloser:
    """Loop detection and correction over the keyframes it is given.

    ``render(T_wc, camera, older_than)``: the map rendered from a pose with only the Gaussians
    whose ID(g) keyframe is older than stamp ``older_than`` (None: all); ``metric()``: whether the
    front end's poses are metric (visual-inertial), which makes the ``auto`` graph SE(3).
    """

    name = LOOP_SOURCE

    def __init__(self, cfg: Optional[LoopConfig] = None, render: Optional[RenderFn] = None,
                 metric: Callable[[], bool] = lambda: False) -> None:
        self.cfg = cfg or LoopConfig()
        self.cfg.validate()
        self.render = render
        self.metric = metric
        self.db = KeyframeDatabase()
        self.follower = PoseFollower(LOOP_SOURCE, self)
        self.loops: list[AcceptedLoop] = []
        self.records: list[dict] = []
        self.corrections: list[dict] = []
        self._out: list[IncrementBatch] = []
        self._verified: list[tuple[int, int]] = []     # (keyframe, candidate) indices awaiting confirmation
        #: first frames of the front end's map segments after the first (segment_started)
        self.segment_starts: set[int] = set()
        #: segment start -> the older keyframe of the first loop across it (the segment rejoined)
        self.joins: dict[int, int] = {}
        self.stats = dict(keyframes=0, candidates_checked=0, rejected=0, accepted=0,
                          detect_s=0.0, correct_s=0.0, max_detect_s=0.0)

    # ------------------------------------------------------------------ the exchange

    def apply_increments(self, increments: dict[int, np.ndarray]) -> int:
        """The follower's owner: keyframe poses (and keypoint depths) in the database move."""
        return self.db.move(increments)

    def receive(self, batch: IncrementBatch) -> None:
        """A batch of the keeper (the front end)."""
        self.follower.receive(batch)

    def poll(self) -> Optional[IncrementBatch]:
        """The correction of the last accepted loop, once (None when there is none)."""
        return self._out.pop(0) if self._out else None

    # ------------------------------------------------------------------ map segments

    def segment_started(self, stamp_ns: int) -> None:
        """The front end started a new map segment at frame ``stamp_ns`` (after tracking was lost, or
        a restart it could not relocalise): its own world frame and scale, placed at the last pose
        the front end knew. The keyframes on either side are not joined by odometry in the pose graph
        (:data:`BREAK_INFO`), and a loop from a keyframe after it to one before is not held to the
        odometry drift limits, so the first loop into the mapped world moves the whole new segment
        there (it rejoins the map's frame)."""
        self.segment_starts.add(int(stamp_ns))

    def _breaks(self, lo: int = 0, hi: Optional[int] = None) -> list[tuple[int, int]]:
        """Consecutive database keyframes ``(older, newer)`` (indices ``lo`` to ``hi``) with a
        segment start between them (``older < start <= newer``)."""
        if not self.segment_starts:
            return []
        ent = self.db.entries[lo:(len(self.db.entries) if hi is None else hi + 1)]
        starts = sorted(self.segment_starts)
        out = []
        for a, b in zip(ent[:-1], ent[1:]):
            i = bisect.bisect_right(starts, a.stamp_ns)
            if i < len(starts) and starts[i] <= b.stamp_ns:
                out.append((a.stamp_ns, b.stamp_ns))
        return out

    # ------------------------------------------------------------------ keyframes

    def add_keyframe(self, kf: Keyframe) -> Optional[dict]:
        """Add ``kf`` (pose as emitted) to the database, look for a loop and, when one is accepted,
        correct every keyframe (the batch waits in :meth:`poll`). Returns the accepted loop's
        record, or None."""
        t0 = time.perf_counter()
        with timed("loop", "features"):
            e = extract(kf, len(self.db), self.cfg)
        with timed("loop", "database"):
            self.db.add(e, self.cfg)
        self.follower.keyframe_added(e.stamp_ns, e.T_wc)
        self.stats["keyframes"] += 1
        loop = self._detect(e, kf)
        dt = time.perf_counter() - t0
        self.stats["detect_s"] += dt
        self.stats["max_detect_s"] = max(self.stats["max_detect_s"], dt)
        if loop is None:
            return None
        return self._correct(*loop)

    def _older_than(self, index: int) -> Optional[int]:
        """Stamp bound of the Gaussians a check may render: those of keyframes at least
        ``min_gap_keyframes`` older than keyframe ``index`` (None: render everything)."""
        if not self.cfg.render_exclude_recent:
            return None
        k = index - self.cfg.min_gap_keyframes
        return self.db.entries[k].stamp_ns + 1 if k >= 0 else None

    def _detect(self, e, kf: Keyframe) -> Optional[tuple[AcceptedLoop, dict]]:
        cfg = self.cfg
        cands = find_candidates(self.db, e, cfg)
        if not cands:
            return None
        image = kf.image.detach().cpu().numpy()[..., :3].astype(np.float32)
        K = np.array([[kf.camera.fx, 0, kf.camera.cx], [0, kf.camera.fy, kf.camera.cy], [0, 0, 1]])
        checks: list[Check] = []
        for c in cands:
            ch = Check(c)
            checks.append(ch)
            older = self.db.get(c.stamp_ns)
            why = self._refuse(ch, e.index)          # the cheap rules before any matching
            if why is not None:
                ch.reason = f"refused: {why}"
                continue
            with timed("loop", "match"):
                pairs = match_descriptors(older.desc, e.desc, cfg.features, cfg.ratio)
            ch.matches = len(pairs)
            if ch.matches < cfg.min_matches:
                ch.reason = f"{ch.matches} matches (need {cfg.min_matches})"
                continue
            with timed("loop", "PnP"):
                if not solve_loop_pnp(older, e, pairs, K, cfg, ch):
                    continue
            with timed("loop", "render check"):
                depth = np.where(kf.valid.detach().cpu().numpy(), kf.depth.detach().cpu().numpy(), 0.0)
                if not render_check(self.render, ch, image, kf.camera, self._older_than(e.index), cfg,
                                    depth.astype(np.float32)):
                    continue
            why = self._implausible(ch, e)
            if why is not None:
                ch.reason = why
                continue
            ch.passed = True
        passing = decide(checks, cfg)
        best = passing[0] if passing else None
        for ch in passing[1:]:
            ch.reason = f"{ch.reason}, but candidate {best.candidate.stamp_ns} rendered better"
        if best is not None and not self._confirmed(best, e.index):
            best.reason = f"{best.reason}; waits for confirmation by the next keyframe"
            best = None
        accepted, accepted_rec = None, None
        for ch in checks:
            rec = ch.record(e.stamp_ns)
            if ch is best:
                older = self.db.get(ch.candidate.stamp_ns)
                floor = cfg.loop_sigma_pos_median * max(older.median_depth, 1e-6)
                accepted = AcceptedLoop(ch.candidate.stamp_ns, e.stamp_ns, ch.candidate.index, e.index,
                                        ch.T_on if not self._se3() else _rigid(ch.T_on),
                                        max(floor, ch.sigma_pos or 0.0),
                                        max(cfg.loop_sigma_rot, ch.sigma_rot or 0.0),
                                        max(cfg.loop_sigma_scale, ch.sigma_log_scale or 0.0))
                rec.update(verdict=Verdict.ACCEPTED.value, reason=ch.reason)
                accepted_rec = rec
            else:
                rec.update(verdict=Verdict.REJECTED.value, reason=ch.reason)
            self.records.append(rec)
        self.stats["candidates_checked"] += len(checks)
        self.stats["rejected"] += len(checks) - int(accepted is not None)
        return None if accepted is None else (accepted, accepted_rec)

    def _implausible(self, ch: Check, e) -> Optional[str]:
        """A verified loop pose farther from the current pose than odometry can drift: more than
        ``max_drift_fraction`` of the path travelled since the candidate (plus one median depth of
        the current keyframe), or turned by more than ``max_drift_rot_deg``."""
        cfg = self.cfg
        if self._breaks(ch.candidate.index, e.index):
            return None         # a new segment placed by a guess: the loop is what places it
        P = np.array([x.T_wc[:3, 3] for x in self.db.entries[ch.candidate.index:e.index + 1]]).reshape(-1, 3)
        path = float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())
        shift = float(np.linalg.norm(ch.T_wc_loop[:3, 3] - e.T_wc[:3, 3]))
        limit = cfg.max_drift_fraction * path + e.median_depth
        if shift > limit:
            return f"loop pose {shift:.3g} from the current one, odometry drifts at most {limit:.3g} over {path:.3g}"
        R = ch.T_wc_loop[:3, :3].T @ e.T_wc[:3, :3]
        ang = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
        if ang > cfg.max_drift_rot_deg:
            return f"loop pose turned {ang:.1f} deg from the current one (at most {cfg.max_drift_rot_deg:g})"
        return None

    def _confirmed(self, ch: Check, index: int) -> bool:
        """Whether the revisit was verified by ``confirmations`` consecutive keyframes, each with a
        candidate within ``confirm_window`` keyframes of the previous one's."""
        cfg = self.cfg
        run = self._verified if self._verified and index - self._verified[-1][0] <= 1 else []
        if run and abs(ch.candidate.index - run[-1][1]) > cfg.confirm_window:
            run = []
        self._verified = run + [(index, ch.candidate.index)]
        if len(self._verified) >= cfg.confirmations:
            self._verified = []
            return True
        return False

    def _refuse(self, ch: Check, index: int) -> Optional[str]:
        """The temporal and geometric acceptance rules; why the loop is refused (None: accepted)."""
        cfg = self.cfg                  # (the least span is a condition of the candidates already)
        if self.loops:
            last = self.loops[-1]
            if index - last.newer_index < cfg.min_spacing_keyframes:
                return f"{index - last.newer_index} keyframes after the last loop (need {cfg.min_spacing_keyframes})"
            if last.older_index < ch.candidate.index < last.newer_index and \
                    index - last.newer_index < cfg.min_span_keyframes:
                return f"nested in the loop {last.older}-{last.newer} closed {index - last.newer_index} " \
                       f"keyframes ago"
        return None

    # ------------------------------------------------------------------ correction

    def _se3(self) -> bool:
        g = self.cfg.graph
        return g == GraphChoice.SE3 or (g == GraphChoice.AUTO and bool(self.metric()))

    def _correct(self, loop: AcceptedLoop, rec: dict) -> dict:
        t0 = time.perf_counter()
        cfg = self.cfg
        self.loops.append(loop)
        for s0 in self.segment_starts:
            if loop.older < s0 <= loop.newer:
                self.joins.setdefault(s0, loop.older)
        mode = GraphMode.SE3 if self._se3() else GraphMode.SIM3
        poses = {e.stamp_ns: e.T_wc for e in self.db.entries}
        edges = [LoopEdge(l.older, l.newer, l.T_on if mode == GraphMode.SIM3 else _rigid(l.T_on),
                          l.sigma_rot, l.sigma_pos, l.sigma_scale) for l in self.loops]
        dim = 7 if mode == GraphMode.SIM3 else 6
        breaks = {ab: np.eye(dim) * BREAK_INFO for ab in self._breaks()}
        with timed("loop", "pose graph"):
            res = optimize_pose_graph(poses, edges, mode, odo_sigma_rot=cfg.odo_sigma_rot,
                                  odo_sigma_pos_rel=cfg.odo_sigma_pos_rel, odo_sigma_pos_min=cfg.odo_sigma_pos_min,
                                  odo_sigma_scale=cfg.odo_sigma_scale, robust_k=cfg.robust_k,
                                  fixed=self.db.entries[0].stamp_ns, odometry_info=breaks)
        incs = {s: C for s, C in res.increments.items() if np.abs(C - np.eye(4)).max() > 1e-12}
        self.db.move(incs)
        batch = self.follower.send(incs, seq_hint=loop.newer)
        if batch is not None:
            self._out.append(batch)
        C = res.increments.get(loop.newer, np.eye(4))
        dt = time.perf_counter() - t0
        self.stats["correct_s"] += dt
        self.stats["accepted"] += 1
        shift = float(np.linalg.norm(self.db.get(loop.newer).T_wc[:3, 3] - poses[loop.newer][:3, 3]))
        info = {"older": loop.older, "newer": loop.newer, "graph": mode.value, "keyframes": len(poses),
                "moved": len(incs), "newer_shift": round(shift, 6), "segment_breaks": len(breaks),
                "newer_scale": round(sim3_scale(C), 6), "error_before": res.error_before,
                "error_after": res.error_after, "loop_residuals": res.loop_residuals, "seconds": round(dt, 4)}
        rec["correction"] = info
        self.corrections.append(info)
        log.info("loop %d -> %d accepted (%s graph over %d keyframes, %.2f s)", loop.older, loop.newer,
                 mode.value, len(poses), dt)
        return rec

    # ------------------------------------------------------------------ outputs, persistence

    def summary(self) -> dict:
        """Counters for metrics.json and diagnostics."""
        st = self.stats
        n = max(st["keyframes"], 1)
        return {"loops_accepted": st["accepted"], "loop_candidates_checked": st["candidates_checked"],
                "loop_candidates_rejected": st["rejected"], "loop_detect_ms_mean": round(1e3 * st["detect_s"] / n, 2),
                "loop_detect_ms_max": round(1e3 * st["max_detect_s"], 2),
                "loop_correct_s": round(st["correct_s"], 3)}

    def state_dict(self) -> dict:
        """Everything a restarted loop closer needs: the database, the accepted loops, the records
        and the follower's view of the keeper."""
        f = self.follower
        return {"db": self.db.state_dict(),
                "loops": [dict(older=l.older, newer=l.newer, older_index=l.older_index, newer_index=l.newer_index,
                               T_on=l.T_on, sigma_pos=l.sigma_pos, sigma_rot=l.sigma_rot,
                               sigma_scale=l.sigma_scale) for l in self.loops],
                "records": list(self.records), "corrections": list(self.corrections), "stats": dict(self.stats),
                "segment_starts": sorted(self.segment_starts), "joins": dict(self.joins),
                "follower": {"seq": f.seq, "seen": f.seen, "keeper": dict(f.keeper)}}

    def load_state_dict(self, st: dict) -> None:
        self.db = KeyframeDatabase.from_state(st["db"])
        self.loops = [AcceptedLoop(int(l["older"]), int(l["newer"]), int(l["older_index"]), int(l["newer_index"]),
                                   np.asarray(l["T_on"], np.float64), float(l["sigma_pos"]), float(l["sigma_rot"]),
                                   float(l["sigma_scale"])) for l in st["loops"]]
        self.records = list(st["records"])
        self.corrections = list(st.get("corrections", []))
        self.stats.update(st.get("stats", {}))
        self.segment_starts = {int(x) for x in st.get("segment_starts", [])}
        self.joins = {int(a): int(b) for a, b in st.get("joins", {}).items()}
        fs = st["follower"]
        self.follower = PoseFollower(LOOP_SOURCE, self)
        self.follower.seq = int(fs["seq"])
        self.follower.resumed({int(s): T for s, T in fs["keeper"].items()}, int(fs["seen"]))


def _rigid(T_on: np.ndarray) -> np.ndarray:
    """A loop measurement without its scale (SE(3) graphs)."""
    s = sim3_scale(T_on)
    out = np.array(T_on, np.float64)
    out[:3, :3] /= s
    return out
