"""The loop closer's keyframe database: per keyframe its features, descriptors, their depth and
depth uncertainty, its pose, and a bag-of-words vector over a vocabulary built online from the
run's own descriptors (no trained model, nothing downloaded).

Pixels are working-resolution ``(u, v)``; ``T_wc`` camera-to-world (4x4 float64) in the world of
the pose exchange; depths are z-depths in the map's units (metres once the front end is metric).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np
import torch

from ..errors import ConfigError, InputError
from ..geometry import sim3_apply_to_pose, sim3_scale
from ..types import Keyframe
from .config import LoopConfig, LoopFeatures


def detector(kind: LoopFeatures, n: int):
    """An OpenCV detector/extractor for ``kind`` and its descriptor norm."""
    kind = LoopFeatures(kind)
    if kind == LoopFeatures.ORB:
        return cv2.ORB_create(nfeatures=n, scaleFactor=1.2, nlevels=6, edgeThreshold=15, patchSize=15,
                              fastThreshold=7), cv2.NORM_HAMMING
    if kind == LoopFeatures.SIFT:
        return cv2.SIFT_create(nfeatures=n), cv2.NORM_L2
    make = getattr(cv2, "AKAZE_create", None)
    if make is None:
        raise ConfigError(f"loop.features: akaze is not in this OpenCV build ({cv2.__version__}); "
                          f"use orb or sift")
    return make(threshold=1e-4), cv2.NORM_HAMMING


def grey_u8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` RGB in [0, 1] (or uint8) -> ``(H, W)`` uint8 grey."""
    a = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    if a.dtype != np.uint8:
        a = (np.clip(a, 0, 1) * 255).round().astype(np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(a[..., :3]), cv2.COLOR_RGB2GRAY) if a.ndim == 3 else a


@dataclass
class KeyframeEntry:
    """One keyframe: ``kps`` ``(N, 2)`` float32 pixels, ``desc`` ``(N, D)`` descriptors (uint8 for
    binary features, float32 for SIFT), ``depth`` ``(N,)`` float32 z-depth at each keypoint (0:
    none), ``inv_depth_var`` ``(N,)`` float32 its inverse-depth variance, ``median_depth`` of the
    keyframe's valid depth, ``T_wc`` its pose, ``index`` its place in keyframe order, ``bow`` its
    bag-of-words vector (``None`` until the vocabulary exists)."""

    stamp_ns: int
    index: int
    T_wc: np.ndarray
    kps: np.ndarray
    desc: np.ndarray
    depth: np.ndarray
    inv_depth_var: np.ndarray
    median_depth: float
    bow: Optional[np.ndarray] = None


def extract(kf: Keyframe, index: int, cfg: LoopConfig) -> KeyframeEntry:
    """Features of keyframe ``kf`` with the depth (nearest pixel, valid only) under each."""
    det, _ = detector(cfg.features, cfg.n_features)
    kp, desc = det.detectAndCompute(grey_u8(kf.image), None)
    H, W = kf.camera.height, kf.camera.width
    if desc is None or not kp:
        kps = np.zeros((0, 2), np.float32)
        desc = np.zeros((0, 128 if cfg.features == LoopFeatures.SIFT else 32),
                        np.float32 if cfg.features == LoopFeatures.SIFT else np.uint8)
    else:
        kps = np.array([k.pt for k in kp], np.float32)
    depth = kf.depth.detach().cpu().numpy()
    var = kf.inv_depth_var.detach().cpu().numpy()
    valid = kf.valid.detach().cpu().numpy() & (depth > 0) & np.isfinite(depth)
    u = np.clip(np.round(kps[:, 0]).astype(int), 0, W - 1)
    v = np.clip(np.round(kps[:, 1]).astype(int), 0, H - 1)
    ok = valid[v, u]
    d = np.where(ok, depth[v, u], 0).astype(np.float32)
    med = float(np.median(depth[valid])) if valid.any() else 0.0
    return KeyframeEntry(int(kf.stamp_ns), int(index), kf.T_wc.detach().cpu().numpy().astype(np.float64),
                         kps, desc, d, np.where(ok, var[v, u], np.inf).astype(np.float32), med)


def _as_float(desc: np.ndarray) -> np.ndarray:
    """Descriptors as float32 rows for clustering: binary ones unpacked to 0/1 bits."""
    if desc.dtype == np.uint8:
        return np.unpackbits(desc, axis=1).astype(np.float32)
    return desc.astype(np.float32)


class Vocabulary:
    """A flat visual vocabulary: ``words`` ``(K, D)`` float32 centres (k-means on the descriptors,
    binary ones as bits) and ``idf`` ``(K,)`` (log of keyframes over keyframes with the word)."""

    def __init__(self, words: np.ndarray, idf: Optional[np.ndarray] = None) -> None:
        self.words = np.ascontiguousarray(words, np.float32)
        self.idf = np.ones(len(words), np.float32) if idf is None else np.asarray(idf, np.float32)
        self._w2 = (self.words ** 2).sum(1)

    @staticmethod
    def build(descs: list[np.ndarray], k: int, seed: int = 0, max_rows: int = 8000) -> "Vocabulary":
        """k-means (OpenCV, k-means++ seeding, fixed seed) on at most ``max_rows`` descriptors."""
        X = np.concatenate([_as_float(d) for d in descs if len(d)], 0)
        if len(X) < k:
            raise InputError(f"loop vocabulary: {len(X)} descriptors for {k} words")
        rng = np.random.default_rng(seed)
        if len(X) > max_rows:
            X = X[rng.choice(len(X), max_rows, replace=False)]
        cv2.setRNGSeed(seed)
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 10, 1e-3)
        _, _, centres = cv2.kmeans(X, k, None, crit, 1, cv2.KMEANS_PP_CENTERS)
        return Vocabulary(centres)

    def assign(self, desc: np.ndarray) -> np.ndarray:
        """Nearest word of each descriptor ``(N,)`` int (squared Euclidean; Hamming for bits)."""
        if not len(desc):
            return np.zeros(0, np.int64)
        X = _as_float(desc)
        d2 = self._w2[None, :] - 2.0 * X @ self.words.T
        return np.argmin(d2, axis=1)

    def histogram(self, desc: np.ndarray) -> np.ndarray:
        """L2-normalised tf-idf vector ``(K,)`` float32 of a keyframe's descriptors."""
        h = np.bincount(self.assign(desc), minlength=len(self.words)).astype(np.float32)
        h = h / max(h.sum(), 1.0) * self.idf
        n = float(np.linalg.norm(h))
        return h / n if n > 0 else h

    def fit_idf(self, descs: list[np.ndarray]) -> None:
        """``idf`` from the keyframes' descriptor sets."""
        df = np.zeros(len(self.words), np.float64)
        for d in descs:
            df[np.unique(self.assign(d))] += 1
        self.idf = np.log((len(descs) + 1.0) / (df + 1.0)).astype(np.float32) + 1e-3


