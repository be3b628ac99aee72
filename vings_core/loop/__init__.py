"""Loop closure (the paper's "NVS Loop Closure"): a keyframe database with weight-free features and
an online bag of words, candidates by radius and retrieval, verification by PnP and a render of the
map, a GTSAM pose graph (Sim(3) visual-only, SE(3) visual-inertial) whose corrections travel
through the pose exchange."""
from .closer import LOOP_SOURCE, AcceptedLoop, LoopCloser
from .config import GraphChoice, LoopConfig, LoopFeatures, Verdict
from .database import KeyframeDatabase, KeyframeEntry, Vocabulary
from .pose_graph import GraphMode, LoopEdge, PoseGraphResult, optimize_pose_graph

__all__ = ["LOOP_SOURCE", "AcceptedLoop", "LoopCloser", "GraphChoice", "LoopConfig", "LoopFeatures", "Verdict",
           "KeyframeDatabase", "KeyframeEntry", "Vocabulary", "GraphMode", "LoopEdge", "PoseGraphResult",
           "optimize_pose_graph"]
