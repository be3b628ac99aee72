"""Seeds for the dense flow when the motion between two images is too large for it (low frame
rates, dropped frames, fast turns): sparse feature matches, and from them either a camera pose
(PnP on a keyframe's depth, for tracking) or a smooth displacement field (for initialisation,
where no depth exists yet).

The dense flow (DIS) is a coarse-to-fine local search: it follows displacements up to a few tens of
pixels at the working resolution and loses the rest. Descriptor matching has no such range limit.
The seeds only make a prior: the dense flow is refined around it and every result still passes
the tracking checks, so a wrong seed costs time, never a wrong pose.

Pixels are working-resolution ``(u, v)``; poses ``T_cw`` (world-to-camera) ``(4, 4)`` float64.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Optional

import cv2
import numpy as np


class SeedFeatures(str, Enum):
    """Sparse features that seed the dense flow after a failed attempt (``frontend.seed_features``)."""

    NONE = "none"       #: never seed
    ORB = "orb"         #: OpenCV ORB, binary descriptors (fast)
    SIFT = "sift"       #: OpenCV SIFT (slower, more distinctive on plain surfaces)


@dataclass
class SparseMatches:
    """Mutually best descriptor matches between two images that pass the ratio test:
    ``p0``/``p1`` ``(N, 2)`` float64 pixel positions in image 0 / image 1."""

    p0: np.ndarray
    p1: np.ndarray

    def __len__(self) -> int:
        return int(self.p0.shape[0])


@dataclass
class PoseSeed:
    """A pose from PnP: ``T_cw`` of image 1, the RANSAC inliers and their count."""

    T_cw: np.ndarray
    inliers: int
    matches: int


def _detector(kind: SeedFeatures, n: int):
    if kind == SeedFeatures.ORB:
        return cv2.ORB_create(nfeatures=n, scaleFactor=1.2, nlevels=6, edgeThreshold=15,
                              patchSize=15, fastThreshold=7), cv2.NORM_HAMMING
    if kind == SeedFeatures.SIFT:
        return cv2.SIFT_create(nfeatures=n), cv2.NORM_L2
    raise ValueError(f"no detector for seed features {kind!r}")


def mutual_matches(d0: np.ndarray, d1: np.ndarray, norm: int, ratio: float) -> np.ndarray:
    """Descriptor pairs ``(M, 2)`` (indices into ``d0``, ``d1``) that are mutual nearest neighbours
    and pass Lowe's ratio test both ways, by OpenCV's brute-force k-NN matcher (``norm``:
    ``cv2.NORM_HAMMING`` or ``cv2.NORM_L2``)."""
    if d0 is None or d1 is None or len(d0) < 2 or len(d1) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(norm)

    def best(da, db):
        out = {}
        for m in bf.knnMatch(da, db, k=2):
            if len(m) == 2 and m[0].distance < ratio * m[1].distance:
                out[m[0].queryIdx] = m[0].trainIdx
        return out

    f, b = best(d0, d1), best(d1, d0)
    return np.array(sorted((i, j) for i, j in f.items() if b.get(j) == i), np.int64).reshape(-1, 2)


def match_features(g0: np.ndarray, g1: np.ndarray, kind: SeedFeatures, n_features: int = 1000,
                   ratio: float = 0.8) -> SparseMatches:
    """Detect ``kind`` features in the grey images ``g0``, ``g1`` (uint8 ``(H, W)``) and keep the
    matches that pass Lowe's ratio test both ways and are mutual nearest neighbours."""
    empty = SparseMatches(np.zeros((0, 2)), np.zeros((0, 2)))
    if kind == SeedFeatures.NONE:
        return empty
    det, norm = _detector(kind, n_features)
    k0, d0 = det.detectAndCompute(np.ascontiguousarray(g0), None)
    k1, d1 = det.detectAndCompute(np.ascontiguousarray(g1), None)
    if d0 is None or d1 is None or len(k0) < 2 or len(k1) < 2:
        return empty
    pairs = mutual_matches(d0, d1, norm, ratio)
    if not len(pairs):
        return empty
    i0, i1 = pairs.T
    p0 = np.array([k.pt for k in k0], np.float64)[i0]
    p1 = np.array([k.pt for k in k1], np.float64)[i1]
    return SparseMatches(p0, p1)


