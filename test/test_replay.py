"""`vings replay` end to end: a replay process publishes a tiny EuRoC recording to a subscriber in
this test process (a unique ROS_DOMAIN_ID per test; every wait is time-capped; the Fast DDS
shared-memory files the test created are removed afterwards)."""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("rclpy")

import msg_adapters as ma  # noqa: E402
from msg_adapters import topics as T  # noqa: E402
from vings_core.errors import ConfigError  # noqa: E402
from vings_ros import ros_env  # noqa: E402
from vings_ros.replay import ReplayOptions, parse_topics  # noqa: E402

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_007
N_FRAMES, W, H = 20, 64, 48
PROC_TIMEOUT_S = 90.0
_domains = itertools.count()


def _next_domain() -> int:
    """A domain id unlikely to be shared with a concurrent test run (1..200)."""
    return 1 + (os.getpid() * 13 + 17 * next(_domains)) % 200


# ----------------------------------------------------------------------------- recording


def make_euroc(root: Path, n: int = N_FRAMES, w: int = W, h: int = H) -> Path:
    """``n`` RGB frames (w x h, 20 Hz, odd stamps) and 195 IMU samples starting 20 ms earlier."""
    mav0 = root / "mav0"
    (mav0 / "cam0" / "data").mkdir(parents=True)
    rows = ["#timestamp [ns],filename"]
    for i in range(n):
        s = T0 + i * 50_000_000
        img = np.random.default_rng(i).integers(0, 256, (h, w, 3), dtype=np.uint8)
        assert cv2.imwrite(str(mav0 / "cam0" / "data" / f"{s}.png"), img[..., ::-1])
        rows.append(f"{s},{s}.png")
    (mav0 / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
    ident = "[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]"
    (mav0 / "cam0" / "sensor.yaml").write_text(
        f"%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: {ident}\n"
        f"rate_hz: 20\nresolution: [{w}, {h}]\ncamera_model: pinhole\n"
        "intrinsics: [50.0, 52.0, 31.5, 23.5]\ndistortion_model: radial-tangential\n"
        "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n")
    (mav0 / "imu0").mkdir()
    rng = np.random.default_rng(99)
    lines = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
             "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
    for k in range(195):
        s = T0 - 20_000_004 + k * 5_000_000
        g = (rng.normal(size=3) * 0.1).tolist()
        a = (rng.normal(size=3) + [0.0, 0.0, 9.81]).tolist()
        lines.append(f"{s},{g[0]!r},{g[1]!r},{g[2]!r},{a[0]!r},{a[1]!r},{a[2]!r}")
    (mav0 / "imu0" / "data.csv").write_text("\n".join(lines) + "\n")
    (mav0 / "imu0" / "sensor.yaml").write_text(
        f"%YAML:1.0\nsensor_type: imu\nT_BS:\n  cols: 4\n  rows: 4\n  data: {ident}\nrate_hz: 200\n"
        "gyroscope_noise_density: 1.0e-4\ngyroscope_random_walk: 2.0e-5\n"
        "accelerometer_noise_density: 3.0e-3\naccelerometer_random_walk: 4.0e-3\n")
    return root


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from vings_core.io import open_source
    root = make_euroc(tmp_path_factory.mktemp("euroc"))
    src = open_source(root)
    frames = list(src.frames())
    imu = src.imu_samples()
    assert len(frames) == N_FRAMES and len(imu) == 195
    return root, src, frames, imu


# ---------------------------------------------------------------------------------- ROS side


@pytest.fixture
def ros(tmp_path, monkeypatch):
    """Environment of one test: unique domain, shared-memory profile, logs in tmp; afterwards the
    Fast DDS files left by processes this test started (and that are dead) are removed."""
    snap = ros_env.shm_snapshot()
    env = ros_env.ros_environment(domain_id=_next_domain(), log_dir=tmp_path / "roslog")
    for k in ("ROS_DOMAIN_ID", "ROS_LOG_DIR", "AMENT_PREFIX_PATH", ros_env.PROFILE_ENV):
        if k in env:
            monkeypatch.setenv(k, env[k])
    env["PYTHONUNBUFFERED"] = "1"
    yield env
    ros_env.cleanup_fastdds_shm(snap)


class Listener:
    """Subscribes to the replay's topics in this process (own context, one executor)."""

    def __init__(self, env: dict, topics: dict = None, image_depth: int = 100,
                 process_s: float = 0.0, ack: bool = False) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image, Imu
        from std_msgs.msg import Header

        tp = dict(T.REPLAY_TOPICS)
        tp.update(topics or {})
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=int(env["ROS_DOMAIN_ID"]),
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("test_listener", context=self.ctx,
                                      start_parameter_services=False)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.images, self.infos, self.imu, self.clock = [], [], [], []
        self.closed = False
        self.process_s = process_s
        self.on_first_image = None
        self.ack_pub = self.node.create_publisher(Header, tp["processed"], T.ack_qos()) if ack else None
        self.node.create_subscription(Image, tp["image"], self._on_image,
                                      T.sensor_qos(image_depth))
        self.node.create_subscription(CameraInfo, tp["camera_info"], self.infos.append,
                                      T.sensor_qos(100))
        self.node.create_subscription(Imu, tp["imu"], self.imu.append, T.sensor_qos(1000))
        self.node.create_subscription(Clock, tp["clock"], self.clock.append,
                                      QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))

    def _on_image(self, msg) -> None:
        if not self.images and self.on_first_image is not None:
            self.on_first_image()
        self.images.append(msg)
        if self.process_s:
            time.sleep(self.process_s)  # a slow front end
        if self.ack_pub is not None:
            self.ack_pub.publish(msg.header)  # the whole back-pressure protocol

    def spin_while(self, proc: subprocess.Popen, done=lambda: False,
                   timeout: float = PROC_TIMEOUT_S, linger: float = 1.0) -> tuple[str, str]:
        """Spin until ``proc`` exits (then ``linger`` s more or until ``done()``); capped."""
        t_end = time.monotonic() + timeout
        exited_at = None
        while time.monotonic() < t_end:
            self.ex.spin_once(timeout_sec=0.02)
            if exited_at is None and proc.poll() is not None:
                exited_at = time.monotonic()
            if exited_at is not None and (done() or time.monotonic() - exited_at > linger):
                break
        else:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f"replay did not finish within {timeout} s; stderr:\n{err}")
        return proc.communicate(timeout=10)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.ex.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()
        self.ctx.destroy()      # the participant goes now, not when the context is collected


