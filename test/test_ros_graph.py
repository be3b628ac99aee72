"""Integration: `vings launch` + `vings replay --wait-for-graph` of a short synthetic MCAP.

Under a unique ROS_DOMAIN_ID and a time cap: every frame after initialisation gets odometry, at least
one rendered image arrives, the graph shuts down cleanly (exit 0) and leaves no processes or Fast DDS
shared-memory files behind.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]
FAST_PARAMS = ["mapping.iters_per_keyframe=5", "mapping.points_per_keyframe=3000",
               "mapping.refine_iters=2", "ros.checkpoint_period_s=0.0"]


def _domain() -> int:
    return 100 + os.getpid() % 100


def _procs_with_env(key: str, value: str) -> list[int]:
    pids = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            env = (d / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if f"{key}={value}".encode() in env:
            pids.append(int(d.name))
    return pids


@pytest.fixture(scope="module")
def synthetic_mcap(tmp_path_factory) -> Path:
    from vings_core.sim import generate
    out = tmp_path_factory.mktemp("ros_graph") / "room"
    generate("room", out, frames=36, width=256, height=160, seed=3, mcap=True)
    mcaps = list(out.glob("*.mcap"))
    assert mcaps, "simulator wrote no MCAP"
    return mcaps[0]


def test_launch_replay_backpressure_end_to_end(synthetic_mcap, tmp_path):
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image

    from msg_adapters import topics as T
    from msg_adapters.stamps import header_ns
    from vings_core.io import open_source
    from vings_ros.ros_env import (apply_ros_environment, cleanup_fastdds_shm, ros_environment,
                                   shm_snapshot)

    domain = _domain()
    snap = shm_snapshot()
    env = ros_environment(domain, log_dir=tmp_path / "roslog")
    env["VINGS_TEST_MARK"] = str(domain)
    ckpt = tmp_path / "map_ckpt.npz"
    launch_cmd = [sys.executable, "-m", "vings_ros.cli", "launch", "--backpressure", "--domain-id",
                  str(domain), "--checkpoint", str(ckpt)]
    for p in FAST_PARAMS:
        launch_cmd += ["-p", p]
    launcher = subprocess.Popen(launch_cmd, env=env, start_new_session=True,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    saved_env = dict(os.environ)
    apply_ros_environment(domain, log_dir=tmp_path / "roslog")
    rclpy.init()
    node = rclpy.create_node("vings_test_listener")
    odom, renders = [], []
    node.create_subscription(Odometry, T.ODOMETRY_TOPIC, lambda m: odom.append(header_ns(m.header)),
                             T.sensor_qos(1000))
    node.create_subscription(Image, T.RENDER_COLOR_TOPIC, lambda m: renders.append(header_ns(m.header)),
                             T.sensor_qos(10))
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    replay = None
    try:
        # the listener must be matched with the graph's publishers before any frame is replayed
        ready = time.monotonic() + 120
        while time.monotonic() < ready and (node.count_publishers(T.ODOMETRY_TOPIC) < 1 or
                                            node.count_publishers(T.RENDER_COLOR_TOPIC) < 1):
            ex.spin_once(timeout_sec=0.1)
            assert launcher.poll() is None, f"graph died:\n{launcher.communicate()[0][-3000:]}"
        assert node.count_publishers(T.ODOMETRY_TOPIC) >= 1, "front end never came up"
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        replay = subprocess.Popen(
            [sys.executable, "-m", "vings_ros.cli", "replay", str(synthetic_mcap), "--rate", "0",
             "--wait-for-graph", "--domain-id", str(domain), "--ack-timeout", "120",
             "--startup-timeout", "60"],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        deadline = time.monotonic() + 240
        while replay.poll() is None and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        assert replay.poll() == 0, f"replay failed or timed out:\n{replay.communicate()[0][-3000:]}"
        # the mapper works on the last keyframes after the front end is done: wait for a render
        settle = time.monotonic() + 90
        while time.monotonic() < settle and (not renders or time.monotonic() < settle - 85):
            ex.spin_once(timeout_sec=0.05)
        assert launcher.poll() is None, f"graph died:\n{launcher.communicate()[0][-3000:]}"
        os.killpg(launcher.pid, signal.SIGINT)
        out, _ = launcher.communicate(timeout=200)
        assert launcher.returncode == 0, f"unclean shutdown (exit {launcher.returncode}):\n{out[-3000:]}"
        end = time.monotonic() + 2
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
    finally:
        for p in (replay, launcher):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL) if p is launcher else p.kill()
                p.wait()
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown()
        os.environ.clear()
        os.environ.update(saved_env)

    stamps = [int(s) for s in open_source(synthetic_mcap).frame_stamps()]
    assert odom, "no odometry received"
    first = min(odom)
    expected = {s for s in stamps if s >= first}
    missing = expected - set(odom)
    assert not missing, f"{len(missing)} of {len(expected)} frames after initialisation got no odometry"
    assert len(expected) >= len(stamps) // 2, "front end initialised too late"
    assert renders, "no rendered image received"
    assert ckpt.exists(), "mapper wrote no checkpoint on shutdown"
    time.sleep(1.0)
    assert not _procs_with_env("VINGS_TEST_MARK", str(domain)), "graph processes left running"
    # files that appeared during the test and that no live process holds (other tests may run)
    left = cleanup_fastdds_shm(snap, dry_run=True)
    assert not left, f"Fast DDS shared-memory files left behind: {left[:5]}"