@dataclass
class KeyframeDatabase:
    """Entries in keyframe order, the vocabulary once built, and the pose table."""

    entries: list[KeyframeEntry] = field(default_factory=list)
    vocabulary: Optional[Vocabulary] = None
    by_stamp: dict[int, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.entries)

    def __contains__(self, stamp: int) -> bool:
        return int(stamp) in self.by_stamp

    def get(self, stamp: int) -> KeyframeEntry:
        return self.entries[self.by_stamp[int(stamp)]]

    def add(self, e: KeyframeEntry, cfg: LoopConfig) -> None:
        """Append ``e``; builds the vocabulary once ``cfg.vocabulary_after`` keyframes exist (and
        gives every earlier entry its vector)."""
        if e.stamp_ns in self.by_stamp:
            raise InputError(f"loop database: keyframe {e.stamp_ns} added twice")
        self.by_stamp[e.stamp_ns] = len(self.entries)
        self.entries.append(e)
        if self.vocabulary is None and len(self.entries) >= cfg.vocabulary_after:
            descs = [x.desc for x in self.entries]
            n = sum(len(d) for d in descs)
            if n >= cfg.vocabulary_words:
                self.vocabulary = Vocabulary.build(descs, cfg.vocabulary_words)
                self.vocabulary.fit_idf(descs)
                for x in self.entries:
                    x.bow = self.vocabulary.histogram(x.desc)
        elif self.vocabulary is not None:
            e.bow = self.vocabulary.histogram(e.desc)

    def positions(self) -> np.ndarray:
        """Camera centres ``(N, 3)`` in keyframe order."""
        return np.array([e.T_wc[:3, 3] for e in self.entries]).reshape(-1, 3)

    def move(self, increments: dict[int, np.ndarray]) -> int:
        """Pose-exchange increments (world-frame similarities): poses moved, keypoint depths scaled
        by ``s`` (a keyframe's content scales with it). Unknown stamps are ignored."""
        n = 0
        for s, C in increments.items():
            i = self.by_stamp.get(int(s))
            if i is None:
                continue
            e = self.entries[i]
            e.T_wc = sim3_apply_to_pose(np.asarray(C, np.float64), e.T_wc)
            k = sim3_scale(C)
            if abs(k - 1.0) > 1e-12:
                e.depth = e.depth * np.float32(k)
                e.inv_depth_var = e.inv_depth_var / np.float32(k * k)
                e.median_depth *= k
            n += 1
        return n

    # ------------------------------------------------------------------ persistence

    def state_dict(self) -> dict:
        """Plain arrays (for ``torch.save``/``np.savez``); :meth:`from_state` restores it."""
        E = self.entries
        out = {"stamps": np.array([e.stamp_ns for e in E], np.int64),
               "index": np.array([e.index for e in E], np.int64),
               "T_wc": np.array([e.T_wc for e in E], np.float64).reshape(-1, 4, 4),
               "median_depth": np.array([e.median_depth for e in E], np.float64),
               "counts": np.array([len(e.kps) for e in E], np.int64)}
        if E:
            out.update(kps=np.concatenate([e.kps for e in E]), desc=np.concatenate([e.desc for e in E]),
                       depth=np.concatenate([e.depth for e in E]),
                       inv_depth_var=np.concatenate([e.inv_depth_var for e in E]))
        if self.vocabulary is not None:
            out.update(words=self.vocabulary.words, idf=self.vocabulary.idf)
        return out

    @staticmethod
    def from_state(st: dict) -> "KeyframeDatabase":
        db = KeyframeDatabase()
        if "words" in st:
            db.vocabulary = Vocabulary(np.asarray(st["words"]), np.asarray(st["idf"]))
        counts = np.asarray(st["counts"], np.int64)
        ends = np.cumsum(counts)
        for i, s in enumerate(np.asarray(st["stamps"], np.int64)):
            a, b = int(ends[i] - counts[i]), int(ends[i])
            e = KeyframeEntry(int(s), int(st["index"][i]), np.asarray(st["T_wc"][i], np.float64).copy(),
                              np.asarray(st["kps"][a:b]), np.asarray(st["desc"][a:b]),
                              np.asarray(st["depth"][a:b]), np.asarray(st["inv_depth_var"][a:b]),
                              float(st["median_depth"][i]))
            if db.vocabulary is not None:
                e.bow = db.vocabulary.histogram(e.desc)
            db.by_stamp[e.stamp_ns] = len(db.entries)
            db.entries.append(e)
        return db
