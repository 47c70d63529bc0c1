"""ROS message fields <-> numpy, without ROS: shared by the bag reader (rosbags objects) and the ROS 2 bridge (rclpy).

Both hand us objects with the ROS 2 field names (`header.stamp.sec`, `encoding`, `data`, `pose.position` ...);
ROS 1 CameraInfo spells its matrix `K` instead of `k`. Everything here raises `ConversionError` on input that
does not fit (wrong encoding, a buffer shorter than height x step, a NaN or zero quaternion), so callers count and
skip one bad message instead of crashing.

Frames: semmap poses are camera-to-world in the *optical* frame (x right, y down, z forward; REP 104). A SLAM
often publishes the pose of another frame (a ROS body frame x forward, y left, z up; REP 103, or `base_link`):
`pose_to_optical` is the fixed transform from that frame to the optical frame, applied on the right.
"""

from __future__ import annotations

import bisect
import math
from typing import Any

import cv2
import numpy as np

from semmap.core.geometry import interpolate_pose
from semmap.core.stamps import exceeds

COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
)
TF_TYPE = "tf2_msgs/msg/TFMessage"
# the optical frame's axes in a REP 103 camera frame (x forward, y left, z up): columns x_opt, y_opt, z_opt
ROS_BODY_TO_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


class ConversionError(ValueError):
    """A ROS message that cannot become semmap input (the caller counts it and skips it)."""


def stamp_seconds(stamp: Any) -> float:
    """builtin_interfaces/Time (ROS 2, and ROS 1 as rosbags reads it) as float seconds."""
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def _image_array(
    height: int, width: int, step: int, data: Any, channels: int, dtype: np.dtype, big_endian: bool
) -> np.ndarray:
    itemsize = np.dtype(dtype).itemsize
    if height <= 0 or width <= 0 or height > 16384 or width > 16384:
        raise ConversionError(f"bad image size {width}x{height}")
    row = width * channels * itemsize
    if step < row:
        raise ConversionError(f"step {step} shorter than a row of {row} bytes")
    buf = np.frombuffer(memoryview(data).cast("B"), np.uint8) if not isinstance(data, np.ndarray) else data
    buf = buf.reshape(-1).view(np.uint8)
    if buf.size < step * height:
        raise ConversionError(f"image data of {buf.size} bytes, expected {step * height}")
    rows = buf[: step * height].reshape(height, step)[:, :row]
    if itemsize == 1:
        return rows.reshape(height, width, channels)
    typed = np.dtype(dtype).newbyteorder(">" if big_endian else "<")
    return np.ascontiguousarray(rows).view(typed).reshape(height, width, channels).astype(dtype, copy=False)


def colour_to_rgb(encoding: str, height: int, width: int, step: int, data: Any) -> np.ndarray:
    """sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8) -> HxWx3 uint8 RGB."""
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}.get(encoding)
    if channels is None:
        raise ConversionError(f"colour encoding {encoding!r} not supported (use one of {', '.join(COLOUR_ENCODINGS)})")
    image = _image_array(height, width, step, data, channels, np.uint8, False)
    if encoding == "rgb8":
        return np.ascontiguousarray(image)
    if encoding == "bgr8":
        return np.ascontiguousarray(image[:, :, ::-1])
    if encoding == "rgba8":
        return np.ascontiguousarray(image[:, :, :3])
    if encoding == "bgra8":
        return np.ascontiguousarray(image[:, :, 2::-1])
    return np.repeat(image, 3, axis=2)


