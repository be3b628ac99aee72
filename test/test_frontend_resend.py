"""frontend_node keeps the keyframes it sent until the mapper lists them on
/vings/keyframes/refined, and sends them again to a mapper that appears (restarted) or after
`frontend_node.resend_after_s`. Child process (own rclpy context), as in test_loop_closer_node.py."""
from __future__ import annotations

import pytest

pytest.importorskip("rclpy")

from test_loop_closer_node import HARNESS, SCENE, _run  # noqa: E402

pytestmark = pytest.mark.ros

SCRIPT = SCENE + HARNESS + """
rclpy.init(args=["x", "--ros-args", "-p", "frontend_node.resend_after_s:=3.0"])
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, Image
from geometry_msgs.msg import PoseStamped
from msg_adapters import topics as T
from msg_adapters.keyframe import KeyframeAssembler, PART_TOPICS
from msg_adapters.pose import trajectory_to_path
from vings_core.types import Trajectory
from vings_ros.frontend_node import FrontendNode

cam = CameraModel(64, 48, 40.0, 40.0, 31.5, 23.5)
kfs = [keyframe(i, pose(0.03 * i, 0.0), pose(0.03 * i, 0.0), cam) for i in range(3)]
types = {"image": Image, "depth": Image, "inv_depth_var": Image, "pose": PoseStamped, "camera_info": CameraInfo}

class FakeMapper(Node):
    def __init__(self, name):
        super().__init__(name)
        self.asm = KeyframeAssembler(max_pending=16)
        self.got = []
        for p, t in PART_TOPICS.items():
            self.create_subscription(types[p], t, lambda m, p=p: self.on(p, m), T.sensor_qos(40))
        self.pub = self.create_publisher(Path, T.REFINED_KEYFRAMES_TOPIC, T.latched_qos(1))
    def on(self, p, m):
        kf = self.asm.add(p, m)
        if kf is not None:
            self.got.append(int(kf.stamp_ns))
    def ack(self, kfs):
        self.pub.publish(trajectory_to_path(Trajectory(np.array([int(k.stamp_ns) for k in kfs]),
                                                       np.stack([k.T_wc.numpy() for k in kfs]))))

res = {}
fe = FrontendNode()
m1 = FakeMapper("mapper_one")
halts = [spin(fe), spin(m1)]
assert wait_for(lambda: fe.pub_kf["image"].get_subscription_count() > 0 and fe.count_publishers(T.REFINED_KEYFRAMES_TOPIC) > 0, 20)
time.sleep(1.5)                 # the front end has seen this mapper: not a new one
fe._exchange_keyframe_sent = lambda kf: None    # no camera yet, so no pose keeper: not under test here
fe._publish_keyframes(kfs)
assert wait_for(lambda: len(m1.got) == 3, 20)
m1.ack(kfs[:1])                 # the mapper holds the first only (then "dies")
assert wait_for(lambda: len(fe.unacked) == 2, 20)
res["unacked_after_ack"] = len(fe.unacked)
halts[1](); m1.destroy_node()
m2 = FakeMapper("mapper_two")   # a restarted mapper
halts.append(spin(m2))
assert wait_for(lambda: len(m2.got) == 2, 30), (m2.got, fe.keyframes_resent)
res["resent_to_new"] = sorted(m2.got)
m2.ack(kfs)
assert wait_for(lambda: len(fe.unacked) == 0, 20)
res["resent"] = fe.keyframes_resent
# a mapper with a checkpoint: the front end releases only the keyframes its checkpoint holds
ckpub = m2.create_publisher(Path, T.CHECKPOINTED_KEYFRAMES_TOPIC, T.latched_qos(1))
assert wait_for(lambda: fe.count_publishers(T.CHECKPOINTED_KEYFRAMES_TOPIC) > 0, 20)
more = [keyframe(i, pose(0.03 * i, 0.0), pose(0.03 * i, 0.0), cam) for i in range(3, 5)]
fe._publish_keyframes(more)
assert wait_for(lambda: len(m2.got) >= 4, 20)
m2.ack(kfs + more)              # mapped ...
time.sleep(2.0)
res["held_until_checkpointed"] = len(fe.unacked)
def ck(ks):
    ckpub.publish(trajectory_to_path(Trajectory(np.array([int(k.stamp_ns) for k in ks]),
                                                np.stack([k.T_wc.numpy() for k in ks]))))
ck(kfs + more[:1])              # ... but only the first of them checkpointed
assert wait_for(lambda: len(fe.unacked) == 1, 20), len(fe.unacked)
ck(kfs + more)
assert wait_for(lambda: len(fe.unacked) == 0, 20), len(fe.unacked)
res["values"] = {k: fe.diagnostics().values[k] for k in ("keyframes_unacknowledged", "keyframes_resent")}
# odometry published before a subscriber exists reaches one that asks for transient_local durability
from nav_msgs.msg import Odometry
for i in range(5):
    m = Odometry(); m.header.stamp.sec = 100 + i; m.pose.pose.orientation.w = 1.0
    fe.pub_odom.publish(m)
late = Node("late_subscriber"); got_odom = []
late.create_subscription(Odometry, T.ODOMETRY_TOPIC, lambda m: got_odom.append(m.header.stamp.sec), T.latched_qos(50))
halts.append(spin(late))
wait_for(lambda: len(got_odom) >= 5, 20)
res["late_odometry"] = got_odom
for h in halts[:1] + halts[2:]:
    h()
fe.shutdown()
fe.destroy_node(); m2.destroy_node(); late.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_frontend_sends_unacknowledged_keyframes_to_a_restarted_mapper():
    res = _run(SCRIPT, offset=13)
    assert res["unacked_after_ack"] == 2
    assert res["resent_to_new"] == [2 * 10 ** 9, 3 * 10 ** 9]
    assert res["resent"] >= 2 and res["values"] == {"keyframes_unacknowledged": 0, "keyframes_resent": res["resent"]}
    assert res["late_odometry"] == [100, 101, 102, 103, 104]
    assert res["held_until_checkpointed"] == 2
