"""ROS node graph figures (issue 6). Last line: one JSON object.

Experiments on one synthetic `room` sequence:

* ``parity``: the graph with back-pressure (`vings replay --wait-for-graph`, front end queue policy
  ``backpressure``) versus `vings run --sync`: Sim(3) ATE of each (graph: the final /vings/path),
  and their relative difference.
* ``live``: replay at 20 Hz without back-pressure (policy ``keep_newest``): fraction of frames that
  get odometry, and publish -> odometry latency (receive wall clock minus publish wall clock) p50/p95.
* ``resume``: the mapper is killed (SIGKILL) mid-run and started again: it resumes from its
  checkpoint, and the final checkpoint holds the keyframes it had before the crash.

    python benchmarks/ros_graph.py [--frames 120] [--width 376 --height 240] [--work DIR]
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
        self.odom, self.path, self.renders = {}, None, 0

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
    return subprocess.Popen(cmd, env=ros_environment(domain), stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)


def stop(p: subprocess.Popen, timeout: float = 200) -> int:
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--width", type=int, default=376)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=None)
    args = ap.parse_args()

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
    t0 = time.perf_counter()
    off = work / "offline"
    mp = work / "bench_params.yaml"
    mp.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 20\n      refine_iters: 3\n")
    subprocess.run([sys.executable, "-m", "vings_ros.cli", "run", str(seq), "--out", str(off), "--sync",
                    "--params", str(mp), "--no-progress"], stdout=log, stderr=subprocess.STDOUT, check=True)
    ate_off = ate(read_tum(off / "trajectory.tum"), gt)
    result["offline_sync"] = {"ate_sim3_m": ate_off, "wall_s": time.perf_counter() - t0}

    domain = 150 + os.getpid() % 50
    lis = Listener(domain)
    try:
        # ---- parity: back-pressure graph
        ck = work / "parity_ckpt.npz"
        fe = node_proc("vings_ros.frontend_node", domain, ["ros.queue_policy=backpressure"], log)
        ma = node_proc("vings_ros.mapper_node", domain, MAPPING + [f"ros.checkpoint_path={ck}", "ros.resume=false"], log)
        lis.wait_for_graph()
        t0 = time.perf_counter()
        replay(mcap, domain, ["--rate", "0", "--wait-for-graph"], log)
        stop(fe)
        time.sleep(2.0)
        stop(ma)
        graph_traj = lis.path
        ate_ros = ate(graph_traj, gt) if graph_traj is not None and len(graph_traj) >= 3 else None
        result["parity"] = {"ate_sim3_m_graph": ate_ros, "ate_sim3_m_offline": ate_off,
                            "rel_diff": (abs(ate_ros - ate_off) / ate_off) if ate_ros is not None and ate_off > 0 else None,
                            "odometry_frames": len(lis.odom), "wall_s": time.perf_counter() - t0,
                            "renders": lis.renders}

        # ---- live: 20 Hz, keep newest
        lis.reset()
        pub_log = work / "publish_log.csv"
        fe = node_proc("vings_ros.frontend_node", domain, ["ros.queue_policy=keep_newest"], log)
        ma = node_proc("vings_ros.mapper_node", domain, MAPPING, log)
        lis.wait_for_graph()
        replay(mcap, domain, ["--rate", "1", "--publish-log", str(pub_log)], log)
        time.sleep(3.0)
        stop(fe)
        stop(ma)
        pubs = {}
        for line in pub_log.read_text().splitlines()[1:]:
            s, w = line.split(",")[:2]
            pubs[int(s)] = int(w)
        lat = np.array([(lis.odom[s] - pubs[s]) / 1e6 for s in pubs if s in lis.odom])
        result["live_20hz"] = {"frames_published": len(pubs), "frames_with_odometry": int(len(lat)),
                               "odometry_fraction": len(lat) / max(len(pubs), 1),
                               "latency_ms_p50": float(np.percentile(lat, 50)) if len(lat) else None,
                               "latency_ms_p95": float(np.percentile(lat, 95)) if len(lat) else None}

        # ---- resume: kill the mapper mid-run, start it again
        lis.reset()
        ck = work / "resume_ckpt.npz"
        if ck.exists():
            ck.unlink()
        mparams = MAPPING + [f"ros.checkpoint_path={ck}", "ros.checkpoint_period_s=1.0", "ros.resume=true"]
        fe = node_proc("vings_ros.frontend_node", domain, ["ros.queue_policy=backpressure"], log)
        ma = node_proc("vings_ros.mapper_node", domain, mparams, log)
        lis.wait_for_graph()
        half = stamps[len(stamps) // 2] - stamps[0]
        replay(mcap, domain, ["--rate", "0", "--wait-for-graph", "--duration", f"{half / 1e9:.3f}"], log)
        time.sleep(4.0)
        os.killpg(ma.pid, signal.SIGKILL)   # crash
        ma.wait()
        from vings_core.mapping import Mapper
        before = set(Mapper.load_checkpoint(ck).keyframe_poses()) if ck.exists() else set()
        ma = node_proc("vings_ros.mapper_node", domain, mparams, log)
        time.sleep(8.0)
        replay(mcap, domain, ["--rate", "0", "--wait-for-graph", "--start", f"{half / 1e9 + 0.01:.3f}"], log)
        stop(fe)
        time.sleep(2.0)
        rc = stop(ma)
        after = set(Mapper.load_checkpoint(ck).keyframe_poses()) if ck.exists() else set()
        result["resume"] = {"keyframes_before_crash": len(before), "keyframes_final": len(after),
                            "all_pre_crash_keyframes_kept": bool(before) and before <= after,
                            "mapper_exit_code": rc}
    finally:
        lis.close()
        log.close()
    print(json.dumps(result))


if __name__ == "__main__":
    main()
