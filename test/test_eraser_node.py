"""The dynamic eraser in the node graph: its message (msg_adapters/eraser.py), eraser_node with a
fake map answering its render requests, mapper_node waiting for the masks (and not waiting without
an eraser), the front end taking them, and ``vings launch --no-eraser``.

The node cases run in a child process (own rclpy context, unique ROS domain, localhost only), one
SingleThreadedExecutor per node on its own thread, on the textured plane of
test_loop_closer_node.py with a red box pasted into the keyframes (the moving object: the map
does not hold it).
"""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy")

from test_loop_closer_node import HARNESS, SCENE, _run, fake_launcher  # noqa: E402

pytestmark = pytest.mark.ros

BOX = SCENE + """
def box_keyframe(i, T, cam, x0=None):
    # keyframe i seen from T with a red box (not in the map) at columns x0.. of rows H/3..2H/3
    kf = keyframe(i, T, T, cam)
    img = kf.image.numpy().copy()
    h, w = cam.height, cam.width
    x0 = w * 3 // 8 if x0 is None else x0
    img[h // 3: 2 * h // 3, x0: x0 + w // 4] = np.array([1.0, 0.2, 0.1], np.float32)
    # the front end's depth is uncertain on an object that moves against the scene (its flow
    # disagrees with the BA): the paper's Sigma term weighs those pixels more
    var = kf.inv_depth_var.clone()
    var[h // 3: 2 * h // 3, x0: x0 + w // 4] *= 5.0
    return Keyframe(kf.stamp_ns, torch.from_numpy(img), kf.T_wc, kf.depth, var, kf.valid, cam, i)

def box_region(cam, x0=None):
    h, w = cam.height, cam.width
    x0 = w * 3 // 8 if x0 is None else x0
    m = np.zeros((h, w), bool)
    m[h // 3: 2 * h // 3, x0: x0 + w // 4] = True
    return m
"""

ERASER_SCRIPT = BOX + HARNESS + """
rclpy.init(args=["x", "--ros-args", "-p", "eraser_node.nice:=0", "-p", "eraser_node.render_timeout_s:=20.0",
                 "-p", "ros.diagnostics_period_s:=0.2"])
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import Image
from msg_adapters import topics as T
from msg_adapters.eraser import msg_to_mask
from msg_adapters.loop import REPLY_TOPICS, RENDER_REQUEST_TOPIC, msg_to_render_request, render_reply_to_msgs
from vings_ros.eraser_node import EraserNode

cam = CameraModel(160, 120, 100.0, 100.0, 79.5, 59.5)

class FakeMap(Node):
    # answers render requests with the plane (without the box) rendered from the requested pose
    def __init__(self):
        super().__init__("fake_map")
        self.requests = []
        self.pubs = {p: self.create_publisher(Image, t, T.sensor_qos(10)) for p, t in REPLY_TOPICS.items()}
        self.create_subscription(PoseStamped, RENDER_REQUEST_TOPIC, self.on_request, T.sensor_qos(10))
    def on_request(self, msg):
        req = msg_to_render_request(msg)
        self.requests.append({"older_than": req.older_than, "t": req.T_wc[:3, 3].tolist(),
                              "camera": [req.camera.width, req.camera.height, req.camera.fx, req.camera.cx]})
        color, depth = render_plane(req.T_wc, req.camera)
        out = {"color": color, "depth": depth, "alpha": np.ones(depth.shape, np.float32)}
        for p, m in render_reply_to_msgs(req.request_id, out).items():
            self.pubs[p].publish(m)

class Listener(Node):
    def __init__(self):
        super().__init__("listener")
        self.masks = []
        self.create_subscription(Image, T.DYNAMIC_MASK_TOPIC, lambda m: self.masks.append(msg_to_mask(m)),
                                 T.sensor_qos(40))

res = {}
node = EraserNode()
fake, listener = FakeMap(), Listener()
halts = [spin(node), spin(fake), spin(listener)]
assert wait_for(lambda: node.count_subscribers(RENDER_REQUEST_TOPIC) > 0 and
                all(p.get_subscription_count() > 0 for p in fake.pubs.values()) and
                node.pub_mask.get_subscription_count() > 0, 20)
T0 = pose(0.0, 0.0)
feed(node, box_keyframe(0, T0, cam))
assert wait_for(lambda: len(listener.masks) == 1, 60), (node.error, node.render_client.counts)
stamp, mask = listener.masks[0]
box = box_region(cam)
res["stamp"] = stamp
res["shape"] = list(mask.shape)
res["in_box"] = float(mask[box].mean())
res["outside"] = float(mask[~box].mean())
res["requests"] = fake.requests
st = node.diagnostics()
res["level"], res["message"] = st.level.value, st.message
res["values"] = {k: st.values[k] for k in ("masks_published", "masks_dynamic", "render_requests", "render_answered",
                                           "processed_without_render", "render_timeouts")}
res["fraction_mean"] = st.values["masked_fraction_mean"]

# the map stops answering: the next keyframe is processed without a render (motion cue only)
halts[1](); fake.destroy_node()
silent = Node("silent")
silent.create_subscription(PoseStamped, RENDER_REQUEST_TOPIC, lambda m: None, T.sensor_qos(10))
halts.append(spin(silent))
assert wait_for(lambda: node.count_subscribers(RENDER_REQUEST_TOPIC) > 0, 20)
node.settings.render_timeout_s = 0.5
feed(node, box_keyframe(1, pose(0.05, 0.0), cam))
assert wait_for(lambda: len(listener.masks) == 2, 60), (node.error, node.render_client.counts)
res["stamp2"] = listener.masks[1][0]
st = node.diagnostics()
res["level2"], res["message2"] = st.level.value, st.message
res["values2"] = {k: st.values[k] for k in ("masks_published", "render_timeouts", "processed_without_render")}
res["error"] = repr(node.error) if node.error else None
for h in halts:
    h()
node.shutdown()
for n in (node, listener, silent):
    n.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""

MAPPER_SCRIPT = BOX + HARNESS + """
rclpy.init(args=["x", "--ros-args", "-p", "mapper_node.checkpoint_period_s:=0.0", "-p", "mapper_node.nice:=0",
                 "-p", "mapping.iters_per_keyframe:=10", "-p", "mapping.points_per_keyframe:=500",
                 "-p", "eraser_node.nice:=0", "-p", "eraser_node.render_timeout_s:=20.0",
                 "-p", "eraser.mask_timeout_s:=20.0"])
