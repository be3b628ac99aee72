"""ROS node graph figures. Last line: one JSON object.

Experiments on one synthetic `room` sequence:

* ``parity``: the graph with back-pressure (`vings replay --wait-for-graph`, front end queue policy
  ``backpressure``) versus `vings run --sync` on the same MCAP with the same params file: Sim(3)
  ATE of each (graph: the final /vings/path), their relative difference, and the front end alone
  (no mapper) as a reference. Both exchange poses with the same classes and write-back policy
  (``exchange.mapper``; ``--writeback`` overrides it for both). Both fuse the simulated IMU (the
  graph's front end gets ``room.calib.yaml`` as ``frontend_node.calib_file``; ``--no-imu``: both
  visual-only); the graph's path is checked for a metric (Sim(3) scale) gravity-aligned frame.
* ``live``: replay at 20 Hz without back-pressure (policy ``keep_newest``): fraction of frames that
  get odometry, and publish -> odometry latency (receive wall clock minus publish wall clock) p50/p95.
* ``resume``: the mapper is killed (SIGKILL) mid-run, once its checkpoint holds keyframes and
  while more are coming, and started again: it resumes from its checkpoint, the final checkpoint
  holds every keyframe stamp of the pre-crash checkpoint with (nearly) the same poses (same world
  frame), and the restarted mapper exits 0 on SIGINT.
* ``loop`` (only when named in ``--only``; its own sequence ``room --route return``,
  ``--loop-frames`` 120 at ``--loop-size`` 192x128, visual-only on both sides, cheap mapping
  ``LOOP_MAPPING``): the loop closer in the graph. Parity: `vings run DIR --sync --no-imu` versus
  `vings launch --use-sim-time --backpressure --no-imu --checkpoint F` fed by `vings replay
  room.mcap --wait-for-graph --rate --loop-rate`: Sim(3) ATE of both (the graph's: its final
  /vings/path) and their relative difference (target 10 %), loops accepted on both sides
  (``loops.json`` of the run, /vings/loop/constraints and the node's ``loops.json``), and whether
  the first accepted loop joins the same keyframes (older, newer stamps). Then the same graph with
  the loop closer killed (SIGKILL) once half the frames have odometry and its checkpoint ``F.loop``
  exists, and started again ``--loop-outage-frames`` frames later with the command line the
  launcher gives it (the nodes are started one by one from the launcher's own command lines: the
  launcher itself stops the whole graph when a node dies): odometry and mapped keyframes during
  the outage (and the odometry in the same wall window of the parity run), the database size in
  ``F.loop`` at the kill and the one the restarted node logs on resuming, the keyframe packets it
  missed, the final ATE and loops, and how far the final path is from the parity run's before,
  inside and after the stretch of those missed keyframes. Before the graph stops, the loop closer must have caught up
  (its checkpoint, every 2 s, holds the newest keyframe packet it could receive): the front end
  applies a correction that comes after its last frame when it stops.

    python benchmarks/ros_graph.py [--frames 120] [--width 376 --height 240] [--work DIR]
                                   [--only parity,live,resume,loop] [--writeback none|all|consistent]
                                   [--no-imu] [-p section.key=value ...]
                                   [--loop-frames 120] [--loop-size 192x128] [--loop-rate 0.15]
                                   [--loop-outage-frames 15]
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

MAPPING = ["mapping.iters_per_keyframe=20", "mapping.refine_iters=3"]
_PROCS: list = []      # every node process started, stopped at the end whatever happened

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import run_experiments  # noqa: E402


class Listener:
    """In-process subscriber to odometry, the final path and renders (its own executor thread)."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from nav_msgs.msg import Odometry, Path as PathMsg
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import Image

        from msg_adapters import topics as T
        from msg_adapters.pose import path_to_trajectory
        from msg_adapters.stamps import header_ns
        from vings_ros.ros_env import apply_ros_environment

        apply_ros_environment(domain)
        rclpy.init()
        self.rclpy = rclpy
        self.node = rclpy.create_node("vings_bench_listener")
        self.odom: dict[int, int] = {}
        self.path = None
        self.renders = 0
        self.node.create_subscription(
            Odometry, T.ODOMETRY_TOPIC,
            lambda m: self.odom.setdefault(header_ns(m.header), time.time_ns()), T.sensor_qos(1000))
        self.node.create_subscription(
            PathMsg, T.PATH_TOPIC, lambda m: setattr(self, "path", path_to_trajectory(m)), T.latched_qos(1))
        from diagnostic_msgs.msg import DiagnosticArray
        from msg_adapters.diagnostics import parse_diagnostic_array
        self.diag: dict = {}

        def _diag(m):
            for name, st in parse_diagnostic_array(m)["status"].items():
                self.diag[name] = st["values"]
        self.node.create_subscription(DiagnosticArray, T.DIAGNOSTICS_TOPIC, _diag, T.sensor_qos(10))
        self.node.create_subscription(Image, T.RENDER_COLOR_TOPIC,
                                      lambda m: setattr(self, "renders", self.renders + 1), T.sensor_qos(10))
        self._subscribe_more(T)
        self.ex = SingleThreadedExecutor()
        self.ex.add_node(self.node)
        self._stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        self.T = T

    def _subscribe_more(self, T) -> None:
        """More subscriptions of a subclass (before the executor starts)."""

    def _spin(self) -> None:
        while not self._stop:
            self.ex.spin_once(timeout_sec=0.05)

    def wait_for_graph(self, timeout: float = 120) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.node.count_publishers(self.T.ODOMETRY_TOPIC) and \
                    self.node.count_publishers(self.T.RENDER_COLOR_TOPIC):
                time.sleep(1.0)
                return
            time.sleep(0.1)
        raise RuntimeError("graph did not come up")

    def reset(self) -> None:
        self.odom, self.path, self.renders, self.diag = {}, None, 0, {}

    def close(self) -> None:
        self._stop = True
        self.thread.join()
        self.ex.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown()


