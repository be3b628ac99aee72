"""The node graph under faults (docs/ros.md): what a stop, a dead launcher and a killed node cost.

Experiments (``--exp``, comma list):

* ``launcher_kill``: ``vings launch`` (every default node), ``kill -9`` of the launcher once the
  nodes are up: seconds until every node process has exited (target <= 5 s) and Fast DDS
  shared-memory files left by them (target 0).
* ``ctrl_c``: ``vings launch --checkpoint`` + ``vings replay --wait-for-graph`` of a synthetic room
  with a slow mapper (``mapping.iters_per_keyframe``), Ctrl-C on the launcher once the mapper is
  ``--behind`` keyframes behind the front end: stop time (target <= 10 s); keyframes the front end
  emitted vs keyframes in the checkpoint plus those stored beside it (target equal); then the mapper
  is started again on the checkpoint: seconds until every stored keyframe is mapped.
* ``node_kill``: for each of ``--nodes`` (default: mapper_node, eraser_node, loop_closer_node,
  frontend_node), ``kill -9`` of that node at a random moment (after 20-70 % of the frames, drawn
  per trial) of a replay (back-pressure, ``--checkpoint``) of ``--scene`` (default a street loop
  with moving objects, ``--frames`` long): seconds until it is back (respawned, its /diagnostics
  heard again; for the front end also its ``restart`` mode and outcome); keyframes emitted vs in
  the final checkpoint (the graph is stopped once the mapper has mapped every emitted keyframe, or
  after ``--timeout``); ATE Sim(3) of the checkpoint's keyframes and of the odometry heard,
  against the mean of ``--fault-free`` runs without a kill (their min / max is the graph's own
  run-to-run spread).

* ``bad_input``: the graph on a live clock, and malformed messages on every input topic (Image,
  CameraInfo, Imu, dynamic masks, keyframe packets, pose-exchange corrections with unknown stamps
  or NaN poses, render requests): per case, whether every node is still running and by how much
  the receiving node's /diagnostics counter went up (target: 0 crashes, each counted).

* ``hosts_apart``: the front end and the replay in one network namespace, the mapper in another
  (a virtual Ethernet pair, ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``), against both on one host:
  keyframes emitted vs received by the mapper (its checkpoint plus those stored beside it), ATE
  Sim(3) of the mapper's keyframes and of the front end's trajectory. Needs root and iproute2.

* ``discovery``: how soon a node that starts (or is respawned) next to a running subscriber is
  heard, with ``--load`` busy processes on the CPU (default 2: this machine's cores, as while a
  graph is busy): a child publishes a std_msgs/Header every 50 ms from the moment its publisher
  exists; the subscriber records which message came first; ``--trials`` children per profile. The
  shipped Fast DDS profile (``vings_ros/config/fastdds_shm.xml``) against the same profile without
  its discovery settings (Fast DDS's: 5 initial announcements, then one every 3 s).

The last stdout line is one JSON object keyed by experiment (``benchmarks/_harness.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import run_experiments  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def _log(*a) -> None:
    print("[bench faults]", *a, file=sys.stderr, flush=True)


def _procs_with_env(key: str, value: str) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            if f"{key}={value}".encode() in (d / "environ").read_bytes().split(b"\0"):
                out.append(int(d.name))
        except OSError:
            continue
    return out


def _node_pids(mark: str) -> dict[str, int]:
    """pid of each VINGS node process of the graph marked ``mark`` (by module name)."""
    out = {}
    for pid in _procs_with_env("VINGS_BENCH_MARK", mark):
        try:
            cmd = (Path("/proc") / str(pid) / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        for c in cmd:
            c = c.decode(errors="replace")
            if c.startswith("vings_ros.") and c.endswith("_node"):
                out[c.split(".")[-1]] = pid
            elif c == "vings_ros.recorder":
                out["recorder_node"] = pid
    return out


def _launch(domain: int, mark: str, params: list[str], ckpt: Path | None, log: Path,
            sim_time: bool = True) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "vings_ros.cli", "launch", "--backpressure", "--domain-id", str(domain)]
    if sim_time:
        cmd.append("--use-sim-time")
    if ckpt is not None:
        cmd += ["--checkpoint", str(ckpt)]
    for p in params:
        cmd += ["-p", p]
    env = dict(os.environ, VINGS_BENCH_MARK=mark, PYTHONPATH=str(REPO))
    return subprocess.Popen(cmd, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)


class _Listener:
    """An rclpy node of this process: keyframe stamps the front end emitted, the mapper's latest
    keyframe list, diagnostics heard per node name."""

    def __init__(self, domain: int) -> None:
        from vings_ros.ros_env import apply_ros_environment
        apply_ros_environment(domain_id=domain)
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path as PathMsg

        from msg_adapters import topics as T
        rclpy.init()
        self.rclpy = rclpy
        self.node = rclpy.create_node("bench_faults")
        self.emitted: set[int] = set()
        self.mapped: set[int] = set()
        self.heard: dict[str, float] = {}
        self.values: dict[str, dict] = {}       # the latest diagnostics values per status name
        self.odom: dict[int, object] = {}       # stamp -> T_wc of /vings/odometry
        st = lambda h: h.stamp.sec * 1_000_000_000 + h.stamp.nanosec  # noqa: E731
        self.node.create_subscription(PoseStamped, T.KEYFRAME_POSE_TOPIC, lambda m: self.emitted.add(st(m.header)),
                                      T.sensor_qos(200))
        self.node.create_subscription(PathMsg, T.REFINED_KEYFRAMES_TOPIC,
                                      lambda m: self.mapped.update(st(p.header) for p in m.poses), T.latched_qos(1))
        self.node.create_subscription(DiagnosticArray, T.DIAGNOSTICS_TOPIC, self._diag, T.sensor_qos(50))
        from nav_msgs.msg import Odometry

        from msg_adapters.pose import odometry_to_estimate

        def odom(m):
            e = odometry_to_estimate(m, T.ODOMETRY_TOPIC)
            self.odom[int(e.stamp_ns)] = e.T_wc
        self.node.create_subscription(Odometry, T.ODOMETRY_TOPIC, odom, T.latched_qos(500))
        from vings_ros.node_common import spin_in_background
        self._stop_spinning = spin_in_background(self.node, 0.05)

    def _diag(self, msg) -> None:
        for s in msg.status:
            self.heard[s.name] = time.monotonic()
            self.values[s.name] = {kv.key: kv.value for kv in s.values}

    def close(self) -> None:
        self._stop_spinning()
        self.node.destroy_node()
        self.rclpy.shutdown()


def _sim(work: Path, frames: int, scene: str = "room", size: tuple[int, int] = (376, 240)) -> Path:
    """The replayed recording: a synthetic room of ``frames`` frames, or (``street``) a street loop
    with moving objects, about ``frames`` frames long at 10 Hz (4 m/s: 0.4 m per frame), at
    ``size`` (width, height)."""
    from vings_core.sim import generate
    d = work / (f"{scene}_{frames}" + ("" if size == (376, 240) else f"_{size[0]}x{size[1]}"))
    if not (d / "sim.json").exists():
        if scene == "street":
            generate("street", d, seed=0, dynamic=True, loop=True, fps=10.0,
                     length_m=max(50.0, 0.4 * frames), width=size[0], height=size[1])
        else:
            generate("room", d, frames=frames, seed=0, width=size[0], height=size[1])
    return next(d.glob("*.mcap"))


def exp_launcher_kill(work: Path, args) -> dict:
    from vings_ros.ros_env import cleanup_fastdds_shm, shm_snapshot
    mark = f"lk{os.getpid()}"
    snap = shm_snapshot()
    p = _launch(args.domain, mark, [], None, work / "launcher_kill.log")
    t_end = time.monotonic() + 120
    while len(_node_pids(mark)) < 4 and time.monotonic() < t_end:
        time.sleep(0.2)
    pids = _node_pids(mark)
    if len(pids) < 4:
        p.kill()
        return {"incomplete": f"only {sorted(pids)} came up (log {work / 'launcher_kill.log'})"}
    time.sleep(3.0)
    t0 = time.monotonic()
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    while any(Path(f"/proc/{q}").exists() for q in pids.values()) and time.monotonic() < t0 + 60:
        time.sleep(0.02)
    gone_s = time.monotonic() - t0
    left = [q for q in pids.values() if Path(f"/proc/{q}").exists()]
    for q in left:
        os.kill(q, signal.SIGKILL)
    time.sleep(1.0)
    leftover = cleanup_fastdds_shm(snap, dry_run=True)
    return {"nodes": sorted(pids), "all_exited_s": round(gone_s, 2), "still_running": len(left),
            "shm_files_left": len(leftover)}


def exp_ctrl_c(work: Path, args) -> dict:
    from vings_core.mapping import Mapper
    mcap = _sim(work, args.frames)
    ck = work / "ctrl_c" / "map.ckpt"
    ck.parent.mkdir(parents=True, exist_ok=True)
    for f in ck.parent.glob("*"):
        if f.is_file():
            f.unlink()
    mark = f"cc{os.getpid()}"
    slow = [f"mapping.iters_per_keyframe={args.iters}", "mapper_node.checkpoint_period_s=0.0"]
    lis = _Listener(args.domain)
    p = _launch(args.domain, mark, slow + ["loop.enabled=false"], ck, work / "ctrl_c.log")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    rep = subprocess.Popen([sys.executable, "-m", "vings_ros.cli", "replay", str(mcap), "--wait-for-graph",
                            "--domain-id", str(args.domain)], env=env, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    t_end = time.monotonic() + args.timeout
    while time.monotonic() < t_end and rep.poll() is None and len(lis.emitted) - len(lis.mapped) < args.behind:
        time.sleep(0.2)
    behind = len(lis.emitted) - len(lis.mapped)
    rep.send_signal(signal.SIGINT)
    rep.wait(60)
    time.sleep(2.0)                         # the front end's last keyframe packets reach the mapper
    emitted = set(lis.emitted)
    t0 = time.monotonic()
    os.killpg(p.pid, signal.SIGINT)
    p.wait(300)
    stop_s = time.monotonic() - t0
    in_ckpt = set(Mapper.load_checkpoint(ck).keyframe_poses()) if ck.exists() else set()
    stored = {int(f.stem.split("-")[2]) for f in (ck.parent / (ck.name + ".queue")).glob("kf-*.pt")}
    # the mapper again on the checkpoint: it maps what was stored
    t1 = time.monotonic()
    p2 = _launch(args.domain, mark + "r", slow + ["loop.enabled=false", "eraser.enabled=false"], ck,
                 work / "ctrl_c_resume.log")
    while time.monotonic() < t1 + args.timeout and not (emitted <= lis.mapped):
        time.sleep(0.5)
    resume_s = time.monotonic() - t1
    os.killpg(p2.pid, signal.SIGINT)
    p2.wait(300)
    lis.close()
    after = set(Mapper.load_checkpoint(ck).keyframe_poses()) if ck.exists() else set()
    return {"behind_at_stop": behind, "stop_s": round(stop_s, 2), "emitted": len(emitted),
            "in_checkpoint": len(in_ckpt & emitted), "stored_beside": len(stored & emitted),
            "lost": len(emitted - in_ckpt - stored), "resume_s_all_mapped": round(resume_s, 1),
            "after_resume_in_checkpoint": len(after & emitted)}


def exp_node_kill(work: Path, args) -> dict:
    from vings_core.eval.traj import evaluate_trajectory
    from vings_core.io import open_source
    from vings_core.mapping import Mapper
    from vings_core.types import Trajectory
    mcap = _sim(work, args.frames, args.scene, tuple(int(v) for v in args.size.split("x")))
    src = open_source(str(mcap))
    gt = src.gt_camera_trajectory()
    n_frames = len(src.frame_stamps())
    names = {"frontend_node": "vings/frontend", "mapper_node": "vings/mapper", "loop_closer_node": "vings/loop_closer",
             "eraser_node": "vings/eraser"}
    out = {}
    for victim in ["none"] + [n for n in args.nodes.split(",") if n]:
        for trial in range(args.trials if victim != "none" else args.fault_free):
            tag = f"{victim}_{trial}"
            d = work / "node_kill" / tag
            shutil.rmtree(d, ignore_errors=True)        # checkpoints and queues of an earlier run
            d.mkdir(parents=True)
            ck = d / "map.ckpt"
            mark = f"nk{os.getpid()}{tag}"
            lis = _Listener(args.domain)
            t0 = time.monotonic()
            p = _launch(args.domain, mark, [f"mapping.iters_per_keyframe={args.iters}"], ck, d / "launch.log")
            env = dict(os.environ, PYTHONPATH=str(REPO))
            rep = subprocess.Popen([sys.executable, "-m", "vings_ros.cli", "replay", str(mcap), "--wait-for-graph",
                                    "--ack-timeout", "300", "--respawn-wait", "120", "--domain-id", str(args.domain)],
                                   env=env, stdout=(d / "replay.log").open("w"), stderr=subprocess.STDOUT)
            rec = {}
            if victim != "none":
                # a random moment: after 20-70 % of the frames were tracked
                after = int(n_frames * random.Random(f"{victim}{trial}").uniform(0.2, 0.7))
                t_end = time.monotonic() + args.timeout
                while len(lis.odom) < after and rep.poll() is None and time.monotonic() < t_end:
                    time.sleep(0.1)
                pid = _node_pids(mark).get(victim)
                if pid is not None and rep.poll() is None:
                    rec["killed_after_frames"] = len(lis.odom)
                    t_kill = time.monotonic()
                    os.kill(pid, signal.SIGKILL)
                    while time.monotonic() < t_kill + 300:
                        new = _node_pids(mark).get(victim)
                        if new not in (None, pid) and lis.heard.get(names[victim], 0.0) > t_kill + 0.5:
                            break
                        time.sleep(0.2)
                    rec["recover_s"] = round(time.monotonic() - t_kill, 1)
                else:
                    rec["not_killed"] = "the replay ended first" if rep.poll() is not None else f"no {victim} process"
            rc = rep.wait(args.timeout)
            rec["replay_rc"] = rc
            # the mapper maps everything before the stop (the fault-free and faulty runs alike)
            t_end = time.monotonic() + args.timeout
            while not (set(lis.emitted) <= lis.mapped) and time.monotonic() < t_end:
                time.sleep(0.5)
            fe = lis.values.get("vings/frontend", {})
            if victim == "frontend_node":
                rec.update(restart=fe.get("restart"), restart_outcome=fe.get("restart_outcome"),
                           restart_gap_s=fe.get("restart_gap_s"))
            rec["segments"] = int(fe.get("segment", "0")) + 1 if fe.get("segment", "").isdigit() else None
            os.killpg(p.pid, signal.SIGINT)
            p.wait(600)
            rec["wall_s"] = round(time.monotonic() - t0, 1)
            emitted = set(lis.emitted)
            odom = dict(lis.odom)
            lis.close()
            kfs = Mapper.load_checkpoint(ck).keyframe_poses() if ck.exists() else {}
            stored = {int(f.stem.split("-")[2]) for f in (ck.parent / (ck.name + ".queue")).glob("kf-*.pt")}
            rec.update(emitted=len(emitted), in_checkpoint=len(emitted & set(kfs)), stored=len(emitted & stored),
                       odometry=len(odom))
            for what, poses in (("kf", kfs), ("odom", odom)):
                if len(poses) >= 3:
                    try:
                        rec[f"{what}_ate_sim3_m"] = evaluate_trajectory(Trajectory.from_poses(poses), gt)["ate_sim3_m"]
                    except Exception as e:  # noqa: BLE001 - reported
                        rec[f"{what}_ate_error"] = str(e)
            out[tag] = rec
            _log(tag, json.dumps(rec))
    # against the mean of the fault-free runs; their own spread says how much of a difference is
    # the run-to-run variation of the graph (thread timing moves poses through the exchange)
    for what in ("kf", "odom"):
        free = [r[f"{what}_ate_sim3_m"] for t, r in out.items() if t.startswith("none_") and f"{what}_ate_sim3_m" in r]
        if not free:
            continue
        b = sum(free) / len(free)
        out[f"fault_free_{what}_ate_sim3_m"] = {"mean": round(b, 4), "min": round(min(free), 4),
                                                "max": round(max(free), 4), "runs": len(free)}
        for tag, rec in list(out.items()):
            a = rec.get(f"{what}_ate_sim3_m") if isinstance(rec, dict) else None
            if a is not None and b:
                rec[f"{what}_ate_vs_fault_free"] = round(a / b - 1.0, 3)
    return out


def _bad_messages(stamp0: int) -> list[tuple[str, str, str, str, object]]:
    """The bad-input cases: (case, topic, node status name, counter key, message). Stamps count up
    from ``stamp0`` (a live clock: a valid image stamp)."""
    import numpy as np
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMsg
    from sensor_msgs.msg import CameraInfo, Image, Imu

    from msg_adapters import topics as T
    from msg_adapters.exchange import exchange_topic
    from msg_adapters.keyframe import PART_TOPICS
    from msg_adapters.loop import RENDER_REQUEST_TOPIC
    from msg_adapters.stamps import make_header

    n = [stamp0]

    def hdr(frame="camera", stamp=None):
        n[0] += 50_000_000
        return make_header(n[0] if stamp is None else stamp, frame, "bench")

    def image(enc="mono8", w=64, h=48, data=None, stamp=None):
        m = Image(header=hdr(stamp=stamp), height=h, width=w, encoding=enc, step=w)
        m.data = bytes(w * h) if data is None else data
        return m

    def imu(**kw):
        m = Imu(header=hdr("imu"))
        m.orientation_covariance[0] = -1.0
        m.linear_acceleration.z = 9.81
        for k, v in kw.items():
            setattr(getattr(m, k.split(".")[0]), k.split(".")[1], v)
        return m

    def pose(x=0.0, qw=1.0, frame="map", stamp=None):
        m = PoseStamped(header=hdr(frame, stamp))
        m.pose.position.x, m.pose.orientation.w = x, qw
        return m

    def path(topic, poses, seq=None):
        m = PathMsg(header=hdr("map", seq))
        m.poses = poses
        return m

    from msg_adapters.camera_info import camera_to_camera_info
    from msg_adapters.keyframe import keyframe_to_msgs
    from vings_core.types import CameraModel, Keyframe
    import torch

    cam = CameraModel(64, 48, 50.0, 50.0, 31.5, 23.5)
    cam_zero = CameraInfo(header=hdr(), width=64, height=48)
    cam_nan = CameraInfo(header=hdr(), width=64, height=48)
    cam_nan.k = [float("nan")] * 9
    far = 10 ** 18 + 12345
    rng = np.random.default_rng(0)

    def good_image():
        return image(data=rng.integers(0, 255, 64 * 48, dtype=np.uint8).tobytes())

    def packet(k: int, broken: str):
        """The five parts of a keyframe with part ``broken`` spoilt (stamp far from any real one)."""
        kf = Keyframe(stamp_ns=far + 100 + k, image=torch.rand(48, 64, 3), T_wc=torch.eye(4, dtype=torch.float64),
                      depth=torch.ones(48, 64), inv_depth_var=torch.ones(48, 64),
                      valid=torch.ones(48, 64, dtype=torch.bool), camera=cam, index=k)
        parts = keyframe_to_msgs(kf).as_dict()
        if broken == "pose":
            parts["pose"].pose.orientation.w = float("nan")
        elif broken == "depth":
            parts["depth"] = float_like(parts["depth"], 32, 24)
        elif broken == "image":
            parts["image"].encoding = "32FC1"
        return [(PART_TOPICS[p], m) for p, m in parts.items()]

    def float_like(m, w, h):
        m.width, m.height, m.step = w, h, 4 * w
        m.data = bytes(4 * w * h)
        return m

    FE, MP, LC, ER = "vings/frontend", "vings/mapper", "vings/loop_closer", "vings/eraser"
    info = camera_to_camera_info(cam, n[0], "camera", T.CAMERA_INFO_TOPIC)
    return [
        ("CameraInfo with K = 0", T.CAMERA_INFO_TOPIC, FE, "bad_camera_infos", cam_zero),
        ("CameraInfo with NaN in K", T.CAMERA_INFO_TOPIC, FE, "bad_camera_infos", cam_nan),
        ("(a valid CameraInfo, so that images are decoded)", T.CAMERA_INFO_TOPIC, FE, None, info),
        ("Image, unknown encoding", T.IMAGE_TOPIC, FE, "bad_frames", image("bogus8")),
        ("Image, data shorter than step x height", T.IMAGE_TOPIC, FE, "bad_frames", image(data=bytes(100))),
        ("Image, 0 x 0", T.IMAGE_TOPIC, FE, "bad_frames", image(w=0, h=0, data=b"")),
        ("Image, another size than CameraInfo's", T.IMAGE_TOPIC, FE, "bad_frames", image(w=32, h=24)),
        ("Image, negative stamp", T.IMAGE_TOPIC, FE, "bad_frames", image(stamp=-5)),
        ("Image, zero stamp on a live topic", T.IMAGE_TOPIC, FE, "bad_frames", image(stamp=0)),
        ("(a valid image)", T.IMAGE_TOPIC, FE, None, good_image()),
        ("Image, stamp before the previous one", T.IMAGE_TOPIC, FE, "bad_frames", image(stamp=stamp0)),
        ("Imu, NaN angular velocity", T.IMU_TOPIC, FE, "bad_imu", imu(**{"angular_velocity.x": float("nan")})),
        ("Imu, infinite acceleration", T.IMU_TOPIC, FE, "bad_imu", imu(**{"linear_acceleration.y": float("inf")})),
        ("dynamic mask, rgb8 instead of mono8", T.DYNAMIC_MASK_TOPIC, FE, "bad_dynamic_masks",
         image("rgb8", 4, 4, bytes(48))),
        ("dynamic mask, rgb8 (mapper)", T.DYNAMIC_MASK_TOPIC, MP, "bad_masks", image("rgb8", 4, 4, bytes(48))),
        ("keyframe packet, NaN quaternion (mapper)", None, MP, "bad_keyframe_parts", packet(0, "pose")),
        ("keyframe packet, NaN quaternion (loop closer)", None, LC, "bad_keyframe_parts", packet(1, "pose")),
        ("keyframe packet, NaN quaternion (eraser)", None, ER, "bad_keyframe_parts", packet(2, "pose")),
        ("keyframe packet, depth of another size (mapper)", None, MP, "bad_keyframe_parts", packet(3, "depth")),
        ("keyframe packet, image as 32FC1 (mapper)", None, MP, "bad_keyframe_parts", packet(4, "image")),
        # then a valid image: the front end reads the corrections before each frame
        ("correction for stamps the front end never sent", None, FE, "corrections_unknown_stamps",
         [(exchange_topic("mapper"), path("m", [pose(0.1, stamp=far), pose(0.2, stamp=far + 1)], seq=10 ** 9)),
          (T.IMAGE_TOPIC, good_image())]),
        ("correction with a NaN pose", exchange_topic("mapper"), FE, "bad_exchange_messages",
         path("m", [pose(qw=float("nan"), stamp=far + 2)], seq=10 ** 9 + 1)),
        ("keeper batch with a NaN pose (mapper)", exchange_topic("frontend"), MP, "bad_exchange_messages",
         path("f", [pose(qw=float("nan"), stamp=far + 3)], seq=10 ** 9 + 2)),
        ("render request, id 0", RENDER_REQUEST_TOPIC, MP, "bad_render_requests", pose(stamp=0)),
        ("render request, unknown frame_id key", RENDER_REQUEST_TOPIC, MP, "bad_render_requests",
         pose(frame="map;colour=1", stamp=7)),
    ]


def exp_bad_input(work: Path, args) -> dict:
    """Malformed messages on every input topic of the running graph (live clock): 0 crashes, each
    counted in the receiving node's /diagnostics."""
    from msg_adapters import topics as T
    mark = f"bi{os.getpid()}"
    lis = _Listener(args.domain)
    p = _launch(args.domain, mark, [], None, work / "bad_input.log", sim_time=False)
    names = ("vings/frontend", "vings/mapper", "vings/loop_closer", "vings/eraser")
    t_end = time.monotonic() + 120
    while not all(n in lis.values for n in names) and time.monotonic() < t_end:
        time.sleep(0.2)
    pids = _node_pids(mark)
    cases = _bad_messages(time.time_ns())
    pubs = {}

    def send(topic, msg) -> None:
        if topic is None:                   # several messages (a keyframe packet's parts)
            for t, m in msg:
                send(t, m)
                time.sleep(0.2)
            return
        if (topic, type(msg)) not in pubs:
            pubs[(topic, type(msg))] = lis.node.create_publisher(type(msg), topic, T.sensor_qos(50))
            time.sleep(2.0)                 # discovery of the new publisher
        pubs[(topic, type(msg))].publish(msg)

    rows = []
    for case, topic, status, key, msg in cases:
        before = _count(lis, status, key) if key else None
        send(topic, msg)
        if key is None:                     # a valid message the next cases rely on
            time.sleep(1.0)
            continue
        t_end = time.monotonic() + 3 * float(os.environ.get("VINGS_DIAG_PERIOD", "1.0")) + 5
        while (_count(lis, status, key) or 0) <= (before or 0) and time.monotonic() < t_end:
            time.sleep(0.1)
        after = _count(lis, status, key)
        alive = {n: Path(f"/proc/{q}").exists() for n, q in pids.items()}
        mtype = " + ".join(dict.fromkeys(type(m).__name__ for _, m in msg)) if topic is None else type(msg).__name__
        rows.append({"case": case, "topic": topic or " + ".join(dict.fromkeys(t for t, _ in msg)), "type": mtype, "node": status,
                     "counter": key, "counted": (after or 0) - (before or 0) if after is not None else None,
                     "nodes_alive": sum(alive.values()), "of": len(alive)})
        _log(json.dumps(rows[-1]))
    os.killpg(p.pid, signal.SIGINT)
    rc = p.wait(300)
    lis.close()
    return {"cases": rows, "crashes": sum(r["nodes_alive"] < r["of"] for r in rows),
            "not_counted": [r["case"] for r in rows if not r["counted"]], "launch_rc": rc}