from sensor_msgs.msg import Image
from msg_adapters import topics as T
from msg_adapters.eraser import mask_to_msg
from msg_adapters.loop import RENDER_REQUEST_TOPIC
from vings_ros.eraser_node import EraserNode
from vings_ros.mapper_node import MapperNode

cam = CameraModel(64, 48, 40.0, 40.0, 31.5, 23.5)
res = {}
mapper, eraser = MapperNode(), EraserNode()
halts = [spin(mapper), spin(eraser)]
assert wait_for(lambda: mapper.count_publishers(T.DYNAMIC_MASK_TOPIC) > 0 and
                eraser.count_subscribers(RENDER_REQUEST_TOPIC) > 0, 20)

def both(kf):
    feed(mapper, kf)
    feed(eraser, kf)

# with the eraser: each keyframe waits for its mask; the eraser's render comes before the add
for i in range(2):
    both(box_keyframe(i, pose(0.02 * i, 0.0), cam))
    assert wait_for(lambda: mapper.keyframes_mapped == i + 1, 120), (mapper.error, eraser.error)
res["with_eraser"] = {k: mapper.diagnostics().values[k] for k in ("keyframes_with_mask", "keyframes_without_mask",
                                                                    "masks_late", "renders_answered")}
res["eraser"] = {"masks": eraser.masks_published, "answered": eraser.render_client.counts["answered"],
                 "empty": eraser.render_client.counts["empty"], "after_mapped": eraser.renders_after_mapped}
res["level_with"] = mapper.diagnostics().level.value

# the eraser goes silent (a mask publisher that never publishes): the mapper waits its timeout
halts[1](); eraser.shutdown(); eraser.destroy_node()
silent = Node("silent_eraser")
pub = silent.create_publisher(Image, T.DYNAMIC_MASK_TOPIC, T.sensor_qos(40))
halts.append(spin(silent))
assert wait_for(lambda: pub.get_subscription_count() > 0 and mapper.count_publishers(T.DYNAMIC_MASK_TOPIC) == 1, 20)
mapper.ecfg.mask_timeout_s = 1.0
kf2 = box_keyframe(2, pose(0.04, 0.0), cam)
t0 = time.time()
feed(mapper, kf2)
assert wait_for(lambda: mapper.keyframes_mapped == 3, 120), mapper.error
res["timeout_map_s"] = time.time() - t0
st = mapper.diagnostics()
res["timeout"] = {"level": st.level.value, "message": st.message,
                  **{k: st.values[k] for k in ("keyframes_with_mask", "keyframes_without_mask", "mask_wait_ms_max")}}
# its mask comes late: applied to the mapped keyframe (set_dynamic_mask)
pub.publish(mask_to_msg(box_region(cam), kf2.stamp_ns))
assert wait_for(lambda: mapper.masks_late == 1, 30), mapper.error
res["late_dynamic"] = bool(mapper.mapper.state.window[-1].dynamic is not None and
                           mapper.mapper.state.window[-1].dynamic.any())

