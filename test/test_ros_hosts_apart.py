"""Hosts apart: two network namespaces joined by a virtual Ethernet pair (addresses this test
creates) stand for two hosts. Keyframe packets (the front end's output, 376x240) published in one
reach a subscriber in the other when discovery is opened (ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET,
docs/ros.md "Hosts apart"), and do not with the default environment (discovery on this host only).
Needs root and iproute2 (skipped otherwise, with the reason)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]
N_KEYFRAMES = 12

PUB = """
import sys, time, numpy as np, torch, rclpy
from msg_adapters import topics as T
from msg_adapters.keyframe import PART_TOPICS, keyframe_to_msgs
from vings_core.types import CameraModel, Keyframe
rclpy.init()
node = rclpy.create_node("host_a_frontend")
from sensor_msgs.msg import CameraInfo, Image
from geometry_msgs.msg import PoseStamped
types = {"image": Image, "depth": Image, "inv_depth_var": Image, "pose": PoseStamped, "camera_info": CameraInfo}
pubs = {p: node.create_publisher(types[p], t, T.sensor_qos(50)) for p, t in PART_TOPICS.items()}
cam = CameraModel(376, 240, 200.0, 200.0, 187.5, 119.5)
t0 = time.time()
while time.time() - t0 < 20 and min(p.get_subscription_count() for p in pubs.values()) < 1:
    rclpy.spin_once(node, timeout_sec=0.1)
time.sleep(1.0)
rng = np.random.default_rng(0)
for i in range(int(sys.argv[1])):
    T_wc = np.eye(4); T_wc[0, 3] = 0.1 * i
    kf = Keyframe(stamp_ns=(i + 1) * 10**9, image=torch.from_numpy(rng.random((240, 376, 3), dtype=np.float32)),
                  T_wc=torch.from_numpy(T_wc), depth=torch.full((240, 376), 2.0), inv_depth_var=torch.full((240, 376), 1e-3),
                  valid=torch.ones(240, 376, dtype=torch.bool), camera=cam, index=i)
    for part, m in keyframe_to_msgs(kf).as_dict().items():
        pubs[part].publish(m)
    rclpy.spin_once(node, timeout_sec=0.05)
t1 = time.time()
while time.time() - t1 < 5:
    rclpy.spin_once(node, timeout_sec=0.1)
"""

SUB = """
import sys, time, rclpy
from msg_adapters import topics as T
from msg_adapters.keyframe import KeyframeAssembler, PART_TOPICS
from sensor_msgs.msg import CameraInfo, Image
from geometry_msgs.msg import PoseStamped
rclpy.init()
node = rclpy.create_node("host_b_mapper")
asm = KeyframeAssembler(max_pending=64)
got = []
types = {"image": Image, "depth": Image, "inv_depth_var": Image, "pose": PoseStamped, "camera_info": CameraInfo}
def on(part, m):
    kf = asm.add(part, m)
    if kf is not None:
        got.append(int(kf.stamp_ns))
for p, t in PART_TOPICS.items():
    node.create_subscription(types[p], t, lambda m, p=p: on(p, m), T.sensor_qos(50))
t0 = time.time()
while time.time() - t0 < float(sys.argv[2]) and len(got) < int(sys.argv[1]):
    rclpy.spin_once(node, timeout_sec=0.1)
print("RESULT", len(got), len(set(got)))
"""


@pytest.fixture
def two_hosts():
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2 to create network namespaces")
    k = os.getpid() % 200 + 20
    a, b = f"vings_a{k}", f"vings_b{k}"
    cmds = [f"ip netns add {a}", f"ip netns add {b}", f"ip link add va{k} type veth peer name vb{k}",
            f"ip link set va{k} netns {a}", f"ip link set vb{k} netns {b}",
            f"ip -n {a} addr add 10.231.{k}.1/24 dev va{k}", f"ip -n {b} addr add 10.231.{k}.2/24 dev vb{k}",
            f"ip -n {a} link set va{k} up", f"ip -n {b} link set vb{k} up",
            f"ip -n {a} link set lo up", f"ip -n {b} link set lo up",
            f"ip -n {a} route add 224.0.0.0/4 dev va{k}", f"ip -n {b} route add 224.0.0.0/4 dev vb{k}"]
    try:
        for c in cmds:
            r = subprocess.run(c.split(), capture_output=True, text=True)
            if r.returncode != 0:
                pytest.skip(f"cannot create network namespaces here ({c}: {r.stderr.strip()})")
        yield a, b
    finally:
        for ns in (a, b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _exchange(a: str, b: str, domain: int, extra_env: dict) -> tuple[int, int]:
    from vings_ros.ros_env import ros_environment
    base = {k: v for k, v in os.environ.items() if k != "ROS_AUTOMATIC_DISCOVERY_RANGE"}
    env = ros_environment(domain_id=domain, base={**base, **extra_env, "PYTHONPATH": str(REPO)})
    pub = subprocess.Popen(["ip", "netns", "exec", a, sys.executable, "-c", textwrap.dedent(PUB), str(N_KEYFRAMES)],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        sub = subprocess.run(["ip", "netns", "exec", b, sys.executable, "-c", textwrap.dedent(SUB), str(N_KEYFRAMES),
                              "40"], env=env, capture_output=True, text=True, timeout=120)
    finally:
        pub.wait(timeout=120)
    line = [ln for ln in sub.stdout.splitlines() if ln.startswith("RESULT")]
    assert line, sub.stderr[-2000:]
    n, uniq = map(int, line[-1].split()[1:])
    return n, uniq


def test_keyframes_cross_hosts_only_when_discovery_is_opened(two_hosts):
    a, b = two_hosts
    base = 150 + os.getpid() % 40
    n, uniq = _exchange(a, b, base, {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})
    assert n == uniq == N_KEYFRAMES
    n, _ = _exchange(a, b, base + 1, {})           # the default: this host only
    assert n == 0
