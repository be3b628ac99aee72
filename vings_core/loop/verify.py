"""Loop candidates and their verification (the paper's "Loop Detection"): descriptor matches,
PnP on the candidate's depth, and a render of the map from the resulting pose compared with the
current image (novel view synthesis).

Conventions: ``T_wc`` camera-to-world; ``T_on`` (a loop edge) the pose of the newer keyframe in
the older one's camera frame as a similarity ``[[s R, t], [0, 1]]`` (``s``: a length in the newer
keyframe's units is ``s`` times that in the older one's; 1 when both are metric); pixels at the
working resolution.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import cv2
import numpy as np

from ..frontend.seed import mutual_matches
from ..geometry import np_pose_inverse, sim3
from ..types import CameraModel
from .config import LoopConfig, LoopFeatures
from .database import KeyframeDatabase, KeyframeEntry

#: ``render(T_wc, camera, older_than_stamp) -> {"color": (H, W, 3), "alpha": (H, W)}`` numpy, or
#: None when no map is available
RenderFn = Callable[[np.ndarray, CameraModel, Optional[int]], Optional[dict]]


@dataclass
class Candidate:
    """A keyframe that may be a revisit of the current one: why it was proposed (``radius``,
    ``retrieval`` or both), its distance (map units) and bag-of-words similarity."""

    stamp_ns: int
    index: int
    sources: tuple[str, ...]
    distance: float
    score: float


@dataclass
class Check:
    """The figures of one verified candidate (a row of ``loops.json``)."""

    candidate: Candidate
    matches: int = 0
    with_depth: int = 0
    inliers: int = 0
    scale: float = 1.0
    scale_source: str = "keypoints"     #: ``keypoints`` (PnP inliers) or ``render`` (dense depth)
    sigma_log_scale: Optional[float] = None
    sigma_rot: Optional[float] = None   #: rad, from the PnP information
    sigma_pos: Optional[float] = None   #: the current camera centre (older's units), from the PnP information
    render_l1: Optional[float] = None
    coverage: Optional[float] = None
    T_on: Optional[np.ndarray] = None
    T_wc_loop: Optional[np.ndarray] = None
    reason: str = ""
    passed: bool = False        #: passed every test up to the render comparison

    def record(self, newer: int) -> dict:
        c = self.candidate
        out = {"newer": int(newer), "older": int(c.stamp_ns), "older_index": int(c.index),
               "sources": list(c.sources), "distance": round(float(c.distance), 4),
               "bow_score": round(float(c.score), 4), "matches": self.matches, "with_depth": self.with_depth,
               "inliers": self.inliers, "scale": round(float(self.scale), 5), "scale_source": self.scale_source,
               "sigma_log_scale": None if self.sigma_log_scale is None else round(float(self.sigma_log_scale), 5),
               "sigma_rot_deg": None if self.sigma_rot is None else round(float(np.degrees(self.sigma_rot)), 4),
               "sigma_pos": None if self.sigma_pos is None else round(float(self.sigma_pos), 5),
               "render_l1": None if self.render_l1 is None else round(float(self.render_l1), 5),
               "coverage": None if self.coverage is None else round(float(self.coverage), 4)}
        return out


def find_candidates(db: KeyframeDatabase, cur: KeyframeEntry, cfg: LoopConfig) -> list[Candidate]:
    """Keyframes at least ``min_gap_keyframes`` (and ``min_span_keyframes``, the least span of a
    loop) older than ``cur``: those within the radius of its pose (nearest first) and the
    ``retrieval_top_k`` most similar by bag of words (score at least ``retrieval_min_score``), at
    most ``max_candidates`` (radius ones first, alternating)."""
    gap = max(cfg.min_gap_keyframes, cfg.min_span_keyframes)
    old = [e for e in db.entries if e.index <= cur.index - gap and e.stamp_ns != cur.stamp_ns]
    if not old:
        return []
    P = np.array([e.T_wc[:3, 3] for e in old])
    dist = np.linalg.norm(P - cur.T_wc[:3, 3], axis=1)
    radius = max(cfg.radius, cfg.radius_median_depths * cur.median_depth)
    score = np.zeros(len(old))
    if cur.bow is not None and all(e.bow is not None for e in old):
        score = np.array([e.bow for e in old]) @ cur.bow
    near = [int(i) for i in np.argsort(dist) if dist[i] <= radius]
    similar = [int(i) for i in np.argsort(-score)[:cfg.retrieval_top_k] if score[i] >= cfg.retrieval_min_score] \
        if cfg.retrieval_top_k else []
    order: list[int] = []
    for pair in zip(near, similar):
        order.extend(pair)
    longer = near if len(near) > len(similar) else similar
    order.extend(longer[min(len(near), len(similar)):])
    picked = list(dict.fromkeys(order))[:cfg.max_candidates]
    return [Candidate(old[i].stamp_ns, old[i].index,
                      tuple(n for n, inside in (("radius", i in near), ("retrieval", i in similar)) if inside),
                      float(dist[i]), float(score[i])) for i in picked]


def match_descriptors(d0: np.ndarray, d1: np.ndarray, features: LoopFeatures, ratio: float) -> np.ndarray:
    """Mutual nearest neighbours passing Lowe's ratio test both ways: ``(M, 2)`` index pairs, by
    OpenCV's brute-force k-NN matcher (SIMD popcount for binary descriptors; a matrix-product
    version in torch measured 2.5x slower on 2 cores for 1000 ORB descriptors)."""
    norm = cv2.NORM_L2 if LoopFeatures(features) == LoopFeatures.SIFT else cv2.NORM_HAMMING
    return mutual_matches(d0, d1, norm, ratio)


def solve_loop_pnp(older: KeyframeEntry, cur: KeyframeEntry, pairs: np.ndarray, K: np.ndarray,
                   cfg: LoopConfig, check: Check) -> bool:
    """PnP (EPnP in RANSAC, LM refinement) of the current camera on the older keyframe's points no
    deeper than ``pnp_max_depth_median`` median depths; fills ``check`` (``T_on`` with the relative
    scale from the current keyframe's own depths at the inliers, ``T_wc_loop``). False (and a
    reason) when it fails a threshold."""
    io, ic = pairs[:, 0], pairs[:, 1]
    z = older.depth[io]
    ok = (z > 0) & (z <= cfg.pnp_max_depth_median * max(older.median_depth, 1e-9))
    check.with_depth = int(ok.sum())
    if check.with_depth < max(cfg.min_inliers, 6):
        check.reason = f"{check.with_depth} matches with depth (need {max(cfg.min_inliers, 6)})"
        return False
    io, ic, z = io[ok], ic[ok], z[ok].astype(np.float64)
    rays = (np.linalg.inv(K) @ np.c_[older.kps[io].astype(np.float64), np.ones(len(io))].T).T
    X = rays * z[:, None]                                       # in the older camera
    img = np.ascontiguousarray(cur.kps[ic], np.float64)
    found, rvec, tvec, inl = cv2.solvePnPRansac(X, img, K, None, iterationsCount=300,
                                                reprojectionError=float(cfg.pnp_ransac_px), confidence=0.999,
                                                flags=cv2.SOLVEPNP_EPNP)
    n_in = 0 if (not found or inl is None) else len(inl)
    check.inliers = n_in
    if n_in < cfg.min_inliers or n_in < cfg.min_inlier_ratio * check.with_depth:
        check.reason = f"PnP: {n_in} inliers of {check.with_depth} (need {cfg.min_inliers} and " \
                       f"{100 * cfg.min_inlier_ratio:g} %)"
        return False
    inl = inl[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(X[inl], img[inl], K, None, rvec, tvec)
    T_co = np.eye(4)                                            # older camera -> current camera
    T_co[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_co[:3, 3] = tvec[:, 0]
    if not np.isfinite(T_co).all():
        check.reason = "PnP: not finite"
        return False
    T_oc = np_pose_inverse(T_co)
    check.sigma_rot, check.sigma_pos = _pnp_sigmas(X[inl], img[inl], K, rvec, tvec)
    # relative scale: the inliers' depth in the current camera (older units) over the current
    # keyframe's own depth of them (its units); the render check replaces it by the dense one
    zc = (X[inl] @ T_co[:3, :3].T + T_co[:3, 3])[:, 2]
    dn = cur.depth[ic[inl]].astype(np.float64)
    good = (dn > 0) & (zc > 0)
    s, check.sigma_log_scale = _robust_log_ratio(zc[good] / dn[good]) if good.sum() >= 5 else (1.0, None)
    check.scale = s
    if abs(np.log(max(s, 1e-12))) > cfg.max_scale_change:
        check.reason = f"relative scale {s:.3g} beyond exp(+-{cfg.max_scale_change:g})"
        return False
    check.T_on = sim3(T_oc[:3, :3], T_oc[:3, 3], s)
    check.T_wc_loop = older.T_wc @ T_oc
    return True


def _robust_log_ratio(r: np.ndarray) -> tuple[float, float]:
    """Median of positive ratios and the standard error of its log (1.4826 MAD, times 1.25 for
    a median, over sqrt(n))."""
    lr = np.log(r[r > 0])
    med = float(np.median(lr))
    mad = 1.4826 * float(np.median(np.abs(lr - med)))
    return float(np.exp(med)), 1.25 * mad / np.sqrt(len(lr))


def _pnp_sigmas(X: np.ndarray, img: np.ndarray, K: np.ndarray, rvec, tvec) -> tuple[float, float]:
    """Standard deviations of the PnP pose from its Gauss-Newton information: the rotation (rad,
    the largest axis) and the current camera's centre (the older keyframe's units, the largest
    axis); the reprojection noise is the inliers' RMS residual (at least 0.5 px). The depth noise
    of the 3D points is not in it: the loop edge's sigmas floor it (``loop_sigma_*``)."""
    proj, J = cv2.projectPoints(X, rvec, tvec, K, None)
    res = proj.reshape(-1, 2) - img
    sig = max(float(np.sqrt((res ** 2).mean())), 0.5)
    Jp = J[:, :6]                                         # d(u, v) / d(rvec, tvec)
    try:
        cov = sig ** 2 * np.linalg.inv(Jp.T @ Jp)
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    R = cv2.Rodrigues(rvec)[0]
    # centre c = -R^T t; to first order (rotation perturbed on the left) dc = -R^T [t]x drot - R^T dt
    Jc = np.zeros((3, 6))
    Jc[:, :3] = -R.T @ _skew(np.asarray(tvec, np.float64).reshape(3))
    Jc[:, 3:] = -R.T
    cov_c = Jc @ cov @ Jc.T
    return float(np.sqrt(np.linalg.eigvalsh(cov[:3, :3]).max())), float(np.sqrt(max(np.linalg.eigvalsh(cov_c).max(), 0)))


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def scaled_camera(camera: CameraModel, f: int) -> CameraModel:
    """``camera`` at ``1/f`` of its resolution (pixel centres kept: ``c' = (c + 0.5) / f - 0.5``)."""
    w, h = max(camera.width // f, 1), max(camera.height // f, 1)
    sx, sy = w / camera.width, h / camera.height
    return CameraModel(width=w, height=h, fx=camera.fx * sx, fy=camera.fy * sy,
                       cx=(camera.cx + 0.5) * sx - 0.5, cy=(camera.cy + 0.5) * sy - 0.5)


def render_agreement(out: dict, image: np.ndarray) -> tuple[float, float]:
    """How a render ``out`` (``color`` (h, w, 3), ``alpha`` (h, w)) agrees with ``image`` (h, w, 3)
    in [0, 1]: the fraction of pixels the map covers (alpha > 0.5) and the mean absolute colour
    error over them (``inf`` when it covers none)."""
    cov = np.asarray(out["alpha"]) > 0.5
    if not cov.any():
        return 0.0, float("inf")
    diff = np.abs(np.asarray(out["color"], np.float32) - np.asarray(image, np.float32)[..., :3])
    return float(cov.mean()), float(diff[cov].mean())


def render_check(render: Optional[RenderFn], check: Check, image: np.ndarray, camera: CameraModel,
                 older_than: Optional[int], cfg: LoopConfig, depth: Optional[np.ndarray] = None) -> bool:
    """Render the map from ``check.T_wc_loop`` at ``1/render_downscale`` of the resolution and
    compare with ``image`` ``(H, W, 3)`` in [0, 1] (area-averaged to that size): mean absolute error
    over the pixels the map covers (alpha > 0.5) and that coverage. With the current keyframe's
    ``depth`` ``(H, W)`` (0: none) and a rendered depth, the loop's relative scale becomes the dense
    one: the median ratio of rendered (older units) to own depth over the covered pixels (the
    keypoints' ratio is kept when fewer than 100 pixels have both). False (and a reason) without a
    map or with too little coverage."""
    if render is None:
        check.reason = "no map to render"
        return False
    f = max(int(cfg.render_downscale), 1)
    cam = camera if f == 1 else scaled_camera(camera, f)
    out = render(check.T_wc_loop, cam, older_than)
    if out is None:
        check.reason = "no map to render"
        return False
    if f > 1:
        image = cv2.resize(image, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    cov = np.asarray(out["alpha"]) > 0.5
    check.coverage, l1 = render_agreement(out, image)
    if check.coverage < cfg.render_min_coverage:
        check.reason = f"render covers {100 * check.coverage:.0f} % of the image (need " \
                       f"{100 * cfg.render_min_coverage:g} %)"
        return False
    check.render_l1 = l1
    if depth is not None and out.get("depth") is not None and check.T_on is not None:
        d = depth if f == 1 else cv2.resize(depth, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
        dr = np.asarray(out["depth"], np.float64)
        both = cov & (d > 0) & (dr > 0)
        if int(both.sum()) >= 100:
            s, sig = _robust_log_ratio(dr[both] / d[both])
            if abs(np.log(s / check.scale)) > cfg.max_scale_disagreement:
                check.reason = f"scale: render {s:.3g} and keypoints {check.scale:.3g} disagree"
                return False
            if abs(np.log(s)) > cfg.max_scale_change:
                check.reason = f"relative scale {s:.3g} (render) beyond exp(+-{cfg.max_scale_change:g})"
                return False
            check.T_on = sim3(check.T_on[:3, :3] / check.scale, check.T_on[:3, 3], s)
            check.scale, check.sigma_log_scale, check.scale_source = s, sig, "render"
    return True


def decide(checks: list[Check], cfg: LoopConfig) -> list[Check]:
    """The paper's criterion over the rendered candidates: render L1 below ``render_l1_max``, or
    below ``render_median_fraction`` of the median of the other candidates' L1 (and below
    ``render_max_accept``). Returns those that pass, lowest L1 first; every rendered check gets its
    reason."""
    rendered = [c for c in checks if c.passed]
    ok: list[Check] = []
    for c in rendered:
        others = [o.render_l1 for o in rendered if o is not c]
        med = float(np.median(others)) if others else None
        if c.render_l1 <= cfg.render_l1_max:
            c.reason = f"render L1 {c.render_l1:.3f} <= {cfg.render_l1_max:g}"
        elif med is not None and c.render_l1 <= cfg.render_median_fraction * med \
                and c.render_l1 <= cfg.render_max_accept:
            c.reason = f"render L1 {c.render_l1:.3f} <= {cfg.render_median_fraction:g} x median {med:.3f}"
        else:
            c.reason = f"render L1 {c.render_l1:.3f} above {cfg.render_l1_max:g}" + \
                       (f" and {cfg.render_median_fraction:g} x median {med:.3f}" if med is not None else "")
            continue
        ok.append(c)
    return sorted(ok, key=lambda c: c.render_l1)