def sample_grid(grid: np.ndarray, pts: np.ndarray, stride: int) -> np.ndarray:
    """Bilinear sample of an ``(h, w)`` grid of block centres (``uv = stride * i + (stride-1)/2``)
    at pixel positions ``pts`` ``(N, 2)``; positions outside the grid take the nearest edge."""
    h, w = grid.shape
    off = (stride - 1) / 2.0
    x = np.clip((pts[:, 0] - off) / stride, 0, w - 1)
    y = np.clip((pts[:, 1] - off) / stride, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(int), w - 2) if w > 1 else np.zeros(len(x), int)
    y0 = np.minimum(np.floor(y).astype(int), h - 2) if h > 1 else np.zeros(len(y), int)
    ax, ay = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    return ((1 - ay) * ((1 - ax) * grid[y0, x0] + ax * grid[y0, x1])
            + ay * ((1 - ax) * grid[y1, x0] + ax * grid[y1, x1]))


def pnp_seed(m: SparseMatches, inv_depth: np.ndarray, valid: np.ndarray, K: np.ndarray,
             T0_cw: np.ndarray, stride: int, min_inliers: int = 20,
             ransac_px: float = 3.0) -> Optional[PoseSeed]:
    """Pose of image 1 from matches with image 0 (pose ``T0_cw``, grid inverse depth ``inv_depth``
    ``(h, w)`` and its validity ``valid`` ``(h, w)`` bool): image-0 points are lifted with the
    sampled depth (only where all four grid neighbours are valid), then EPnP in RANSAC and a
    Levenberg-Marquardt refinement on the inliers. ``None`` when fewer than ``min_inliers`` agree."""
    if len(m) < max(min_inliers, 6):
        return None
    d = sample_grid(inv_depth, m.p0, stride)
    ok = sample_grid(valid.astype(np.float64), m.p0, stride) > 0.999
    ok &= np.isfinite(d) & (d > 0)
    if int(ok.sum()) < max(min_inliers, 6):
        return None
    Kinv = np.linalg.inv(K)
    rays = (Kinv @ np.c_[m.p0[ok], np.ones(int(ok.sum()))].T).T
    X_c0 = rays / d[ok, None]
    R0, t0 = T0_cw[:3, :3], T0_cw[:3, 3]
    X_w = (X_c0 - t0) @ R0                       # R0^T (X_c0 - t0)
    img = np.ascontiguousarray(m.p1[ok], np.float64)
    found, rvec, tvec, inl = cv2.solvePnPRansac(X_w, img, K, None, iterationsCount=200,
                                                reprojectionError=float(ransac_px),
                                                confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not found or inl is None or len(inl) < min_inliers:
        return None
    inl = inl[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(X_w[inl], img[inl], K, None, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec[:, 0]
    if not np.isfinite(T).all():
        return None
    return PoseSeed(T, int(len(inl)), len(m))


def interpolate_displacements(m: SparseMatches, uv: np.ndarray, k: int = 6,
                              ransac_px: float = 3.0, min_inliers: int = 20) -> Optional[np.ndarray]:
    """Displacement field ``(P, 2)`` at the grid pixels ``uv`` ``(P, 2)`` from the matches that fit a
    fundamental matrix (RANSAC, ``ransac_px``): inverse-distance weighted mean of the ``k`` nearest
    inlier displacements. ``None`` when fewer than ``min_inliers`` matches agree."""
    from scipy.spatial import cKDTree
    if len(m) < max(min_inliers, 8):
        return None
    _, mask = cv2.findFundamentalMat(m.p0, m.p1, cv2.FM_RANSAC, float(ransac_px), 0.999)
    if mask is None:
        return None
    inl = mask[:, 0].astype(bool)
    if int(inl.sum()) < min_inliers:
        return None
    p0, disp = m.p0[inl], (m.p1 - m.p0)[inl]
    kk = min(k, len(p0))
    dist, idx = cKDTree(p0).query(uv, k=kk)
    dist, idx = dist.reshape(len(uv), kk), idx.reshape(len(uv), kk)
    wgt = 1.0 / np.maximum(dist, 1.0) ** 2
    return (wgt[..., None] * disp[idx]).sum(1) / wgt.sum(1, keepdims=True)