# eraser.enabled false (vings launch --no-eraser): no wait, even with a mask publisher present
mapper.ecfg.enabled = False
waits = mapper.mask_waits
t0 = time.time()
feed(mapper, box_keyframe(3, pose(0.06, 0.0), cam))
assert wait_for(lambda: mapper.keyframes_mapped == 4, 120), mapper.error
res["disabled"] = {"waits": mapper.mask_waits - waits, "s": time.time() - t0,
                   "without": mapper.keyframes_without_mask}
res["errors"] = [repr(n.error) for n in (mapper,) if n.error]
for h in halts[:1] + halts[2:]:
    h()
mapper.shutdown()
mapper.destroy_node(); silent.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


# ------------------------------------------------------------------------------------- adapters


def test_dynamic_mask_message_round_trips():
    from sensor_msgs.msg import Image

    from msg_adapters import topics as T
    from msg_adapters.eraser import DYNAMIC_MASK_TOPIC, mask_to_msg, msg_to_mask
    from msg_adapters.image import array_to_msg
    from vings_core.eraser.mask_io import mask_to_mono8
    from vings_core.errors import InputError

    assert DYNAMIC_MASK_TOPIC == T.DYNAMIC_MASK_TOPIC == "/vings/keyframe/dynamic_mask"
    rng = np.random.default_rng(4)
    mask = rng.random((7, 11)) > 0.6
    msg = mask_to_msg(mask, 1_700_000_000_123_456_789, "cam")
    assert (msg.encoding, msg.width, msg.height, msg.step, msg.is_bigendian) == ("mono8", 11, 7, 11, 0)
    assert msg.header.frame_id == "cam"
    assert set(np.frombuffer(msg.data, np.uint8).tolist()) == {0, 255}
    stamp, back = msg_to_mask(msg)
    assert stamp == 1_700_000_000_123_456_789 and back.dtype == bool and np.array_equal(back, mask)
    # torch masks too; empty masks travel (the mapper waits for them)
    import torch
    assert np.array_equal(msg_to_mask(mask_to_msg(torch.from_numpy(mask), 5))[1], mask)
    assert not msg_to_mask(mask_to_msg(np.zeros((3, 4), bool), 6))[1].any()
    # on input: > 127 is dynamic, row padding honoured
    vals = np.array([[0, 127, 128, 255]], np.uint8)
    padded = array_to_msg(vals, 7, "cam")
    padded.data = np.concatenate([vals, np.full((1, 4), 9, np.uint8)], 1).tobytes()
    padded.step = 8
    assert msg_to_mask(padded)[1].tolist() == [[False, False, True, True]]
    # refused, naming the topic
    with pytest.raises(InputError, match="dynamic_mask.*mono8"):
        msg_to_mask(array_to_msg(mask_to_mono8(mask)[..., None].repeat(3, 2), 8, "cam"))
    with pytest.raises(InputError, match="at least one pixel"):
        msg_to_mask(Image(encoding="mono8"))
    with pytest.raises(InputError, match="bool"):
        mask_to_msg(mask.astype(np.uint8), 9)
    bad = mask_to_msg(mask, 10)
    bad.step = 10
    with pytest.raises(InputError, match="dynamic_mask"):
        msg_to_mask(bad)


# ----------------------------------------------------------------------------------- the nodes


def test_eraser_node_masks_a_keyframe_from_the_maps_render_and_goes_on_without_one():
    res = _run(ERASER_SCRIPT, offset=11)
    assert res["error"] is None
    # the render was asked for the keyframe's pose, camera and the Gaussians older than it
    assert len(res["requests"]) == 1
    rq = res["requests"][0]
    assert rq["older_than"] == 10**9 and rq["camera"] == [160, 120, 100.0, 79.5] and rq["t"] == [0.0, 0.0, 0.0]
    # the mask carries the keyframe's stamp and covers the box the map does not hold
    assert res["stamp"] == 10**9 and res["shape"] == [120, 160]
    assert res["in_box"] > 0.9 and res["outside"] < 0.05
    assert res["values"] == {"masks_published": 1, "masks_dynamic": 1, "render_requests": 1, "render_answered": 1,
                             "processed_without_render": 0, "render_timeouts": 0}
    assert res["level"] == "ok" and 0.05 < res["fraction_mean"] < 0.2
    # nobody answers: processed with the motion cue only, a mask all the same, a warning
    assert res["stamp2"] == 2 * 10**9
    assert res["values2"] == {"masks_published": 2, "render_timeouts": 1, "processed_without_render": 1}
    assert res["level2"] == "warn" and "motion cue only" in res["message2"]