@pytest.fixture
def listener_factory(ros):
    made = []

    def make(**kw):
        lis = Listener(ros, **kw)
        made.append(lis)
        return lis
    yield make
    for lis in made:
        lis.close()


def _inodes(names) -> dict:
    out = {}
    for n in names:
        try:
            out[n] = (ros_env.SHM_DIR / n).stat().st_ino
        except FileNotFoundError:
            pass
    return out


def _left_over(inodes: dict, wait_s: float = 3.0) -> list:
    """Files of ``inodes`` that still exist as the same file (not re-created by someone else),
    after waiting up to ``wait_s`` for them to go (a peer releases a port a moment after it closes)."""
    t_end = time.monotonic() + wait_s
    while True:
        left = [n for n, ino in _inodes(inodes).items() if inodes[n] == ino]
        if not left or time.monotonic() >= t_end:
            return left
        time.sleep(0.1)


def start_replay(env: dict, root: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "vings_ros.cli", "replay", str(root), "--json",
                             *args], env=env, cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _stats(out: str) -> dict:
    import json
    return json.loads(out.strip().splitlines()[-1])


# ------------------------------------------------------------------------------------- tests


def test_replay_publishes_every_message_with_exact_stamps(recording, ros, listener_factory,
                                                         tmp_path):
    root, src, frames, imu = recording
    lis = listener_factory()
    log = tmp_path / "published.csv"
    proc = start_replay(ros, root, "--rate", "4", "--publish-log", str(log))
    out, err = lis.spin_while(proc, done=lambda: len(lis.images) == N_FRAMES and len(lis.imu) == 195)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    st = _stats(out)
    assert st["images"] == N_FRAMES and st["imu"] == 195 and st["camera_info"] == N_FRAMES

    # images: all, in order, exact stamps and pixels, frame id
    assert [ma.header_ns(m.header) for m in lis.images] == [f.stamp_ns for f in frames]
    for m, f in zip(lis.images, frames):
        assert m.header.frame_id == "camera_optical_frame" and m.encoding == "rgb8"
        assert np.array_equal(ma.msg_to_image(m), f.image)
    # camera_info with every image, same stamps, describing the published images
    assert [ma.header_ns(m.header) for m in lis.infos] == [f.stamp_ns for f in frames]
    cam = ma.camera_info_to_camera(lis.infos[0])
    assert cam == src.calibration.camera
    # IMU: every sample, exact stamps and values
    got = [ma.msg_to_imu_sample(m) for m in lis.imu]
    assert [s.stamp_ns for s in got] == [s.stamp_ns for s in imu]
    assert all(np.array_equal(a.gyro, b.gyro) and np.array_equal(a.accel, b.accel)
               for a, b in zip(got, imu))
    assert lis.imu[0].header.frame_id == "imu_link"
    # /clock: sensor time, monotonic, ends at the last stamp
    clock = [ma.time_to_ns(c.clock) for c in lis.clock]
    stamps = {f.stamp_ns for f in frames} | {s.stamp_ns for s in imu}
    assert clock and all(b > a for a, b in zip(clock, clock[1:]))
    assert set(clock) <= stamps and clock[-1] == max(stamps)
    # paced at 4x real time: 0.97 s of data in about 0.24 s, images 12.5 ms apart
    assert st["sensor_s"] == pytest.approx(0.97)
    assert 0.2 < st["wall_s"] < 3.0 and st["achieved_rate"] < 4.5
    pub = np.loadtxt(log, delimiter=",", dtype=np.int64)
    assert pub[:, 0].tolist() == [f.stamp_ns for f in frames]
    gaps_ms = np.diff(pub[:, 1]) / 1e6
    assert np.all(gaps_ms > 0) and abs(np.median(gaps_ms) - 12.5) < 4.0


