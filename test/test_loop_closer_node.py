"""The loop closer in the node graph: its messages (msg_adapters/loop.py), loop_closer_node with a
fake map answering its render requests (a loop closed, a reply that never comes, checkpoint and
resume), and mapper_node answering render requests and retraining after a loop correction.

The node cases run in a child process (own rclpy context, unique ROS domain, localhost only), one
SingleThreadedExecutor per node on its own thread. The scene is a textured plane seen straight on:
keyframes, renders and depths are exact functions of the pose (``SCENE``).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]

# A textured plane z = 2 (world), cameras looking along +z; keyframe i is seen from TRUE[i] and
# emitted with the drifted pose EMIT[i]; keyframes 4 and 5 (the latter in the timeout case) revisit
# keyframe 0's view.
SCENE = """
import numpy as np, cv2, torch
from vings_core.types import CameraModel, Keyframe
W, H, F = 320, 240, 200.0
CAM = CameraModel(W, H, F, F, (W - 1) / 2, (H - 1) / 2)
PPU, HALF, Z = 100.0, 6.0, 2.0

def _texture(seed=0):
    rng = np.random.default_rng(seed)
    n = int(2 * HALF * PPU)
    tex = np.zeros((n, n), np.float32)
    for cells, w in ((12, 1.0), (40, 0.7), (150, 0.5), (400, 0.35)):
        tex += w * cv2.resize(rng.random((cells, cells)).astype(np.float32), (n, n), interpolation=cv2.INTER_CUBIC)
    tex -= tex.min()
    return tex / tex.max()

TEX = _texture()

def pose(x, y, z=0.0):
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T

def render_plane(T_wc, cam=CAM):
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    dw = d @ np.asarray(T_wc)[:3, :3].T
    c = np.asarray(T_wc)[:3, 3]
    t = (Z - c[2]) / dw[..., 2]
    X = c + t[..., None] * dw
    mx = ((X[..., 0] + HALF) * PPU).astype(np.float32)
    my = ((X[..., 1] + HALF) * PPU).astype(np.float32)
    g = cv2.remap(TEX, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.repeat(g[..., None], 3, 2).astype(np.float32), t.astype(np.float32)

def keyframe(i, true_T, emitted_T, cam=CAM):
    img, depth = render_plane(true_T, cam)
    img = (np.rint(img * 255) / 255).astype(np.float32)
    h, w = cam.height, cam.width
    return Keyframe(stamp_ns=(i + 1) * 10**9, image=torch.from_numpy(img), T_wc=torch.from_numpy(emitted_T),
                    depth=torch.from_numpy(depth), inv_depth_var=torch.full((h, w), 1e-6),
                    valid=torch.ones(h, w, dtype=torch.bool), camera=cam, index=i)

TRUE = [pose(0, 0), pose(3.5, 0), pose(3.5, 3.0), pose(0, 3.2), pose(0.1, 0.05), pose(-0.1, 0.05)]
EMIT = [pose(0, 0), pose(3.5, 0.05), pose(3.6, 3.1), pose(0.15, 3.4), pose(0.4, 0.3), pose(0.2, 0.3)]
"""

HARNESS = """
import json, sys, threading, time
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

def spin(node):
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = threading.Event()
    def run():
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.02)
    th = threading.Thread(target=run, daemon=True)
    th.start()
    def halt():
        stop.set()
        th.join(5)
        ex.shutdown(timeout_sec=1.0)
    return halt

