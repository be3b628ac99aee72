"""Front-end configuration: one dataclass, section ``frontend`` of the params YAML.

Load with ``load_section(FrontendConfig, 'frontend', params_file)``. Pixel quantities say at which
resolution they are measured: ``*_lr_px`` at the 1/8 BA grid, ``*_px`` at the working resolution.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

ROBUST_LOSSES = ("huber", "cauchy", "none")
FLOW_METHODS = ("dis", "torchscript")
DIS_PRESETS = ("ultrafast", "fast", "medium")
SEED_FEATURES = ("orb", "sift", "none")


@dataclass
class FrontendConfig:
    # ---- flow targets
    flow_method: str = "dis"            #: 'dis' (OpenCV DIS, no weights) or 'torchscript' (local file)
    flow_weights_path: str = ""         #: TorchScript flow model file for flow_method='torchscript'
    dis_preset: str = "medium"          #: OpenCV DIS preset
    dis_finest_scale: int = 1           #: DIS finest pyramid level (0 = full working resolution)
    chain_preset: str = "fast"          #: DIS preset of the frame-to-frame flow that chains the
                                        #: tracking prior (refined afterwards with dis_preset)
    fb_sigma_px: float = 1.0            #: forward-backward inconsistency giving weight 1/2 (px)
    photo_sigma: float = 12.0           #: photometric error (grey levels) giving weight 1/2
    ncc_min: float = 0.5                #: block NCC (image vs flow-warped image) giving weight 0
    texture_tau: float = 4.0            #: block gradient energy (grey levels^2) giving weight 1/2
    block_spread_sigma_px: float = 1.0  #: flow spread inside an 8x8 block giving weight 1/2 (px)
    flow_sigma_px: float = 0.3          #: flow noise std at weight 1 (px): information = w / sigma^2
    min_weight: float = 0.05            #: block weights below this are treated as unobserved
    # ---- keyframes and graph
    keyframe_flow_lr_px: float = 2.4    #: mean flow at 1/8 res to the last keyframe making a keyframe
    keyframe_conf_ratio: float = 0.5   #: ...or when mean confidence falls below this x its value
                                        #: on the first frame after the last keyframe (overlap loss)
    window: int = 8                     #: keyframes in the local BA window
    temporal_radius: int = 2            #: edges to the previous `temporal_radius` keyframes
    proximity_flow_lr_px: float = 6.0   #: extra edges where mean induced flow (1/8 res) is below this
    max_edges_per_keyframe: int = 4     #: cap on proximity edges added per new keyframe
    # ---- dense BA
    ba_iters: int = 6                   #: Levenberg-Marquardt iterations per keyframe
    init_ba_iters: int = 15             #: LM iterations of the two-view initialisation
    fixed_poses: int = 2                #: oldest window poses held fixed (gauge incl. monocular scale)
    robust_loss: str = "huber"          #: 'huber', 'cauchy' or 'none'
    robust_delta_px: float = 2.0        #: robust kernel width (px, working resolution)
    lm_lambda: float = 1e-4             #: initial Levenberg-Marquardt damping (relative to diag)
    min_inv_depth: float = 1e-3         #: inverse-depth clamp relative to the window median (lower)
    max_inv_depth: float = 50.0         #: inverse-depth clamp relative to the window median (upper)
    refine_flow: bool = True            #: re-measure the new keyframe's flow to the last keyframe
                                        #: around the flow induced by its first depth estimate
    # ---- tracking
    track_iters: int = 8                #: motion-only Gauss-Newton iterations per frame
    track_fb_check: bool = False        #: also run the backward flow for every tracked frame
                                        #: (otherwise only for frames that become keyframes)
    min_confident_frac: float = 0.03    #: mean grid confidence below this -> tracking failure
    max_track_rms_px: float = 6.0       #: robust residual RMS above this -> tracking failure
    relocalize_frames: int = 5          #: failed frames tried against the window before re-initialising
    seed_features: str = "orb"          #: sparse features seeding a failed dense flow: 'orb',
                                        #: 'sift' or 'none' (see frontend/seed.py)
    seed_max_features: int = 1000       #: features detected per image for seeding
    seed_min_inliers: int = 20          #: RANSAC inliers (PnP / fundamental matrix) a seed needs
    seed_ransac_px: float = 3.0         #: RANSAC threshold of the seeds (px, working resolution)
    seed_above_rms_px: float = 2.0      #: a tracked frame whose residual RMS (px) is above this is
                                        #: also tried seeded (the better fit is kept)
    # ---- initialisation
    init_min_parallax_lr_px: float = 1.0  #: median rotation-compensated flow (1/8 res) to initialise
    init_min_angle_deg: float = 1.0     #: a "wide" triangulation angle of an inlier (deg) ...
    init_min_wide_frac: float = 0.3     #: ... and the inlier fraction that also initialises (0 = off)
    init_min_inlier_frac: float = 0.5   #: essential-matrix RANSAC inlier fraction needed
    init_ransac_px: float = 1.0         #: essential-matrix RANSAC threshold (px)
    still_flow_lr_px: float = 0.25      #: mean flow (1/8 res) below which the camera is reported still
    # ---- depth output
    emit_delay: int = 2                 #: a keyframe is emitted once this many newer keyframes exist
    upsample_sigma_spatial: float = 0.8  #: joint bilateral spatial sigma (1/8-res cells)
    upsample_sigma_range: float = 12.0   #: joint bilateral range sigma (grey levels)
    upsample_spread_var: bool = True     #: add the interpolation uncertainty (depth edges) to the variance
    max_rel_depth_std: float = 0.1       #: valid only if std(inv depth) / inv depth below this
    max_depth_factor: float = 8.0        #: valid only if depth < factor * keyframe median depth
    far_factor: float = 3.0              #: textureless pixels beyond factor * median depth invalid
    textureless_grad: float = 3.0        #: local gradient (grey levels/px) below which a pixel is flat
    num_threads: int = 1                 #: torch threads while the front end runs (0 = leave as is)

    def validate(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                # NaN passes every ``x > limit`` test below and disables the check it feeds
                raise ValueError(f"{f.name} must be a finite number, got {v}")
        if self.flow_method not in FLOW_METHODS:
            raise ValueError(f"flow_method must be one of {FLOW_METHODS}, got {self.flow_method!r}")
        if self.flow_method == "torchscript" and not self.flow_weights_path:
            raise ValueError("flow_method 'torchscript' needs flow_weights_path (a local file)")
        if self.dis_preset not in DIS_PRESETS:
            raise ValueError(f"dis_preset must be one of {DIS_PRESETS}, got {self.dis_preset!r}")
        if self.chain_preset not in DIS_PRESETS:
            raise ValueError(f"chain_preset must be one of {DIS_PRESETS}, got {self.chain_preset!r}")
        if self.seed_features not in SEED_FEATURES:
            raise ValueError(f"seed_features must be one of {SEED_FEATURES}, got {self.seed_features!r}")
        if self.seed_max_features < 8 or self.seed_min_inliers < 6:
            raise ValueError("seed_max_features must be >= 8 and seed_min_inliers >= 6")
        if self.robust_loss not in ROBUST_LOSSES:
            raise ValueError(f"robust_loss must be one of {ROBUST_LOSSES}, got {self.robust_loss!r}")
        if not -1.0 <= self.ncc_min < 1.0:
            raise ValueError(f"ncc_min must be in [-1, 1), got {self.ncc_min}")
        if self.num_threads < 0:
            raise ValueError("num_threads must be >= 0")
        if not 0 <= self.dis_finest_scale <= 4:
            raise ValueError(f"dis_finest_scale must be in 0..4 (pyramid level), got {self.dis_finest_scale}")
        if self.window < 3:
            raise ValueError(f"window must be >= 3 keyframes, got {self.window}")
        if not 1 <= self.fixed_poses < self.window:
            raise ValueError(f"fixed_poses must be in [1, window), got {self.fixed_poses}")
        if self.keyframe_flow_lr_px <= 0:
            raise ValueError("keyframe_flow_lr_px must be positive")
        if self.temporal_radius < 1:
            raise ValueError("temporal_radius must be >= 1")
        if not 0 <= self.emit_delay < self.window:
            raise ValueError(f"emit_delay must be in [0, window), got {self.emit_delay}")
        for name in ("fb_sigma_px", "photo_sigma", "texture_tau", "block_spread_sigma_px",
                     "flow_sigma_px", "robust_delta_px", "upsample_sigma_spatial",
                     "upsample_sigma_range", "max_track_rms_px", "init_ransac_px", "seed_ransac_px", "seed_above_rms_px",
                     "max_rel_depth_std", "max_depth_factor", "far_factor"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive")
        for name in ("keyframe_conf_ratio", "min_confident_frac", "min_weight", "init_min_inlier_frac",
                     "init_min_wide_frac"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("proximity_flow_lr_px", "init_min_parallax_lr_px", "init_min_angle_deg", "still_flow_lr_px",
                     "textureless_grad", "lm_lambda"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 < self.min_inv_depth < self.max_inv_depth:
            raise ValueError(f"need 0 < min_inv_depth < max_inv_depth, got {self.min_inv_depth} and "
                             f"{self.max_inv_depth}")
        for name in ("ba_iters", "init_ba_iters", "track_iters", "relocalize_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_edges_per_keyframe < 0:
            raise ValueError(f"max_edges_per_keyframe must be >= 0, got {self.max_edges_per_keyframe}")