def test_back_pressure_slow_subscriber_gets_every_frame_in_order(recording, ros, listener_factory):
    """A front end that takes 50 ms per image and keeps only the newest image (depth 1) receives
    every frame with --wait-for-graph, and loses frames without it."""
    root, src, frames, imu = recording
    stamps = [f.stamp_ns for f in frames]

    lis = listener_factory(image_depth=1, process_s=0.05, ack=True)
    replay_files: dict = {}
    proc = start_replay(ros, root, "--rate", "0", "--wait-for-graph", "--ack-timeout", "20")
    lis.on_first_image = lambda: replay_files.update(_inodes(ros_env.shm_files_of(proc.pid)))
    out, err = lis.spin_while(proc, done=lambda: len(lis.imu) == 195)
    assert proc.returncode == 0, err
    st = _stats(out)
    assert [ma.header_ns(m.header) for m in lis.images] == stamps
    assert st["acks"] == N_FRAMES and st["ack_wait_mean_ms"] >= 40
    assert len(lis.imu) == 195 and len(lis.infos) == N_FRAMES
    # the replay exited cleanly: once its peer is gone too, none of its shared-memory files is left
    assert replay_files, "could not read the replay process's shared-memory files"
    lis.close()
    assert not _left_over(replay_files)

    # contrast: the same subscriber (now 200 ms per image) without back-pressure misses frames
    lis2 = listener_factory(image_depth=1, process_s=0.2, ack=True)
    proc = start_replay(ros, root, "--rate", "0")
    out, err = lis2.spin_while(proc, linger=1.0)
    assert proc.returncode == 0, err
    got = [ma.header_ns(m.header) for m in lis2.images]
    assert len(got) < N_FRAMES and got == sorted(got)