def node_proc(module: str, domain: int, params: list[str], log) -> subprocess.Popen:
    from vings_ros.params import default_params_file
    from vings_ros.ros_env import ros_environment
    cmd = [sys.executable, "-m", module, "--ros-args", "--params-file", str(default_params_file())]
    for p in params:
        cmd += ["-p", p.replace("=", ":=", 1)]
    p = subprocess.Popen(cmd, env=ros_environment(domain), stdout=log, stderr=subprocess.STDOUT,
                         start_new_session=True)
    _PROCS.append(p)
    return p


def wait_checkpoint(ck: Path, timeout: float) -> set:
    """Keyframe stamps of the checkpoint once it exists and holds at least one keyframe."""
    from vings_core.errors import InputError
    from vings_core.mapping import Mapper
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if ck.exists():
            try:
                kfs = Mapper.load_checkpoint(ck).keyframe_poses()
            except InputError:
                kfs = {}
            if kfs:
                return set(kfs)
        time.sleep(0.5)
    return set()


def stop(p: subprocess.Popen, timeout: float = 300) -> int:
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    return p.returncode


def replay(mcap: Path, domain: int, extra: list[str], log) -> subprocess.CompletedProcess:
    from vings_ros.ros_env import ros_environment
    return subprocess.run([sys.executable, "-m", "vings_ros.cli", "replay", str(mcap), "--domain-id",
                           str(domain), "--startup-timeout", "120", "--ack-timeout", "300"] + extra,
                          env=ros_environment(domain), stdout=log, stderr=subprocess.STDOUT, check=True)


def ate(traj, gt) -> float:
    from vings_core.eval.traj import evaluate_trajectory
    return float(evaluate_trajectory(traj, gt)["ate_sim3_m"])


