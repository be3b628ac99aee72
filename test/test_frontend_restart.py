"""A front end killed mid-replay comes back from its checkpoint: `vings launch` respawns it, `vings
replay --wait-for-graph` waits for it and sends the lost image again, and the restored front end
goes on in the same world frame (resumed after a short gap, relocalised after a long one). Real
processes (launcher, node, replay) in a child script with its own ROS domain."""
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
REPO = Path(__file__).resolve().parent.parent

SCRIPT = r"""
import json, os, signal, subprocess, sys, time
from pathlib import Path
import numpy as np
work, dom, max_gap, with_mapper = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4] == "1"
from vings_core.sim import generate
from vings_core.io import open_source
from vings_core.eval.traj import evaluate_trajectory
from vings_core.types import Trajectory
if not (work / "room" / "sim.json").exists():
    generate("room", work / "room", frames=90, seed=0, width=188, height=120)
mcap = next((work / "room").glob("*.mcap"))
gt = open_source(str(mcap)).gt_camera_trajectory()

from vings_ros.ros_env import apply_ros_environment
apply_ros_environment(domain_id=int(dom))
import rclpy
from vings_ros.node_common import spin_in_background
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from msg_adapters import topics as T
from msg_adapters.pose import odometry_to_estimate
rclpy.init()
node = rclpy.create_node("restart_probe")
odom, diag, errors = {}, {}, []
def on_odom(m):
    try:
        e = odometry_to_estimate(m, T.ODOMETRY_TOPIC)
    except Exception as ex:         # counted: an exception would end the spin thread
        errors.append(repr(ex))
        return
    odom[int(e.stamp_ns)] = e.T_wc
def on_diag(m):
    for s in m.status:
        if s.name == "vings/frontend":
            diag.update({kv.key: kv.value for kv in s.values})
# transient local, as a subscriber that needs every pose asks: discovery of a (re)started front end
# can take seconds on a loaded machine, and its odometry history is delivered once it matches
node.create_subscription(Odometry, T.ODOMETRY_TOPIC, on_odom, T.odometry_qos())
node.create_subscription(DiagnosticArray, T.DIAGNOSTICS_TOPIC, on_diag, T.sensor_qos(50))
stop_spinning = spin_in_background(node)

mark = f"restart{os.getpid()}"
env = dict(os.environ, VINGS_TEST_MARK=mark)
launch = subprocess.Popen([sys.executable, "-m", "vings_ros.cli", "launch", "--use-sim-time", "--backpressure",
                           "--no-loop", "--no-eraser", "--checkpoint", str(work / "map.ckpt"),
                           "--domain-id", dom, "-p", "frontend_node.respawn_backoff_s=0.2",
                           "-p", f"frontend_node.resume_max_gap_s={max_gap}", "-p", "mapping.iters_per_keyframe=20"]
                          + ([] if with_mapper else ["--no-mapper"]),
                          env=env, stdout=open(work / "launch.log", "w"), stderr=subprocess.STDOUT,
                          start_new_session=True)
replay = subprocess.Popen([sys.executable, "-m", "vings_ros.cli", "replay", str(mcap), "--wait-for-graph",
                           "--respawn-wait", "90", "--ack-timeout", "90", "--domain-id", dom],
                          env=env, stdout=open(work / "replay.log", "w"), stderr=subprocess.STDOUT)

def frontend_pid():
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if f"VINGS_TEST_MARK={mark}".encode() not in (d / "environ").read_bytes().split(b"\0"):
                continue
            if b"vings_ros.frontend_node" in (d / "cmdline").read_bytes():
                return int(d.name)
        except OSError:
            pass
    return None

t_end = time.time() + 240
while len(odom) < 30 and time.time() < t_end and replay.poll() is None:
    time.sleep(0.05)
before = dict(odom)
pid = frontend_pid()
assert pid is not None and replay.poll() is None, (len(odom), replay.poll())
os.kill(pid, signal.SIGKILL)
t_kill = time.time()
rc = replay.wait(300)
t_end = time.time() + 30
while diag.get("restart", "fresh") == "fresh" and time.time() < t_end:
    time.sleep(0.1)
cams = sorted(f.stamp_ns for f in open_source(str(mcap)).frames())
t_end = time.time() + 30        # the last frame's pose (late discovery: from the history)
while cams[-1] not in odom and time.time() < t_end:
    time.sleep(0.1)
time.sleep(0.5)
t_end = time.time() + 60
while diag.get("restart") == "relocalising" and not diag.get("restart_outcome") and time.time() < t_end:
    time.sleep(0.1)
res = {"replay_rc": rc, "restart": diag.get("restart"), "outcome": diag.get("restart_outcome"),
       "render": diag.get("restart_render"),
       "gap": diag.get("restart_gap_s"), "segment": diag.get("segment"),
       "odom_before": len(before), "odom_after": len(odom) - len(before), "odom_errors": errors[:3],
       "frontend_diag": {k: diag.get(k) for k in ("state", "frames", "keyframes")}}
os.killpg(launch.pid, signal.SIGINT)
launch.wait(120)
stop_spinning()
st = np.array(sorted(odom))
traj = Trajectory(st, np.stack([odom[s] for s in st]))
res["ate_sim3_m"] = evaluate_trajectory(traj, gt)["ate_sim3_m"]
res["frames_without_odometry"] = [i for i, s in enumerate(cams) if s not in odom]
res["killed_after_frame"] = int(np.searchsorted(cams, max(before)))
p = gt.poses[:, :3, 3]
res["path_m"] = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
res["replay_log"] = (work / "replay.log").read_text()[-800:]
res["ckpt"] = (work / "map.ckpt.frontend").exists()
print("RESULT " + json.dumps(res))
"""