def test_mapper_node_waits_for_the_mask_and_maps_without_it_after_the_timeout():
    res = _run(MAPPER_SCRIPT, offset=13)
    assert res["errors"] == []
    # with the eraser running, every keyframe was mapped with its mask, the render answered before
    # the keyframe was added (the first one: no map yet)
    assert res["with_eraser"]["keyframes_with_mask"] == 2 and res["with_eraser"]["keyframes_without_mask"] == 0
    assert res["eraser"]["masks"] == 2 and res["eraser"]["answered"] == 2 and res["eraser"]["empty"] == 1
    assert res["eraser"]["after_mapped"] == 0 and res["level_with"] == "ok"
    # no mask within eraser.mask_timeout_s: mapped without, reported as a warning
    t = res["timeout"]
    assert t["keyframes_without_mask"] == 1 and t["keyframes_with_mask"] == 2
    assert t["level"] == "warn" and "did not come within eraser.mask_timeout_s" in t["message"]
    assert 950 <= t["mask_wait_ms_max"] < 5000 and res["timeout_map_s"] >= 0.95
    # the late mask reached the mapped keyframe
    assert res["late_dynamic"]
    # eraser.enabled false: no wait at all
    assert res["disabled"]["waits"] == 0 and res["disabled"]["without"] == 1


def test_vings_launch_no_eraser_leaves_the_eraser_out(monkeypatch):
    from vings_ros import cli, registry
    from vings_ros.launch import default_nodes
    from vings_ros.recorder import OUTPUT_TOPICS

    assert default_nodes() == ("frontend_node", "mapper_node", "loop_closer_node", "eraser_node")
    assert registry.node_spec("eraser_node").optional
    assert "eraser_node = vings_ros.eraser_node:main" in registry.console_scripts()
    assert ("/vings/keyframe/dynamic_mask", "sensor_msgs/msg/Image", False) in OUTPUT_TOPICS
    seen, real = fake_launcher(monkeypatch)
    assert cli.main(["launch", "--no-eraser"]) == 0
    assert seen[-1].nodes == ("frontend_node", "mapper_node", "loop_closer_node")
    assert seen[-1].extra_params["eraser.enabled"] == "false"
    checked = real(seen[-1])        # the parameters pass the launcher's checks (nothing started)
    assert checked.nodes == ["frontend_node", "mapper_node", "loop_closer_node"]
    assert cli.main(["launch"]) == 0
    assert seen[-1].nodes is None and "eraser.enabled" not in seen[-1].extra_params
    assert real(seen[-1]).nodes == ["frontend_node", "mapper_node", "loop_closer_node", "eraser_node"]
    assert cli.main(["launch", "--no-eraser", "--no-loop"]) == 0
    assert seen[-1].nodes == ("frontend_node", "mapper_node")


def test_front_end_node_posts_the_masks_to_the_front_end():
    """frontend_node's mask callback (no ROS context needed: a stand-in node): a mask of the
    working size goes to ``Frontend.post_dynamic_mask``, an empty one is not posted, a mask of
    another size or before the camera is known is counted, a malformed message too."""
    import logging
    import types

    from msg_adapters.eraser import mask_to_msg
    from vings_core.types import CameraModel
    from vings_ros.frontend_node import FrontendNode

    posted = []
    node = types.SimpleNamespace(masks_received=0, masks_unused=0, bad_masks=0, frontend=None, undist=None,
                                 get_logger=lambda: logging.getLogger("test"))
    mask = np.zeros((48, 64), bool)
    mask[10:20, 30:40] = True
    FrontendNode._on_mask(node, mask_to_msg(mask, 5))
    assert (node.masks_received, node.masks_unused, posted) == (1, 1, [])
    node.frontend = types.SimpleNamespace(post_dynamic_mask=lambda s, m: posted.append((s, m)))
    node.undist = types.SimpleNamespace(camera=CameraModel(64, 48, 40.0, 40.0, 31.5, 23.5))
    FrontendNode._on_mask(node, mask_to_msg(mask, 7))
    FrontendNode._on_mask(node, mask_to_msg(np.zeros((48, 64), bool), 8))
    FrontendNode._on_mask(node, mask_to_msg(mask[:40], 9))
    bad = mask_to_msg(mask, 10)
    bad.encoding = "rgb8"
    FrontendNode._on_mask(node, bad)
    assert [s for s, _ in posted] == [7] and np.array_equal(posted[0][1], mask)
    assert (node.masks_received, node.masks_unused, node.bad_masks) == (4, 1, 2)
