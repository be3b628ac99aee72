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
rclpy.init(args=["x", "--ros-args", "-p", f"frontend_node.calib_file:={calib}",
                 "-p", "frontend_node.queue_policy:=backpressure"])
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
rclpy.init(args=["x", "--ros-args", "-p", "mapper_node.checkpoint_period_s:=0.0"])
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


CAMERA_CHANGE_SCRIPT = """
import json, math, time
import numpy as np, rclpy
from sensor_msgs.msg import CameraInfo, Imu
import msg_adapters as ma
from msg_adapters.diagnostics import parse_diagnostic_array
rclpy.init(args=["x", "--ros-args", "-p", "frontend_node.queue_policy:=backpressure"])
from vings_ros.frontend_node import FrontendNode
node = FrontendNode()
sent = []
node.pub_diag.publish = sent.append         # capture /diagnostics
def info(w, h):
    m = CameraInfo(width=w, height=h, distortion_model="plumb_bob")
    m.k = [0.8 * w, 0.0, (w - 1) / 2, 0.0, 0.8 * w, (h - 1) / 2, 0.0, 0.0, 1.0]
    m.d = [0.0] * 5
    return m
rng = np.random.default_rng(0)
def img(stamp, w, h):
    return ma.image_to_msg(rng.integers(0, 256, (h, w), dtype=np.uint8), stamp, "cam")
def drain():
    t0 = time.time()
    while time.time() - t0 < 60 and node.error is None and len(node.queue):
        time.sleep(0.05)
    time.sleep(0.3)
node._on_camera_info(info(64, 48))
for i in range(2):
    node._on_image(img(10**9 + i * 10**8, 64, 48))
drain()
node.publish_diagnostics()
node._on_camera_info(info(32, 24))        # the camera changes while running
for i in range(2, 8):
    node._on_image(img(10**9 + i * 10**8, 32, 24))
drain()
node.publish_diagnostics()
bad = Imu()
bad.header.stamp.sec = 1
bad.angular_velocity.x = math.nan
good = Imu()
good.header.stamp.sec = 1
good.linear_acceleration.z = 9.81
node._on_imu(bad)
node._on_imu(good)
st = [parse_diagnostic_array(m)["status"]["vings/frontend"] for m in sent]
res = {"levels": [s["level"] for s in st], "message": st[-1]["message"],
       "camera_changes": node.camera_changes, "raw_width": node.raw_camera.width,
       "bad_streak": node.bad_streak, "imu": [node.imu_count, node.bad_imu],
       "error": repr(node.error) if node.error else None}
node.queue.close(); node.worker.stop(5)
node.destroy_node(); rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_frontend_node_reports_a_camera_change_and_checks_imu():
    res = _run(CAMERA_CHANGE_SCRIPT)
    assert res["error"] is None and res["raw_width"] == 64 and res["camera_changes"] == 1, res
    assert res["bad_streak"] == 6 and res["levels"][-1] == "error", res
    assert res["levels"][0] != "error", res
    assert "the last 6 images were skipped" in res["message"] and "32x24" in res["message"], res
    assert res["imu"] == [1, 1], res      # the NaN sample is counted as bad, not as a sample


START_ERROR_SCRIPT = """
import json, sys
import rclpy
rclpy.init(args=["x", "--ros-args"] + sys.argv[2:])
from vings_core.errors import VingsError
from vings_ros.frontend_node import FrontendNode
from vings_ros.mapper_node import MapperNode
try:
    {"frontend": FrontendNode, "mapper": MapperNode}[sys.argv[1]]()
    res = {"error": None}
except VingsError as e:
    res = {"error": type(e).__name__ + ": " + str(e)}
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_nodes_refuse_outputs_and_models_they_would_fail_on_later(tmp_path):
    # a checkpoint path that cannot be written: refused at start, not at the first checkpoint
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = _run(START_ERROR_SCRIPT, "mapper", "-p", f"mapper_node.checkpoint_path:={blocker}/sub/ckpt.npz")
    assert res["error"] and res["error"].startswith("ConfigError: mapper_node.checkpoint_path"), res
    # a temporary file of a mapper killed mid-write is removed at start
    ck = tmp_path / "ok" / "map.npz"
    ck.parent.mkdir()
    stale = ck.parent / ".map.npz.abc123.tmp"
    stale.write_bytes(b"half a checkpoint")
    other = ck.parent / ".other.npz.abc123.tmp"
    other.write_bytes(b"not ours")
    res = _run(START_ERROR_SCRIPT, "mapper", "-p", f"mapper_node.checkpoint_path:={ck}")
    assert res["error"] is None and not stale.exists() and other.exists(), res
    # a learned flow model that is not there: refused at start, not when the camera appears
    res = _run(START_ERROR_SCRIPT, "frontend", "-p", "frontend.flow_method:=torchscript",
               "-p", f"frontend.flow_weights_path:={tmp_path / 'raft.pt'}")
    assert res["error"] and "frontend.flow_weights_path" in res["error"] and "not found" in res["error"], res


