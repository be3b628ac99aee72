"""Replay any recording on the live input topics: ``vings replay SOURCE``.

Reads a :class:`vings_core.io.Source` (EuRoC/TUM/KITTI folder, ROS 1/2 bag, MCAP) and publishes, with
the recording's ORIGINAL stamps:

* ``/camera/image_raw`` (sensor_msgs/Image, rgb8 or mono8, undistorted, working resolution),
* ``/camera/camera_info`` (CameraInfo of those images, same stamp as each image, sent just before it),
* ``/imu/data`` (sensor_msgs/Imu, body frame),
* ``/clock`` (rosgraph_msgs/Clock) at sensor time, before every message that advances it,

paced at ``rate`` x real time (``rate = 0``: as fast as possible). Frames of the window
``[first frame + start_s, + duration_s]`` are published, and IMU samples from ``imu_lead_s`` before
the first of them up to the last (IMU-only stretches at the ends of a recording are skipped).

Start-up: waits until the image publisher is matched with a subscriber (then up to
:data:`ENDPOINT_GRACE_S` more for the IMU / camera-info subscribers of the same node), at most
``startup_timeout_s``.

Back-pressure (``wait_for_graph``): after each image the replay waits until a std_msgs/Header with a
stamp >= that image's stamp arrives on ``/vings/frontend/processed``. The front-end node implements it
by republishing the header of every image it has finished with (processed or deliberately skipped)::

    self._processed = self.create_publisher(Header, "/vings/frontend/processed", 100)
    ...                                   # at the end of the image callback / processing step:
    self._processed.publish(image_msg.header)

The replay waits at start for that publisher, raises :class:`GraphTimeout` if no acknowledgement
comes within ``ack_timeout_s`` or the acknowledging publisher disappears for longer than
``respawn_wait_s`` (when it comes back, the image it lost is published again), and otherwise publishes
every frame, so nothing is dropped however slow the graph is. Pacing is re-anchored at every
image that goes out more than 20 ms late, so a slow graph (or slow decoding) slows the replay
without bursts afterwards: an image goes out at max(previous image + its period / rate,
acknowledgement of the previous image).

One node, one :class:`SingleThreadedExecutor`, all in the calling thread.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import re
import sys
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional, TextIO

from vings_core.errors import ConfigError, VingsError
from vings_core.util import atomic_write_text, check_output_file
from vings_core.types import Frame, ImuSample

from msg_adapters import topics as T

log = logging.getLogger("vings.replay")

ENDPOINT_GRACE_S = 1.0
LAG_TOLERANCE_S = 0.02  # an image later than this behind schedule re-anchors the pacing
FLUSH_TIMEOUT_S = 4.0  # at the end, wait this long at most for reliable readers to confirm


class GraphTimeout(VingsError):
    """The ROS graph did not show up or stopped acknowledging frames."""


@dataclass
class ReplayOptions:
    """How to replay. Times in seconds. Frames with stamps in ``[first frame + start_s,
    + duration_s]`` are published; IMU samples from ``imu_lead_s`` before the first published frame
    up to the last published frame (IMU-only stretches at either end of a recording are skipped)."""

    rate: float = 1.0
    topics: dict = field(default_factory=lambda: dict(T.REPLAY_TOPICS))
    wait_for_graph: bool = False
    wait_subscribers: bool = True
    startup_timeout_s: float = 30.0
    ack_timeout_s: float = 60.0
    respawn_wait_s: float = 30.0    # with wait_for_graph: how long to wait for a front end that went away
    loop: bool = False
    loop_shift: bool = False    # with loop: every pass's stamps come after the previous pass's
    start_s: float = 0.0
    duration_s: Optional[float] = None
    imu_lead_s: float = 1.0
    camera_frame: str = T.CAMERA_FRAME
    imu_frame: str = T.IMU_FRAME
    publish_clock: bool = True
    progress_period_s: float = 2.0
    node_name: str = "vings_replay"
    publish_log: Optional[str] = None  # CSV "stamp_ns,wall_ns" of every image (for latency)

    def validate(self) -> None:
        if self.loop_shift and not self.loop:
            raise ConfigError("--loop-shift needs --loop")
        if not (self.rate >= 0 and math.isfinite(self.rate)):
            raise ConfigError(f"--rate must be a finite number >= 0 (0 = as fast as possible), got {self.rate}")
        if not (self.start_s >= 0 and math.isfinite(self.start_s)):
            raise ConfigError(f"--start must be a finite number of seconds >= 0, got {self.start_s}")
        if self.duration_s is not None and not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise ConfigError(f"--duration must be a finite number of seconds > 0, got {self.duration_s}")
        if not (self.imu_lead_s >= 0 and math.isfinite(self.imu_lead_s)):
            raise ConfigError(f"--imu-lead must be a finite number of seconds >= 0, got {self.imu_lead_s}")
        if not (self.ack_timeout_s > 0 and self.startup_timeout_s >= 0):   # NaN fails both
            raise ConfigError(f"--ack-timeout must be > 0 and --startup-timeout >= 0, got "
                              f"{self.ack_timeout_s} and {self.startup_timeout_s}")
        if not (self.respawn_wait_s >= 0 and math.isfinite(self.respawn_wait_s)):
            raise ConfigError(f"--respawn-wait must be a finite number of seconds >= 0, got {self.respawn_wait_s}")
        unknown = set(self.topics) - set(T.REPLAY_TOPICS)
        if unknown:
            raise ConfigError(f"--topics: unknown key(s) {sorted(unknown)}; known: "
                              f"{', '.join(T.REPLAY_TOPICS)}")
        for k, v in self.topics.items():
            if not isinstance(v, str) or not _valid_topic(v):
                raise ConfigError(f"--topics: topic for {k!r} must be an absolute ROS name "
                                  f"(/ then tokens of letters, digits and _ not starting with a "
                                  f"digit, separated by single /), got {v!r}")
        full = dict(T.REPLAY_TOPICS)
        full.update(self.topics)
        seen: dict = {}
        for k, v in full.items():
            if v in seen:
                raise ConfigError(f"--topics: {seen[v]!r} and {k!r} would both publish on {v} (the "
                                  f"message types differ); give each its own topic")
            seen[v] = k
        if self.publish_log:    # found before the replay, not after it
            self.publish_log = str(check_output_file(self.publish_log, "--publish-log", ConfigError))
        self.topics = full


_TOPIC_RE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def _valid_topic(name: str) -> bool:
    """Absolute ROS 2 topic name (the subset rclpy accepts: no ``~``, ``{}`` substitutions)."""
    return bool(_TOPIC_RE.match(name))


def parse_topics(spec: str) -> dict:
    """``"image=/cam/img,imu=/imu0"`` -> ``{"image": "/cam/img", "imu": "/imu0"}`` (ConfigError if bad)."""
    out = {}
    for part in (p.strip() for p in spec.split(",")):
        if not part:
            continue
        key, sep, val = part.partition("=")
        if not sep or not key.strip() or not val.strip():
            raise ConfigError(f"--topics entry {part!r} must look like key=/topic "
                              f"(keys: {', '.join(T.REPLAY_TOPICS)})")
        out[key.strip()] = val.strip()
    return out


@dataclass
class ReplayStats:
    images: int = 0
    imu: int = 0
    camera_info: int = 0
    clock: int = 0
    acks: int = 0
    loops: int = 0
    first_stamp_ns: Optional[int] = None
    last_stamp_ns: Optional[int] = None
    wall_s: float = 0.0
    sensor_s: float = 0.0
    achieved_rate: Optional[float] = None
    image_rate_hz: Optional[float] = None
    ack_wait_mean_ms: Optional[float] = None
    ack_wait_max_ms: Optional[float] = None
    startup_wait_s: float = 0.0
    respawns: int = 0               # front ends that went away and came back (image sent again)
    interrupted: bool = False

    def as_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        rate = f"x{self.achieved_rate:.2f} real time" if self.achieved_rate else "n/a"
        hz = f"{self.image_rate_hz:.1f} Hz" if self.image_rate_hz else "n/a"
        s = (f"replay: published {self.images} images, {self.camera_info} camera_info, {self.imu} "
             f"imu, {self.clock} clock in {self.wall_s:.2f} s wall for {self.sensor_s:.2f} s of "
             f"sensor time ({rate}, images {hz})")
        if self.interrupted:
            s += " (interrupted)"
        if self.acks:
            s += (f"; {self.acks} acks, wait mean {self.ack_wait_mean_ms:.1f} ms, max "
                  f"{self.ack_wait_max_ms:.1f} ms")
        if self.respawns:
            s += f"; the front end came back {self.respawns} time(s)"
        return s


class Replayer:
    """Publishes one :class:`Source` on the input topics (see the module docstring).

    ``Replayer(source, options).run()`` initialises its own rclpy context, so it can share a
    process with other nodes; call it from the thread that should block.
    """

    def __init__(self, source, options: Optional[ReplayOptions] = None,
                 out: Optional[TextIO] = None,
                 on_image: Optional[Callable[[int], None]] = None) -> None:
        self.source = source
        self.opt = options or ReplayOptions()
        self.opt.validate()
        self.out = out if out is not None else sys.stderr
        self.on_image = on_image
        self.stats = ReplayStats()
        self._acked = -1 << 63
        self._ack_waits: list[float] = []
        self._ack_gids: set[tuple] = set()      # the acknowledgement publishers seen

    # ------------------------------------------------------------------------------- set-up
    def _setup(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image, Imu
        from std_msgs.msg import Header

        self._ctx = rclpy.Context()
        try:
            # no rclpy signal handlers: Ctrl-C raises KeyboardInterrupt here and we clean up
            rclpy.init(context=self._ctx, signal_handler_options=SignalHandlerOptions.NO)
            self.node = rclpy.create_node(self.opt.node_name, context=self._ctx,
                                          start_parameter_services=False)
        except RuntimeError as e:      # rclpy's RCLError (environment, DDS set-up): one line
            why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ConfigError(f"replay: cannot start ROS: {why}") from None
        self.executor = SingleThreadedExecutor(context=self._ctx)
        self.executor.add_node(self.node)
        tp = self.opt.topics
        self.pub_image = self.node.create_publisher(Image, tp["image"], T.image_qos())
        self.pub_info = self.node.create_publisher(CameraInfo, tp["camera_info"],
                                                   T.camera_info_qos())
        self.pub_imu = self.node.create_publisher(Imu, tp["imu"], T.imu_qos())
        self.pub_clock = (self.node.create_publisher(Clock, tp["clock"], T.clock_qos())
                          if self.opt.publish_clock else None)
        self.sub_ack = None
        if self.opt.wait_for_graph:
            self.sub_ack = self.node.create_subscription(Header, tp["processed"], self._on_ack,
                                                         T.ack_qos())
        self._Clock = Clock

    def _teardown(self) -> None:
        ctx = getattr(self, "_ctx", None)
        if ctx is None:
            return
        try:
            if ctx.ok():
                # let reliable readers fetch what is still in flight before the writers go
                from .node_common import wait_all_acked
                pubs = [p for p in (self.pub_info, self.pub_imu, self.pub_image, self.pub_clock) if p is not None]
                topic = wait_all_acked(pubs, FLUSH_TIMEOUT_S)
                if topic is not None:
                    log.warning("replay: not every subscriber of %s confirmed the last messages within "
                                "%.0f s", topic, FLUSH_TIMEOUT_S)
        finally:
            try:    # a set-up that failed half-way has no executor or node
                if getattr(self, "executor", None) is not None:
                    self.executor.shutdown(timeout_sec=1.0)
                if getattr(self, "node", None) is not None:
                    self.node.destroy_node()
            finally:
                if ctx.ok():
                    ctx.try_shutdown()
                ctx.destroy()       # the DDS participant goes now (its shared-memory ports with it)
                self._ctx = None

    def _on_ack(self, msg) -> None:
        from msg_adapters.stamps import header_ns
        self._acked = max(self._acked, header_ns(msg, self.opt.topics["processed"]))

    # -------------------------------------------------------------------------------- waits
    def _spin_for(self, seconds: float) -> None:
        self.executor.spin_once(timeout_sec=max(0.0, seconds))

    def _spin_until(self, wall_target: float) -> None:
        while True:
            rem = wall_target - time.monotonic()
            if rem <= 0:
                return
            self._spin_for(min(rem, 0.05))

    def _wait_startup(self) -> None:
        if not self.opt.wait_subscribers and not self.opt.wait_for_graph:
            return
        t0 = time.monotonic()
        deadline = t0 + self.opt.startup_timeout_s
        tp = self.opt.topics

        def ready() -> bool:
            if self.pub_image.get_subscription_count() < 1:
                return False
            return self.sub_ack is None or self.sub_ack.get_publisher_count() >= 1

        announced = False
        while not ready():
            if time.monotonic() >= deadline:
                what = []
                if self.pub_image.get_subscription_count() < 1:
                    what.append(f"nothing subscribes to {tp['image']}")
                if self.sub_ack is not None and self.sub_ack.get_publisher_count() < 1:
                    what.append(f"nothing publishes the front end's acknowledgements "
                                f"(std_msgs/Header) on {tp['processed']}")
                msg = (f"after {self.opt.startup_timeout_s:g} s {' and '.join(what)}; is the "
                       f"graph running, with the same ROS_DOMAIN_ID?")
                if self.opt.wait_for_graph:
                    raise GraphTimeout(msg)
                self._print(f"replay: warning: {msg} Publishing anyway.")
                self.stats.startup_wait_s = time.monotonic() - t0
                return
            if not announced and time.monotonic() - t0 > 1.0:
                self._print(f"replay: waiting for subscribers on {tp['image']}"
                            + (f" and acknowledgements on {tp['processed']}"
                               if self.sub_ack is not None else "") + " ...")
                announced = True
            self._spin_for(0.05)
        # the other endpoints of the same node are discovered together; allow a little time
        grace = time.monotonic() + ENDPOINT_GRACE_S
        others = [self.pub_info] + ([self.pub_imu] if self._has_imu else [])
        while time.monotonic() < grace and any(p.get_subscription_count() < 1 for p in others):
            self._spin_for(0.02)
        if self.sub_ack is not None:
            self._ack_gids = self._ack_publishers()
        self.stats.startup_wait_s = time.monotonic() - t0

    def _ack_publishers(self) -> set[tuple]:
        """The endpoint ids of the acknowledgement publishers now (a restarted front end has a new one)."""
        from .node_common import publisher_ids
        return publisher_ids(self.node, self.sub_ack.topic_name)

    def _wait_ack(self, frame: Frame) -> None:
        """Wait for the acknowledgement of ``frame``. A front end that went away (its acknowledgement
        publisher is gone) is waited for ``respawn_wait_s`` (``vings launch`` respawns it); a new
        front end (a new acknowledgement publisher, seen once a second) gets the frame again, as
        the one before lost it."""
        stamp_ns = frame.stamp_ns
        t0 = time.monotonic()
        deadline = t0 + self.opt.ack_timeout_s
        next_check = t0 + 1.0
        while self._acked < stamp_ns:
            now = time.monotonic()
            if now >= deadline:
                raise GraphTimeout(
                    f"no acknowledgement of the image stamped {stamp_ns} on "
                    f"{self.opt.topics['processed']} within {self.opt.ack_timeout_s:g} s (the "
                    f"front end publishes each processed image's header there); raise "
                    f"--ack-timeout if the graph is just slow")
            if now >= next_check:
                next_check = now + 1.0
                gids = self._ack_publishers()
                if self.sub_ack.get_publisher_count() < 1:
                    self._wait_respawn(frame)
                    deadline = time.monotonic() + self.opt.ack_timeout_s
                elif gids - self._ack_gids:
                    self._resend(frame, "a new front end appeared", 0.0)
                    deadline = time.monotonic() + self.opt.ack_timeout_s
                else:
                    self._ack_gids = gids
            self._spin_for(min(deadline - now, 0.05))
        self._ack_waits.append(time.monotonic() - t0)
        self.stats.acks += 1

    def _wait_respawn(self, frame: Frame) -> None:
        """The front end went away while ``frame`` waited: wait for one to come back (with the
        image subscription too), then publish the frame again. Raises :class:`GraphTimeout` after
        ``respawn_wait_s``."""
        stamp_ns, topic = frame.stamp_ns, self.opt.topics["processed"]
        t0 = time.monotonic()
        if self.opt.respawn_wait_s > 0:
            self._print(f"replay: the front end went away while image {stamp_ns} waited (nothing publishes "
                        f"{topic}); waiting up to {self.opt.respawn_wait_s:g} s for it to come back")
        while (self.sub_ack.get_publisher_count() < 1 or self.pub_image.get_subscription_count() < 1) \
                and time.monotonic() - t0 < self.opt.respawn_wait_s:
            self._spin_for(0.1)
        if self.sub_ack.get_publisher_count() < 1 or self.pub_image.get_subscription_count() < 1:
            raise GraphTimeout(f"the publisher of {topic} went away while waiting for image {stamp_ns} "
                               f"(did the front-end node die?)"
                               + (f"; it did not come back within {self.opt.respawn_wait_s:g} s"
                                  if self.opt.respawn_wait_s > 0 else ""))
        self._resend(frame, "the front end is back", time.monotonic() - t0)

    def _resend(self, frame: Frame, what: str, after_s: float) -> None:
        """Publish ``frame`` again for a restarted front end, once its image subscription is there."""
        t_end = time.monotonic() + 10.0
        while self.pub_image.get_subscription_count() < 1 and time.monotonic() < t_end:
            self._spin_for(0.1)
        self._spin_for(0.5)         # its subscriptions match ours before the image goes out
        self.stats.respawns += 1
        self._print(f"replay: {what}" + (f" after {after_s:.1f} s" if after_s else "")
                    + f"; image {frame.stamp_ns} published again")
        self._ack_gids = self._ack_publishers()
        self._publish_frame(frame)

    # ------------------------------------------------------------------------------ publish
    def _print(self, line: str) -> None:
        print(line, file=self.out, flush=True)

    def _publish_clock(self, stamp_ns: int) -> None:
        if self.pub_clock is None or stamp_ns <= self._last_clock:
            return
        from msg_adapters.stamps import ns_to_time
        self.pub_clock.publish(self._Clock(clock=ns_to_time(stamp_ns, self.opt.topics["clock"])))
        self._last_clock = stamp_ns
        self.stats.clock += 1

    def _publish_frame(self, f: Frame) -> None:
        from msg_adapters.camera_info import camera_to_camera_info
        from msg_adapters.image import frame_to_msg
        from msg_adapters.stamps import ns_to_time

        tp = self.opt.topics
        if self._info_msg is None:
            self._info_msg = camera_to_camera_info(self.source.calibration.camera, f.stamp_ns,
                                                   self.opt.camera_frame, tp["camera_info"])
        self._info_msg.header.stamp = ns_to_time(f.stamp_ns, tp["camera_info"])
        self.pub_info.publish(self._info_msg)
        self.stats.camera_info += 1
        msg = frame_to_msg(f, self.opt.camera_frame, tp["image"])
        self._pub_log.append((f.stamp_ns, time.time_ns()))
        self.pub_image.publish(msg)
        self.stats.images += 1

    def _publish_imu(self, s: ImuSample) -> None:
        from msg_adapters.imu import imu_sample_to_msg
        self.pub_imu.publish(imu_sample_to_msg(s, self.opt.imu_frame, self._gyro_var,
                                               self._accel_var, self.opt.topics["imu"]))
        self.stats.imu += 1

    # ---------------------------------------------------------------------------------- run
    def _plan(self) -> None:
        """The frame window: first and last published frame, first IMU stamp, frame count."""
        import numpy as np
        fs = np.asarray(self.source.frame_stamps(), dtype=np.int64)
        if len(fs) == 0:
            raise ConfigError(f"{self.source.path}: the recording has no camera frames")
        lo = int(fs[0]) + int(round(self.opt.start_s * 1e9))
        sel = fs[fs >= lo]
        if self.opt.duration_s is not None:
            sel = sel[sel <= lo + int(round(self.opt.duration_s * 1e9))]
        if len(sel) == 0:
            raise ConfigError(f"no frames in the selected window of {self.source.path} (--start "
                              f"{self.opt.start_s:g} s, --duration {self.opt.duration_s}; the "
                              f"recording has {(fs[-1] - fs[0]) * 1e-9:.2f} s of frames)")
        self._f_first, self._f_last = int(sel[0]), int(sel[-1])
        self._imu_first = self._f_first - int(round(self.opt.imu_lead_s * 1e9))
        self._n_frames = int(len(sel))
        # --loop-shift: pass k is published k * shift later, so stamps keep increasing (a graph
        # that drops stamps that do not increase, as the VINGS front end does, sees every pass)
        period = int(np.median(np.diff(sel))) if len(sel) > 1 else 50_000_000
        self._loop_shift_ns = (self._f_last - min(self._imu_first, self._f_first)) + max(period, 1)

    def _play_once(self, wall0: float) -> None:
        rate = self.opt.rate
        anchor: Optional[tuple[float, int]] = None
        total = self._n_frames
        next_progress = time.monotonic() + self.opt.progress_period_s
        self._acked = -1 << 63
        self._last_clock = -1 << 63
        self._sensor_ns_pass = 0
        n_img_pass = 0
        pass_first: Optional[int] = None
        shift = self.stats.loops * self._loop_shift_ns if self.opt.loop_shift else 0
        for item in self.source.stream():
            stamp = int(item.stamp_ns)
            is_frame = isinstance(item, Frame)
            if stamp > self._f_last:
                break
            if stamp < (self._f_first if is_frame else self._imu_first):
                continue
            if shift:
                stamp += shift
                item = dataclasses.replace(item, stamp_ns=stamp)
            if rate > 0:
                if anchor is None:
                    anchor = (time.monotonic(), stamp)
                ideal = anchor[0] + (stamp - anchor[1]) * 1e-9 / rate
                self._spin_until(ideal)
                if is_frame and time.monotonic() - ideal > LAG_TOLERANCE_S:
                    # behind schedule (slow graph or slow decoding): continue from here rather
                    # than bursting to catch up
                    anchor = (time.monotonic(), stamp)
            self._publish_clock(stamp)
            if is_frame:
                self._publish_frame(item)
                n_img_pass += 1
                if self.on_image is not None:
                    self.on_image(stamp)
                if self.opt.wait_for_graph:
                    self._wait_ack(item)
                elif rate == 0 and n_img_pass % 10 == 0:
                    self._spin_for(0.0)
            else:
                self._publish_imu(item)
            if self.stats.first_stamp_ns is None:
                self.stats.first_stamp_ns = stamp
            self.stats.last_stamp_ns = stamp
            if pass_first is None:
                pass_first = stamp
            self._sensor_ns_pass = stamp - pass_first
            now = time.monotonic()
            if now >= next_progress:
                next_progress = now + self.opt.progress_period_s
                self._print(f"replay: {n_img_pass}/{total} images (loop {self.stats.loops + 1}), "
                            f"{self.stats.imu} imu, t = {(stamp - shift - self._f_first) * 1e-9:.2f} s, "
                            f"wall {now - wall0:.1f} s")
        self._sensor_ns += self._sensor_ns_pass
        self._sensor_ns_pass = 0
        self.stats.loops += 1

    def run(self) -> ReplayStats:
        """Publish the recording (until done, or until Ctrl-C with ``loop``); returns statistics.

        Ctrl-C (KeyboardInterrupt) stops cleanly: ``stats.interrupted`` is set and the statistics
        so far are returned.
        """
        self._info_msg = None
        self._sensor_ns = 0
        self._pub_log: list[tuple[int, int]] = []
        self._has_imu = bool(self.source.calibration.has_imu or self.source.imu_samples())
        from msg_adapters.imu import imu_variances
        self._gyro_var, self._accel_var = imu_variances(self.source.calibration)
        self._plan()
        wall0 = None
        error = None
        try:
            self._setup()
            self._wait_startup()
            wall0 = time.monotonic()
            while True:
                self._play_once(wall0)
                if not self.opt.loop:
                    break
        except KeyboardInterrupt:
            self.stats.interrupted = True
        except VingsError as e:     # e.g. GraphTimeout mid-replay: what was published is still logged
            error = e
        finally:
            wall = time.monotonic() - wall0 if wall0 is not None else 0.0
            self._teardown()
        st = self.stats
        st.wall_s = wall
        self._sensor_ns += getattr(self, "_sensor_ns_pass", 0)  # an interrupted pass
        self._sensor_ns_pass = 0
        st.sensor_s = self._sensor_ns * 1e-9
        if wall > 0 and st.sensor_s > 0:
            st.achieved_rate = st.sensor_s / wall
        if wall > 0 and st.images > 1:
            st.image_rate_hz = st.images / wall
        if self._ack_waits:
            st.ack_wait_mean_ms = 1e3 * sum(self._ack_waits) / len(self._ack_waits)
            st.ack_wait_max_ms = 1e3 * max(self._ack_waits)
        if self.opt.publish_log:
            try:
                atomic_write_text(self.opt.publish_log, "# stamp_ns,publish_wall_ns\n" + "".join(
                    f"{s},{w}\n" for s, w in self._pub_log))
            except VingsError as e:   # the replay itself is done: report, keep the statistics
                self._print(f"replay: warning: publish log not written: {e}")
        if error is not None:
            raise error
        return st


def replay(source, options: Optional[ReplayOptions] = None,
           out: Optional[TextIO] = None) -> ReplayStats:
    """Publish ``source`` on the input topics; see :class:`Replayer`."""
    return Replayer(source, options, out).run()