def test_window_and_topic_remapping_from_mcap(recording, ros, listener_factory, tmp_path):
    """The same recording written as a ROS 2 MCAP (vings_core.io.write_mcap), replayed in a window
    on remapped topics."""
    from vings_core.io import write_mcap
    _, src, frames, imu = recording
    root = tmp_path / "rec.mcap"
    write_mcap(root, src)
    tp = {"image": "/cam0/image_raw", "camera_info": "/cam0/camera_info", "imu": "/imu0",
          "clock": "/sim_clock"}
    lis = listener_factory(topics=tp)
    proc = start_replay(ros, root, "--rate", "0", "--start", "0.3", "--duration", "0.4",
                        "--topics", ",".join(f"{k}={v}" for k, v in tp.items()),
                        "--camera-frame", "cam0_optical", "--imu-lead", "0.2")
    out, err = lis.spin_while(proc, linger=1.5)
    assert proc.returncode == 0, err
    lo, hi = T0 + 300_000_000, T0 + 700_000_000  # relative to the first frame
    want = [f.stamp_ns for f in frames if lo <= f.stamp_ns <= hi]
    assert [ma.header_ns(m.header) for m in lis.images] == want
    # IMU from 0.2 s (--imu-lead) before the first published frame up to the last one
    assert [ma.header_ns(m.header) for m in lis.imu] == \
        [s.stamp_ns for s in imu if want[0] - 200_000_000 <= s.stamp_ns <= want[-1]]
    assert lis.images[0].header.frame_id == "cam0_optical"
    assert ma.time_to_ns(lis.clock[-1].clock) == want[-1]


def test_graph_errors_are_one_line(recording, ros, listener_factory):
    root = recording[0]
    # nobody there
    proc = start_replay(ros, root, "--wait-for-graph", "--startup-timeout", "1")
    out, err = proc.communicate(timeout=PROC_TIMEOUT_S)
    assert proc.returncode == 2
    assert "Traceback" not in err
    assert "nothing subscribes to /camera/image_raw" in err
    assert "nothing publishes the front end's acknowledgements" in err
    # a front end that subscribes but never acknowledges
    lis = listener_factory(ack=False)
    from std_msgs.msg import Header
    lis.node.create_publisher(Header, T.PROCESSED_TOPIC, T.ack_qos())
    log = Path(tempfile.mkdtemp()) / "pub.csv"
    proc = start_replay(ros, root, "--wait-for-graph", "--ack-timeout", "1", "--rate", "0",
                        "--publish-log", str(log))
    _, err = lis.spin_while(proc, linger=0.0)
    assert proc.returncode == 2
    assert f"no acknowledgement of the image stamped {T0}" in err and "Traceback" not in err
    # the image that went out before the timeout is in the publish log all the same
    assert [ln.split(",")[0] for ln in log.read_text().splitlines()[1:]] == [str(T0)]


def test_sigterm_stops_a_looping_replay_cleanly(recording, ros, listener_factory):
    root = recording[0]
    lis = listener_factory()
    proc = start_replay(ros, root, "--rate", "2", "--loop")
    files: dict = {}
    t_end = time.monotonic() + PROC_TIMEOUT_S
    while len(lis.images) < 25 and time.monotonic() < t_end and proc.poll() is None:
        lis.ex.spin_once(timeout_sec=0.02)
        if not files and lis.images:
            files = _inodes(ros_env.shm_files_of(proc.pid))
    assert len(lis.images) >= 25, "looping replay did not go past the end of the recording"
    proc.send_signal(signal.SIGTERM)
    out, err = lis.spin_while(proc, linger=0.0)
    assert proc.returncode == 0, err
    st = _stats(out)
    assert st["interrupted"] and st["loops"] >= 1
    stamps = [ma.header_ns(m.header) for m in lis.images]
    assert stamps[N_FRAMES] == stamps[0]  # second pass repeats the original stamps
    lis.close()
    assert files
    left = _left_over(files)
    # the replay's own segment and lock files are gone. A port it closed (lock file removed) can
    # outlive it while a live peer -- this process's participant, which lives until rclpy shuts
    # down -- still references it (Fast DDS); such an orphan is what the launcher's cleanup
    # removes, and only it may remain
    assert not [n for n in left if n.endswith(("_el", "_sl"))], left
    assert all("_port" in n for n in left), left
    assert sorted(ros_env.cleanup_fastdds_shm(names=left, min_age_s=0.0)) == sorted(left)