def gravity_and_scale(traj, gt) -> dict:
    """Whether ``traj`` is in a metric gravity-aligned frame: the Sim(3) scale to the truth and the
    median angle between the estimated and the true gravity in the camera frame (deg)."""
    from vings_core.eval.traj import associate, evaluate_trajectory
    e, g = associate(traj, gt, max_dt_ns=5_000_000)
    z = np.array([0.0, 0.0, -1.0])
    ang = [np.degrees(np.arccos(np.clip((Pe[:3, :3].T @ z) @ (Pg[:3, :3].T @ z), -1, 1)))
           for Pe, Pg in zip(e.poses, g.poses)]
    return {"sim3_scale_graph": float(evaluate_trajectory(traj, gt)["sim3_scale"]),
            "gravity_err_deg_graph": float(np.median(ang))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--width", type=int, default=376)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=None)
    ap.add_argument("--only", default="parity,live,resume",
                    help="experiments to run (comma list of parity, live, resume, loop)")
    ap.add_argument("--writeback", default=None, choices=("none", "all", "consistent"),
                    help="exchange.mapper (the write-back policy for the mapper's refinements) for both the offline run and the graph")
    ap.add_argument("--no-imu", action="store_true",
                    help="visual-only on both sides (vings run --no-imu; the graph without "
                         "frontend_node.calib_file); by default both fuse the simulated IMU")
    ap.add_argument("-p", "--param", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="extra ROS parameter for both graph nodes (e.g. mapper_node.threads=1)")
    ap.add_argument("--loop-frames", type=int, default=120, help="loop: frames of the room --route return sequence")
    ap.add_argument("--loop-size", default="192x128", metavar="WxH", help="loop: its resolution")
    ap.add_argument("--loop-rate", type=float, default=0.15,
                    help="loop: `vings replay --rate` of both graph runs (with --wait-for-graph; "
                         "default 0.15: a restarted loop closer takes seconds to come up, and it must be "
                         "up before the revisit at the end)")
    ap.add_argument("--loop-outage-frames", type=int, default=15,
                    help="loop: odometry frames the front end publishes between the loop closer's "
                         "kill and its restart")
    args = ap.parse_args()
    only = set(args.only.split(","))
    unknown = only - {"parity", "live", "resume", "loop"}
    if unknown:
        ap.error(f"unknown experiment(s) {sorted(unknown)}")
    needs_room = bool(only & {"parity", "live", "resume"})   # `loop` has its own sequence

    from vings_core.io import open_source
    from vings_core.sim import generate
    from vings_core.trajectory_io import read_tum

    work = Path(args.work or tempfile.mkdtemp(prefix="vings_bench_ros_"))
    work.mkdir(parents=True, exist_ok=True)
    log = open(work / "log.txt", "a")
    seq = work / "room"
    mcap = seq / "room.mcap"
    gt, stamps = None, []
    result: dict = {"cores": os.cpu_count()}
    if needs_room:
        if not (seq / "room.mcap").exists():
            generate("room", seq, frames=args.frames, width=args.width, height=args.height, seed=args.seed)
        src = open_source(seq)
        gt = src.gt_camera_trajectory()
        stamps = [int(s) for s in src.frame_stamps()]
        result = {"frames": len(stamps), "resolution": [args.width, args.height], "cores": os.cpu_count()}

    # ---- offline reference
    off = work / "offline"
    mp = work / "bench_params.yaml"
    text = "/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 20\n      refine_iters: 3\n"
    if args.writeback:
        text += f"    exchange:\n      mapper: {args.writeback}\n"
    mp.write_text(text)
    graph_params = ([] if not args.writeback else [f"exchange.mapper={args.writeback}"]) + list(args.param)
    if not args.no_imu:      # the calibration vings run reads beside the MCAP gives the node T_bc
        graph_params.append(f"frontend_node.calib_file={seq / 'room.calib.yaml'}")
    result["imu_fused"] = not args.no_imu
    result["uptime_start"] = os.getloadavg()
    from vings_core.frontend import Frontend, FrontendConfig
    from vings_core.config import load_section
    ate_off = None
    # 201..232: the tests use 1..200; another run on the same domain with the same synthetic stamps
    # would be counted as ours
    domain = 201 + os.getpid() % 32
    from vings_ros.ros_env import cleanup_fastdds_shm, shm_snapshot
    snap = shm_snapshot()
    lis = None

    def listener():
        nonlocal lis
        if lis is None:
            lis = LoopListener(domain) if "loop" in only else Listener(domain)
        return lis

    def frontend_alone() -> dict:
        from vings_core.types import POSED_STATES, Frame
        from vings_core.vio.config import ViConfig
        from vings_core.vio.fusion import ViFusion
        bag = open_source(mcap)
        vio = None if args.no_imu else ViFusion.for_source(ViConfig(), bag.calibration, True)[0]
        fe_alone = Frontend(load_section(FrontendConfig, "frontend", str(mp)), bag.calibration.camera, vio=vio)
        items = list(bag.stream()) if vio is not None else list(bag.frames())
        t1 = time.perf_counter()
        for it in items:
            if isinstance(it, Frame):
                fe_alone.process(it)
            else:
                fe_alone.add_imu(it)
        fe_alone.finish()
        fe_wall = time.perf_counter() - t1
        # in-process, no ROS, same load: what the live graph's front end could reach at best
        return {"ate_sim3_m": ate(fe_alone.trajectory(states=POSED_STATES), gt),
                "fps": len(stamps) / fe_wall, "loadavg": os.getloadavg(),
                "vi_state": fe_alone.status()["vi_state"]}

    def offline() -> dict:
        nonlocal ate_off
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "vings_ros.cli", "run", str(mcap), "--out", str(off), "--sync",
                        "--params", str(mp), "--no-progress"] + (["--no-imu"] if args.no_imu else []),
                       stdout=log, stderr=subprocess.STDOUT, check=True)
        ate_off = ate(read_tum(off / "trajectory.tum"), gt)
        m = json.loads((off / "metrics.json").read_text())
        return {"ate_sim3_m": ate_off, "wall_s": time.perf_counter() - t0, "vi_state": m.get("vi_state"),
                "sim3_scale": m.get("sim3_scale"), "frames_tracked": m.get("frames_tracked")}

    steps = [("frontend_alone", frontend_alone)] if needs_room else []
    if "parity" in only:
        steps += [("offline_sync", offline),
                  ("parity", lambda: run_parity(listener(), domain, mcap, gt, graph_params, ate_off, work, log))]
    if "live" in only:
        steps.append(("live_20hz", lambda: run_live(listener(), domain, mcap, graph_params, work, log)))
    if "resume" in only:
        steps.append(("resume", lambda: run_resume(listener(), domain, mcap, stamps, graph_params, work, log)))
    if "loop" in only:
        steps.append(("loop", lambda: run_loop(listener(), domain, args, work, log)))

    def finish(r: dict) -> None:
        for p in _PROCS:     # a failed experiment leaves its nodes running: stop them
            stop(p, 30)
        if lis is not None:
            lis.close()
        log.close()
        time.sleep(1.0)
        # the SIGKILLed mapper leaves its Fast DDS segment and ports behind
        r["shm_files_removed"] = len(cleanup_fastdds_shm(snap))
        r["uptime_end"] = os.getloadavg()
    return run_experiments(steps, result, finish=finish)


def run_parity(lis, domain, mcap, gt, graph_params, ate_off, work, log) -> dict:
    """Back-pressure graph on the same MCAP as the offline --sync run."""
    lis.reset()
    ck = work / "parity_ckpt.npz"
    fe = node_proc("vings_ros.frontend_node", domain, ["frontend_node.queue_policy=backpressure"] + graph_params, log)
    ma = node_proc("vings_ros.mapper_node", domain, MAPPING + graph_params +
                   [f"mapper_node.checkpoint_path={ck}", "mapper_node.resume=false"], log)
    lis.wait_for_graph()
    t0 = time.perf_counter()
    replay(mcap, domain, ["--rate", "0", "--wait-for-graph"], log)
    wall = time.perf_counter() - t0
    time.sleep(1.5)  # last diagnostics
    diag = dict(lis.diag.get("vings/frontend", {}))
    rc_fe = stop(fe)
    time.sleep(2.0)
    rc_ma = stop(ma)
    graph_traj = lis.path
    ate_ros = ate(graph_traj, gt) if graph_traj is not None and len(graph_traj) >= 3 else None
    frame = gravity_and_scale(graph_traj, gt) if ate_ros is not None else {}
    return {"ate_sim3_m_graph": ate_ros, "ate_sim3_m_offline": ate_off, **frame,
            "vi_state_graph": diag.get("vi_state"),
            "rel_diff": (abs(ate_ros - ate_off) / ate_off) if ate_ros is not None and ate_off else None,
            "odometry_frames": len(lis.odom), "replay_wall_s": wall, "renders": lis.renders,
            "graph_corrections": {k: diag.get(k) for k in ("writeback_policy", "corrections_received",
                                                          "corrections_applied", "corrections_rejected")},
            "exit_codes": [rc_fe, rc_ma]}


