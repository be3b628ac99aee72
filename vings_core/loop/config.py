"""Loop closure configuration: section ``loop`` of the params YAML."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import Enum


class LoopFeatures(str, Enum):
    """Weight-free local features of the keyframe database (OpenCV)."""

    ORB = "orb"         #: binary, fast (default)
    SIFT = "sift"       #: float, slower, more distinctive on plain surfaces
    AKAZE = "akaze"     #: binary (MLDB), between the two; needs an OpenCV build that has it

    def __str__(self) -> str:
        return self.value


class GraphChoice(str, Enum):
    """Which pose graph corrects a loop."""

    AUTO = "auto"       #: Sim(3) while the front end is visual-only, SE(3) once it is metric (IMU)
    SIM3 = "sim3"
    SE3 = "se3"

    def __str__(self) -> str:
        return self.value


class Verdict(str, Enum):
    """What became of a checked candidate (``loops.json``)."""

    ACCEPTED = "accepted"
    REJECTED = "rejected"

    def __str__(self) -> str:
        return self.value


@dataclass
class LoopConfig:
    """Units: metres in the map's frame (visual-only: the front end's arbitrary scale, median depth
    of the first keyframe 1), radians, colour in [0, 1]."""

    enabled: bool = True                  #: run the loop closer (``--no-loop``: false)
    features: LoopFeatures = LoopFeatures.ORB
    n_features: int = 1000                #: features per keyframe
    ratio: float = 0.8                    #: Lowe ratio of the mutual descriptor matches
    # ---- candidates
    min_gap_keyframes: int = 10           #: a candidate is at least this many keyframes older
    radius: float = 15.0                  #: candidates within this distance of the current pose
                                          #: (the paper: 15 m indoors, 50 m outdoors)
    radius_median_depths: float = 0.0     #: > 0: the radius is also at least this many median
                                          #: scene depths of the current keyframe (scale-free)
    vocabulary_words: int = 256           #: words of the online bag-of-words vocabulary
    vocabulary_after: int = 15            #: keyframes whose descriptors build the vocabulary
    retrieval_top_k: int = 3              #: most similar keyframes (bag of words) added as candidates
    retrieval_min_score: float = 0.1      #: their least cosine similarity (tf-idf histograms)
    max_candidates: int = 4               #: candidates matched per keyframe (radius ones by distance,
                                          #: then retrieval ones by score)
    # ---- verification
    min_matches: int = 50                 #: descriptor matches a candidate needs (the paper's 50)
    pnp_max_depth_median: float = 3.0     #: PnP uses points no deeper than this many median depths
    pnp_ransac_px: float = 3.0            #: RANSAC reprojection threshold (working px)
    min_inliers: int = 30                 #: PnP inliers a candidate needs
    min_inlier_ratio: float = 0.3         #: inliers over the matches with depth
    render_l1_max: float = 0.15           #: mean |render - image| over covered pixels (the paper's 0.15)
    render_median_fraction: float = 0.1   #: ... or at most this fraction of the other candidates' median
    render_max_accept: float = 0.25       #: the fraction rule never accepts an L1 above this
    render_min_coverage: float = 0.3      #: fraction of pixels the earlier map covers (alpha > 0.5)
    render_exclude_recent: bool = True    #: render only Gaussians of keyframes older than the gap
    render_downscale: int = 2             #: the check renders at 1/this of the working resolution
    # ---- acceptance
    min_span_keyframes: int = 20          #: older and newer at least this many keyframes apart
    min_spacing_keyframes: int = 5        #: keyframes between two accepted loops
    max_scale_change: float = 0.5         #: largest |log| relative scale of a loop edge
    max_scale_disagreement: float = 0.15  #: largest |log| ratio of the render's and the keypoints' scale
    max_drift_fraction: float = 0.3       #: the loop pose may be at most this fraction of the path
                                          #: travelled since the candidate (plus its median depth)
                                          #: from the current pose: more drift is not odometry's
    max_drift_rot_deg: float = 30.0       #: ... and turned by at most this much
    confirmations: int = 2                #: consecutive keyframes that must verify the revisit
                                          #: (candidates within confirm_window keyframes of each other)
    confirm_window: int = 5
    # ---- correction
    graph: GraphChoice = GraphChoice.AUTO
    odo_sigma_rot: float = 0.02           #: odometry edge: rotation std (rad)
    odo_sigma_pos_rel: float = 0.05       #: ... position std per unit of distance between keyframes
    odo_sigma_pos_min: float = 0.005      #: ... least position std
    odo_sigma_scale: float = 0.02         #: ... log-scale std (Sim(3))
    loop_sigma_rot: float = 0.005         #: loop edge: rotation std (rad)
    loop_sigma_pos_median: float = 0.01   #: ... position std in median depths of the older keyframe
    loop_sigma_scale: float = 0.02        #: ... log-scale std
    robust_k: float = 1.345               #: Huber threshold on loop edges (whitened)
    retrain_iters: int = 100              #: map iterations over the corrected keyframes afterwards
    retrain_max_s: float = 10.0           #: time bound of that retrain (s)
    prune_after: bool = True              #: prune by contribution score after the retrain

    def validate(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{f.name} must be finite, got {v}")
        self.features = LoopFeatures(self.features)
        self.graph = GraphChoice(self.graph)
        pos_int = ("n_features", "min_gap_keyframes", "vocabulary_words", "vocabulary_after",
                   "max_candidates", "min_matches", "min_inliers", "render_downscale")
        for name in pos_int:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("max_scale_disagreement", "max_drift_fraction", "max_drift_rot_deg", "confirmations",
                     "confirm_window"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("radius", "pnp_max_depth_median", "pnp_ransac_px", "render_l1_max", "odo_sigma_rot",
                     "odo_sigma_pos_rel", "odo_sigma_pos_min", "odo_sigma_scale", "loop_sigma_rot",
                     "loop_sigma_pos_median", "loop_sigma_scale", "robust_k", "max_scale_change"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("ratio", "min_inlier_ratio", "render_median_fraction", "render_min_coverage",
                     "retrieval_min_score"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("radius_median_depths", "render_max_accept", "retrain_max_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("retrieval_top_k", "min_span_keyframes", "min_spacing_keyframes", "retrain_iters"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.vocabulary_after < 2:
            raise ValueError(f"vocabulary_after must be >= 2, got {self.vocabulary_after}")