def test_loop_shift_keeps_every_stamp_increasing_across_passes(recording, ros, listener_factory):
    """With --loop-shift pass k is pass 0 shifted by k x (span + one frame period): images, IMU and
    /clock keep increasing, so a front end that drops non-increasing stamps sees every pass."""
    root, src, frames, imu = recording
    lis = listener_factory(ack=True)
    proc = start_replay(ros, root, "--rate", "0", "--loop", "--loop-shift", "--wait-for-graph",
                        "--startup-timeout", "30")
    t_end = time.monotonic() + PROC_TIMEOUT_S
    while len(lis.images) < 2 * N_FRAMES + 1 and time.monotonic() < t_end and proc.poll() is None:
        lis.ex.spin_once(timeout_sec=0.02)
    proc.send_signal(signal.SIGTERM)
    out, err = lis.spin_while(proc, linger=0.0)
    assert proc.returncode == 0, err
    img = [ma.header_ns(m.header) for m in lis.images]
    assert len(img) > 2 * N_FRAMES, err
    first = [f.stamp_ns for f in frames]
    period = int(np.median(np.diff(first)))
    shift = first[-1] - (first[0] - 1_000_000_000) + period     # span from the IMU lead (1 s)
    assert img[:N_FRAMES] == first
    assert img[N_FRAMES:2 * N_FRAMES] == [s + shift for s in first]
    assert all(b > a for a, b in zip(img, img[1:]))
    imu_st = [ma.header_ns(m.header) for m in lis.imu]
    assert all(b > a for a, b in zip(imu_st, imu_st[1:])) and imu_st[-1] > first[-1]
    clk = [m.clock.sec * 10**9 + m.clock.nanosec for m in lis.clock]
    assert all(b > a for a, b in zip(clk, clk[1:]))
    lis.close()


