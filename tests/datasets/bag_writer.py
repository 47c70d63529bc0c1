"""Write real ROS bags (rosbag2 MCAP / sqlite3, ROS 1) from dataset frames with `rosbags`, as a robot would record them.

Topics follow the RealSense ROS 2 wrapper; the camera pose goes on an odometry topic or on /tf (world -> camera
optical frame). Header stamps are the frames' stamps.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from semmap.datasets.base import FrameData
from semmap.datasets.ros_convert import matrix_quaternion

COLOR = "/camera/camera/color/image_raw"
DEPTH = "/camera/camera/aligned_depth_to_color/image_raw"
INFO = "/camera/camera/color/camera_info"
ODOM = "/slam/odom"
OPTICAL = "camera_color_optical_frame"


def _time(ts, stamp: float):
    sec = int(np.floor(stamp))
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp - sec) * 1e9)))


def _header(ts, stamp: float, frame: str, ros1: bool):
    header = ts.types["std_msgs/msg/Header"]
    return (
        header(seq=0, stamp=_time(ts, stamp), frame_id=frame)
        if ros1
        else header(stamp=_time(ts, stamp), frame_id=frame)
    )


def write_bag(
    path: Path,
    frames: Sequence[FrameData],
    kind: str = "mcap",
    depth: str | None = "16UC1",
    pose: str = "odom",
    colour_encoding: str = "rgb8",
) -> Path:
    """Write `frames` to a bag at `path` ("mcap" / "sqlite3": a rosbag2 folder; "ros1": a .bag file).

    depth: "16UC1" (mm), "32FC1" (m) or None (no depth topic); pose: "odom" (nav_msgs/Odometry), "tf" (/tf
    world -> optical frame, plus a static /tf_static edge) or "none".
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:  # rosbags' Noetic store lacks tf2_msgs (ROS 1 /tf carries tf2_msgs/TFMessage)
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    T = ts.types
    if ros1:
        writer = Writer1(path)
        serialize = ts.serialize_ros1
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
        serialize = ts.serialize_cdr
    with writer:
        conns = {}

        def connect(topic: str, msgtype: str) -> None:
            conns[topic] = (writer.add_connection(topic, msgtype, typestore=ts), msgtype)

        def put(topic: str, msg, stamp: float) -> None:
            conn, msgtype = conns[topic]
            writer.write(conn, int(round(stamp * 1e9)) + 1_000_000, serialize(msg, msgtype))

        connect(COLOR, "sensor_msgs/msg/CompressedImage" if colour_encoding == "jpeg" else "sensor_msgs/msg/Image")
        if depth:
            connect(DEPTH, "sensor_msgs/msg/Image")
        connect(INFO, "sensor_msgs/msg/CameraInfo")
        if pose == "odom":
            connect(ODOM, "nav_msgs/msg/Odometry")
        elif pose == "tf":
            connect("/tf", "tf2_msgs/msg/TFMessage")
            connect("/tf_static", "tf2_msgs/msg/TFMessage")
        def raw_image(stamp: float, encoding: str, pixels: np.ndarray):  # noqa: ANN202 - a sensor_msgs/Image
            h, w = pixels.shape[:2]
            return T["sensor_msgs/msg/Image"](header=_header(ts, stamp, OPTICAL, ros1), height=h, width=w,
                                              encoding=encoding, is_bigendian=0, step=pixels.strides[0],
                                              data=pixels.view(np.uint8).reshape(-1))

        body_to_optical = np.array([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
        for n, f in enumerate(frames):
            h, w = f.rgb.shape[:2]
            if colour_encoding == "jpeg":  # the frame's own JPEG file where it has one, as a camera driver sends it
                jpeg = f.rgb_file.data if f.rgb_file is not None and f.rgb_file.fmt == "jpeg" else \
                    cv2.imencode(".jpg", f.rgb[:, :, ::-1])[1].tobytes()
                put(COLOR, T["sensor_msgs/msg/CompressedImage"](header=_header(ts, f.stamp, OPTICAL, ros1),
                                                                 format="jpeg",
                                                                 data=np.frombuffer(jpeg, np.uint8)), f.stamp)
            else:
                rgb = f.rgb if colour_encoding == "rgb8" else f.rgb[:, :, ::-1]
                put(COLOR, raw_image(f.stamp, colour_encoding, np.ascontiguousarray(rgb)), f.stamp)
            if depth == "16UC1":
                put(DEPTH, raw_image(f.stamp, "16UC1", np.ascontiguousarray(f.depth)), f.stamp)
            elif depth == "32FC1":
                metres = f.depth.astype(np.float32) * np.float32(f.depth_scale)
                metres[f.depth == 0] = np.nan
                put(DEPTH, raw_image(f.stamp, "32FC1", metres), f.stamp)
            k = f.intrinsics
            kmat = np.array([k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], float)
            pmat = np.array([k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0], float)
            info_fields = dict(
                header=_header(ts, f.stamp, OPTICAL, ros1),
                height=h,
                width=w,
                distortion_model="plumb_bob",
                binning_x=0,
                binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            )
            if ros1:
                info_fields.update(D=np.zeros(5), K=kmat, R=np.eye(3).reshape(-1), P=pmat)
            else:
                info_fields.update(d=np.zeros(5), k=kmat, r=np.eye(3).reshape(-1), p=pmat)
            if n == 0 or n % 30 == 0:
                put(INFO, T["sensor_msgs/msg/CameraInfo"](**info_fields), f.stamp)
            if pose == "none":
                continue
            pose_m = f.gt_pose
            if pose == "odom":
                put(ODOM, _odometry(ts, f.stamp, pose_m, ros1), f.stamp)
            else:  # /tf: world -> camera_link (moving), camera_link -> optical (static)
                link = pose_m @ np.linalg.inv(body_to_optical)
                put(
                    "/tf",
                    T["tf2_msgs/msg/TFMessage"](
                        transforms=[_transform(ts, f.stamp, "world", "camera_link", link, ros1)]
                    ),
                    f.stamp,
                )
                if n == 0:
                    put(
                        "/tf_static",
                        T["tf2_msgs/msg/TFMessage"](
                            transforms=[_transform(ts, f.stamp, "camera_link", OPTICAL, body_to_optical, ros1)]
                        ),
                        f.stamp,
                    )
    return path


def _pose_fields(ts, matrix: np.ndarray):
    T = ts.types
    x, y, z, w = matrix_quaternion(matrix[:3, :3])
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=float(matrix[0, 3]), y=float(matrix[1, 3]), z=float(matrix[2, 3])),
        orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def _odometry(ts, stamp: float, matrix: np.ndarray, ros1: bool):
    T = ts.types
    cov = np.zeros(36)
    twist = T["geometry_msgs/msg/Twist"](
        linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return T["nav_msgs/msg/Odometry"](
        header=_header(ts, stamp, "world", ros1),
        child_frame_id=OPTICAL,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=_pose_fields(ts, matrix), covariance=cov),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov),
    )


def _transform(ts, stamp: float, parent: str, child: str, matrix: np.ndarray, ros1: bool):
    T = ts.types
    x, y, z, w = matrix_quaternion(matrix[:3, :3])
    return T["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, stamp, parent, ros1),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](
                x=float(matrix[0, 3]), y=float(matrix[1, 3]), z=float(matrix[2, 3])
            ),
            rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        ),
    )