def _count(lis: "_Listener", status: str, key: str):
    v = lis.values.get(status, {}).get(key)
    try:
        return int(float(v)) if v is not None else None
    except ValueError:
        return None


class _TwoHosts:
    """Two network namespaces joined by a virtual Ethernet pair (addresses made here) standing for
    two hosts; removed on exit. Needs root and iproute2."""

    def __init__(self) -> None:
        k = os.getpid() % 200 + 20
        self.a, self.b = f"vbench_a{k}", f"vbench_b{k}"
        a, b = self.a, self.b
        self.cmds = [f"ip netns add {a}", f"ip netns add {b}", f"ip link add vba{k} type veth peer name vbb{k}",
                     f"ip link set vba{k} netns {a}", f"ip link set vbb{k} netns {b}",
                     f"ip -n {a} addr add 10.232.{k}.1/24 dev vba{k}", f"ip -n {b} addr add 10.232.{k}.2/24 dev vbb{k}",
                     f"ip -n {a} link set vba{k} up", f"ip -n {b} link set vbb{k} up",
                     f"ip -n {a} link set lo up", f"ip -n {b} link set lo up",
                     f"ip -n {a} route add 224.0.0.0/4 dev vba{k}", f"ip -n {b} route add 224.0.0.0/4 dev vbb{k}"]

    def __enter__(self) -> "_TwoHosts":
        for c in self.cmds:
            r = subprocess.run(c.split(), capture_output=True, text=True)
            if r.returncode != 0:
                self.__exit__()
                raise RuntimeError(f"cannot create network namespaces ({c}: {r.stderr.strip()})")
        return self

    def __exit__(self, *exc) -> None:
        for ns in (self.a, self.b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def exp_hosts_apart(work: Path, args) -> dict:
    """The front end (and the replay) on one host, the mapper on another (network namespaces,
    discovery over the subnet), against the same two on one host: keyframes the front end emitted
    vs received by the mapper (in its checkpoint or stored beside it), keyframe ATE."""
    from vings_core.eval.traj import evaluate_trajectory
    from vings_core.frontend import DISFlow, FrontendConfig
    from vings_core.frontend.checkpoint import load_frontend_checkpoint
    from vings_core.io import open_source
    from vings_core.mapping import Mapper
    from vings_core.types import Trajectory
    mcap = _sim(work, args.frames, "room", tuple(int(v) for v in args.size.split("x")))
    gt = open_source(str(mcap)).gt_camera_trajectory()
    out = {}
    for how in ("same_host", "two_hosts"):
        d = work / "hosts_apart" / how
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        ck = d / "map.ckpt"
        common = ["--use-sim-time", "--backpressure", "--no-loop", "--no-eraser", "--checkpoint", str(ck),
                  "--domain-id", str(args.domain), "-p", f"mapping.iters_per_keyframe={args.iters}"]
        env = dict(os.environ, PYTHONPATH=str(REPO),
                   ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET" if how == "two_hosts" else "LOCALHOST")
        cli = [sys.executable, "-m", "vings_ros.cli"]
        ctx = _TwoHosts() if how == "two_hosts" else None
        try:
            if ctx is not None:
                ctx.__enter__()
            na = ["ip", "netns", "exec", ctx.a] if ctx else []
            nb = ["ip", "netns", "exec", ctx.b] if ctx else []
            t0 = time.monotonic()
            mapper = subprocess.Popen(nb + cli + ["launch", "--nodes", "mapper_node"] + common, env=env,
                                      stdout=(d / "mapper.log").open("w"), stderr=subprocess.STDOUT,
                                      start_new_session=True)
            front = subprocess.Popen(na + cli + ["launch", "--nodes", "frontend_node"] + common, env=env,
                                     stdout=(d / "frontend.log").open("w"), stderr=subprocess.STDOUT,
                                     start_new_session=True)
            rep = subprocess.run(na + cli + ["replay", str(mcap), "--wait-for-graph", "--domain-id", str(args.domain)],
                                 env=env, capture_output=True, text=True, timeout=args.timeout)
            time.sleep(2.0)
            os.killpg(front.pid, signal.SIGINT)          # the front end flushes its window to the mapper
            front.wait(300)
            time.sleep(args.settle)
            os.killpg(mapper.pid, signal.SIGINT)         # on_stop store: what is queued waits beside the checkpoint
            mapper.wait(600)
            wall = time.monotonic() - t0
        finally:
            if ctx is not None:
                ctx.__exit__()
        fe = load_frontend_checkpoint(f"{ck}.frontend", FrontendConfig(), DISFlow()).frontend
        emitted = set(int(s) for s in fe.keyframe_trajectory().stamps_ns)
        kfs = Mapper.load_checkpoint(ck).keyframe_poses() if ck.exists() else {}
        stored = {int(f.stem.split("-")[2]) for f in (ck.parent / (ck.name + ".queue")).glob("kf-*.pt")}
        kept = {int(f.stem.split("-")[1]) for f in Path(f"{ck}.frontend.unacked").glob("kf-*.pt")}
        got = set(kfs) | stored
        rec = {"replay_rc": rep.returncode, "emitted": len(emitted), "received": len(emitted & got),
               "mapped": len(emitted & set(kfs)), "stored": len(emitted & stored - set(kfs)),
               "kept_by_frontend": len(emitted & kept - got), "lost": len(emitted - got - kept),
               "wall_s": round(wall, 1)}
        if len(kfs) >= 3:
            rec["kf_ate_sim3_m"] = evaluate_trajectory(Trajectory.from_poses(kfs), gt)["ate_sim3_m"]
        traj = fe.trajectory()
        rec["frontend_ate_sim3_m"] = evaluate_trajectory(traj, gt)["ate_sim3_m"] if len(traj) >= 3 else None
        out[how] = rec
        _log(how, json.dumps(rec))
    return out


_DISCOVERY_PUB = r"""
import sys, time
from vings_ros.ros_env import apply_ros_environment
apply_ros_environment(domain_id=int(sys.argv[1]))
import rclpy
from std_msgs.msg import Header
from msg_adapters import topics as T
rclpy.init()
node = rclpy.create_node("bench_discovery_pub")
pub = node.create_publisher(Header, "/bench/discovery", T.sensor_qos(10))
for i in range(int(sys.argv[2])):
    pub.publish(Header(frame_id=str(i)))
    time.sleep(0.05)
"""

_DISCOVERY_SUB = r"""
import json, subprocess, sys, time
from vings_ros.ros_env import apply_ros_environment
dom, trials, count = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
apply_ros_environment(domain_id=int(dom))
import rclpy
from std_msgs.msg import Header
from msg_adapters import topics as T
from vings_ros.node_common import spin_in_background
rclpy.init()
node = rclpy.create_node("bench_discovery_sub")
got = []
node.create_subscription(Header, "/bench/discovery", lambda m: got.append(int(m.frame_id)), T.sensor_qos(10))
stop_spinning = spin_in_background(node)
first = []
for _ in range(trials):
    got.clear()
    subprocess.run([sys.executable, "-c", sys.argv[4], dom, str(count)], check=True)
    first.append(got[0] if got else None)
    time.sleep(1.0)
stop_spinning()
print("FIRST " + json.dumps(first), flush=True)
"""


def _busy(seconds: float) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)   # not the harness's (a forked copy)
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        sum(i * i for i in range(10000))


def exp_discovery(work: Path, args) -> dict:
    """Seconds from a publisher's creation until a running subscriber hears it, per Fast DDS
    profile (the shipped one; the same without its discovery settings), with ``--load`` busy
    processes beside them."""
    import multiprocessing as mp
    import re

    import numpy as np

    from vings_ros.ros_env import cleanup_fastdds_shm, shm_profile_path, shm_snapshot
    shipped = shm_profile_path()
    plain = work / "fastdds_no_discovery_settings.xml"
    text = shipped.read_text()
    stripped = re.sub(r"<builtin>.*?</builtin>", "", text, flags=re.S)
    if stripped == text:
        raise RuntimeError(f"{shipped}: no <builtin> discovery block to compare against")
    plain.write_text(stripped)
    period, count = 0.05, 100
    out: dict = {"load_processes": args.load, "trials": args.trials, "publish_period_s": period}
    for name, prof in (("shipped", shipped), ("fastdds_default_discovery", plain)):
        hogs = [mp.Process(target=_busy, args=(3600.0,), daemon=True) for _ in range(args.load)]
        for h in hogs:
            h.start()
        snap = shm_snapshot()
        try:
            env = dict(os.environ, PYTHONPATH=str(REPO), FASTRTPS_DEFAULT_PROFILES_FILE=str(prof))
            p = subprocess.run([sys.executable, "-c", _DISCOVERY_SUB, str(args.domain), str(args.trials),
                                str(count), _DISCOVERY_PUB], env=env, cwd=REPO, capture_output=True,
                               text=True, timeout=60 + args.trials * 30)
        finally:
            for h in hogs:
                h.terminate()
            cleanup_fastdds_shm(snap)
        line = next((ln for ln in p.stdout.splitlines() if ln.startswith("FIRST ")), None)
        if line is None:
            raise RuntimeError(f"{name}: the discovery child failed (rc {p.returncode}): {p.stderr[-1500:]}")
        first = json.loads(line[len("FIRST "):])
        heard = np.array([f * period for f in first if f is not None])
        rec = {"first_heard_s": [round(float(v), 2) for v in heard], "never_heard": sum(f is None for f in first)}
        if len(heard):
            rec.update(median_s=round(float(np.median(heard)), 2), p90_s=round(float(np.quantile(heard, 0.9)), 2),
                       max_s=round(float(heard.max()), 2))
        out[name] = rec
        _log(name, json.dumps(rec))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", default="launcher_kill,ctrl_c")
    ap.add_argument("--frames", type=int, default=120, help="frames of the replayed recording (ctrl_c: a room; "
                    "node_kill: --scene)")
    ap.add_argument("--scene", choices=("street", "room"), default="street",
                    help="node_kill: a street loop with moving objects (10 Hz) or the room")
    ap.add_argument("--size", default="376x240", help="node_kill, hosts_apart: image size WxH of the recording")
    ap.add_argument("--settle", type=float, default=20.0,
                    help="hosts_apart: seconds the mapper gets after the front end stopped")
    ap.add_argument("--iters", type=int, default=150, help="mapping.iters_per_keyframe (a slow mapper)")
    ap.add_argument("--behind", type=int, default=8, help="ctrl_c: stop when the mapper is this far behind")
    ap.add_argument("--nodes", default="mapper_node,eraser_node,loop_closer_node,frontend_node")
    ap.add_argument("--trials", type=int, default=3, help="node_kill: trials per node; discovery: per profile")
    ap.add_argument("--fault-free", type=int, default=1,
                    help="node_kill: fault-free runs (the ATE is compared with their mean; their spread is reported)")
    ap.add_argument("--load", type=int, default=2, help="discovery: busy processes beside it")
    ap.add_argument("--timeout", type=float, default=1200.0)
    ap.add_argument("--domain", type=int, default=140 + os.getpid() % 60)
    args = ap.parse_args()
    work = Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "vings_bench_faults"
    work.mkdir(parents=True, exist_ok=True)
    fns = {"launcher_kill": exp_launcher_kill, "ctrl_c": exp_ctrl_c, "node_kill": exp_node_kill,
           "bad_input": exp_bad_input, "hosts_apart": exp_hosts_apart, "discovery": exp_discovery}
    names = [e.strip() for e in args.exp.split(",") if e.strip()]
    bad = [n for n in names if n not in fns]
    if bad:
        ap.error(f"unknown experiment(s) {bad}; known: {', '.join(fns)}")
    out: dict = {}
    return run_experiments([(n, lambda n=n: fns[n](work, args)) for n in names], out, log=_log)


if __name__ == "__main__":
    sys.exit(main())