def run_live(lis, domain, mcap, graph_params, work, log) -> dict:
    """20 Hz replay without back-pressure, keep-newest queue."""
    lis.reset()
    pub_log = work / "publish_log.csv"
    fe = node_proc("vings_ros.frontend_node", domain, ["frontend_node.queue_policy=keep_newest"] + graph_params, log)
    ma = node_proc("vings_ros.mapper_node", domain, MAPPING + graph_params, log)
    lis.wait_for_graph()
    load = os.getloadavg()
    lis.reset()
    t_start = time.time_ns()
    replay(mcap, domain, ["--rate", "1", "--publish-log", str(pub_log)], log)
    time.sleep(3.0)
    diag = dict(lis.diag.get("vings/frontend", {}))
    stop(fe)
    stop(ma)
    pubs = {}
    for line in pub_log.read_text().splitlines()[1:]:
        st, w = line.split(",")[:2]
        pubs[int(st)] = int(w)
    # odometry received before its image was published cannot be ours (another graph on the domain)
    foreign = sum(1 for st in pubs if st in lis.odom and lis.odom[st] < max(pubs[st], t_start))
    lat = np.array([(lis.odom[st] - pubs[st]) / 1e6 for st in pubs
                    if st in lis.odom and lis.odom[st] >= max(pubs[st], t_start)])
    return {"frames_published": len(pubs), "frames_with_odometry": int(len(lat)),
            "odometry_fraction": len(lat) / max(len(pubs), 1),
            "latency_ms_p50": float(np.percentile(lat, 50)) if len(lat) else None,
            "latency_ms_p95": float(np.percentile(lat, 95)) if len(lat) else None,
            "frontend_frames_received": diag.get("frames_received"),
            "frontend_frames_dropped": diag.get("frames_dropped"),
            "frontend_frames_processed": diag.get("frames"), "frontend_keyframes": diag.get("keyframes"),
            "loadavg_at_start": load,
            "odometry_not_ours": foreign}


