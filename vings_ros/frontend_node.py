"""``frontend_node``: images (+ camera_info, IMU) in; odometry, path and keyframe packets out.

It only translates messages (``msg_adapters``) and calls :class:`vings_core.frontend.Frontend`, the
class ``vings run`` uses. The dynamic eraser's masks (``/vings/keyframe/dynamic_mask``, from
``eraser_node``) go to ``Frontend.post_dynamic_mask`` (applied before the next frame, never waited
for). Settings: params sections ``frontend_node`` (node_config.FrontendNodeConfig),
``ros``, ``frontend`` and ``run``. Topics and parameters: docs/ros.md.
"""
from __future__ import annotations

import threading
import time
from typing import Optional

import cv2
import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import CameraInfo, Image, Imu
from std_msgs.msg import Header

from msg_adapters import topics as T
from msg_adapters.camera_info import camera_info_to_camera
from msg_adapters.diagnostics import TRACKING_STATE_LEVEL
from msg_adapters.eraser import msg_to_mask
from msg_adapters.image import FrameDecoder
from msg_adapters.imu import msg_to_imu_sample
from msg_adapters.keyframe import PART_TOPICS, keyframe_to_msgs
from msg_adapters.exchange import batch_to_path, exchange_topic
from msg_adapters.pose import estimate_to_odometry, path_to_trajectory, trajectory_to_path
from msg_adapters.stamps import header_ns
from vings_core.errors import InputError
from vings_core.frontend import Frontend, FrontendConfig
from vings_core.frontend.checkpoint import (FrontendCheckpoint, RestartMode, load_frontend_checkpoint,
                                            restart_policy, save_frontend_checkpoint)
from vings_core.frontend.flow import make_flow_estimator
from vings_core.io.calib_yaml import is_rectified_topic, load_calibration_yaml
from vings_core.io.undistort import Undistorter
from vings_core.keyframe_queue import UnackedKeyframes
from vings_core.loop.config import LoopConfig
from vings_core.loop.verify import render_agreement, scaled_camera
from vings_core.exchange import ExchangeConfig, PoseKeeper
from vings_core.exchange.config import KEEPER
from vings_core.types import POSED_STATES, Calibration, CameraModel, Frame, TrackState
from vings_core.vio.config import ViConfig
from vings_core.vio.fusion import ViFusion

from . import registry
from .node_base import BatchInbox, Level, NodeStatus, StageNode
from .node_common import RateMeter, publisher_ids, wait_all_acked, worth_reporting as _report
from .node_config import FrontendNodeConfig, QueuePolicy
from .render_client import RenderClient

#: consecutive skipped images after which /diagnostics reports an error
BAD_STREAK_ERROR = 5
#: at the stop: how long the last keyframe packets may take to be confirmed by their readers (s)
FLUSH_TIMEOUT_S = 5.0


