"""The front-end and mapper nodes drop bad messages with a warning instead of dying.

Each case runs in a child process (own rclpy context, unique ROS domain, localhost only) and calls
the nodes' subscription callbacks directly with hand-built messages.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]

FRONTEND_SCRIPT = """
import json, sys, time
import numpy as np, rclpy
from sensor_msgs.msg import CameraInfo
import msg_adapters as ma
calib = sys.argv[1]
rclpy.init(args=["x", "--ros-args", "-p", f"ros.calib_file:={calib}",
                 "-p", "ros.queue_policy:=backpressure"])
from vings_ros.frontend_node import FrontendNode
node = FrontendNode()
rng = np.random.default_rng(0)
def img(stamp):
    return ma.image_to_msg(rng.integers(0, 256, (48, 64), dtype=np.uint8), stamp, "cam")
bad_nsec = img(1_200_000_000)
bad_nsec.header.stamp.nanosec = 1_500_000_000       # outside [0, 1e9)
msgs = [img(1_000_000_000), img(1_050_000_000),
        img(1_050_000_000),                         # repeated stamp
        img(1_020_000_000),                         # backwards
        bad_nsec,
        img(1_100_000_000)]                         # a good one after them
for m in msgs:
    node._on_image(m)
t0 = time.time()
while time.time() - t0 < 60 and node.error is None and len(node.queue):
    time.sleep(0.1)
time.sleep(0.5)
res = {"error": repr(node.error) if node.error else None, "alive": node.worker.thread.is_alive(),
       "bad_frames": node.bad_frames, "last_stamp": node._last_stamp}
node.queue.close(); node.worker.stop(5)
node.destroy_node(); rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""

CAMERA_INFO_SCRIPT = """
import json
import rclpy
from sensor_msgs.msg import CameraInfo
rclpy.init(args=["x"])
from vings_ros.frontend_node import FrontendNode
node = FrontendNode()
node._on_camera_info(CameraInfo(width=64, height=48, distortion_model="plumb_bob"))  # K = 0
waiting = node.raw_camera is None
good = CameraInfo(width=64, height=48, distortion_model="plumb_bob")
good.k = [50.0, 0.0, 31.5, 0.0, 52.0, 23.5, 0.0, 0.0, 1.0]
good.d = [0.0, 0.0, 0.0, 0.0, 0.0]
node._on_camera_info(good)
res = {"waiting_after_bad": waiting, "bad": node.bad_camera_infos,
       "fx": node.raw_camera.fx if node.raw_camera is not None else None}
node.queue.close(); node.worker.stop(5)
node.destroy_node(); rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""

MAPPER_SCRIPT = """
import json
import numpy as np, rclpy
import msg_adapters as ma
rclpy.init(args=["x", "--ros-args", "-p", "ros.checkpoint_period_s:=0.0"])
from vings_ros.mapper_node import MapperNode
import torch
from msg_adapters.keyframe import keyframe_to_msgs
from vings_core.types import CameraModel, Keyframe
node = MapperNode()
cam = CameraModel(8, 6, 5.0, 5.0, 4.0, 3.0)
kf = Keyframe(stamp_ns=10**9, image=torch.rand(6, 8, 3), T_wc=torch.eye(4, dtype=torch.float64),
              depth=torch.ones(6, 8), inv_depth_var=torch.ones(6, 8),
              valid=torch.ones(6, 8, dtype=torch.bool), camera=cam, index=0)
parts = keyframe_to_msgs(kf).as_dict()
parts["depth"] = ma.float_image_to_msg(np.ones((3, 4), np.float32), 10**9, "cam")  # wrong size
for part, m in parts.items():
    node._on_part(part, m)
node._on_part("no_such_part", parts["depth"])
res = {"bad_parts": node.bad_parts, "error": repr(node.error) if node.error else None}
node.queue.close(); node.worker.stop(5)
node.destroy_node(); rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def _run(script: str, *args: str) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(script), *args], env=env, cwd=REPO,
                       capture_output=True, text=True, timeout=180)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    assert p.returncode == 0 and lines, f"child failed (rc {p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}"
    return json.loads(lines[-1][len("RESULT "):])


def test_frontend_node_skips_bad_stamps_and_keeps_running(tmp_path):
    calib = tmp_path / "cal.yaml"
    calib.write_text("camera: {width: 64, height: 48, fx: 50.0, fy: 52.0, cx: 31.5, cy: 23.5}\n")
    res = _run(FRONTEND_SCRIPT, str(calib))
    assert res["error"] is None and res["alive"], res
    assert res["bad_frames"] == 3, res               # repeated, backwards, bad nanosec
    assert res["last_stamp"] == 1_100_000_000, res   # the good image after them was processed


def test_frontend_node_waits_past_an_uncalibrated_camera_info():
    res = _run(CAMERA_INFO_SCRIPT)
    assert res == {"waiting_after_bad": True, "bad": 1, "fx": 50.0}, res


def test_mapper_node_drops_a_malformed_keyframe_part():
    res = _run(MAPPER_SCRIPT)
    assert res == {"bad_parts": 2, "error": None}, res