def test_node_with_a_params_file_rcl_cannot_parse_exits_with_one_line(tmp_path):
    p = tmp_path / "mixed.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      background: [0, 0.5, 0]\n")
    env = dict(os.environ, ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-m", "vings_ros.mapper_node", "--ros-args", "--params-file", str(p)],
                       env=env, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "mixed.yaml: mapping.background" in r.stderr and "Traceback" not in r.stderr, r.stderr


RECORDER_SCRIPT = """
import errno, json, sys
from pathlib import Path
import rclpy
from rclpy.serialization import serialize_message
from nav_msgs.msg import Odometry
from msg_adapters import topics as T
rclpy.init(args=["x"])
from vings_ros.recorder import RecorderNode
out = Path(sys.argv[1])
res = {}
node = RecorderNode(str(out / "a.mcap"))
conn = next(c for c in node.writer.connections if c.topic == T.ODOMETRY_TOPIC)
for i in range(5):
    m = Odometry()
    m.header.stamp.sec = i + 1
    node._write(conn, T.ODOMETRY_TOPIC, serialize_message(m))
node.shutdown()
res["files"] = sorted(p.name for p in out.iterdir())
from mcap.reader import make_reader
with open(out / "a.mcap", "rb") as f:
    res["read_back"] = [(ch.topic, msg.log_time > 0) for _, ch, msg in make_reader(f).iter_messages()]
node.destroy_node()
# a write that fails (disk full): the node stops with one error naming the target, nothing raised
node = RecorderNode(str(out / "b.mcap"))
conn = next(c for c in node.writer.connections if c.topic == T.ODOMETRY_TOPIC)
def full(*a, **k):
    raise OSError(errno.ENOSPC, "No space left on device")
node.writer.write = full
node._write(conn, T.ODOMETRY_TOPIC, serialize_message(Odometry()))
res["error"] = str(node.error)
# ... and a close that fails keeps the partial file where the error says
def close_fails():
    raise OSError(errno.ENOSPC, "No space left on device")
node.writer.close = close_fails
try:
    node.shutdown()
    res["shutdown"] = None
except Exception as e:
    res["shutdown"] = type(e).__name__ + ": " + str(e)
node.destroy_node(); rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_recorder_writes_atomically_and_reports_write_errors_in_one_line(tmp_path):
    res = _run(RECORDER_SCRIPT, str(tmp_path))
    assert res["files"] == ["a.mcap"], res        # the temporary bag folder is gone
    assert res["read_back"] == [["/vings/odometry", True]] * 5
    assert "b.mcap: cannot write the recording (No space left on device)" in res["error"]
    assert "what was written so far is in" in res["error"]
    assert res["shutdown"].startswith("VingsError: ") and "partial file stays at" in res["shutdown"]
    assert not (tmp_path / "b.mcap").exists()


IMU_FUSION_SCRIPT = """
import json, sys
import rclpy
from sensor_msgs.msg import Imu
from msg_adapters.diagnostics import parse_diagnostic_array
args = ["x", "--ros-args"] + (["-p", f"frontend_node.calib_file:={sys.argv[1]}"] if sys.argv[1] else [])
rclpy.init(args=args)
from vings_ros.frontend_node import FrontendNode
node = FrontendNode()
sent = []
node.pub_diag.publish = sent.append
for k in range(3):
    m = Imu()
    m.header.stamp.nanosec = 5_000_000 * (k + 1)
    m.linear_acceleration.z = 9.81
    node._on_imu(m)
node.publish_diagnostics()
st = parse_diagnostic_array(sent[-1])["status"]["vings/frontend"]
vio = node.frontend.vio if node.frontend is not None else None
res = {"level": st["level"], "message": st["message"], "vi_state": st["values"].get("vi_state"),
       "fused": vio is not None, "buffered": vio.imu.count if vio is not None else 0}
node.queue.close(); node.worker.stop(5)
node.destroy_node(); rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_frontend_node_fuses_the_imu_only_with_a_known_extrinsic(tmp_path):
    # without a calibration file the camera-IMU extrinsic is unknown: visual-only, ERROR, not identity
    res = _run(IMU_FUSION_SCRIPT, "")
    assert res["level"] == "error" and "T_bc" in res["message"] and not res["fused"], res
    # a VINGS calibration with T_bc: the fusion runs and the readings reach its buffer
    calib = tmp_path / "cal.yaml"
    calib.write_text("camera: {width: 64, height: 48, fx: 50.0, fy: 52.0, cx: 31.5, cy: 23.5}\n"
                     "T_bc: [[0, 0, 1, 0.05], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]]\nhas_imu: true\n")
    res = _run(IMU_FUSION_SCRIPT, str(calib))
    assert res["fused"] and res["buffered"] == 3 and res["level"] != "error", res
    assert res["vi_state"] == "initialising", res
