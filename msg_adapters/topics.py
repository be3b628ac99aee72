"""Topic names, frame ids and QoS profiles shared by the nodes, the replay tool and the tests.

Everything here is a default: every topic is remappable (``--ros-args -r from:=to``) and every frame
id is a parameter. See docs/ros.md.
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# ------------------------------------------------------------------------------------- frames
WORLD_FRAME = "map"                      # REP-105 world-fixed frame of the SLAM map
CAMERA_FRAME = "camera_optical_frame"    # REP-103 optical convention: x right, y down, z forward
IMU_FRAME = "imu_link"                   # body (IMU) frame, REP-103 x forward, y left, z up

# ------------------------------------------------------------------------------------- inputs
IMAGE_TOPIC = "/camera/image_raw"
CAMERA_INFO_TOPIC = "/camera/camera_info"
IMU_TOPIC = "/imu/data"
CLOCK_TOPIC = "/clock"

# ------------------------------------------------------------------------- replay back-pressure
#: std_msgs/Header the front end publishes after it has finished with an image: the header of that
#: image, republished unchanged. ``vings replay --wait-for-graph`` waits for it.
PROCESSED_TOPIC = "/vings/frontend/processed"

# -------------------------------------------------------------------------------- front end out
ODOMETRY_TOPIC = "/vings/odometry"
PATH_TOPIC = "/vings/path"
KEYFRAME_IMAGE_TOPIC = "/vings/keyframe/image"
KEYFRAME_DEPTH_TOPIC = "/vings/keyframe/depth"
KEYFRAME_VAR_TOPIC = "/vings/keyframe/inv_depth_var"
KEYFRAME_POSE_TOPIC = "/vings/keyframe/pose"
KEYFRAME_INFO_TOPIC = "/vings/keyframe/camera_info"

# ---------------------------------------------------------------------------------- eraser out
#: the dynamic eraser's mask of a keyframe (mono8, 255 = dynamic, stamped with the keyframe's stamp;
#: wire format in msg_adapters/eraser.py): eraser_node -> mapper_node, frontend_node
DYNAMIC_MASK_TOPIC = "/vings/keyframe/dynamic_mask"

# ----------------------------------------------------------------------------------- mapper out
RENDER_COLOR_TOPIC = "/vings/render/color"
RENDER_DEPTH_TOPIC = "/vings/render/depth"
RENDER_NORMAL_TOPIC = "/vings/render/normal"
MAP_POINTS_TOPIC = "/vings/map/points"
REFINED_KEYFRAMES_TOPIC = "/vings/keyframes/refined"
#: nav_msgs/Path (latched) of the keyframes in the mapper's last checkpoint (published only by a
#: mapper with a checkpoint): what survives a crash of the mapper
CHECKPOINTED_KEYFRAMES_TOPIC = "/vings/keyframes/checkpointed"
#: pose-exchange batches of stage ``<source>`` (nav_msgs/Path, wire format in msg_adapters/exchange.py):
#: ``EXCHANGE_TOPIC_PREFIX + source``; the front end's are ``/vings/exchange/frontend``
EXCHANGE_TOPIC_PREFIX = "/vings/exchange/"
MARKERS_TOPIC = "/vings/markers"
DIAGNOSTICS_TOPIC = "/diagnostics"

#: the replay tool's ``--topics`` keys and their defaults
REPLAY_TOPICS = {"image": IMAGE_TOPIC, "camera_info": CAMERA_INFO_TOPIC, "imu": IMU_TOPIC,
                 "clock": CLOCK_TOPIC, "processed": PROCESSED_TOPIC}

# ----------------------------------------------------------------------------------------- QoS
#: publisher / subscriber history depths (messages)
IMAGE_DEPTH = 10       # ~0.5 s of 20 Hz images (~10 MB at 752x480 rgb8)
IMU_DEPTH = 1000       # 5 s at 200 Hz: IMU samples are never dropped
CAMERA_INFO_DEPTH = 10
ACK_DEPTH = 100
OUTPUT_DEPTH = 10
POSE_EXCHANGE_DEPTH = 100   # pose updates / corrections between the nodes: none may be lost
ODOMETRY_HISTORY = 100      # odometry messages kept for a late subscriber (transient local)


def sensor_qos(depth: int) -> QoSProfile:
    """Reliable, keep-last ``depth``, volatile: inputs and per-frame outputs.

    Reliable rather than ``qos_profile_sensor_data``: between processes on one host it lost no
    frames where best effort lost 4-54 % (docs/ros.md). A best-effort subscriber still matches it.
    """
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth),
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable + transient local: late joiners get the last ``depth`` messages (paths, markers,
    refined keyframes, map points)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth),
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def odometry_qos() -> QoSProfile:
    """``/vings/odometry`` publisher: reliable, transient local, the last :data:`ODOMETRY_HISTORY`
    messages kept, so that a subscriber that asks for ``transient_local`` durability gets the
    poses published before it was discovered (a volatile subscriber matches too and gets only new
    ones)."""
    return latched_qos(ODOMETRY_HISTORY)


def clock_qos() -> QoSProfile:
    """``/clock`` publisher: reliable depth 1 (rclpy's time source subscribes best effort depth 1)."""
    return sensor_qos(1)


def image_qos() -> QoSProfile:
    return sensor_qos(IMAGE_DEPTH)


def imu_qos() -> QoSProfile:
    return sensor_qos(IMU_DEPTH)


def camera_info_qos() -> QoSProfile:
    return sensor_qos(CAMERA_INFO_DEPTH)


def ack_qos() -> QoSProfile:
    return sensor_qos(ACK_DEPTH)