class FrontendNode(StageNode):
    spec = registry.node_spec("frontend_node")
    STATUS_NAME = "vings/frontend"
    WORKER_STOP_TIMEOUT_S = 60.0

    settings: FrontendNodeConfig

    def setup(self) -> None:
        self.fcfg: FrontendConfig = self.config("frontend")
        self.vcfg: ViConfig = self.config("vio")
        self.calib: Optional[Calibration] = None     # from frontend_node.calib_file (T_bc, IMU noise)
        self.vio_why = "visual-only: no IMU message yet"
        self._exchange_setup()      # before a calibration file makes the front end (and its keeper)
        self.raw_camera: Optional[CameraModel] = None
        self.undist: Optional[Undistorter] = None
        self.frontend: Optional[Frontend] = None
        self.decoder = FrameDecoder(T.IMAGE_TOPIC)
        # keep_newest: depth 1, a new image replaces the waiting one (dropped and counted)
        policy = self.settings.queue_policy
        self.queue = self.input_queue(policy, 1 if policy is QueuePolicy.KEEP_NEWEST
                                      else self.settings.queue_size)
        self._camera_ready = threading.Event()
        self.rate = RateMeter()
        self.imu_count = 0
        self.bad_imu = 0
        self.late_poses = 0         # back-filled odometry published after its frame (initialisation)
        self.frames_without_camera = 0
        self.bad_frames = 0
        self.bad_streak = 0             # images skipped since the last one processed
        self._last_skip = ""
        self.bad_camera_infos = 0
        self.camera_changes = 0         # CameraInfo messages that differ from the camera in use
        self.masks_received = 0         # the eraser's dynamic masks
        self.masks_unused = 0           # came before the front end had a camera
        self.bad_masks = 0
        # made now (a learned model loads its weights file): a wrong path is a start-up error, not
        # one that ends the node when the camera appears
        self._flow = make_flow_estimator(self.fcfg)
        self._last_stamp: Optional[int] = None
        calib_file = self.settings.calib_file
        if calib_file:
            calib = load_calibration_yaml(calib_file)
            if calib.camera is None:
                raise InputError(f"{calib_file}: calibration has no camera")
            self.calib = calib
            self._set_camera(calib.camera)

        sq = T.sensor_qos
        image_sub = self.create_subscription(Image, T.IMAGE_TOPIC, self._on_image, sq(T.IMAGE_DEPTH))
        # remapped to image_proc's rectified output: the camera is CameraInfo's P, not K and D
        self._rectified = is_rectified_topic(image_sub.topic_name)
        self.create_subscription(CameraInfo, T.CAMERA_INFO_TOPIC, self._on_camera_info,
                                 sq(T.CAMERA_INFO_DEPTH))
        self.create_subscription(Imu, T.IMU_TOPIC, self._on_imu, sq(T.IMU_DEPTH))
        self.create_subscription(Image, T.DYNAMIC_MASK_TOPIC, self._on_mask, sq(T.OUTPUT_DEPTH * 4))
        self.pub_odom = self.create_publisher(Odometry, T.ODOMETRY_TOPIC, T.odometry_qos())
        self.pub_path = self.create_publisher(Path, T.PATH_TOPIC, T.latched_qos(1))
        self.pub_kf = {p: self.create_publisher(type_, PART_TOPICS[p], sq(T.OUTPUT_DEPTH * 4))
                       for p, type_ in (("image", Image), ("depth", Image), ("inv_depth_var", Image),
                                        ("pose", PoseStamped), ("camera_info", CameraInfo))}
        self.pub_ack = self.create_publisher(Header, T.PROCESSED_TOPIC, sq(T.ACK_DEPTH))
        self._last_path_pub = 0.0
        # keyframes until the mapper lists them (sent again to a mapper that missed them)
        self.unacked = self._new_unacked()
        self._unacked_lock = threading.Lock()
        self.keyframes_resent = 0
        self._mapper_up: Optional[bool] = None     # None: never seen; False: seen, then gone
        self._mapper_gids: set[tuple] = set()       # endpoint ids of the mapper's keyframe list
        self._next_ack_check = 0.0
        self._last_refined = time.monotonic()
        self._refined_seen = False      # the mapper's (latched) keyframe list heard since the start
        self.sub_refined = self.create_subscription(Path, T.REFINED_KEYFRAMES_TOPIC, self._on_refined,
                                                    T.latched_qos(1))
        self.create_subscription(Path, T.CHECKPOINTED_KEYFRAMES_TOPIC, self._on_checkpointed, T.latched_qos(1))
        # a restart: the checkpoint's front end, decided on at the first new image (RestartMode)
        self.restart = RestartMode.FRESH
        self.restart_gap_s: Optional[float] = None
        self.restart_outcome = ""
        self._restored: Optional[FrontendCheckpoint] = None
        self._resend_restored = False
        self._ckpt_stamp: Optional[int] = None      # the last frame of the last checkpoint
        self.restart_render: dict = {}              # the render check of a relocalisation
        self.lcfg: LoopConfig = self.config("loop")
        self._abort = threading.Event()             # stopping: a render wait ends at once
        self.render_client: Optional[RenderClient] = None
        self._finished = False
        resume = self.resume_file()
        if resume is not None:
            self._restore(load_frontend_checkpoint(resume, self.fcfg, self._flow), resume)
            # renders to check a relocalisation: asked for only after a restart, and the client is
            # removed once the restart is settled (the eraser's renders do not reach this node)
            self.render_client = RenderClient(self, self._abort, ids="clock",
                                              consequence="the relocalisation after the restart stays unverified")

    def _new_unacked(self) -> UnackedKeyframes:
        """With a checkpoint, the unacknowledged keyframes are also kept in ``<checkpoint>.unacked/``
        (a restarted front end sends them again)."""
        keep = f"{self.checkpoint_file}.unacked" if self.checkpoint_file is not None else None
        return UnackedKeyframes(self.settings.unacked_memory_keyframes, keep_dir=keep)

    def ready_message(self) -> str:
        return (f"front end ready (queue policy {self.settings.queue_policy.value}); waiting for "
                f"{T.IMAGE_TOPIC} and {'calibration' if self.raw_camera is None else 'images'}")

    # ------------------------------------------------------------------------------ callbacks

    def _on_image(self, msg: Image) -> None:
        self.queue.put(msg)

    def _listed(self, msg: Path, topic: str) -> Optional[list[int]]:
        """The keyframe stamps a mapper's list (``nav_msgs/Path``) names; None (warned) if malformed."""
        try:
            return path_to_trajectory(msg, topic).stamps_ns.tolist()
        except InputError as e:
            self.get_logger().warning(f"{topic}: ignored ({e})", throttle_duration_sec=10.0)
            return None

    def _on_refined(self, msg: Path) -> None:
        """The mapper's keyframes: every stamp listed is acknowledged, unless the mapper keeps a
        checkpoint (it publishes what it holds there, :meth:`_on_checkpointed`)."""
        stamps = self._listed(msg, T.REFINED_KEYFRAMES_TOPIC)
        if stamps is None:
            return
        durable = self.count_publishers(T.CHECKPOINTED_KEYFRAMES_TOPIC) > 0
        with self._unacked_lock:
            if not durable:         # a mapper without a checkpoint: what it lists is all there is
                self.unacked.acknowledged(stamps)
            self._last_refined = time.monotonic()
            self._refined_seen = True

    def _on_checkpointed(self, msg: Path) -> None:
        """The keyframes in the mapper's last checkpoint: those survive a crash of the mapper, so
        only they are released (a mapper with a checkpoint)."""
        stamps = self._listed(msg, T.CHECKPOINTED_KEYFRAMES_TOPIC)
        if stamps is None:
            return
        with self._unacked_lock:
            self.unacked.acknowledged(stamps)

    def _resend_unacked(self) -> None:
        """Send again the keyframes the mapper has not acknowledged, when a mapper (re)appeared, or
        when the oldest waited ``resend_after_s`` and the mapper listed nothing new for as long (a
        mapper that is only behind keeps listing: no re-send). Worker thread, at most once a
        second."""
        now = time.monotonic()
        if self.settings.resend_after_s <= 0 or now < self._next_ack_check:
            return
        self._next_ack_check = now + 1.0
        gids = publisher_ids(self, T.REFINED_KEYFRAMES_TOPIC)
        up = len(gids) > 0
        # a mapper that came back after it was gone, or a new one while the killed one's endpoint
        # still lingers in discovery (a new endpoint id); the first one to appear gets the keyframes
        appeared = up and (self._mapper_up is False or bool(self._mapper_gids and gids - self._mapper_gids))
        self._mapper_gids = gids
        if self._resend_restored and up and (self._refined_seen or now - self._last_refined > 5.0):
            # restored from the checkpoint: what the mapper has not listed by now is sent again
            appeared, self._resend_restored = True, False
        if up or self._mapper_up is not None:
            self._mapper_up = up
        with self._unacked_lock:
            wait = self.settings.resend_after_s
            stalled = self.unacked.overdue(now, wait) and now - self._last_refined > wait
            if not len(self.unacked) or not up or not (appeared or stalled):
                return
            kfs = self.unacked.pending()
            self.unacked.restamp(now)
        for kf in kfs:
            self._publish_parts(kf)
        self.keyframes_resent += len(kfs)
        self.get_logger().info(f"sent {len(kfs)} keyframe(s) again that the mapper had not acknowledged"
                               + (" (a mapper appeared, or the front end restarted)" if appeared else f" within {self.settings.resend_after_s:g} s"))

    def _on_camera_info(self, msg: CameraInfo) -> None:
        if self.settings.calib_file:
            return      # frontend_node.calib_file gives the camera
        try:
            cam = camera_info_to_camera(msg, T.CAMERA_INFO_TOPIC, self._rectified)
        except InputError as e:
            # e.g. a driver that publishes K = 0 until its calibration is loaded: keep waiting
            self.bad_camera_infos += 1
            if _report(self.bad_camera_infos):
                self.get_logger().warning(f"ignored {self.bad_camera_infos} unusable "
                                          f"{T.CAMERA_INFO_TOPIC} message(s): {e}")
            return
        if self.raw_camera is None:
            self._set_camera(cam)
        elif cam != self.raw_camera:
            # the map and the front end's state belong to the first camera: keep it
            self.camera_changes += 1
            if _report(self.camera_changes):
                r = self.raw_camera
                self.get_logger().warning(
                    f"{T.CAMERA_INFO_TOPIC} changed ({cam.width}x{cam.height}, fx {cam.fx:.6g}) from the "
                    f"camera in use ({r.width}x{r.height}, fx {r.fx:.6g}); the front end keeps the first "
                    f"one: restart the nodes for a new camera ({self.camera_changes} such message(s))")

    def _on_imu(self, msg: Imu) -> None:
        # checked, counted, and given to the fusion when it runs (its buffer is thread-safe)
        try:
            sample = msg_to_imu_sample(msg, T.IMU_TOPIC)
        except InputError as e:
            self.bad_imu += 1
            if _report(self.bad_imu):
                self.get_logger().warning(f"bad IMU message ({self.bad_imu} so far): {e}")
            return
        self.imu_count += 1
        fe = self.frontend
        if fe is not None and fe.vio is not None:
            fe.add_imu(sample)
        elif self.imu_count == 1 and self.vcfg.enabled:
            self.get_logger().error(self._no_fusion_why())

    def _on_mask(self, msg: Image) -> None:
        """The eraser's mask of a keyframe -> the front end (thread-safe; applied before its next
        frame to the keyframe if it is still in the window)."""
        try:
            stamp, mask = msg_to_mask(msg, T.DYNAMIC_MASK_TOPIC)
        except InputError as e:
            self.bad_masks += 1
            if _report(self.bad_masks):
                self.get_logger().warning(f"ignored a malformed dynamic mask ({self.bad_masks} so far): {e}")
            return
        self.masks_received += 1
        fe, undist = self.frontend, self.undist
        if fe is None or undist is None:
            self.masks_unused += 1
            return
        cam = undist.camera
        if mask.shape != (cam.height, cam.width):
            self.bad_masks += 1
            if _report(self.bad_masks):
                self.get_logger().warning(f"ignored the dynamic mask of keyframe {stamp}: {mask.shape[1]}x"
                                          f"{mask.shape[0]}, the working resolution is {cam.width}x{cam.height}")
            return
        if mask.any():
            fe.post_dynamic_mask(stamp, mask)

    def _no_fusion_why(self) -> str:
        if not self.vcfg.enabled:
            return "visual-only: IMU fusion switched off (vio.enabled false)"
        return ("visual-only: IMU messages arrive but the camera-IMU extrinsic T_bc is unknown; give "
                "frontend_node.calib_file (Kalibr/EuRoC YAML with T_BS / T_cam_imu) to fuse them")

    def _make_fusion(self) -> Optional[ViFusion]:
        """The fusion when the calibration file gives ``T_bc`` (there is no tf2 here)."""
        if self.calib is None:
            self.vio_why = self._no_fusion_why()
            return None
        vio, self.vio_why = ViFusion.for_source(self.vcfg, self.calib, True)
        return vio

    def _set_camera(self, raw: CameraModel) -> None:
        w = self.settings.width or None
        h = self.settings.height or None
        self.undist = Undistorter(raw, w, h, undistort=True)
        self.raw_camera = raw
        self.frontend = Frontend(self.fcfg, self.undist.camera, flow=self._flow, vio=self._make_fusion())
        self.keeper = PoseKeeper(self.frontend, self.xcfg)
        cam = self.undist.camera
        self._camera_ready.set()
        self.get_logger().info(f"camera {raw.width}x{raw.height} -> working {cam.width}x{cam.height}")

    # ------------------------------------------------------------------------------ checkpoint

    def _restore(self, ck: FrontendCheckpoint, path) -> None:
        """The checkpoint's front end, pose keeper, camera and unacknowledged keyframes; what to do
        with them is decided at the first new image (:meth:`_first_after_restore`)."""
        raw = ck.extra.get("raw_camera")
        if raw is None:
            raise InputError(f"{path}: the front-end checkpoint has no camera")
        self.raw_camera = CameraModel.from_dict(raw)
        self.undist = Undistorter(self.raw_camera, self.settings.width or None, self.settings.height or None,
                                  undistort=True)
        if self.undist.camera != ck.frontend.camera:
            raise InputError(f"{path}: the checkpoint's working camera differs from frontend_node.width/"
                             f"height now; start without it (move the file away) or set the same size")
        self.frontend = ck.frontend
        self.keeper = ck.state["keeper"]
        self.keeper.cfg = self.xcfg
        self._resend_restored = len(self.unacked.restore()) > 0
        self._restored = ck
        self._last_stamp = ck.last_stamp_ns
        self._camera_ready.set()
        fe = ck.frontend
        self.get_logger().info(
            f"restored the front end from {path}: {fe.stats['frames']} frames, {len(fe.window)} keyframes in "
            f"its window, state {fe.state}, last frame {ck.last_stamp_ns}; {len(self.unacked)} keyframe(s) "
            f"the mapper had not acknowledged")

    def _first_after_restore(self, stamp: int) -> None:
        """The first image after a restore: go on (short gap), relocalise (long gap), or, for an
        image not after the checkpoint's last frame (another recording), start afresh."""
        ck, self._restored = self._restored, None
        last = ck.last_stamp_ns
        if last is not None and stamp <= last:
            self.get_logger().warning(
                f"image {stamp} is not after the checkpoint's last frame ({last}): another recording; "
                f"the front end starts afresh (the checkpoint is overwritten)")
            with self._unacked_lock:
                self.unacked.discard()      # none of them belongs to this recording
                self.unacked.close()
                self.unacked = self._new_unacked()
            self._resend_restored = False
            self._last_stamp = None
            self._set_camera(self.raw_camera)
            self._drop_render_client()
            return
        gap = (stamp - last) * 1e-9 if last is not None else 0.0
        self.restart = restart_policy(gap, self.settings.resume_max_gap_s)
        self.restart_gap_s = gap
        self._restart_counts = (self.frontend.stats["relocalisations"], self.frontend.stats["segments"])
        self.frontend.restarted(self.restart is RestartMode.RESUMED, gap)
        if self.restart is RestartMode.RESUMED:
            self._drop_render_client()
        self.get_logger().info(
            f"restart: {self.restart.value} (the first image is {gap:.2f} s after the checkpoint's last "
            f"frame; frontend_node.resume_max_gap_s {self.settings.resume_max_gap_s:g})")

    def _restart_result(self, frame: Frame, est) -> None:
        """After a relocalising restart: relocalised (the same world frame, its pose checked against
        a render of the map when a mapper answers) or a new map segment."""
        if self.restart is not RestartMode.RELOCALISING or self.restart_outcome:
            return
        reloc, seg = self._restart_counts
        st = self.frontend.stats
        if st["segments"] > seg:
            self.restart_outcome = "new_segment"
        elif st["relocalisations"] > reloc and est is not None and est.state == TrackState.TRACKING:
            why = self._verify_by_render(frame, est.T_wc)
            if why is not None:
                self.frontend.new_segment(f"the relocalisation after the restart disagrees with the map: {why}")
                self.restart_outcome = "new_segment"
            else:
                self.restart_outcome = "relocalised"
        else:
            return
        self._drop_render_client()
        self.get_logger().info(f"restart: {self.restart_outcome.replace('_', ' ')} ({self.frontend.reason}; "
                               f"render check {self.restart_render or 'none'})")

    def _drop_render_client(self) -> None:
        if self.render_client is not None:
            self.render_client.disconnect()
            self.render_client = None

    def _verify_by_render(self, frame: Frame, T_wc: np.ndarray) -> Optional[str]:
        """Render the map at the relocalised pose (``1/loop.render_downscale`` size) and compare it
        with the frame as the loop closer verifies a loop (coverage, mean colour error); the reason
        it disagrees, or None (agrees, or no render: recorded in ``restart_render``)."""
        if self.render_client is None:
            self.restart_render = {"outcome": "no_client"}
            return None
        f = max(int(self.lcfg.render_downscale), 1)
        cam = self.undist.camera if f == 1 else scaled_camera(self.undist.camera, f)
        res = self.render_client.request(np.asarray(T_wc, np.float64), cam, None,
                                         self.settings.relocalise_render_timeout_s,
                                         about=f"relocalisation of frame {frame.stamp_ns}")
        if res.render is None:
            self.restart_render = {"outcome": res.outcome}
            return None
        img = frame.rgb().astype(np.float32) / 255.0
        if f > 1:
            img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        cov, l1 = render_agreement(res.render, img)
        self.restart_render = {"outcome": res.outcome, "coverage": round(cov, 3), "l1": round(l1, 4)}
        if cov < self.lcfg.render_min_coverage:
            # too little of the map in view to tell: kept, as the window's tracking checks passed
            return None
        if l1 > self.lcfg.render_l1_max:
            return f"render L1 {l1:.3f} above {self.lcfg.render_l1_max:g} (coverage {100 * cov:.0f} %)"
        return None

    def checkpoint_ready(self) -> bool:
        return self.frontend is not None and not self._finished and self._restored is None

    def write_checkpoint(self, path) -> str:
        size = save_frontend_checkpoint(path, {"frontend": self.frontend, "keeper": self.keeper},
                                        extra={"raw_camera": self.raw_camera.to_dict()})
        fe = self.frontend
        self._ckpt_stamp = fe.last_stamp_ns
        return f"{fe.stats['frames']} frames, {len(fe.window)} window keyframes, {size / 1e6:.1f} MB"

    # ----------------------------------------------------------------------------- the worker

    def _sim_time(self) -> bool:
        try:
            return bool(self.get_parameter("use_sim_time").value)
        except Exception:  # noqa: BLE001 - undeclared in stand-ins: a live clock
            return False

    def step(self) -> None:
        self._resend_unacked()
        msg = self.queue.get(timeout=0.1)
        if msg is None:
            return
        try:
            stamp = header_ns(msg.header, f"{T.IMAGE_TOPIC}.header")
        except InputError as e:
            self._skip(msg, f"skipped an image: {e}")
            return
        if stamp < 0 or (stamp == 0 and not self._sim_time()):
            # no clock gives a negative stamp; 0 on a live topic is a driver that never set it
            # (a replayed recording whose clock starts at 0, as KITTI's, runs on sim time)
            self._skip(msg, f"skipped an image stamped {stamp}: "
                            + ("negative stamp" if stamp < 0 else "zero stamp on a live topic (the driver does not "
                                                                  "stamp its images; with a recording, use sim time)"))
            return
        if self._last_stamp is not None and stamp <= self._last_stamp and self._restored is None:
            # a repeated stamp, a driver stamping 0, or a recording played again from its start:
            # tracking cannot go back in time, so such images are dropped (restart the node for
            # a new recording)
            self._skip(msg, f"skipped image {stamp}: stamps must increase (last processed "
                            f"{self._last_stamp}); restart the front end to process a recording "
                            f"again from its start")
            return
        if self.frontend is None:
            # the image and its camera_info travel on two topics: the first image may overtake
            # its calibration, so wait for it briefly instead of dropping the image
            self._camera_ready.wait(self.settings.calib_wait_s)
        if self.frontend is None:
            self.frames_without_camera += 1
            if _report(self.frames_without_camera):
                self.get_logger().warning(f"no calibration yet (no {T.CAMERA_INFO_TOPIC} and no "
                                          f"frontend_node.calib_file): {self.frames_without_camera} "
                                          f"images skipped")
            self._ack(msg.header)
            return
        try:
            frame = self.decoder(msg, self.raw_camera)
        except InputError as e:  # a bad message is reported and skipped, the node keeps running
            self._skip(msg, f"skipped image {stamp}: {e}")
            return
        finally:
            while self.decoder.warnings:    # 16-bit / float to 8-bit mapping notes (once each)
                self.get_logger().warning(self.decoder.warnings.pop(0))
        if self._restored is not None:
            self._first_after_restore(stamp)
        frame = Frame(stamp, self.undist(frame.image), self.undist.camera)
        self._last_stamp = stamp
        self.bad_streak = 0
        self._exchange_receive()
        ests = self.frontend.process(frame)
        sims = self.frontend.take_similarities()
        if sims:       # the metric alignment: the mapper scales its Gaussians with it
            self.keeper.own_similarity(sims)
        for est in ests:
            if est.state in POSED_STATES:
                # a back-filled pose (a frame that waited for initialisation) is published late,
                # in stamp order, before the current frame's; /diagnostics counts them
                self.late_poses += int(est.stamp_ns != stamp)
                twist = (self.frontend.vio.twist(est.stamp_ns, est.T_wc)
                         if self.frontend.vio is not None and est.stamp_ns == stamp else None)
                self.pub_odom.publish(estimate_to_odometry(est, self.ros.world_frame,
                                                           self.ros.camera_frame, T.ODOMETRY_TOPIC,
                                                           twist=twist))
        # as in `vings run`: moved keyframe poses first, then the new keyframes
        kfs = self.frontend.pop_keyframes()
        self._exchange_send(stamp)
        self._publish_keyframes(kfs)
        self._restart_result(frame, ests[-1] if ests else None)
        self.rate.tick()
        self.mark_changed()
        every = self.settings.checkpoint_every_s
        if (kfs and every > 0 and self.checkpoint_file is not None and self.checkpoint_ready()
                and (self._ckpt_stamp is None or (stamp - self._ckpt_stamp) * 1e-9 >= every)):
            self.save_checkpoint(f"keyframe {kfs[-1].stamp_ns}")
        else:
            self.maybe_checkpoint(idle=False)
        now = time.monotonic()
        if now - self._last_path_pub > 1.0:
            self._publish_path()
            self._last_path_pub = now
        self._ack(msg.header)

    def _skip(self, msg: Image, why: str) -> None:
        """Drop a bad image: counted, reported (rate-limited), acknowledged."""
        self.bad_frames += 1
        self.bad_streak += 1
        self._last_skip = why
        if _report(self.bad_frames):
            self.get_logger().warning(f"{why} ({self.bad_frames} image(s) skipped so far)")
        self._ack(msg.header)

    def _ack(self, header: Header) -> None:
        self.pub_ack.publish(header)

    def _publish_parts(self, kf) -> None:
        msgs = keyframe_to_msgs(kf, self.ros.camera_frame, self.ros.world_frame)
        for part, m in msgs.as_dict().items():
            self.pub_kf[part].publish(m)

    def _publish_keyframes(self, kfs) -> None:
        for kf in kfs:
            self._publish_parts(kf)
            self._exchange_keyframe_sent(kf)
            if self.settings.resend_after_s > 0:
                with self._unacked_lock:
                    self.unacked.sent(kf, time.monotonic())

    def _publish_path(self) -> None:
        traj = self.frontend.trajectory(states=POSED_STATES, max_poses=self.settings.path_max_poses)
        if len(traj) == 0:
            return
        self.pub_path.publish(trajectory_to_path(traj, self.ros.world_frame))

    def diagnostics(self) -> NodeStatus:
        st = self.frontend.status() if self.frontend is not None else {
            "state": "waiting", "reason": "no calibration yet"}
        state = st.get("state", "waiting")
        values = {"state": state, "reason": st.get("reason", ""), "segment": st.get("segment", 0),
                  "frames": st.get("frames", 0),
                  "keyframes": st.get("keyframes", 0), "rate_hz": self.rate.hz,
                  "queue_length": len(self.queue), "queue_policy": self.queue.policy,
                  "frames_dropped": self.queue.dropped, "frames_received": self.queue.received,
                  "bad_frames": self.bad_frames, "bad_streak": self.bad_streak,
                  "camera_changes": self.camera_changes, "bad_camera_infos": self.bad_camera_infos,
                  "imu_samples": self.imu_count, "bad_imu": self.bad_imu,
                  "late_poses": self.late_poses,
                  "dynamic_masks_received": self.masks_received,
                  "dynamic_masks_applied": self.frontend.stats.get("dynamic_masks", 0) if self.frontend else 0,
                  "dynamic_masks_late": self.frontend.stats.get("dynamic_masks_late", 0) if self.frontend else 0,
                  "bad_dynamic_masks": self.bad_masks,
                  "keyframes_unacknowledged": len(self.unacked), "keyframes_resent": self.keyframes_resent,
                  "restart": self.restart.value, "restart_outcome": self.restart_outcome,
                  "restart_gap_s": self.restart_gap_s if self.restart_gap_s is not None else "",
                  "restart_render": str(self.restart_render) if self.restart_render else "",
                  **self._vi_values(st),
                  **self._exchange_values()}
        if st.get("vi_error"):
            # the IMU's units are wrong (in g, or gravity removed): not fused, never silently
            return NodeStatus(Level.ERROR, f"IMU not fused: {st['vi_error']}", values)
        if self.imu_count and self.vcfg.enabled and (self.frontend is None or self.frontend.vio is None):
            # an IMU that cannot be fused (no T_bc): never a silent identity
            return NodeStatus(Level.ERROR, self._no_fusion_why(), values)
        if self.bad_streak >= BAD_STREAK_ERROR:
            # images arrive but none can be used (wrong size after a camera change, bad encoding)
            return NodeStatus(Level.ERROR, f"the last {self.bad_streak} images were skipped: "
                                           f"{self._last_skip}", values)
        return NodeStatus(Level(TRACKING_STATE_LEVEL[state]), st.get("reason") or state, values)

    def _vi_values(self, st: dict) -> dict:
        """The visual-inertial state for /diagnostics (plain values)."""
        out = {"vi_state": st.get("vi_state", "visual-only"), "vi_reason": st.get("vi_reason", self.vio_why)}
        for k in ("vi_scale_applied", "acc_bias", "gyro_bias", "velocity", "gravity_visual_world",
                  "imu_refused", "alignments_refused", "td_s", "td_estimates", "vi_error", "imu_only_frames"):
            if k in st:
                v = st[k]
                out[k] = str(v) if isinstance(v, (list, dict)) else v
        return out

    # ----------------------------------------------------------------------- pose exchange
    # The front end keeps the poses (vings_core.exchange.PoseKeeper): the writers' batches come in on
    # /vings/exchange/<writer> and pass their write-back policy (section exchange); its own batch
    # (window BA moves, accepted increments, acks) goes out on /vings/exchange/frontend.

    def _exchange_setup(self) -> None:
        self.xcfg: ExchangeConfig = self.config("exchange")
        self.keeper: Optional[PoseKeeper] = None       # made with the front end (needs the camera)
        self.inbox = BatchInbox(self, self.xcfg.writers())
        self.pub_exchange = self.create_publisher(Path, exchange_topic(KEEPER),
                                                  T.sensor_qos(T.POSE_EXCHANGE_DEPTH))

    def _exchange_receive(self) -> None:
        """The writers' batches received since the last frame -> their write-back policies."""
        for batch in self.inbox.take():
            self.keeper.receive(batch)

    def _exchange_send(self, seq_hint: int = 0) -> None:
        """The keeper's batch since the last one, if anything moved or a writer's batch was processed."""
        batch = self.keeper.outgoing(seq_hint)
        if batch is not None:
            self.pub_exchange.publish(batch_to_path(batch, self.ros.world_frame))

    def _exchange_keyframe_sent(self, kf) -> None:
        self.keeper.keyframe_sent(kf.stamp_ns, kf.T_wc.detach().cpu().numpy().astype(np.float64))

    def _exchange_values(self) -> dict:
        st = self.keeper.stats if self.keeper is not None else {}
        return {"writeback_policy": self.xcfg.mapper,
                "corrections_received": st.get("corrections", 0),
                "corrections_applied": st.get("applied", 0),
                "corrections_rejected": st.get("rejected", 0),
                "corrections_unknown_stamps": st.get("unknown_stamps", 0),
                "bad_exchange_messages": self.inbox.bad}

    # -------------------------------------------------------------------------------- shutdown

    def finish(self) -> None:
        """After the worker: the checkpoint (the window as it is, so a restart tracks on), then flush
        the keyframes still in the window to the mapper."""
        self._abort.set()
        if self.checkpoint_file is not None and self.error is None and self.checkpoint_ready():
            self.save_checkpoint("shutdown")
        self._finished = True
        if self.frontend is not None and self.error is None:
            self._exchange_receive()
            kfs = self.frontend.finish()
            self._exchange_send()
            self._publish_keyframes(kfs)
            self._publish_path()
            self._flush_keyframes(FLUSH_TIMEOUT_S)

    def _flush_keyframes(self, timeout_s: float) -> None:
        """Wait (at most ``timeout_s``) until every subscriber of the keyframe topics confirmed the
        packets in flight: a reliable writer that goes away drops what its readers had not fetched
        (a keyframe still lost waits in ``<checkpoint>.unacked/`` for the next front end)."""
        topic = wait_all_acked(self.pub_kf.values(), timeout_s)
        if topic is not None:
            self.get_logger().warning(f"not every subscriber of {topic} confirmed the last keyframes "
                                      f"within {timeout_s:g} s")

    def close(self) -> None:
        with self._unacked_lock:
            if len(self.unacked):
                self.get_logger().info(f"{len(self.unacked)} keyframe(s) sent were not acknowledged by a mapper")
            self.unacked.close()


def main(args: Optional[list[str]] = None) -> int:
    return FrontendNode.main(args)


if __name__ == "__main__":
    raise SystemExit(main())