def compressed_to_rgb(fmt: str, data: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage (JPEG or PNG colour) -> HxWx3 uint8 RGB."""
    buf = np.frombuffer(memoryview(data).cast("B"), np.uint8) if not isinstance(data, np.ndarray) else data
    if "compressedDepth" in fmt:
        raise ConversionError("compressedDepth images are not supported: record the raw depth topic")
    bgr = cv2.imdecode(buf.reshape(-1).view(np.uint8), cv2.IMREAD_COLOR) if buf.size else None
    if bgr is None:
        raise ConversionError(f"cannot decode compressed image ({fmt!r})")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def depth_to_mm(encoding: str, height: int, width: int, step: int, data: Any, big_endian: bool = False) -> np.ndarray:
    """sensor_msgs/Image depth -> HxW uint16 millimetres (0 = invalid).

    16UC1 / mono16 are millimetres already; 32FC1 is metres (NaN, inf, <= 0 and beyond 65.535 m become 0).
    """
    if encoding in ("16UC1", "mono16"):
        return _image_array(height, width, step, data, 1, np.uint16, big_endian).reshape(height, width)
    if encoding == "32FC1":
        metres = _image_array(height, width, step, data, 1, np.float32, big_endian).reshape(height, width)
        mm = np.rint(np.nan_to_num(metres, nan=0.0, posinf=0.0, neginf=0.0) * 1000.0)
        mm[(mm <= 0) | (mm > 65535)] = 0
        return mm.astype(np.uint16)
    raise ConversionError(f"depth encoding {encoding!r} not supported (use 16UC1 millimetres or 32FC1 metres)")


def camera_info_intrinsics(msg: Any) -> tuple[float, float, float, float, int, int]:
    """(fx, fy, cx, cy, width, height) of a sensor_msgs/CameraInfo (ROS 2 `k`, ROS 1 `K`)."""
    k = getattr(msg, "k", None)
    if k is None:
        k = getattr(msg, "K", None)
    values = np.asarray(k if k is not None else [], float).reshape(-1)
    width, height = int(msg.width), int(msg.height)
    if values.size != 9 or not np.all(np.isfinite(values)) or values[0] <= 0 or values[4] <= 0:
        raise ConversionError("camera info without a valid K matrix")
    if not (0 < width <= 16384 and 0 < height <= 16384):
        raise ConversionError(f"camera info with bad size {width}x{height}")
    return float(values[0]), float(values[4]), float(values[2]), float(values[5]), width, height


def quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """3x3 rotation of a (normalised) quaternion; ConversionError on NaN or a near-zero quaternion."""
    q = np.array([x, y, z, w], float)
    norm = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or norm < 1e-6:
        raise ConversionError(f"invalid quaternion {q.tolist()}")
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a 3x3 rotation (w >= 0)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(rotation, float)).as_quat()
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    return float(x), float(y), float(z), float(w)


def transform_matrix(translation: Any, rotation: Any) -> np.ndarray:
    """4x4 from a Point/Vector3 and a Quaternion (geometry_msgs field objects)."""
    t = np.array([translation.x, translation.y, translation.z], float)
    if not np.all(np.isfinite(t)):
        raise ConversionError(f"invalid position {t.tolist()}")
    out = np.eye(4)
    out[:3, :3] = quaternion_matrix(rotation.x, rotation.y, rotation.z, rotation.w)
    out[:3, 3] = t
    return out


def pose_message(msg: Any, msgtype: str) -> tuple[float, str, np.ndarray]:
    """(stamp s, child frame or "", 4x4 pose in header.frame_id) of an Odometry / PoseStamped /
    PoseWithCovarianceStamped / TransformStamped message."""
    stamp = stamp_seconds(msg.header.stamp)
    if msgtype == "nav_msgs/msg/Odometry":
        p = msg.pose.pose
        return stamp, str(msg.child_frame_id), transform_matrix(p.position, p.orientation)
    if msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        p = msg.pose.pose
        return stamp, "", transform_matrix(p.position, p.orientation)
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return stamp, "", transform_matrix(msg.pose.position, msg.pose.orientation)
    if msgtype == "geometry_msgs/msg/TransformStamped":
        t = msg.transform
        return stamp, str(msg.child_frame_id), transform_matrix(t.translation, t.rotation)
    raise ConversionError(f"{msgtype} is not a pose type (use one of {', '.join(POSE_TYPES)})")


def parse_pose_to_optical(spec: str | None) -> np.ndarray:
    """The pose-frame -> optical-frame transform: "identity" (the pose already is the optical frame's, default),
    "ros" (the pose is of a REP 103 frame at the camera: x forward, y left, z up), or seven numbers
    "x y z qx qy qz qw" (the optical frame in the pose's frame, as `ros2 run tf2_ros static_transform_publisher`
    takes them)."""
    text = (spec or "identity").strip().lower()
    if text in ("", "identity", "optical"):
        return np.eye(4)
    if text in ("ros", "body", "rep103"):
        return ROS_BODY_TO_OPTICAL.copy()
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        values = []
    if len(values) != 7 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"pose_to_optical must be identity, ros or 'x y z qx qy qz qw', got {spec!r}")
    out = np.eye(4)
    out[:3, :3] = quaternion_matrix(*values[3:])
    out[:3, 3] = values[:3]
    return out


def pose_at(stamps: list[float], poses: list[np.ndarray], t: float, max_gap: float) -> np.ndarray | None:
    """The pose at `t` from a sorted stamped series: the one stamped `t` (within 1 us), else interpolated between
    the two around it; None outside the series or across a gap longer than `max_gap` seconds."""
    i = bisect.bisect_left(stamps, t)
    if i < len(stamps) and abs(stamps[i] - t) < 1e-6:
        return poses[i].copy()
    if i > 0 and abs(stamps[i - 1] - t) < 1e-6:
        return poses[i - 1].copy()
    if i == 0 or i == len(stamps) or exceeds(stamps[i] - stamps[i - 1], max_gap):
        return None
    return pose_between(t, stamps[i - 1], poses[i - 1], stamps[i], poses[i])


def pose_between(t: float, t0: float, pose0: np.ndarray, t1: float, pose1: np.ndarray) -> np.ndarray:
    """The pose at `t` between two stamped poses (clamped to them)."""
    if t1 <= t0:
        return pose0.copy()
    return interpolate_pose(pose0, pose1, (t - t0) / (t1 - t0))
