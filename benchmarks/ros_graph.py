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

    python benchmarks/ros_graph.py [--frames 120] [--width 376 --height 240] [--work DIR]
                                   [--only parity,live,resume] [--writeback none|all|consistent]
                                   [--no-imu] [-p section.key=value ...]
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
        self.ex = SingleThreadedExecutor()
        self.ex.add_node(self.node)
        self._stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        self.T = T

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
    ap.add_argument("--only", default="parity,live,resume", help="experiments to run (comma list)")
    ap.add_argument("--writeback", default=None, choices=("none", "all", "consistent"),
                    help="exchange.mapper (the write-back policy for the mapper's refinements) for both the offline run and the graph")
    ap.add_argument("--no-imu", action="store_true",
                    help="visual-only on both sides (vings run --no-imu; the graph without "
                         "frontend_node.calib_file); by default both fuse the simulated IMU")
    ap.add_argument("-p", "--param", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="extra ROS parameter for both graph nodes (e.g. mapper_node.threads=1)")
    args = ap.parse_args()
    only = set(args.only.split(","))

    from vings_core.io import open_source
    from vings_core.sim import generate
    from vings_core.trajectory_io import read_tum

    work = Path(args.work or tempfile.mkdtemp(prefix="vings_bench_ros_"))
    work.mkdir(parents=True, exist_ok=True)
    log = open(work / "log.txt", "a")
    seq = work / "room"
    if not (seq / "room.mcap").exists():
        generate("room", seq, frames=args.frames, width=args.width, height=args.height, seed=args.seed)
    mcap = seq / "room.mcap"
    src = open_source(seq)
    gt = src.gt_camera_trajectory()
    stamps = [int(s) for s in src.frame_stamps()]
    result: dict = {"frames": len(stamps), "resolution": [args.width, args.height], "cores": os.cpu_count()}

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
            lis = Listener(domain)
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

    steps = [("frontend_alone", frontend_alone)]
    if "parity" in only:
        steps += [("offline_sync", offline),
                  ("parity", lambda: run_parity(listener(), domain, mcap, gt, graph_params, ate_off, work, log))]
    if "live" in only:
        steps.append(("live_20hz", lambda: run_live(listener(), domain, mcap, graph_params, work, log)))
    if "resume" in only:
        steps.append(("resume", lambda: run_resume(listener(), domain, mcap, stamps, graph_params, work, log)))

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


if __name__ == "__main__":
    raise SystemExit(main())
