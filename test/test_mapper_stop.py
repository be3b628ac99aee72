"""mapper_node stopped with keyframes still queued (on_stop store, a checkpoint set): the stop takes
seconds, the queued keyframes are stored beside the checkpoint, and a resumed mapper maps them all.
Child process with its own rclpy context, as in test_loop_closer_node.py."""
from __future__ import annotations

import pytest

pytest.importorskip("rclpy")

from test_loop_closer_node import HARNESS, SCENE, _run  # noqa: E402

pytestmark = pytest.mark.ros

SCRIPT = SCENE + HARNESS + """
ck = sys.argv[1]
rclpy.init(args=["x", "--ros-args", "-p", "mapper_node.checkpoint_period_s:=0.0", "-p", "mapper_node.nice:=0",
                 "-p", f"mapper_node.checkpoint_path:={ck}", "-p", "mapper_node.render_every_keyframes:=0",
                 "-p", "mapping.iters_per_keyframe:=400", "-p", "mapping.points_per_keyframe:=500",
                 "-p", "eraser.enabled:=false", "-p", "loop.enabled:=false"])
from vings_core.mapping import Mapper
from vings_ros.mapper_node import MapperNode

cam = CameraModel(64, 48, 40.0, 40.0, 31.5, 23.5)
kfs = [keyframe(i, pose(0.03 * i, 0.0), pose(0.03 * i, 0.0), cam) for i in range(5)]
res = {}
node = MapperNode()
halt = spin(node)
for kf in kfs:
    feed(node, kf)
assert wait_for(lambda: node._busy, 60), node.error
halt()
t0 = time.time()
node.shutdown()
res["stop_s"] = time.time() - t0
node.destroy_node()
res["in_checkpoint"] = len(Mapper.load_checkpoint(ck).keyframe_poses())
import glob
res["stored"] = len(glob.glob(ck + ".queue/*"))

# the resumed mapper maps what was stored
node2 = MapperNode()
halt2 = spin(node2)
ok = wait_for(lambda: len(node2.mapper.keyframe_poses()) == 5, 300)
res["resumed_all"] = ok
res["resumed_kf"] = len(node2.mapper.keyframe_poses())
halt2()
node2.settings.on_stop = type(node2.settings.on_stop)("train")
node2.shutdown()
node2.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_stop_stores_queued_keyframes_and_the_resumed_mapper_maps_them(tmp_path):
    res = _run(SCRIPT, str(tmp_path / "map.ckpt"), offset=11)
    assert res["stop_s"] < 10.0, res
    assert res["in_checkpoint"] >= 1 and res["in_checkpoint"] + res["stored"] == 5, res
    assert res["stored"] >= 1, res                 # something was still queued at the stop
    assert res["resumed_all"], res


HURRY = SCENE + HARNESS + """
ck = sys.argv[1]
rclpy.init(args=["x", "--ros-args", "-p", "mapper_node.checkpoint_period_s:=0.0", "-p", "mapper_node.nice:=0",
                 "-p", f"mapper_node.checkpoint_path:={ck}", "-p", "mapper_node.render_every_keyframes:=0",
                 "-p", "mapper_node.on_stop:=train", "-p", "mapper_node.shutdown_timeout_s:=600.0",
                 "-p", "mapping.iters_per_keyframe:=400", "-p", "mapping.points_per_keyframe:=500",
                 "-p", "eraser.enabled:=false", "-p", "loop.enabled:=false"])
from vings_core.mapping import Mapper
from vings_ros.mapper_node import MapperNode

cam = CameraModel(64, 48, 40.0, 40.0, 31.5, 23.5)
node = MapperNode()
halt = spin(node)
for i in range(6):
    feed(node, keyframe(i, pose(0.03 * i, 0.0), pose(0.03 * i, 0.0), cam))
assert wait_for(lambda: node._busy, 60), node.error
halt()
res = {}
t0 = time.time()
th = threading.Thread(target=node.shutdown)
th.start()
time.sleep(1.0)                 # mapping the queue (on_stop train) ...
res["still_draining"] = th.is_alive()
t1 = time.time()
node.hurry()                    # ... a second Ctrl-C
th.join(60)
res["after_hurry_s"] = time.time() - t1
res["mapped"] = len(Mapper.load_checkpoint(ck).keyframe_poses())
import glob
res["stored"] = len(glob.glob(ck + ".queue/*"))
node.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_a_second_stop_request_skips_to_a_loadable_checkpoint(tmp_path):
    res = _run(HURRY, str(tmp_path / "map.ckpt"), offset=12)
    assert res["still_draining"], res
    assert res["after_hurry_s"] < 3.0, res
    assert res["mapped"] >= 1 and res["mapped"] + res["stored"] == 6, res
