"""/diagnostics runs on the wall clock: a node on sim time with no /clock (a replay that ended, or
has not started) still reports. Child process as in test_loop_closer_node.py."""
from __future__ import annotations

import pytest

pytest.importorskip("rclpy")

from test_loop_closer_node import HARNESS, _run  # noqa: E402

pytestmark = pytest.mark.ros

SCRIPT = HARNESS + """
rclpy.init(args=["x", "--ros-args", "-p", "use_sim_time:=true", "-p", "ros.diagnostics_period_s:=0.2"])
from diagnostic_msgs.msg import DiagnosticArray
from msg_adapters import topics as T
from vings_ros.eraser_node import EraserNode

node = EraserNode()
got = []
lis = Node("listener")
lis.create_subscription(DiagnosticArray, T.DIAGNOSTICS_TOPIC, lambda m: got.append(time.time()), T.sensor_qos(50))
halts = [spin(node), spin(lis)]
ok = wait_for(lambda: len(got) >= 5, 20)
res = {"ok": ok, "n": len(got), "sim_time": node.get_parameter("use_sim_time").value}
for h in halts:
    h()
node.shutdown()
node.destroy_node(); lis.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_diagnostics_without_clock():
    res = _run(SCRIPT, offset=7)
    assert res["sim_time"] is True
    assert res["ok"], res