def wait_for(cond, timeout=60.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if cond():
            return True
        time.sleep(0.02)
    return False

def feed(node, kf):
    from msg_adapters.keyframe import keyframe_to_msgs
    add = node.keyframes_in.add if hasattr(node, "keyframes_in") else node._on_part   # the mapper: _on_part
    for part, m in keyframe_to_msgs(kf).as_dict().items():
        add(part, m)
"""

LOOP_SCRIPT = SCENE + HARNESS + """
import os
ck, out = sys.argv[1], sys.argv[2]
rclpy.init(args=["x", "--ros-args", "-p", "loop.min_gap_keyframes:=3", "-p", "loop.min_span_keyframes:=3",
                 "-p", "loop.min_spacing_keyframes:=1", "-p", "loop.vocabulary_after:=50", "-p", "loop.graph:=sim3",
                 "-p", "loop.confirmations:=1",
                 "-p", f"loop_closer_node.checkpoint_path:={ck}", "-p", f"loop_closer_node.output_dir:={out}",
                 "-p", "loop_closer_node.render_timeout_s:=20.0", "-p", "loop_closer_node.checkpoint_period_s:=0.0",
                 "-p", "ros.diagnostics_period_s:=0.2"])
from nav_msgs.msg import Path
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import Image
from msg_adapters import topics as T
from msg_adapters.exchange import exchange_topic, path_to_batch
from msg_adapters.loop import (LOOP_CONSTRAINTS_TOPIC, RENDER_REQUEST_TOPIC, REPLY_TOPICS, msg_to_render_request,
                               path_to_loop_constraint, render_reply_to_msgs)
from vings_ros.loop_closer_node import LoopCloserNode

class FakeMap(Node):
    # answers render requests with the plane rendered from the requested pose
    def __init__(self):
        super().__init__("fake_map")
        self.older_than, self.cameras = [], []
        self.pubs = {p: self.create_publisher(Image, t, T.sensor_qos(10)) for p, t in REPLY_TOPICS.items()}
        self.create_subscription(PoseStamped, RENDER_REQUEST_TOPIC, self.on_request, T.sensor_qos(10))
    def on_request(self, msg):
        req = msg_to_render_request(msg)
        self.older_than.append(req.older_than)
        self.cameras.append([req.camera.width, req.camera.height, req.camera.fx, req.camera.cx])
        color, depth = render_plane(req.T_wc, req.camera)
        out = {"color": color, "depth": depth, "alpha": np.ones(depth.shape, np.float32)}
        for p, m in render_reply_to_msgs(req.request_id, out).items():
            self.pubs[p].publish(m)

class Listener(Node):
    def __init__(self):
        super().__init__("listener")
        self.constraints, self.batches = [], []
        self.create_subscription(Path, LOOP_CONSTRAINTS_TOPIC, self.constraints.append, T.latched_qos(100))
        self.create_subscription(Path, exchange_topic("loop_closer"), self.batches.append, T.sensor_qos(100))

res = {}
node = LoopCloserNode()
fake, listener = FakeMap(), Listener()
halts = [spin(node), spin(fake), spin(listener)]
assert wait_for(lambda: node.count_subscribers(RENDER_REQUEST_TOPIC) > 0 and
                all(p.get_subscription_count() > 0 for p in fake.pubs.values()) and
                node.pub_constraints.get_subscription_count() > 0 and
                node.pub_exchange.get_subscription_count() > 0, 20)
for i in range(5):
    feed(node, keyframe(i, TRUE[i], EMIT[i]))
assert wait_for(lambda: node.keyframes_done == 5 and listener.constraints and listener.batches, 60), \\
    (node.keyframes_done, node.error)
res["checkpoint_after_loop"] = wait_for(lambda: node.checkpoints >= 1 and os.path.exists(ck), 20)
c = path_to_loop_constraint(listener.constraints[0])
res["constraint"] = {"older": c.older, "newer": c.newer, "t": c.T_on[:3, 3].tolist(), "scale": c.scale,
                     "figures": c.figures}
b = path_to_batch(listener.batches[0], "loop_closer")
res["batch"] = {"seq": b.seq, "stamps": sorted(b.increments), "acks": b.acks}
res["older_than"] = fake.older_than
res["cameras"] = fake.cameras
res["renders"] = dict(node.render_client.counts)
res["diag"] = {k: v for k, v in node.diagnostics().values.items() if k in ("loops_accepted", "keyframes", "metric")}
assert wait_for(lambda: node._reported_records == 3, 20)       # written after the loop's messages
res["loops_json"] = json.load(open(out + "/loops.json"))

# the map stops answering: a silent subscriber takes the requests, nothing replies
halts[1](); fake.destroy_node()
silent = Node("silent")
silent.create_subscription(PoseStamped, RENDER_REQUEST_TOPIC, lambda m: None, T.sensor_qos(10))
halts.append(spin(silent))
assert wait_for(lambda: node.count_subscribers(RENDER_REQUEST_TOPIC) > 0, 20)
node.settings.render_timeout_s = 1.0
t0 = time.time()
res["timeout_render"] = node.render_map(pose(0, 0), CAM, None)
res["timeout_s"] = time.time() - t0
feed(node, keyframe(5, TRUE[5], EMIT[5]))
assert wait_for(lambda: node.keyframes_done == 6, 60), (node.keyframes_done, node.error)
res["after_timeout"] = [r for r in node.closer.records if r["newer"] == 6 * 10**9]
res["error"] = repr(node.error) if node.error else None
res["timeouts"] = node.render_client.counts["timeouts"]
halts[0]()
node.shutdown()           # final checkpoint (the front end never answered: the correction is undone)
state = node.closer.state_dict()
node.destroy_node()

# a new node resumes the database from the checkpoint
node2 = LoopCloserNode()
state2 = node2.closer.state_dict()

def same(a, b):
    if isinstance(a, dict):
        return isinstance(b, dict) and set(map(str, a)) == set(map(str, b)) and all(
            same(a[k], b[k] if k in b else b[str(k)]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b))
    if isinstance(a, float) and a != a:
        return isinstance(b, float) and b != b
    return a == b

res["resumed_equal"] = same(state, state2)
res["resumed_keyframes"] = len(node2.closer.db)
halts.append(spin(node2))
feed(node2, keyframe(5, TRUE[5], EMIT[5]))         # the front end re-sends a keyframe the DB holds
assert wait_for(lambda: node2.keyframes_skipped == 1, 30)
res["resumed_done"] = node2.keyframes_done
for h in halts[1:]:
    h()
node2.shutdown()
node2.destroy_node(); listener.destroy_node(); silent.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""

MAPPER_SCRIPT = SCENE + HARNESS + """
rclpy.init(args=["x", "--ros-args", "-p", "mapper_node.checkpoint_period_s:=0.0", "-p", "mapper_node.nice:=0",
                 "-p", "mapping.iters_per_keyframe:=10", "-p", "mapping.points_per_keyframe:=500",
                 "-p", "loop.retrain_iters:=5", "-p", "loop_closer_node.render_timeout_s:=30.0"])
from nav_msgs.msg import Path
from msg_adapters.exchange import batch_to_path, exchange_topic
from msg_adapters.loop import RENDER_REQUEST_TOPIC
from msg_adapters import topics as T
from vings_core.exchange import IncrementBatch
from vings_core.geometry import sim3
from vings_core.types import CameraModel
from vings_ros.loop_closer_node import LoopCloserNode
from vings_ros.mapper_node import MapperNode

cam = CameraModel(64, 48, 40.0, 40.0, 31.5, 23.5)
res = {}
mapper, closer = MapperNode(), LoopCloserNode()
keeper = Node("keeper")
pub = keeper.create_publisher(Path, exchange_topic("frontend"), T.sensor_qos(100))
halts = [spin(mapper), spin(closer), spin(keeper)]
assert wait_for(lambda: closer.count_subscribers(RENDER_REQUEST_TOPIC) > 0 and
                pub.get_subscription_count() >= 2, 20)
# before any keyframe: the mapper answers at once that it has no map
t0 = time.time()
res["before"] = closer.render_map(pose(0, 0), cam, None)
res["before_s"] = time.time() - t0
res["before_empty"] = closer.render_client.counts["empty"]
feed(mapper, keyframe(0, TRUE[0], EMIT[0], cam))
assert wait_for(lambda: mapper.keyframes_mapped == 1, 120), mapper.error
T_req = pose(0.05, 0.02)
out = closer.render_map(T_req, cam, None)
direct = mapper.mapper.render(T_req, mapper.mapper.state.camera)    # the worker idles now
res["shapes"] = [list(out[k].shape) for k in ("color", "depth", "alpha")]
res["max_diff"] = max(float(np.abs(out[k] - direct[k]).max()) for k in ("color", "depth", "alpha"))
res["alpha_mean"] = float(out["alpha"].mean())
small = CameraModel(32, 24, 20.0, 20.0, 15.5, 11.5)
half = closer.render_map(T_req, small, None)        # the request's camera, not the mapper's
res["half_shape"] = list(half["color"].shape)
res["half_diff"] = float(np.abs(half["color"] - mapper.mapper.render(T_req, small)["color"]).max())
bounded = closer.render_map(T_req, cam, 10**9)       # only Gaussians of keyframes older than the first
res["bounded_alpha_max"] = float(bounded["alpha"].max())
res["answered"] = mapper.renders_answered
# a keeper batch that first acknowledges a loop-closer batch: the mapper retrains the region
C = sim3(np.eye(3), [0.01, 0.0, 0.0])
pub.publish(batch_to_path(IncrementBatch("frontend", 5 * 10**9, {10**9: C}, {"loop_closer": 7})))
assert wait_for(lambda: mapper.retrains, 60), mapper.error
res["retrains"] = len(mapper.retrains)
res["retrain_iters"] = mapper.retrains[0]["retrain_iters"]
res["pose_moved"] = float(mapper.mapper.keyframe_poses()[10**9][0, 3])
res["errors"] = [repr(n.error) for n in (mapper, closer) if n.error]
for h in halts:
    h()
mapper.shutdown(); closer.shutdown()
for n in (mapper, closer, keeper):
    n.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def _run(script: str, *args: str, offset: int = 0) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(200 + (os.getpid() + offset) % 30),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONPATH=str(REPO))
    from vings_ros.ros_env import cleanup_fastdds_shm, shm_snapshot
    snap = shm_snapshot()
    try:
        p = subprocess.run([sys.executable, "-c", textwrap.dedent(script), *args], env=env, cwd=REPO,
                           capture_output=True, text=True, timeout=240)
    finally:
        cleanup_fastdds_shm(snap)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    assert p.returncode == 0 and lines, f"child failed (rc {p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-4000:]}"
    return json.loads(lines[-1][len("RESULT "):])


# ------------------------------------------------------------------------------------- adapters


def test_loop_messages_round_trip_exactly():
    from geometry_msgs.msg import PoseStamped

    from msg_adapters.loop import (REPLY_PARTS, LoopConstraint, RenderReplyAssembler, RenderRequest,
                                   color32_to_msg, loop_constraint_to_path, msg_to_color32, msg_to_render_request,
                                   path_to_loop_constraint, render_reply_to_msgs, render_request_to_msg)
    from msg_adapters.pose import matrix_to_pose
    from msg_adapters.stamps import make_header
    from vings_core.errors import InputError
    from vings_core.geometry import np_quat_to_rotmat, sim3
    from vings_core.types import CameraModel

    rng = np.random.default_rng(3)

    def rot():
        q = rng.normal(size=4)
        return np_quat_to_rotmat(q / np.linalg.norm(q))

    # render request: id, pose, the optional bound
    T = sim3(rot(), rng.normal(size=3))
    for older in (None, 1_700_000_000_123_456_789, -5):
        msg = render_request_to_msg(RenderRequest(1_700_000_000_987_654_321, T, older))
        back = msg_to_render_request(msg)
        assert back.request_id == 1_700_000_000_987_654_321 and back.older_than == older
        assert np.abs(back.T_wc - T).max() < 1e-12
    assert render_request_to_msg(RenderRequest(5, T, 7)).header.frame_id == "map;older_than=7"
    cam = CameraModel(160, 120, 100.123456789, 99.5, 79.5, 59.25)
    back = msg_to_render_request(render_request_to_msg(RenderRequest(9, T, None, cam)))
    assert back.older_than is None and back.camera == cam
    with pytest.raises(InputError, match="undistorted"):
        render_request_to_msg(RenderRequest(9, T, None, CameraModel(8, 6, 5.0, 5.0, 4.0, 3.0, "radtan",
                                                                    [0.1, 0, 0, 0])))
    for frame_id, match in (("map;older=7", "unknown key"), ("map;older_than=x", "integer"),
                            ("map;older_than", "key=value"), (";older_than=3", "frame id"),
                            ("map;width=8;height=6", "needs all"),
                            ("map;width=8;height=6;fx=0;fy=5;cx=4;cy=3", "fx, fy > 0")):
        bad = PoseStamped(header=make_header(5, frame_id), pose=matrix_to_pose(T))
        with pytest.raises(InputError, match=match):
            msg_to_render_request(bad)
    with pytest.raises(InputError, match="request id"):
        msg_to_render_request(PoseStamped(header=make_header(0, "map"), pose=matrix_to_pose(T)))

    # reply: three images with the id, bit-exact floats, parts in any order
    out = {"color": rng.random((5, 7, 3), dtype=np.float32), "depth": rng.random((5, 7), dtype=np.float32) * 4,
           "alpha": rng.random((5, 7), dtype=np.float32)}
    msgs = render_reply_to_msgs(42, out, "cam")
    assert msgs["color"].encoding == "32FC3" and msgs["depth"].encoding == "32FC1"
    asm = RenderReplyAssembler()
    assert asm.add("depth", msgs["depth"]) is None and asm.add("color", msgs["color"]) is None
    reply = asm.add("alpha", msgs["alpha"])
    assert reply.request_id == 42 and not reply.empty and asm.pending == 0
    for k in REPLY_PARTS:
        assert np.array_equal(getattr(reply, k), out[k]) and getattr(reply, k).dtype == np.float32
    # the "no map" reply
    asm = RenderReplyAssembler()
    empty = [asm.add(p, m) for p, m in render_reply_to_msgs(43, None).items()][-1]
    assert empty.request_id == 43 and empty.empty and empty.as_dict() is None
    # 32FC3 big-endian with row padding reads back too; sizes and ids must agree
    c = out["color"]
    be = color32_to_msg(c, 1, "cam")
    rows = c.astype(">f4").reshape(5, 21).view(np.uint8).reshape(5, 84)
    be.data = np.concatenate([rows, np.zeros((5, 4), np.uint8)], 1).tobytes()
    be.is_bigendian, be.step = 1, 88
    assert np.array_equal(msg_to_color32(be), c)
    be.step = 80
    with pytest.raises(InputError, match="step"):
        msg_to_color32(be)
    odd = render_reply_to_msgs(44, {k: v[:4] for k, v in out.items()})
    asm = RenderReplyAssembler()
    asm.add("color", msgs["color"])
    asm.add("depth", msgs["depth"])
    odd["alpha"].header = msgs["alpha"].header
    with pytest.raises(InputError, match="sizes"):
        asm.add("alpha", odd["alpha"])

    # loop constraint: stamps, T_on (rotation, translation, scale), the older pose, the figures
    T_on = sim3(rot(), rng.normal(size=3) * 0.3, 1.2345678901234567)
    T_wo = sim3(rot(), rng.normal(size=3) * 5)
    fig = {"matches": 587, "inliers": 582, "render_l1": 0.0010923456789, "coverage": 1.0, "graph": "sim3",
           "sources": "radius+retrieval", "moved": 4}
    c = LoopConstraint(1_000_000_001, 5_000_000_002, T_on, T_wo, fig)
    path = loop_constraint_to_path(c)
    assert [p.header.frame_id.split(";")[0] for p in path.poses] == ["map", "map"]
    back = path_to_loop_constraint(path)
    assert (back.older, back.newer) == (1_000_000_001, 5_000_000_002)
    assert back.scale == pytest.approx(c.scale, abs=1e-15)
    assert np.abs(back.T_on - T_on).max() < 1e-12 and np.abs(back.T_wc_older - T_wo).max() < 1e-12
    assert back.figures == fig and isinstance(back.figures["matches"], int)
    path.poses[1].header.frame_id = "map;matches=3"
    with pytest.raises(InputError, match="scale"):
        path_to_loop_constraint(path)
    path.poses.pop()
    with pytest.raises(InputError, match="2 poses"):
        path_to_loop_constraint(path)


def test_loop_checkpoint_file_round_trips_the_closer_state(tmp_path):
    import types

    from vings_core.errors import ConfigError
    from vings_core.loop import LoopCloser, LoopConfig
    from vings_ros.loop_closer_node import load_loop_state, save_loop_state

    scene = types.ModuleType("scene")
    exec(SCENE, scene.__dict__)
    cfg = LoopConfig(min_gap_keyframes=3, min_span_keyframes=3, vocabulary_after=3, vocabulary_words=16,
                     graph="sim3", confirmations=1)

    def render(T, cam, older):
        color, depth = scene.render_plane(T, cam)
        return {"color": color, "depth": depth, "alpha": np.ones(depth.shape, np.float32)}

    lc = LoopCloser(cfg, render=render)
    for i in range(5):
        lc.add_keyframe(scene.keyframe(i, scene.TRUE[i], scene.EMIT[i]))
    assert lc.loops and lc.db.vocabulary is not None
    st = lc.state_dict()
    f = tmp_path / "loop.ckpt"
    save_loop_state(f, st, cfg)
    lc2 = LoopCloser(cfg)
    lc2.load_state_dict(load_loop_state(f, cfg))
    st2 = lc2.state_dict()
    for k, v in st["db"].items():
        assert np.array_equal(v, st2["db"][k]) and v.dtype == st2["db"][k].dtype, k
    assert [e.bow.tolist() for e in lc.db.entries] == [e.bow.tolist() for e in lc2.db.entries]
    assert json.dumps(st["records"]) == json.dumps(st2["records"])
    assert json.dumps(st["corrections"]) == json.dumps(st2["corrections"]) and st["stats"] == st2["stats"]
    assert len(st2["loops"]) == 1 and np.array_equal(st["loops"][0]["T_on"], st2["loops"][0]["T_on"])
    assert {k: v for k, v in st["loops"][0].items() if k != "T_on"} == \
        {k: v for k, v in st2["loops"][0].items() if k != "T_on"}
    fs, fs2 = st["follower"], st2["follower"]
    assert (fs["seq"], fs["seen"]) == (fs2["seq"], fs2["seen"]) and fs["seq"] > 0
    assert sorted(fs["keeper"]) == sorted(fs2["keeper"])
    assert all(np.array_equal(fs["keeper"][s], fs2["keeper"][s]) for s in fs["keeper"])
    # other features, or a foreign file: one error naming the file
    with pytest.raises(ConfigError, match="orb features but loop.features is sift"):
        load_loop_state(f, LoopConfig(features="sift"))
    (tmp_path / "junk").write_text("not a checkpoint")
    with pytest.raises(ConfigError, match="junk: not a loop closer checkpoint"):
        load_loop_state(tmp_path / "junk", cfg)


# ----------------------------------------------------------------------------------- the nodes


def test_loop_closer_node_closes_a_loop_survives_a_silent_map_and_resumes(tmp_path):
    ck, out = tmp_path / "loop.ckpt", tmp_path / "out"
    res = _run(LOOP_SCRIPT, str(ck), str(out))
    # the loop 1 s -> 5 s was found with the fake map's render, corrected and published
    c = res["constraint"]
    assert (c["older"], c["newer"]) == (10**9, 5 * 10**9)
    assert np.allclose(c["t"], [0.1, 0.05, 0.0], atol=0.01) and c["scale"] == pytest.approx(1.0, abs=0.01)
    assert c["figures"]["graph"] == "sim3" and c["figures"]["matches"] >= 50
    assert c["figures"]["render_l1"] < 0.05 and c["figures"]["moved"] == 4
    assert res["batch"]["stamps"] == [2 * 10**9, 3 * 10**9, 4 * 10**9, 5 * 10**9]
    assert res["batch"]["acks"] == {"frontend": 0}
    # renders ask for the Gaussians of keyframes at least min_gap older than keyframe 4: up to
    # keyframe 1 (stamp 2 s) included
    assert res["older_than"] == [2 * 10**9 + 1]
    # at the check's camera: half the keyframes' resolution (loop.render_downscale 2)
    assert res["cameras"] == [[160, 120, 100.0, 79.5]]
    assert res["renders"]["answered"] == 1 and res["renders"]["timeouts"] == 0
    assert res["diag"] == {"keyframes": 5, "loops_accepted": 1, "metric": False}
    assert res["checkpoint_after_loop"]
    lj = res["loops_json"]
    assert set(lj) == {"candidates", "corrections", "summary"}
    assert [r["verdict"] for r in lj["candidates"]] == ["rejected", "accepted", "rejected"]
    assert lj["summary"]["loops_accepted"] == 1 and lj["corrections"][0]["newer"] == 5 * 10**9
    # nobody answers: the render is None after the timeout, the candidate is rejected, the node goes on
    assert res["timeout_render"] is None and 0.9 <= res["timeout_s"] < 5
    assert res["error"] is None and res["timeouts"] >= 2
    kf0 = [r for r in res["after_timeout"] if r["older"] == 10**9]
    assert kf0 and kf0[0]["verdict"] == "rejected" and kf0[0]["reason"] == "no map to render"
    assert kf0[0]["inliers"] >= 30      # it passed PnP: only the render was missing
    # resumed from the checkpoint: the same database, loops, records and exchange state
    assert res["resumed_equal"] and res["resumed_keyframes"] == 6 and res["resumed_done"] == 0


def test_mapper_node_answers_render_requests_and_retrains_after_a_loop():
    res = _run(MAPPER_SCRIPT, offset=7)
    assert res["errors"] == []
    # no keyframe yet: an empty reply, at once (no timeout)
    assert res["before"] is None and res["before_empty"] == 1 and res["before_s"] < 5
    # the reply is the mapper's own render from the requested pose with its camera
    assert res["shapes"] == [[48, 64, 3], [48, 64], [48, 64]]
    assert res["max_diff"] < 1e-6 and res["alpha_mean"] > 0.3
    # older_than = the first keyframe's stamp: none of its Gaussians
    assert res["bounded_alpha_max"] == 0.0
    assert res["half_shape"] == [24, 32, 3] and res["half_diff"] < 1e-6
    assert res["answered"] == 4
    # the keeper batch acknowledging loop-closer batch 7 moved the keyframe and started one retrain
    assert res["retrains"] == 1 and res["retrain_iters"] == 5
    assert res["pose_moved"] == pytest.approx(0.01, abs=1e-9)


def fake_launcher(monkeypatch) -> tuple[list, type]:
    """``vings launch`` without starting anything: ``(the Launcher options each call made, the real
    Launcher)``."""
    from vings_ros import launch

    seen = []
    real = launch.Launcher

    class FakeLauncher:
        def __init__(self, opt):
            seen.append(opt)

        def run(self):
            return 0

    monkeypatch.setattr(launch, "Launcher", FakeLauncher)
    return seen, real


def test_vings_launch_no_loop_leaves_the_loop_closer_out(monkeypatch, tmp_path):
    from vings_ros import cli
    from vings_ros.launch import default_nodes

    assert default_nodes() == ("frontend_node", "mapper_node", "loop_closer_node", "eraser_node")
    seen, real = fake_launcher(monkeypatch)
    ck = tmp_path / "map.ckpt"
    assert cli.main(["launch", "--no-loop", "--checkpoint", str(ck)]) == 0
    assert seen[-1].nodes == ("frontend_node", "mapper_node", "eraser_node")
    assert seen[-1].extra_params["loop.enabled"] == "false"
    assert "loop_closer_node.checkpoint_path" not in seen[-1].extra_params
    assert cli.main(["launch", "--checkpoint", str(ck)]) == 0
    assert seen[-1].nodes is None and "loop.enabled" not in seen[-1].extra_params
    assert seen[-1].extra_params["loop_closer_node.checkpoint_path"] == str(ck.resolve()) + ".loop"
    checked = real(seen[-1])        # the parameters pass the launcher's checks (nothing started)
    assert checked.nodes == ["frontend_node", "mapper_node", "loop_closer_node", "eraser_node"]
    assert checked.stop_timeout["loop_closer_node"] == 60.0
    assert cli.main(["launch", "--no-loop", "--no-mapper", "--no-eraser"]) == 0
    assert seen[-1].nodes == ("frontend_node",)