def _run(tmp_path: Path, max_gap: float, offset: int, mapper: bool = False) -> dict:
    from vings_ros.ros_env import cleanup_fastdds_shm, shm_snapshot
    dom = str(200 + (os.getpid() + offset) % 30)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    snap = shm_snapshot()
    try:
        p = subprocess.run([sys.executable, "-c", textwrap.dedent(SCRIPT), str(tmp_path), dom, str(max_gap), "1" if mapper else "0"],
                           env=env, cwd=REPO, capture_output=True, text=True, timeout=600)
    finally:
        cleanup_fastdds_shm(snap)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    log = (tmp_path / "launch.log").read_text()[-3000:] if (tmp_path / "launch.log").exists() else ""
    assert p.returncode == 0 and lines, f"child failed (rc {p.returncode}):\n{p.stderr[-4000:]}\n{log}"
    return json.loads(lines[-1][len("RESULT "):])


def _summary(res: dict) -> str:
    """The result without the replay's log (an assertion message pytest does not cut)."""
    return json.dumps({k: v for k, v in res.items() if k != "replay_log"})


def test_a_killed_front_end_resumes_from_its_checkpoint(tmp_path):
    res = _run(tmp_path, 3.0, 17)
    assert res["replay_rc"] == 0, res["replay_log"]
    assert "the front end came back" in res["replay_log"], res["replay_log"]
    assert res["restart"] == "resumed" and float(res["gap"]) <= 3.0, _summary(res)
    # the poses go on after the restart and every frame has one: those tracked before the kill from
    # the killed front end, the rest (the image in flight at the kill sent again) from the new one
    assert res["ckpt"] and res["odom_after"] >= 10 and not res["odom_errors"], _summary(res)
    assert len(res["frames_without_odometry"]) <= 2, _summary(res)
    # the poses after the restart continue the same trajectory: one Sim(3) fits all of them
    assert res["ate_sim3_m"] < 0.02 * res["path_m"], _summary(res)


@pytest.mark.slow
def test_after_a_long_gap_the_front_end_relocalises_in_its_world_frame(tmp_path):
    """With the mapper running, the relocalised pose is also checked against a render of the map."""
    res = _run(tmp_path, 0.0, 19, mapper=True)
    assert res["replay_rc"] == 0, res["replay_log"]
    assert res["restart"] == "relocalising" and res["outcome"] == "relocalised", _summary(res)
    assert "'answered'" in res["render"] and "'l1'" in res["render"], _summary(res)
    assert res["segment"] == "0", _summary(res)
    assert res["ate_sim3_m"] < 0.02 * res["path_m"], _summary(res)
