"""Visual front end: dense flow targets, keyframes, covisibility graph, dense BA at 1/8 resolution
with Schur complement, reduced pose system export, depth uncertainty, dense depth, per-frame tracking.

Main entry point: :class:`Frontend` (``Frontend(config, camera)``, ``process(frame)``,
``pop_keyframes()``, ``set_poses(...)``, ``apply_increments(...)``, ``state``/``reason``). See
docs/frontend.md.
"""
from .ba import PoseSystem, bundle_adjust, motion_only, reduced_pose_system
from .config import FrontendConfig
from .flow import DISFlow, FlowEstimator, TorchScriptFlow, make_flow_estimator
from .tracker import Frontend

__all__ = ["Frontend", "FrontendConfig", "FlowEstimator", "DISFlow", "TorchScriptFlow",
           "make_flow_estimator", "PoseSystem", "bundle_adjust", "motion_only",
           "reduced_pose_system"]