def run_resume(lis, domain, mcap, stamps, graph_params, work, log) -> dict:
    """Kill -9 the mapper once its checkpoint holds keyframes (more are queued), restart it,
    replay the rest; the final checkpoint must hold the pre-crash keyframes in the same frame."""
    from vings_core.mapping import Mapper
    lis.reset()
    ck = work / "resume_ckpt.npz"
    if ck.exists():
        ck.unlink()
    mparams = MAPPING + graph_params + [f"mapper_node.checkpoint_path={ck}", "mapper_node.checkpoint_period_s=5.0",
                                        "mapper_node.checkpoint_every_keyframes=5", "mapper_node.resume=true"]
    fe = node_proc("vings_ros.frontend_node", domain, ["frontend_node.queue_policy=backpressure"] + graph_params, log)
    ma = node_proc("vings_ros.mapper_node", domain, mparams, log)
    lis.wait_for_graph()
    half = stamps[len(stamps) // 2] - stamps[0]
    replay(mcap, domain, ["--rate", "0", "--wait-for-graph", "--duration", f"{half / 1e9:.3f}"], log)
    t_wait = time.monotonic()
    before_stamps = wait_checkpoint(ck, 600)
    waited = time.monotonic() - t_wait
    os.killpg(ma.pid, signal.SIGKILL)   # crash, mid-run
    ma.wait()
    before = Mapper.load_checkpoint(ck).keyframe_poses() if ck.exists() else {}
    lis.diag.pop("vings/mapper", None)
    ma = node_proc("vings_ros.mapper_node", domain, mparams, log)
    # the killed mapper's endpoints linger in discovery: wait for the new one's diagnostics
    end = time.monotonic() + 120
    while time.monotonic() < end and "vings/mapper" not in lis.diag:
        time.sleep(0.2)
    time.sleep(1.0)
    replay(mcap, domain, ["--rate", "0", "--wait-for-graph", "--start", f"{half / 1e9 + 0.01:.3f}"], log)
    rc_fe = stop(fe)
    time.sleep(2.0)
    rc = stop(ma)
    after = Mapper.load_checkpoint(ck).keyframe_poses() if ck.exists() else {}
    kept = [st for st in before if st in after]
    shift = max((float(np.linalg.norm(after[st][:3, 3] - before[st][:3, 3])) for st in kept), default=None)
    return {"keyframes_before_crash": len(before), "keyframes_final": len(after),
            "new_keyframes_after_restart": len(set(after) - set(before)),
            "all_pre_crash_keyframes_kept": bool(before) and set(before) <= set(after),
            "pre_crash_keyframe_max_shift_m": shift, "s_waited_for_first_checkpoint": waited,
            "mapper_exit_code": rc, "frontend_exit_code": rc_fe, "renders_after_restart": lis.renders}


# ------------------------------------------------------------------------------------------ loop

#: mapping of the `loop` experiment (offline and graph alike): cheap enough for a shared 2-core
#: host, and the map still passes the loop closer's render check on `room --route return`
LOOP_MAPPING = {"iters_per_keyframe": 10, "refine_iters": 2, "points_per_keyframe": 4000}
#: graph-only settings of the `loop` experiment (both graph runs): the nodes' own +10 niceness
#: starves them on a host shared with other jobs (back-pressure paces the front end anyway); the
#: loop closer checkpoints every 2 s (there is one to resume from at the kill); the mapper stops
#: 10 s after SIGINT (its queue goes to its spill folder: the figures here are the front end's
#: path and the loop closer's); /diagnostics every 0.2 s of sim time (the replay runs slower than
#: real time)
LOOP_NODE_PARAMS = ["mapper_node.nice=0", "loop_closer_node.nice=0", "mapper_node.shutdown_timeout_s=10.0",
                    "loop_closer_node.checkpoint_period_s=2.0", "ros.diagnostics_period_s=0.2"]


class LoopListener(Listener):
    """The Listener plus the loop constraints and the keyframe packets (their pose part)."""

    def _subscribe_more(self, T) -> None:
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path as PathMsg

        from msg_adapters.keyframe import PART_TOPICS
        from msg_adapters.loop import LOOP_CONSTRAINTS_TOPIC, path_to_loop_constraint
        from msg_adapters.stamps import header_ns
        self.LOOP_CONSTRAINTS_TOPIC = LOOP_CONSTRAINTS_TOPIC
        self.constraints: list = []         # (older, newer, receive wall ns)
        self.kf_packets: dict[int, int] = {}

        def _constraint(m):
            c = path_to_loop_constraint(m)
            if (c.older, c.newer) not in [(o, n) for o, n, _ in self.constraints]:
                self.constraints.append((c.older, c.newer, time.time_ns()))
        self.node.create_subscription(PathMsg, LOOP_CONSTRAINTS_TOPIC, _constraint, T.latched_qos(100))
        self.node.create_subscription(PoseStamped, PART_TOPICS["pose"],
                                      lambda m: self.kf_packets.setdefault(header_ns(m.header), time.time_ns()),
                                      T.sensor_qos(T.OUTPUT_DEPTH * 4))

    def reset(self) -> None:
        super().reset()
        self.constraints, self.kf_packets = [], {}

    def wait_for_loop_closer(self, timeout: float = 120) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.node.count_publishers(self.LOOP_CONSTRAINTS_TOPIC):
                return
            time.sleep(0.1)
        raise RuntimeError("the loop closer did not come up")


def _loop_db_stamps(f: Path) -> Optional[set]:
    """Keyframe stamps in the loop closer's checkpoint ``f`` (None: no file)."""
    if not f.exists():
        return None
    with np.load(f, allow_pickle=False) as z:
        return {int(x) for x in z["db.stamps"]}


def _loop_state(f: Path) -> Optional[dict]:
    """The checkpoint ``f`` restored into a LoopCloser: its database size and loops."""
    from vings_core.loop import LoopCloser, LoopConfig
    from vings_ros.loop_closer_node import load_loop_state
    if not f.exists():
        return None
    lc = LoopCloser(LoopConfig())
    lc.load_state_dict(load_loop_state(f, LoopConfig()))
    return {"keyframes": len(lc.db), "loops": [(int(l.older), int(l.newer)) for l in lc.loops]}


def _loops_json(d: Path) -> dict:
    """Accepted loops of a loops.json (``vings run`` / ``loop_closer_node.output_dir``)."""
    f = d / "loops.json"
    if not f.exists():
        return {"loops_accepted": None, "first_loop": None}
    j = json.loads(f.read_text())
    acc = [(int(c["older"]), int(c["newer"])) for c in j.get("corrections", [])]
    summ = j.get("summary", {})
    return {"loops_accepted": summ.get("loops_accepted", len(acc)), "first_loop": acc[0] if acc else None,
            "candidates_checked": summ.get("loop_candidates_checked"),
            "render_rejects": sum(1 for c in j.get("candidates", []) if "render" in str(c.get("reason", "")))}


def _displacement_split(traj, ref, lo: int, hi: int) -> dict:
    """Mean distance (m) between the positions of ``traj`` and ``ref`` (same world frame, same
    stamps) before, inside and after the stamp interval [lo, hi]."""
    common, ia, ib = np.intersect1d(traj.stamps_ns, ref.stamps_ns, return_indices=True)
    d = np.linalg.norm(traj.positions[ia] - ref.positions[ib], axis=1)
    parts = {"before": common < lo, "inside": (common >= lo) & (common <= hi), "after": common > hi}
    return {f"{k}_mean_m": float(d[m].mean()) if m.any() else None for k, m in parts.items()} | \
        {"frames_inside": int(parts["inside"].sum())}


def _num(v):
    """A /diagnostics value (a string) as a number, if it is one."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return v
    return int(f) if f.is_integer() else f


def _grep(log: Path, pattern: str, node: Optional[str] = None) -> list:
    import re
    if not log.exists():
        return []
    lines = log.read_text(errors="replace").splitlines()
    return [re.search(pattern, ln) for ln in lines
            if (node is None or node in ln) and re.search(pattern, ln)]


def run_loop(lis, domain, args, work, log) -> dict:
    """Loop closer in the graph: parity with `vings run --sync`, then kill -9 of the loop closer
    mid-run and its restart from its checkpoint."""
    from vings_core.io import open_source
    from vings_core.sim import generate
    from vings_core.trajectory_io import read_tum
    import vings_ros.loop_closer_node  # noqa: F401 - imported now, not between the kill and the restart
    w, h = (int(x) for x in args.loop_size.lower().split("x"))
    seq = work / f"room_return_{args.loop_frames}_{w}x{h}"
    if not (seq / "room.mcap").exists():
        generate("room", seq, frames=args.loop_frames, width=w, height=h, seed=args.seed, route="return")
    mcap = seq / "room.mcap"
    src = open_source(seq)
    gt = src.gt_camera_trajectory()
    n_frames = len(src.frame_stamps())
    out: dict = {"sequence": f"room --route return, {n_frames} frames, {w}x{h}, seed {args.seed}",
                 "imu": False, "mapping": LOOP_MAPPING, "graph_params": LOOP_NODE_PARAMS + list(args.param),
                 "replay_rate": args.loop_rate}
    t_all = time.perf_counter()

    # ---- offline: vings run DIR --sync --no-imu
    pf = work / "loop_params.yaml"
    pf.write_text("/**:\n  ros__parameters:\n    mapping:\n" +
                  "".join(f"      {k}: {v}\n" for k, v in LOOP_MAPPING.items()) +
                  "    run:\n      eval_keyframes: 10\n      eval_novel: 10\n")
    off = work / "loop_offline"
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "vings_ros.cli", "run", str(seq), "--out", str(off), "--sync",
                    "--no-imu", "--params", str(pf), "--no-progress"], stdout=log, stderr=subprocess.STDOUT,
                   check=True)
    ate_off = ate(read_tum(off / "trajectory.tum"), gt)
    lo = _loops_json(off)
    out["offline"] = {"ate_sim3_m": ate_off, "wall_s": time.perf_counter() - t0, **lo}
    print(f"loop: offline done ({out['offline']})", file=sys.stderr, flush=True)

    # ---- the graph, twice: as is, and with the loop closer killed mid-run
    parity = _loop_graph(lis, domain, mcap, n_frames, gt, args, work, "parity", kill=False)
    print("loop: parity graph done", file=sys.stderr, flush=True)
    killed = _loop_graph(lis, domain, mcap, n_frames, gt, args, work, "kill", kill=True, parity=parity)
    for r in (parity, killed):
        a = r.get("ate_sim3_m")
        r["ate_rel_diff_vs_offline"] = abs(a - ate_off) / ate_off if a is not None and ate_off else None
        r["first_loop_same_keyframes_as_offline"] = (r["first_loop"] is not None and lo["first_loop"] is not None
                                                     and tuple(r["first_loop"]) == tuple(lo["first_loop"]))
    for r in (parity, killed):
        for k in ("_window", "_traj", "mapper_timeline"):
            r.pop(k, None)
    out["graph"] = parity
    out["graph_within_10pct"] = parity["ate_rel_diff_vs_offline"] is not None and parity["ate_rel_diff_vs_offline"] <= 0.10
    out["kill_restart"] = killed
    out["wall_s"] = time.perf_counter() - t_all
    missing = [k for k, v in (("offline ATE", ate_off), ("graph ATE", parity.get("ate_sim3_m")),
                              ("kill-run ATE", killed.get("ate_sim3_m"))) if v is None]
    if missing:
        out["incomplete"] = f"no {', '.join(missing)}"
    return out


def _launch_options(domain: int, ck: Path, params: list):
    """The LaunchOptions `vings launch --use-sim-time --backpressure --no-imu --checkpoint ck
    --domain-id domain -p ...` builds (vings_ros/commands/launch.py), checked by a Launcher."""
    from vings_ros.launch import Launcher, LaunchOptions
    from vings_ros.params import default_params_file
    extra = dict(p.split("=", 1) for p in params)
    extra["frontend_node.queue_policy"] = "backpressure"
    extra["vio.enabled"] = "false"
    extra.setdefault("loop_closer_node.checkpoint_path", str(ck.resolve()) + ".loop")
    opt = LaunchOptions(params_file=str(default_params_file()), use_sim_time=True, domain_id=domain,
                        checkpoint=str(ck), extra_params=extra)
    return opt, Launcher(opt, out=open(os.devnull, "w"))


def _loop_graph(lis, domain, mcap, n_frames, gt, args, work, tag, kill, parity=None) -> dict:
    """One graph run with the loop closer: `vings launch` (kill=False) or the launcher's own node
    command lines started one by one (kill=True: the launcher stops the whole graph when a node
    dies, so the loop closer's kill -9 and restart are done without its watch)."""
    import shutil
    from vings_ros.launch import node_command
    from vings_ros.ros_env import ros_environment
    lis.reset()
    ck = work / f"loop_{tag}_ckpt.npz"
    ck_loop = Path(str(ck.resolve()) + ".loop")
    outdir = work / f"loop_{tag}_out"
    for f in (ck, ck_loop):
        f.unlink(missing_ok=True)
    for d in (outdir, Path(str(ck) + ".queue")):
        shutil.rmtree(d, ignore_errors=True)
    outdir.mkdir(parents=True)
    params = [f"mapping.{k}={v}" for k, v in LOOP_MAPPING.items()] + LOOP_NODE_PARAMS + list(args.param) + \
        [f"loop_closer_node.output_dir={outdir}"]
    glog = work / f"loop_{tag}_graph.log"
    lc_log = work / f"loop_{tag}_loop_closer.log"
    lc2_log = work / f"loop_{tag}_loop_closer_restarted.log"
    r: dict = {}
    procs: dict = {}
    launcher_proc = launcher = opt = None
    if not kill:
        cmd = [sys.executable, "-m", "vings_ros.cli", "launch", "--use-sim-time", "--backpressure", "--no-imu",
               "--domain-id", str(domain), "--checkpoint", str(ck)]
        for p in params:
            cmd += ["-p", p]
        r["command"] = " ".join(cmd[1:])
        with open(glog, "w") as f:
            launcher_proc = subprocess.Popen(cmd, env=ros_environment(domain), stdout=f, stderr=subprocess.STDOUT,
                                             start_new_session=True)
        _PROCS.append(launcher_proc)
    else:
        from vings_ros.ros_env import shm_snapshot
        opt, launcher = _launch_options(domain, ck, params)
        launcher.snapshot = shm_snapshot()
        for name in reversed(launcher.nodes):     # as Launcher.start: loop closer, mapper, front end
            f = open(lc_log if name == "loop_closer_node" else glog, "a")
            procs[name] = subprocess.Popen(node_command(name, opt), env=launcher.env, stdout=f,
                                           stderr=subprocess.STDOUT, start_new_session=True)
            _PROCS.append(procs[name])
        launcher.procs = procs
        r["loop_closer_command"] = " ".join(node_command("loop_closer_node", opt)[1:])
    lis.wait_for_graph()
    lis.wait_for_loop_closer()
    time.sleep(1.0)
    lis.reset()
    rep_cmd = [sys.executable, "-m", "vings_ros.cli", "replay", str(mcap), "--domain-id", str(domain),
               "--startup-timeout", "120", "--ack-timeout", "300", "--wait-for-graph", "--rate", str(args.loop_rate)]
    t_rep = time.time_ns()
    with open(work / f"loop_{tag}_replay.log", "w") as f:
        rep = subprocess.Popen(rep_cmd, env=ros_environment(domain), stdout=f, stderr=subprocess.STDOUT,
                               start_new_session=True)
    _PROCS.append(rep)

    mapper_tl: list = []      # (wall s since the replay started, keyframes mapped, queue length)

    def sample_mapper() -> None:
        ma = lis.diag.get("vings/mapper", {})
        v = (_num(ma.get("keyframes_mapped")), _num(ma.get("queue_length")))
        if None not in v and (not mapper_tl or mapper_tl[-1][1:] != v):
            mapper_tl.append(((time.time_ns() - t_rep) / 1e9, *v))

    def snapshot() -> dict:
        fe, ma = lis.diag.get("vings/frontend", {}), lis.diag.get("vings/mapper", {})
        return {"wall_s": (time.time_ns() - t_rep) / 1e9, "odometry": len(lis.odom),
                "keyframe_packets": len(lis.kf_packets), "frontend_frames": _num(fe.get("frames")),
                "mapper_keyframes_mapped": _num(ma.get("keyframes_mapped")),
                "mapper_queue": _num(ma.get("queue_length"))}

    at_kill = at_restart = at_ready = ck_at_kill = resumed = None
    t_kill = t_restart = t_ready = None
    lc2 = None
    while rep.poll() is None or (kill and t_restart is None):
        time.sleep(0.1)
        sample_mapper()
        if not kill:
            continue
        if t_kill is None and ((len(lis.odom) >= n_frames // 2 and ck_loop.exists()) or rep.poll() is not None):
            lc = procs["loop_closer_node"]
            os.killpg(lc.pid, signal.SIGKILL)        # kill -9, mid-run
            t_kill = time.time_ns()
            at_kill = snapshot()
            lc.wait()
            r["killed_exit_code"] = lc.returncode
            ck_at_kill = _loop_state(ck_loop)
        elif t_kill is not None and t_restart is None and (
                len(lis.odom) >= at_kill["odometry"] + args.loop_outage_frames or rep.poll() is not None
                or time.time_ns() - t_kill > 20e9):
            at_restart = snapshot()
            t_restart = time.time_ns()
            r["replay_running_at_restart"] = rep.poll() is None
            r["frontend_mapper_alive_at_restart"] = [procs["frontend_node"].poll() is None,
                                                     procs["mapper_node"].poll() is None]
            with open(lc2_log, "w") as f:      # the same command line the launcher gave it
                lc2 = subprocess.Popen(node_command("loop_closer_node", opt), env=launcher.env, stdout=f,
                                       stderr=subprocess.STDOUT, start_new_session=True)
            _PROCS.append(lc2)
            procs["loop_closer_node"] = lc2
        if lc2 is not None and t_ready is None and _grep(lc2_log, r"loop closer ready: (\d+) keyframes"):
            t_ready = time.time_ns()
            at_ready = snapshot()
            r["replay_running_when_restarted_ready"] = rep.poll() is None
    # the replay may end before the restarted node is up: wait for it (its start is in its log)
    end = time.monotonic() + 120
    while lc2 is not None and t_ready is None and time.monotonic() < end and lc2.poll() is None:
        if _grep(lc2_log, r"loop closer ready: (\d+) keyframes"):
            t_ready = time.time_ns()
            at_ready = snapshot()
            r["replay_running_when_restarted_ready"] = False
        time.sleep(0.2)
    t_end = time.time_ns()
    r["replay_exit_code"] = rep.returncode
    r["replay_wall_s"] = (t_end - t_rep) / 1e9
    at_end = snapshot()
    # the loop closer has caught up once its checkpoint (every 2 s while it changes) holds the
    # newest keyframe packet it could have received (FIFO)
    time.sleep(1.0)
    since = t_ready if kill else t_rep
    last = max((st for st, t in lis.kf_packets.items() if since is not None and t >= since), default=None)
    t_wait = time.monotonic()
    caught_up = False
    while last is not None and time.monotonic() - t_wait < 180:
        db = _loop_db_stamps(ck_loop)
        if db is not None and last in db:
            caught_up = True
            break
        time.sleep(1.0)
    r["loop_closer_caught_up"] = caught_up if last is not None else None   # None: nothing to wait for
    r["s_waited_for_loop_closer"] = time.monotonic() - t_wait
    time.sleep(1.0)    # a correction it just sent reaches the front end's inbox
    # stop: front end (applies the pending correction, publishes its final path), mapper, loop closer
    t_stop = time.perf_counter()
    if kill:
        launcher.stop()
        r["exit_codes"] = {n: p.returncode for n, p in procs.items()}
    else:
        r["exit_codes"] = {"vings launch": stop(launcher_proc, 400)}
    r["stop_s"] = time.perf_counter() - t_stop
    time.sleep(1.0)
    traj = lis.path
    r["ate_sim3_m"] = ate(traj, gt) if traj is not None and len(traj) >= 3 else None
    if traj is not None and len(traj):
        from vings_core.trajectory_io import write_tum
        write_tum(work / f"loop_{tag}_path.tum", traj)
        r["_traj"] = traj
    r["odometry_frames"] = len(lis.odom)
    r["keyframe_packets"] = len(lis.kf_packets)
    r["constraints_received"] = len(lis.constraints)
    r["first_loop"] = tuple(lis.constraints[0][:2]) if lis.constraints else None
    lj = _loops_json(outdir)
    r["loops_json"] = lj
    final = _loop_state(ck_loop)
    r["final_loop_db_keyframes"] = final["keyframes"] if final else None
    r["final_loops"] = final["loops"] if final else None
    r["at_replay_end"] = at_end
    r["mapper_timeline"] = mapper_tl
    if not kill:
        # odometry per wall window after the replay started, for the kill run's outage window
        r["_window"] = sorted((t - t_rep) / 1e9 for t in lis.odom.values())
        return r
    w_kill, w_restart = (t_kill - t_rep) / 1e9, (t_restart - t_rep) / 1e9
    outage_odom = sum(1 for t in lis.odom.values() if t_kill <= t <= t_restart)
    outage_odom_ready = sum(1 for t in lis.odom.values() if t_ready and t_kill <= t <= t_ready)
    pw = (parity or {}).get("_window", [])
    m_kill, m_restart = (at_kill or {}).get("mapper_keyframes_mapped"), (at_restart or {}).get("mapper_keyframes_mapped")
    res = _grep(lc2_log, r"resumed from checkpoint \S+: (\d+) keyframes, (\d+) loops")
    resumed = {"keyframes": int(res[0].group(1)), "loops": int(res[0].group(2))} if res else None
    down = sorted(st for st, t in lis.kf_packets.items() if t_kill <= t < (t_ready or t_end))
    # keyframes never in the database: sent while it was down or starting, or received but not yet
    # in the checkpoint at the kill
    final_db = _loop_db_stamps(ck_loop) or set()
    missed = sorted(set(lis.kf_packets) - final_db)
    w_ready = (t_ready - t_rep) / 1e9 if t_ready else None

    def mapper_at(tl, x):
        """(keyframes mapped, received = mapped + queued) by wall time x of a timeline."""
        v = [(m, m + q) for w, m, q in tl if w <= x]
        return v[-1] if v else (None, None)

    def mapper_delta(tl, a, b):
        (m0, r0), (m1, r1) = mapper_at(tl, a), mapper_at(tl, b)
        return {"mapped": m1 - m0 if None not in (m0, m1) else None,
                "received": r1 - r0 if None not in (r0, r1) else None}

    # where the final path differs from the parity run's (both start in the same frame and are
    # identical up to the kill): before, inside and after the stretch of the keyframes the
    # restarted loop closer never received
    err_split = None
    if missed and r.get("_traj") is not None and (parity or {}).get("_traj") is not None:
        err_split = {"missed_keyframe_stamps": [missed[0], missed[-1]],
                     **_displacement_split(r["_traj"], parity["_traj"], missed[0], missed[-1])}
    r.update({
        "at_kill": at_kill, "at_restart": at_restart, "at_restarted_ready": at_ready,
        "outage_s": (t_restart - t_kill) / 1e9,
        "restart_to_ready_s": (t_ready - t_restart) / 1e9 if t_ready else None,
        "outage_odometry": outage_odom,
        "outage_odometry_until_ready": outage_odom_ready,
        "parity_odometry_same_wall_window": sum(1 for x in pw if w_kill <= x <= w_restart),
        "mapper_keyframes_mapped_during_outage": (m_restart - m_kill) if None not in (m_kill, m_restart) else None,
        "mapper_kill_to_ready": mapper_delta(mapper_tl, w_kill, w_ready) if w_ready else None,
        "parity_mapper_same_wall_window": (mapper_delta((parity or {}).get("mapper_timeline", []), w_kill, w_ready)
                                           if w_ready else None),
        "parity_odometry_kill_to_ready_window": sum(1 for x in pw if w_ready and w_kill <= x <= w_ready),
        "path_vs_parity_path": err_split,
        "checkpoint_at_kill": ck_at_kill,
        "resumed_from_log": resumed,
        "resumed_matches_checkpoint_at_kill": (resumed is not None and ck_at_kill is not None
                                               and resumed["keyframes"] == ck_at_kill["keyframes"]),
        "keyframe_packets_sent_while_down": len(down),
        "keyframes_never_in_loop_db": len(missed),
        "loop_closer_restart_exit_code": r["exit_codes"].get("loop_closer_node"),
    })
    return r


if __name__ == "__main__":
    raise SystemExit(main())
