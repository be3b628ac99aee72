"""Conversions between ROS 2 messages and vings_core types (numpy / torch).

Pure functions, no node or executor: ``msg_adapters.<module>.<x>_to_msg`` builds a message with an
exact nanosecond stamp, ``msg_to_<x>`` parses one and raises :class:`vings_core.errors.InputError`
naming the topic and field when it is malformed (pass the topic as ``where``).

Modules: :mod:`.stamps` (ns <-> builtin_interfaces/Time), :mod:`.image` (Image, 32FC1),
:mod:`.camera_info`, :mod:`.imu`, :mod:`.pose` (Pose, PoseStamped, Odometry, Path),
:mod:`.pointcloud` (PointCloud2 xyz + rgb), :mod:`.diagnostics`, :mod:`.markers`,
:mod:`.keyframe` (the five-topic keyframe packet), :mod:`.exchange` (pose-exchange batches),
:mod:`.loop` (render requests and replies, loop constraints), :mod:`.eraser` (the dynamic mask of a
keyframe), :mod:`.topics` (names, frames, QoS).
"""
from .camera_info import camera_info_to_camera, camera_to_camera_info
from .diagnostics import (diagnostic_array, make_status, parse_diagnostic_array,
                          tracking_status)
from .eraser import mask_to_msg, msg_to_mask
from .image import (FrameDecoder, array_to_msg, float_image_to_msg, frame_to_msg, image_to_msg,
                    msg_to_depth,
                    msg_to_float_image, msg_to_frame, msg_to_image)
from .imu import imu_sample_to_msg, imu_variances, msg_to_imu_sample
from .keyframe import KeyframeAssembler, KeyframeMessages, keyframe_to_msgs, msgs_to_keyframe
from .loop import (LoopConstraint, RenderReply, RenderReplyAssembler, RenderRequest, loop_constraint_to_path,
                   msg_to_render_request, msgs_to_render_reply, path_to_loop_constraint, render_reply_to_msgs,
                   render_request_to_msg)
from .markers import keyframe_frustums_marker, marker_array, marker_points, trajectory_marker
from .pointcloud import pointcloud2_to_points, points_to_pointcloud2
from .pose import (estimate_to_odometry, matrix_to_pose, matrix_to_pose_stamped,
                   odometry_to_estimate, path_to_trajectory, pose_stamped_to_matrix,
                   pose_to_matrix, trajectory_to_path)
from .stamps import header_ns, make_header, ns_to_time, time_to_ns
from .topics import CAMERA_FRAME, IMU_FRAME, WORLD_FRAME

__all__ = [
    "camera_info_to_camera", "camera_to_camera_info", "diagnostic_array", "make_status",
    "parse_diagnostic_array", "tracking_status", "float_image_to_msg", "frame_to_msg",
    "mask_to_msg", "msg_to_mask",
    "FrameDecoder", "array_to_msg", "image_to_msg", "msg_to_depth", "msg_to_float_image", "msg_to_frame", "msg_to_image",
    "imu_sample_to_msg", "imu_variances", "msg_to_imu_sample", "KeyframeAssembler",
    "KeyframeMessages", "keyframe_to_msgs", "msgs_to_keyframe", "LoopConstraint", "RenderReply",
    "RenderReplyAssembler", "RenderRequest", "loop_constraint_to_path", "msg_to_render_request",
    "msgs_to_render_reply", "path_to_loop_constraint", "render_reply_to_msgs", "render_request_to_msg",
    "keyframe_frustums_marker",
    "marker_array", "marker_points", "trajectory_marker", "pointcloud2_to_points",
    "points_to_pointcloud2", "estimate_to_odometry", "matrix_to_pose", "matrix_to_pose_stamped",
    "odometry_to_estimate", "path_to_trajectory", "pose_stamped_to_matrix", "pose_to_matrix",
    "trajectory_to_path", "header_ns", "make_header", "ns_to_time", "time_to_ns",
    "CAMERA_FRAME", "IMU_FRAME", "WORLD_FRAME",
]