def test_cleanup_removes_only_dead_processes_files(ros, listener_factory):
    """kill -9 leaves segments/ports behind; the cleanup removes those and leaves a live
    participant's (this process's listener) alone; once the listener has closed too, nothing of
    either is left (including the listener's port the killed peer still referenced)."""
    snap = ros_env.shm_snapshot()
    lis = listener_factory()
    mine = ros_env.shm_files_of(os.getpid())
    assert mine, "this process's Fast DDS files are not visible"
    mine_ino = _inodes(f for f in mine if f not in snap.names)  # (it may reuse older ports)
    code = ("import rclpy, time; rclpy.init(); n = rclpy.create_node('victim'); "
            "print('up', flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code], env=ros, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "up"
        t_end = time.monotonic() + 10
        victim = set()
        while time.monotonic() < t_end and not any(f.endswith("_el") for f in victim):
            victim = ros_env.shm_files_of(proc.pid)
            time.sleep(0.05)
        t_end = time.monotonic() + 10  # let the two discover each other (the victim maps our ports)
        while time.monotonic() < t_end and lis.node.count_publishers("/rosout") < 2:
            lis.ex.spin_once(timeout_sec=0.05)
    finally:
        proc.kill()
        proc.wait()
    victim -= mine  # the domain's multicast port is shared with the listener
    assert victim and all((ros_env.SHM_DIR / f).exists() for f in victim)  # left by kill -9
    victim_ino = _inodes(victim)
    removed = ros_env.cleanup_fastdds_shm(snap, min_age_s=0.0)
    assert not _left_over(victim_ino)
    assert set(removed) >= victim
    assert not set(removed) & mine and not [f for f in mine_ino if f not in _left_over(mine_ino)]
    lis.ex.spin_once(timeout_sec=0.01)  # still alive
    lis.close()
    time.sleep(0.6)
    ros_env.cleanup_fastdds_shm(snap)
    assert not _left_over(mine_ino)


@pytest.mark.slow
def test_full_size_images_at_20hz_lose_nothing_without_back_pressure(ros, listener_factory,
                                                                     tmp_path):
    """752x480 rgb8 at 20 Hz (real time, no back-pressure) between processes through the shipped
    Fast DDS profile: every frame arrives, in order (subscriber depth 10). Slow only because it
    writes 100 full-size PNGs; it checks the transport claim of docs/ros.md."""
    n = 100
    root = make_euroc(tmp_path / "big", n=n, w=752, h=480)
    lis = listener_factory(image_depth=10)
    proc = start_replay(ros, root, "--rate", "1")
    out, err = lis.spin_while(proc, done=lambda: len(lis.images) == n, linger=3.0)
    assert proc.returncode == 0, err
    st = _stats(out)
    assert st["images"] == n and st["image_rate_hz"] > 15
    got = [ma.header_ns(m.header) for m in lis.images]
    assert got == [T0 + i * 50_000_000 for i in range(n)]
    assert lis.images[0].width == 752 and lis.images[0].height == 480


# ------------------------------------------------------------------------- no transport needed


def test_topics_and_options_validation():
    assert parse_topics("image=/a/b, imu=/imu0") == {"image": "/a/b", "imu": "/imu0"}
    with pytest.raises(ConfigError, match="key=/topic"):
        parse_topics("image")
    for kw, pat in (({"rate": -1.0}, "--rate"), ({"topics": {"camera": "/x"}}, "unknown key"),
                    ({"topics": {"image": "relative"}}, "absolute"), ({"duration_s": 0.0}, "--duration"),
                    ({"start_s": -2.0}, "--start"), ({"imu_lead_s": -1.0}, "--imu-lead"),
                    ({"loop_shift": True}, "--loop-shift needs --loop"), ({"rate": float("inf")}, "finite")):
        with pytest.raises(ConfigError, match=pat):
            ReplayOptions(**kw).validate()
    # the publish log is checked before the replay (a folder, a place nothing can be written)
    with pytest.raises(ConfigError, match="--publish-log .*is a folder"):
        ReplayOptions(publish_log="/tmp").validate()
    with pytest.raises(ConfigError, match="--publish-log .*cannot write"):
        ReplayOptions(publish_log="/proc/vings/log.csv").validate()
    import tempfile
    with tempfile.TemporaryDirectory() as d:     # missing folders: fine, and not created by the check
        ReplayOptions(publish_log=f"{d}/a/b/log.csv").validate()
        assert not os.path.exists(f"{d}/a")
    o = ReplayOptions(topics={"image": "/cam/img"})
    o.validate()
    assert o.topics["image"] == "/cam/img" and o.topics["imu"] == T.IMU_TOPIC


def test_ros_environment(tmp_path, monkeypatch):
    base = {"PATH": "/usr/bin"}
    env = ros_env.ros_environment(domain_id=42, base=base, log_dir=tmp_path)
    prof = env[ros_env.PROFILE_ENV]
    assert Path(prof).is_file() and prof == str(ros_env.shm_profile_path())
    text = Path(prof).read_text()
    assert "<type>SHM</type>" in text and "<type>UDPv4</type>" in text
    assert f"<segment_size>{ros_env.SEGMENT_BYTES}</segment_size>" in text
    assert env["ROS_DOMAIN_ID"] == "42" and env["ROS_LOG_DIR"] == str(tmp_path)
    assert sys.prefix in env["AMENT_PREFIX_PATH"].split(os.pathsep)
    assert base == {"PATH": "/usr/bin"}  # not modified
    # udp: our profile removed (also when inherited), a user's own profile kept
    udp = ros_env.ros_environment(base={**env, "VINGS_DDS": "udp"})
    assert ros_env.PROFILE_ENV not in udp
    user = ros_env.ros_environment(base={ros_env.PROFILE_ENV: "/etc/my_dds.xml"})
    assert user[ros_env.PROFILE_ENV] == "/etc/my_dds.xml"
    assert ros_env.ros_environment(base={ros_env.PROFILE_ENV: "/etc/my_dds.xml", "VINGS_DDS": "udp"}
                                   )[ros_env.PROFILE_ENV] == "/etc/my_dds.xml"
    # /dev/shm too small (Docker's 64 MiB): no profile, built-in transports
    monkeypatch.setattr(ros_env, "MIN_SHM_FREE", 1 << 62)
    assert ros_env.PROFILE_ENV not in ros_env.ros_environment(base=base)
    assert ros_env.PROFILE_ENV in ros_env.ros_environment(base=base, use_shm=True)
    monkeypatch.undo()
    # in-process, before rclpy.init(): os.environ changes (restored afterwards)
    keys = ("ROS_DOMAIN_ID", "ROS_LOG_DIR", "AMENT_PREFIX_PATH", *ros_env._PROFILE_ENVS)
    saved = {k: os.environ.get(k) for k in keys}
    try:
        os.environ.pop(ros_env.PROFILE_ENV, None)
        os.environ["ROS_LOG_DIR"] = str(tmp_path / "log")
        changed = ros_env.apply_ros_environment(domain_id=7)
        assert os.environ["ROS_DOMAIN_ID"] == "7" and changed["ROS_DOMAIN_ID"] == "7"
        assert os.environ[ros_env.PROFILE_ENV] == prof and (tmp_path / "log").is_dir()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    with pytest.raises(ConfigError, match="VINGS_DDS"):
        ros_env.ros_environment(base={"VINGS_DDS": "carrier-pigeon"})
    with pytest.raises(ConfigError, match="ROS_DOMAIN_ID"):
        ros_env.ros_environment(domain_id=300, base=base)
    # an inherited value rcl cannot use is named before rclpy.init() (which fails deep inside)
    for bad in ("abc", "-1", "300"):
        with pytest.raises(ConfigError, match=f"environment variable ROS_DOMAIN_ID='{bad}' is not an integer"):
            ros_env.ros_environment(base={**base, "ROS_DOMAIN_ID": bad})
    assert ros_env.ros_environment(base={**base, "ROS_DOMAIN_ID": "abc"}, domain_id=3)["ROS_DOMAIN_ID"] == "3"
    assert ros_env.ros_environment(base={**base, "ROS_DOMAIN_ID": ""})["ROS_DOMAIN_ID"] == ""
    # the ament index finds a package registered under a prefix listed in AMENT_PREFIX_PATH (the
    # editable install does not register vings_ros under sys.prefix: a prefix made here instead)
    prefix = tmp_path / "prefix"
    (prefix / "share" / "ament_index" / "resource_index" / "packages").mkdir(parents=True)
    (prefix / "share" / "ament_index" / "resource_index" / "packages" / "vings_ros").write_text("")
    (prefix / "share" / "vings_ros").mkdir()
    env2 = ros_env.ros_environment(base={**base, "AMENT_PREFIX_PATH": str(prefix)})
    assert str(prefix) in env2["AMENT_PREFIX_PATH"].split(os.pathsep)
    monkeypatch.setenv("AMENT_PREFIX_PATH", env2["AMENT_PREFIX_PATH"])
    from ament_index_python.packages import get_package_share_directory
    assert Path(get_package_share_directory("vings_ros")) == prefix / "share" / "vings_ros"


def test_cli_reports_bad_arguments_in_one_line(tmp_path, capsys, recording, monkeypatch):
    from vings_ros.cli import main
    from vings_ros.replay import Replayer
    # a ROS environment rcl refuses: one line (it was an RCLError hidden behind an AttributeError
    # from the teardown of the half-made set-up)
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    assert main(["replay", str(recording[0]), "--no-wait"]) == 2
    err = capsys.readouterr().err
    assert "ROS_DOMAIN_ID='abc'" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    with pytest.raises(ConfigError, match="replay: cannot start ROS: .*ROS_DOMAIN_ID"):
        Replayer(recording[1], ReplayOptions(wait_subscribers=False)).run()   # past the CLI's check
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert main(["replay", str(recording[0]), "--start", "5", "--no-wait"]) == 2
    assert "no frames in the selected window" in capsys.readouterr().err
    (tmp_path / "afile").write_text("a file where the log's folder would be")
    assert main(["replay", str(tmp_path / "nope"), "--no-wait"]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert main(["replay", str(tmp_path), "--rate", "-3"]) == 2
    assert "--rate must be a finite number >= 0" in capsys.readouterr().err
    assert main(["replay", str(tmp_path), "--topics", "image"]) == 2
    assert "key=/topic" in capsys.readouterr().err
    for args, msg in ((["--topics", "image=/1bad"], "absolute ROS name"),
                      (["--topics", "image=/a//b"], "absolute ROS name"),
                      (["--topics", "image=/x,imu=/x"], "would both publish on /x"),
                      (["--start", "nan"], "--start must be a finite"),
                      (["--duration", "inf"], "--duration must be a finite"),
                      (["--imu-lead", "inf"], "--imu-lead must be a finite"),
                      (["--startup-timeout", "nan"], "--startup-timeout >= 0"),
                      (["--publish-log", str(tmp_path / "afile" / "x.csv")], "--publish-log")):
        assert main(["replay", str(recording[0]), "--no-wait", *args]) == 2, args
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err, (args, err)
