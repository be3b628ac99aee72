"""rerun_node: the graph's outputs logged for the rerun viewer (vings_ros/rerun_node.py), read back
with the rerun SDK; and `vings launch --rerun` starting it. The node runs in a child process (own
rclpy context, unique ROS domain, localhost only), as in test_loop_closer_node.py."""
from __future__ import annotations

import collections

import pytest

pytest.importorskip("rclpy")

from test_loop_closer_node import HARNESS, _run, fake_launcher  # noqa: E402
from test_report import _need  # noqa: E402

pytestmark = pytest.mark.ros

SCRIPT = HARNESS + """
import numpy as np
out = sys.argv[1]
rclpy.init(args=["x"])
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from msg_adapters import topics as T
from msg_adapters.camera_info import camera_to_camera_info
from msg_adapters.image import float_image_to_msg, image_to_msg
from msg_adapters.pointcloud import points_to_pointcloud2
from msg_adapters.pose import estimate_to_odometry, trajectory_to_path
from vings_core.types import CameraModel, PoseEstimate, Trajectory
from vings_ros.rerun_node import RerunNode

cam = CameraModel(64, 48, 40.0, 40.0, 31.5, 23.5)
node = RerunNode(out)
src = Node("source")
q = T.sensor_qos(100)
pubs = {"odo": src.create_publisher(Odometry, T.ODOMETRY_TOPIC, q),
        "info": src.create_publisher(CameraInfo, T.KEYFRAME_INFO_TOPIC, q),
        "img": src.create_publisher(Image, T.KEYFRAME_IMAGE_TOPIC, q),
        "col": src.create_publisher(Image, T.RENDER_COLOR_TOPIC, q),
        "dep": src.create_publisher(Image, T.RENDER_DEPTH_TOPIC, q),
        "kfs": src.create_publisher(Path, T.REFINED_KEYFRAMES_TOPIC, T.latched_qos(1)),
        "pts": src.create_publisher(PointCloud2, T.MAP_POINTS_TOPIC, T.latched_qos(1))}
halts = [spin(node), spin(src)]
assert wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 20)
frame = "camera_optical_frame"
poses = []
for i in range(6):
    T_wc = np.eye(4); T_wc[0, 3] = 0.1 * i
    s = 1_000_000_000 + i * 100_000_000
    poses.append((s, T_wc))
    pubs["odo"].publish(estimate_to_odometry(PoseEstimate(s, T_wc)))
    if i % 2 == 0:          # a keyframe
        pubs["info"].publish(camera_to_camera_info(cam, s, frame))
        pubs["img"].publish(image_to_msg(np.full((48, 64, 3), 40 * i, np.uint8), s, frame))
        pubs["col"].publish(image_to_msg(np.full((48, 64, 3), 30 * i, np.uint8), s, frame))
        pubs["dep"].publish(float_image_to_msg(np.full((48, 64), 2.0, np.float32), s, frame))
kf = [p for i, p in enumerate(poses) if i % 2 == 0]
pubs["kfs"].publish(trajectory_to_path(Trajectory(np.array([s for s, _ in kf]), np.stack([T for _, T in kf]))))
pubs["pts"].publish(points_to_pointcloud2(np.random.rand(100, 3).astype(np.float32),
                                          (np.random.rand(100, 3) * 255).astype(np.uint8), kf[-1][0]))
bad = Image(); bad.encoding = "nonsense"; bad.width = 4; bad.height = 4; bad.step = 4
pubs["img"].publish(bad)     # skipped and counted, no crash
ok = wait_for(lambda: sum(node.counts.values()) + node.skipped >= 6 + 3 * 4 + 2 + 1, 30)
res = {"counts": node.counts, "skipped": node.skipped, "ok": ok}
for h in halts:
    h()
node.shutdown()
node.destroy_node(); src.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def test_rerun_node_logs_the_graph_outputs(tmp_path):
    try:
        from rerun.chunk import RrdReader
    except ImportError:
        RrdReader = None
    _need(RrdReader is not None, "the rerun SDK (pip install '.[viz]')")
    rrd = tmp_path / "graph.rrd"
    res = _run(SCRIPT, str(rrd))
    assert res["ok"] and res["skipped"] == 1, res
    rows = collections.Counter()
    for ch in RrdReader(rrd).stream():
        rows[ch.entity_path] += ch.num_rows
    assert rows["/world/camera"] == 6
    assert rows["/world/camera/image/rgb"] == 3
    assert rows["/world/camera/image"] == 1          # the pinhole, once
    assert rows["/world/keyframes/render"] == 3 and rows["/world/keyframes/depth"] == 3
    assert rows["/world/trajectory"] == 1 and rows["/world/map"] == 1


def test_vings_launch_rerun_starts_the_node(monkeypatch, tmp_path):
    from vings_ros import cli
    seen, real = fake_launcher(monkeypatch)
    assert cli.main(["launch", "--rerun", str(tmp_path / "g.rrd")]) == 0
    assert seen[-1].rerun == str(tmp_path / "g.rrd")
    try:
        import rerun  # noqa: F401
    except ImportError:
        return
    launcher = real(seen[-1])
    assert "rerun_node" in launcher.nodes
    assert cli.main(["launch", "--rerun", str(tmp_path / "g.txt")]) == 0     # the fake launcher accepts it
    with pytest.raises(Exception, match=r"\.rrd"):
        real(seen[-1])
