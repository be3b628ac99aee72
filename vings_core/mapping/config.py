"""Mapper configuration (params section ``mapping``).

Units: distances in metres, angles in radians, learning rates per Adam step, score thresholds in
*pixel-weight units at the working resolution* (one fully opaque pixel covered by a Gaussian counts
1). Contribution and error scores scale with the number of pixels a Gaussian covers, i.e. with
``width * height``: when the working resolution changes from ``W0 x H0`` to ``W x H`` multiply
``sc_status``, ``se_status`` and ``sc_storage`` by ``(W * H) / (W0 * H0)`` to keep the same
behaviour (the paper's values were set at higher resolutions; the defaults here are for 376x240).
See docs/mapping.md.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import ClassVar


class RefineMode(str, enum.Enum):
    """Which poses single-to-multi pose refinement moves (params strings: the values)."""
    NONE = "none"          # no refinement
    SINGLE = "single"      # only the rendered keyframe's camera; the map is held (MonoGS/SplaTAM baseline)
    MULTI = "multi"        # every keyframe owning visible Gaussians, its Gaussians moving with it

    def __str__(self) -> str:
        return str(self.value)


class RefineSolver(str, enum.Enum):
    """How a pose-refinement step is computed (params strings: the values)."""
    GN = "gn"              # damped Gauss-Newton on the normal equations of a batch of renders (pose_gn.py)
    ADAM = "adam"          # Adam steps on autograd gradients of the training loss

    def __str__(self) -> str:
        return str(self.value)


@dataclass
class MapperConfig:
    # ---- representation
    sh_degree: int = 0                 # spherical-harmonics degree of the colours (0..3)
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # RGB in [0, 1]

    # ---- keyframe window and training
    window_size: int = 8               # local keyframe list length (paper 8)
    iters_per_keyframe: int = 50       # training iterations after each new keyframe (paper 50-100)
    # keeping up: a keyframe mapped while at least catch_up_backlog more wait behind it is trained
    # lightly (catch_up_iters iterations, no pose refinement); it stays in the map and in the window,
    # whose later training rounds keep training it (0 = every keyframe fully)
    catch_up_backlog: int = 2
    catch_up_iters: int = 10
    # coarse iterations: this fraction of the window's training renders is done at 1/coarse_factor
    # of the resolution (several times cheaper); they leave the scores and loss maps alone (0 = off)
    coarse_fraction: float = 0.0
    coarse_factor: int = 2
    sample_ratio: float = 0.5          # sample rasterizer: fraction r of pixels per tile back-propagated
    lambda_rgb: float = 1.0
    lambda_depth: float = 0.5
    lambda_normal: float = 0.1
    lambda_acc: float = 0.1
    lambda_ssim: float = 0.2           # L_rgb = (1 - l) L1 + l (1 - SSIM)
    depth_rel_std0: float = 0.02       # depth weight w = 1 / (1 + (sigma_d/d / depth_rel_std0)^2)
    normal_loss_warmup: int = 0        # iterations of a Gaussian map before L_n is switched on
    history_ratio: float = 0.3         # fraction of iterations on an older keyframe (left the window,
                                       # within tau of the camera) against forgetting; 0 = window only

    # ---- learning rates (sparse Adam, only unstable Gaussians are updated)
    lr_means: float = 2.0e-4           # m per step (indoor)
    outdoor: bool = False              # lower position learning rate outdoors (paper, from 3DGS)
    lr_means_outdoor_factor: float = 0.1
    lr_quats: float = 1.0e-3
    lr_scales: float = 5.0e-3          # on log-scales
    lr_opacity: float = 2.5e-2         # on opacity logits
    lr_sh: float = 2.5e-3              # DC band; higher bands use lr_sh / 20
    adam_betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    adam_eps: float = 1.0e-15

    # ---- initialisation / adding Gaussians from keyframe depth
    points_per_keyframe: int = 20000   # k new Gaussians for a fully uncovered frame (paper 50 000 at
                                       # 640x480); scaled by the low-accumulation area fraction
    max_depth: float = 40.0            # m: pixels farther are masked ("excessive depth")
    max_depth_rel_std: float = 0.05    # sigma_d / d above which a pixel is masked (high uncertainty)
    init_opacity: float = 0.7
    init_scale_factor: float = 0.9     # sigma = factor * mean distance to the 3 nearest new points
    min_scale_px: float = 0.3          # clamp of the initial sigma, in pixels of the adding frame
    max_scale_px: float = 6.0
    add_alpha_threshold: float = 0.6   # pixels with accumulated alpha below are "low accumulation"
    fill_unknown_depth: bool = True    # seed low-accumulation pixels whose depth is unknown (dropped as
                                       # uncertain, not empty) at push-pull-interpolated depth

    # ---- deleting conflicting Gaussians when a keyframe arrives
    delete_depth_rel: float = 0.15     # centre in front of the observed surface by > this x depth
    delete_rgb: float = 0.35           # mean abs RGB error at the centre's pixel above which a
                                       # Gaussian lying on the observed surface is removed
    delete_max_radius_frac: float = 0.15  # seen splats with projected radius > frac * diagonal go

    # ---- score manager (paper Algorithm 1); thresholds in pixel-weight units, see module doc
    score_manager: bool = True
    delta_status: int = 400            # status control every n iterations
    delta_storage: int = 200           # storage control every n iterations
    sc_status: float = 1.0e-4          # unstable -> stable when S_C below
    se_status: float = 0.5             # stable -> unstable when S_E above
    sc_storage: float = 2.7            # prune unstable Gaussians with S_C below (per view, see next)
    min_score_age: int = 100           # iterations of scoring before a Gaussian may be judged
    sc_storage_per_view: bool = True   # storage control compares S_C per window keyframe that sees the
                                       # Gaussian (S_C / #views) with sc_storage instead of the sum
    sc_view_floor: float = 0.1         # per-view rule: a window keyframe "sees" a Gaussian when its
                                       # contribution is >= this x the Gaussian's best window view
    prune_window_owned_only: bool = True  # storage control prunes only Gaussians whose ID(g) is a
                                       # window keyframe (False: the paper's rule on every Gaussian)
    prune_spare_high_error: bool = True   # storage control spares Gaussians whose window error per
                                       # contribution (sum e_t / sum c_t) exceeds the window keyframes'
                                       # mean L1 (small splats where the render is still wrong);
                                       # default with sc_storage 2.7 (docs/mapping.md)
    loop_prune_contribution: float = 0.01  # after a loop correction's retrain: an active Gaussian in
                                       # front of a retrained view whose summed contribution
                                       # (sum alpha T) over those views is below this is pruned
    erase_owner_keyframes: int = 8    # a keyframe's dynamic mask erases the Gaussians inside it
                                       # whose ID(g) keyframe is among this many latest keyframes
                                       # (what a moving object left before it was caught)

    # ---- storage tiers (paper "GPU-CPU transfer")
    delta_k: int = 8                   # tier update every n keyframes
    tau: float = 30.0                  # m: Gaussians whose ID(g) keyframe is nearer stay active
    max_active: int = 400000           # cap on the active (optimised, rendered) set
    passive_memory_mb: float = 1024.0  # host-memory budget of the passive store; beyond: spill to disk
    history_memory_mb: float = 256.0   # host-memory budget of the history keyframes; beyond: spill
    spill_dir: str = ""                # "" = a private temporary folder

    # ---- single-to-multi pose refinement
    refine_mode: RefineMode = RefineMode.MULTI   # none | single (rendered pose only) | multi
    refine_iters: int = 10             # per call of refine_poses()
    refine_solver: RefineSolver = RefineSolver.GN  # gn: damped Gauss-Newton (pose_gn.py); adam: gradient steps
    refine_gn_sigma_rgb: float = 0.05  # gn: colour residual noise (intensity in [0, 1]); depth uses depth_rel_std0
    refine_gn_huber: float = 2.0       # gn: Huber threshold in noise stds
    refine_gn_blur_px: float = 1.0     # gn: Gaussian blur of render and keyframe (wider convergence basin), px
    refine_gn_stride: int = 2          # gn: residuals on every stride-th pixel per axis (cost / stride^2)
    refine_gn_batch: int = 0           # gn: renders whose normal equations one joint step solves (0: window size)
    refine_gn_damping: float = 0.1     # gn: Levenberg-Marquardt damping, relative to the Hessian diagonal
    refine_gn_max_trans_rel: float = 0.005  # gn: trust region, translation per step as a fraction of the
                                       # window's median keyframe depth (1.45 cm at 2.9 m)
    refine_gn_max_rot: float = 0.01    # gn: trust region, rotation per step, rad
    refine_gn_decay: bool = False      # gn: a keyframe's t-th step is scaled by 1/t (averages the noise;
                                       # keeps exact poses closer, stops far ones short: docs/mapping.md)
    refine_lr_trans_rel: float = 3.5e-4  # translation per Adam step, as a fraction of the window's
                                       # median keyframe depth (1 mm at the room's 2.9 m): scale-free,
                                       # so a monocular map of any scale takes the same pixel-size steps
    refine_lr_rot: float = 2.0e-3      # rad per Adam step
    refine_lr_decay: bool = True       # step t of a keyframe's refinement uses lr / sqrt(t)
    refine_min_pixels: float = 50.0    # a keyframe needs this much contribution to be refined
    refine_fix_first: bool = True      # gauge: the first keyframe's pose is held fixed

    seed: int = 0

    # removed parameter names -> what replaces them (the params loader names it in its error)
    RENAMED: ClassVar[dict] = {
        "refine_lr_trans": "'refine_lr_trans_rel', a fraction of the window's median keyframe depth "
                           "per step instead of metres (3.5e-4 = 1 mm at 2.9 m)"}

    def __post_init__(self) -> None:
        # the string policies as their Enum (a params string, or a value given in code); an unknown
        # string stays as it is for validate() to name
        for name, kind in (("refine_mode", RefineMode), ("refine_solver", RefineSolver)):
            value = getattr(self, name)
            if not isinstance(value, kind) and value in [k.value for k in kind]:
                setattr(self, name, kind(value))

    def validate(self) -> None:
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if len(self.background) != 3:
            raise ValueError("background must have 3 values")
        if self.window_size < 1:
            raise ValueError("window_size must be >= 1")
        if self.iters_per_keyframe < 0:
            raise ValueError("iters_per_keyframe must be >= 0")
        if self.catch_up_backlog < 0 or self.catch_up_iters < 0:
            raise ValueError("catch_up_backlog and catch_up_iters must be >= 0")
        if not 0 <= self.history_ratio < 1:
            raise ValueError(f"history_ratio must be in [0, 1), got {self.history_ratio}")
        if not 0 <= self.coarse_fraction < 1:
            raise ValueError(f"coarse_fraction must be in [0, 1), got {self.coarse_fraction}")
        if self.coarse_factor < 2:
            raise ValueError(f"coarse_factor must be >= 2, got {self.coarse_factor}")
        if not 0 < self.sample_ratio <= 1:
            raise ValueError(f"sample_ratio must be in (0, 1], got {self.sample_ratio}")
        for name, kind in (("refine_mode", RefineMode), ("refine_solver", RefineSolver)):
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name} must be {'|'.join(k.value for k in kind)}, got {getattr(self, name)!r}")
        for name in ("refine_gn_sigma_rgb", "refine_gn_huber", "refine_gn_max_trans_rel", "refine_gn_max_rot"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.refine_gn_stride < 1:
            raise ValueError(f"refine_gn_stride must be >= 1, got {self.refine_gn_stride}")
        if not (self.refine_gn_damping >= 0 and self.refine_gn_blur_px >= 0 and self.refine_gn_batch >= 0):
            raise ValueError("refine_gn_damping, refine_gn_blur_px and refine_gn_batch must be >= 0")
        if self.delta_status < 1 or self.delta_storage < 1 or self.delta_k < 1:
            raise ValueError("delta_status, delta_storage and delta_k must be >= 1")
        if self.points_per_keyframe < 1:
            raise ValueError("points_per_keyframe must be >= 1")
        if not 0 <= self.sc_view_floor <= 1:
            raise ValueError(f"sc_view_floor must be in [0, 1], got {self.sc_view_floor}")
        if self.max_active < 1:
            raise ValueError("max_active must be >= 1")
        if self.erase_owner_keyframes < 0:
            raise ValueError(f"erase_owner_keyframes must be >= 0, got {self.erase_owner_keyframes}")
        if not self.loop_prune_contribution >= 0:
            raise ValueError(f"loop_prune_contribution must be >= 0, got {self.loop_prune_contribution}")
        if not (self.passive_memory_mb >= 0 and self.history_memory_mb >= 0):
            raise ValueError("passive_memory_mb and history_memory_mb must be >= 0 (MB)")
        if len(self.adam_betas) != 2:
            raise ValueError("adam_betas must have 2 values")
