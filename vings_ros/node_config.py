"""Settings of the nodes: the shared section ``ros`` and one section per node (named after it).

Plain dataclasses without rclpy, so ``vings run --params`` and ``vings launch`` check every section
of a params file without starting ROS. The library stages' sections (``frontend``, ``mapping``,
``run``, ...) are vings_core's (vings_core.config.LIBRARY_SECTIONS).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass


class QueuePolicy(str, enum.Enum):
    """Input queue of a node (vings_ros.node_common.InputQueue).

    ``keep_newest`` (live): the worker takes the newest waiting input, older ones are dropped and
    counted. ``backpressure`` (replay with ``--wait-for-graph``): nothing is dropped; the queue
    holds up to ``queue_size`` items and the replay waits for acknowledgements."""

    KEEP_NEWEST = "keep_newest"
    BACKPRESSURE = "backpressure"


class ExitPolicy(str, enum.Enum):
    """What ``vings launch`` does when a node exits by itself (crash, kill, error)."""

    RESPAWN = "respawn"     # start it again after a back-off; the other nodes keep working
    STOP = "stop"           # stop the whole graph
    CONTINUE = "continue"   # report it; the graph goes on without it


class StopPolicy(str, enum.Enum):
    """What the mapper does with keyframes it received but has not mapped when it is stopped."""

    STORE = "store"     # store them with the checkpoint (its queue folder) and stop within seconds;
                        # the mapper maps them when it resumes (needs checkpoint_path, else TRAIN)
    TRAIN = "train"     # map them first, for at most shutdown_timeout_s


@dataclass
class RespawnSettings:
    """How ``vings launch`` treats the node's exit (:class:`ExitPolicy`): ``on_exit``;
    ``respawn_max``: restarts at most (then a node the graph needs stops it, an optional one is left
    out); ``respawn_backoff_s``: wait before the first restart, doubled for each further one. A
    respawned node resumes from its checkpoint when it has one (``checkpoint_path``)."""

    on_exit: ExitPolicy = ExitPolicy.RESPAWN
    respawn_max: int = 3
    respawn_backoff_s: float = 1.0

    def validate(self) -> None:
        if self.respawn_max < 0:
            raise ValueError(f"respawn_max must be >= 0, got {self.respawn_max}")
        if not self.respawn_backoff_s >= 0:
            raise ValueError(f"respawn_backoff_s must be >= 0, got {self.respawn_backoff_s}")


def _check_frame(name: str, value: str) -> None:
    if not value.strip() or value.startswith("/"):
        raise ValueError(f"{name} must be a frame id without a leading '/', got {value!r}")


@dataclass
class RosConfig:
    """Settings every node shares (params section ``ros``): the frame ids of its outputs and the
    /diagnostics period."""

    world_frame: str = "map"
    camera_frame: str = "camera_optical_frame"
    diagnostics_period_s: float = 1.0

    def validate(self) -> None:
        if not self.diagnostics_period_s > 0:
            raise ValueError(f"diagnostics_period_s must be > 0, got {self.diagnostics_period_s}")
        _check_frame("world_frame", self.world_frame)
        _check_frame("camera_frame", self.camera_frame)


@dataclass
class CheckpointSettings:
    """Checkpointing of a node's state (vings_ros.node_base.StageNode checkpoint hooks).

    ``checkpoint_path``: the checkpoint file ("" = none); ``resume``: load it at start if it
    exists. It is written (atomically) on shutdown, whenever ``checkpoint_period_s`` seconds
    passed since the last one and the state changed (0 = no periodic checkpoint), and when the
    node asks for one."""

    checkpoint_path: str = ""
    resume: bool = True
    checkpoint_period_s: float = 30.0

    def validate(self) -> None:
        validate = getattr(super(), "validate", None)   # a settings mixin after this one in the MRO
        if validate is not None:
            validate()
        if self.checkpoint_period_s < 0:
            raise ValueError("checkpoint_period_s must be >= 0")


@dataclass
class FrontendNodeConfig(CheckpointSettings, RespawnSettings):
    """``frontend_node`` settings (params section ``frontend_node``).

    ``queue_policy`` / ``queue_size``: the image queue (:class:`QueuePolicy`; ``keep_newest`` holds
    one image). ``calib_file``: calibration YAML used instead of the camera_info topic.
    ``calib_wait_s``: how long an image that arrived before any calibration is held.
    ``width``/``height``: working resolution the images are resized/undistorted to (0 = as
    published). ``path_max_poses``: poses in /vings/path. ``resend_after_s``: keyframes the mapper
    has not acknowledged (listed on /vings/keyframes/refined) this long after they were sent while
    the mapper listed nothing new for as long, or when a mapper comes back after it was gone, are
    sent again (a mapper that was down or restarted gets what it
    missed; 0 = never); ``unacked_memory_keyframes``: of those, held in memory (the others wait in
    a private folder on disk).

    Checkpoint (:class:`CheckpointSettings`; ``vings launch --checkpoint F`` sets ``F.frontend``):
    the window, every frame's pose, the motion model and the smoother, written at the first new
    keyframe ``checkpoint_every_s`` (sensor time) after the last checkpoint's frame (0 = only
    every ``checkpoint_period_s`` of wall time and at the stop); the keyframes the mapper has not
    acknowledged wait in ``F.frontend.unacked/``. A restarted node loads it; its first image goes on
    tracking when it comes at most ``resume_max_gap_s`` after the checkpoint's last frame, else it is
    relocalised against the checkpoint's window (a new map segment if that fails) and the pose found
    verified against a render of the map (the loop closer's ``render_l1_max`` and
    ``render_min_coverage``; the mapper answers within ``relocalise_render_timeout_s`` or it stays
    unverified); an image not after the checkpoint's last frame (another recording) starts a fresh
    front end."""

    queue_policy: QueuePolicy = QueuePolicy.KEEP_NEWEST
    queue_size: int = 64
    calib_file: str = ""
    calib_wait_s: float = 2.0
    width: int = 0
    height: int = 0
    path_max_poses: int = 10000
    resend_after_s: float = 30.0
    unacked_memory_keyframes: int = 8
    checkpoint_every_s: float = 0.5
    resume_max_gap_s: float = 1.0
    relocalise_render_timeout_s: float = 2.0

    def validate(self) -> None:
        super().validate()
        if not self.checkpoint_every_s >= 0:
            raise ValueError(f"checkpoint_every_s must be >= 0, got {self.checkpoint_every_s}")
        if not self.resume_max_gap_s >= 0:
            raise ValueError(f"resume_max_gap_s must be >= 0, got {self.resume_max_gap_s}")
        if not self.relocalise_render_timeout_s > 0:
            raise ValueError(f"relocalise_render_timeout_s must be > 0, got {self.relocalise_render_timeout_s}")
        if self.resend_after_s < 0:
            raise ValueError("resend_after_s must be >= 0")
        if self.unacked_memory_keyframes < 1:
            raise ValueError("unacked_memory_keyframes must be >= 1")
        if self.queue_size < 1:
            raise ValueError("queue_size must be >= 1")
        if self.width < 0 or self.height < 0:
            raise ValueError("width/height must be >= 0")
        if self.calib_wait_s < 0:
            raise ValueError("calib_wait_s must be >= 0")
        if self.path_max_poses < 1:
            raise ValueError("path_max_poses must be >= 1")


@dataclass
class MapperNodeConfig(CheckpointSettings, RespawnSettings):
    """``mapper_node`` settings (params section ``mapper_node``), besides the checkpoint ones
    (:class:`CheckpointSettings`).

    The mapper also checkpoints after its first keyframe and every ``checkpoint_every_keyframes``
    keyframes (0 = off). ``on_stop`` (:class:`StopPolicy`): on a stop, keyframes not mapped yet
    are stored with the checkpoint and mapped when the node resumes (``store``, the default: the
    stop takes seconds; without ``checkpoint_path`` there is nowhere to keep them and the mapper
    trains them instead), or trained first (``train``). ``shutdown_timeout_s``: how long it may work
    through queued keyframes after SIGINT with ``train`` (the rest then waits on disk when a
    checkpoint is set, else is lost and said so). ``nice``: niceness the mapper process adds to itself, so tracking wins the CPU
    (0 = off); ``threads``: torch / numba threads (0 = library default). ``points_period_s``:
    throttle of /vings/map/points, ``max_points`` its size. ``render_every_keyframes``: publish
    renders after every n-th keyframe (0 = never). ``queue_memory_keyframes``: received keyframes
    waiting for the mapper held in memory; later ones wait on disk
    (:class:`vings_core.keyframe_queue.KeyframeQueue`), none is dropped. ``queue_spill_dir``: their
    folder; empty: ``<checkpoint_path>.queue`` when a checkpoint is set (a stopped or killed node
    that resumes maps what waited there), else a private temporary folder."""

    checkpoint_every_keyframes: int = 5
    on_stop: StopPolicy = StopPolicy.STORE
    shutdown_timeout_s: float = 120.0
    nice: int = 10
    threads: int = 0
    points_period_s: float = 2.0
    max_points: int = 200000
    render_every_keyframes: int = 1
    queue_memory_keyframes: int = 8
    queue_spill_dir: str = ""

    def validate(self) -> None:
        super().validate()
        if self.queue_memory_keyframes < 1:
            raise ValueError(f"queue_memory_keyframes must be >= 1, got {self.queue_memory_keyframes}")
        if self.checkpoint_every_keyframes < 0:
            raise ValueError("checkpoint_every_keyframes must be >= 0")
        if not 0 <= self.nice <= 19:
            raise ValueError(f"nice must be in 0..19, got {self.nice}")
        if self.threads < 0:
            raise ValueError("threads must be >= 0")
        if self.shutdown_timeout_s < 0:
            raise ValueError("shutdown_timeout_s must be >= 0")
        if self.points_period_s < 0:
            raise ValueError("points_period_s must be >= 0")
        if self.max_points < 0 or self.render_every_keyframes < 0:
            raise ValueError("max_points and render_every_keyframes must be >= 0")



@dataclass
class LoopCloserNodeConfig(CheckpointSettings, RespawnSettings):
    """``loop_closer_node`` settings (params section ``loop_closer_node``), besides the checkpoint
    ones (:class:`CheckpointSettings`: the keyframe database, accepted loops, records and the
    exchange state, written atomically; resumed at start).

    ``render_timeout_s``: how long a render request waits for the mapper's reply; a reply that
    does not come counts as "no map to render" (the candidate is rejected, the node goes on). The
    mapper answers between training chunks, but not during its retrain after a loop (up to
    ``loop.retrain_max_s``): keep the timeout above that.
    ``queue_memory_keyframes``: received keyframes waiting for the loop closer held in memory;
    later ones wait on disk in a private temporary folder (none is dropped while the node runs).
    ``output_dir``: folder of ``loops.json`` ("" = none), rewritten atomically after an accepted
    loop, at most every ``report_period_s`` seconds otherwise while candidates are checked, and at
    shutdown. ``nice``: niceness the process adds to itself, so tracking wins the CPU (0 = off)."""

    render_timeout_s: float = 30.0
    queue_memory_keyframes: int = 8
    output_dir: str = ""
    report_period_s: float = 5.0
    nice: int = 10

    def validate(self) -> None:
        super().validate()
        if not self.render_timeout_s > 0:
            raise ValueError(f"render_timeout_s must be > 0, got {self.render_timeout_s}")
        if self.queue_memory_keyframes < 1:
            raise ValueError(f"queue_memory_keyframes must be >= 1, got {self.queue_memory_keyframes}")
        if self.report_period_s < 0:
            raise ValueError(f"report_period_s must be >= 0, got {self.report_period_s}")
        if not 0 <= self.nice <= 19:
            raise ValueError(f"nice must be in 0..19, got {self.nice}")


@dataclass
class EraserNodeConfig(RespawnSettings):
    """``eraser_node`` settings (params section ``eraser_node``); the eraser's own settings are the
    library section ``eraser`` (``eraser.mask_timeout_s``: how long the mapper waits for a mask).

    ``render_timeout_s``: how long the node waits for the mapper's render of a keyframe's pose;
    without a reply in time (or without a mapper) the keyframe is processed with the motion cue
    only. The mapper answers between training chunks but not during its retrain after a loop:
    keep the timeout short, a mask that comes after ``eraser.mask_timeout_s`` is late for the
    mapper anyway (it is applied to the mapped keyframe then). ``queue_memory_keyframes``:
    received keyframes waiting for the eraser held in memory; later ones wait on disk in a private
    temporary folder (none is dropped while the node runs; they are processed in order). ``nice``:
    niceness the process adds to itself, so tracking wins the CPU (0 = off)."""

    render_timeout_s: float = 1.0
    queue_memory_keyframes: int = 8
    nice: int = 10

    def validate(self) -> None:
        super().validate()
        if not self.render_timeout_s > 0:
            raise ValueError(f"render_timeout_s must be > 0, got {self.render_timeout_s}")
        if self.queue_memory_keyframes < 1:
            raise ValueError(f"queue_memory_keyframes must be >= 1, got {self.queue_memory_keyframes}")
        if not 0 <= self.nice <= 19:
            raise ValueError(f"nice must be in 0..19, got {self.nice}")


#: ``ros.<key>`` names of node settings that live in a node's own section: a params file or ``-p``
#: that uses one gets an error naming the section's key instead of "unknown parameter"
MOVED_PARAMETERS = {
    **{f"ros.{k}": f"frontend_node.{k}" for k in ("queue_policy", "queue_size", "calib_file",
                                                   "calib_wait_s", "width", "height", "path_max_poses")},
    **{f"ros.{k}": f"mapper_node.{k}" for k in ("checkpoint_path", "resume", "checkpoint_period_s",
                                                 "checkpoint_every_keyframes", "shutdown_timeout_s",
                                                 "points_period_s", "max_points", "render_every_keyframes")},
    "ros.mapper_nice": "mapper_node.nice",
    "ros.mapper_threads": "mapper_node.threads",
}
