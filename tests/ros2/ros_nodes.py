"""Real rclpy nodes for the bridge tests, each run as its own process:

    python tests/ros2/ros_nodes.py publish DATASET FRAMES [--bad]   # a camera + SLAM: 7-Scenes frames as ROS 2
    python tests/ros2/ros_nodes.py listen OUT.json FRAMES            # records /semmap/* until the bridge is done
    python tests/ros2/ros_nodes.py camera DATASET FRAMES OUT.json [--rate 30] [--reliable] [--start N]
                                                                     # a camera as a robot's: on a clock, no waits
    python tests/ros2/ros_nodes.py count OUT.json [--idle 3]          # counts camera messages (a do-nothing node)

`publish` sends, per frame, a colour image (rgb8), the aligned depth (16UC1), the camera info and the camera pose
(nav_msgs/Odometry on /slam/odom, the frame's ground truth in the optical frame), stamped with the frame's stamp,
reliably, after every input of the bridge is matched. `--bad` then sends one of each kind of bad message (a
wrong encoding, a colour image of another size than the camera info, a NaN pose) after the frames, at stamps of
their own.
`camera` builds every message first, waits until the bridge's four subscriptions are matched, then publishes frame
i at t0 + i / rate whatever happens downstream (best effort by default, as a RealSense node): what a live camera
does. It writes what it sent (and how late it was) to OUT.json.
Depth goes out in millimetres whatever the dataset's unit (TUM folders: 1/5000 m).
`listen` keeps the last MarkerArray, the last Path, the bridge status and every MarkerArray on /semmap/dynamic; it
writes them as JSON once the bridge reports FRAMES frames done (FRAMES 0: every frame it sent) and its stream ended
(or after its timeout).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import Point, Quaternion
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from visualization_msgs.msg import Marker, MarkerArray

from semmap.datasets import open_dataset
from semmap.datasets.ros_convert import matrix_quaternion

COLOUR = "/camera/camera/color/image_raw"
DEPTH = "/camera/camera/aligned_depth_to_color/image_raw"
INFO = "/camera/camera/color/camera_info"
POSE = "/slam/odom"
OPTICAL = "camera_color_optical_frame"
RELIABLE = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)


def _stamp(header, t: float) -> None:
    sec = math.floor(t)
    header.stamp.sec = int(sec)
    header.stamp.nanosec = min(int(round((t - sec) * 1e9)), 999_999_999)


def _image(t: float, encoding: str, array: np.ndarray) -> Image:
    msg = Image(
        height=array.shape[0],
        width=array.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=array.shape[1] * array.itemsize * (array.shape[2] if array.ndim == 3 else 1),
    )
    _stamp(msg.header, t)
    msg.header.frame_id = OPTICAL
    msg.data = np.ascontiguousarray(array).tobytes()
    return msg


def _odometry(t: float, pose: np.ndarray) -> Odometry:
    msg = Odometry(child_frame_id=OPTICAL)
    _stamp(msg.header, t)
    msg.header.frame_id = "world"
    x, y, z, w = matrix_quaternion(pose[:3, :3]) if np.all(np.isfinite(pose)) else (math.nan,) * 4
    msg.pose.pose.position = Point(x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3]))
    msg.pose.pose.orientation = Quaternion(x=x, y=y, z=z, w=w)
    return msg


def _info(t: float, k) -> CameraInfo:
    msg = CameraInfo(height=k.height, width=k.width, distortion_model="plumb_bob")
    _stamp(msg.header, t)
    msg.header.frame_id = OPTICAL
    msg.k = [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]
    msg.p = [k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def _millimetres(frame) -> np.ndarray:  # noqa: ANN001
    if abs(frame.depth_scale - 0.001) < 1e-12:
        return frame.depth
    return np.clip(np.rint(frame.depth * (frame.depth_scale * 1000.0)), 0, 65535).astype(np.uint16)


def publish(dataset: str, frames: int, bad: bool, rate_hz: float = 15.0) -> int:
    rclpy.init()
    node = rclpy.create_node("semmap_test_camera")
    pubs = {
        "colour": node.create_publisher(Image, COLOUR, RELIABLE),
        "depth": node.create_publisher(Image, DEPTH, RELIABLE),
        "info": node.create_publisher(CameraInfo, INFO, RELIABLE),
        "pose": node.create_publisher(Odometry, POSE, RELIABLE),
    }
    deadline = time.monotonic() + 60
    while any(p.get_subscription_count() == 0 for p in pubs.values()):
        if time.monotonic() > deadline:
            print("no bridge subscribed within 60 s", file=sys.stderr)
            return 1
        rclpy.spin_once(node, timeout_sec=0.1)
    data = open_dataset(dataset)
    first = data[0]
    period = 1.0 / rate_hz
    for i in range(frames):
        started = time.monotonic()
        f = data[i]
        if i % 10 == 0:
            pubs["info"].publish(_info(f.stamp, f.intrinsics))
        pubs["colour"].publish(_image(f.stamp, "rgb8", f.rgb))
        pubs["depth"].publish(_image(f.stamp, "16UC1", _millimetres(f)))
        pubs["pose"].publish(_odometry(f.stamp, f.gt_pose))
        rclpy.spin_once(node, timeout_sec=max(0.0, period - (time.monotonic() - started)))
    if bad:  # after the real frames, at stamps of their own
        t = data[frames - 1].stamp + 5.0
        pubs["info"].publish(_info(t, first.intrinsics))
        pubs["colour"].publish(_image(t, "yuv422", first.rgb[:, :, :2]))  # an encoding the bridge does not take
        pubs["depth"].publish(_image(t, "16UC1", first.depth))
        pubs["pose"].publish(_odometry(t, first.gt_pose))
        t += 1.0  # a colour image of another size than the camera info
        pubs["colour"].publish(_image(t, "rgb8", np.ascontiguousarray(first.rgb[:240, :320])))
        pubs["depth"].publish(_image(t, "16UC1", first.depth))
        pubs["pose"].publish(_odometry(t, first.gt_pose))
        t += 1.0  # a NaN pose
        pubs["colour"].publish(_image(t, "rgb8", first.rgb))
        pubs["depth"].publish(_image(t, "16UC1", first.depth))
        pubs["pose"].publish(_odometry(t, np.full((4, 4), math.nan)))
        time.sleep(0.5)
    for pub in pubs.values():  # reliable: everything delivered before the publishers go
        if not pub.wait_for_all_acked(Duration(seconds=120)):
            print(f"{pub.topic_name}: not all messages acknowledged within 120 s", file=sys.stderr)
            return 1
    node.destroy_node()
    rclpy.shutdown()
    return 0


def listen(out: Path, frames: int, timeout_s: float = 600.0) -> int:
    rclpy.init()
    node = rclpy.create_node("semmap_test_listener")
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    state: dict = {"markers": None, "path": None, "status": None, "deletes": 0, "arrays": 0, "dynamic": []}

    def on_markers(msg: MarkerArray) -> None:
        state["arrays"] += 1
        state["deletes"] += sum(m.action == Marker.DELETE for m in msg.markers)
        cubes = {m.id: m for m in msg.markers if m.ns == "landmarks" and m.action == Marker.ADD}
        labels = {m.id: m.text for m in msg.markers if m.ns == "labels" and m.action == Marker.ADD}
        state["markers"] = [
            {
                "id": i,
                "label": labels.get(i, ""),
                "frame": m.header.frame_id,
                "centroid": [m.pose.position.x, m.pose.position.y, m.pose.position.z],
                "scale": [m.scale.x, m.scale.y, m.scale.z],
                "colour": [m.color.r, m.color.g, m.color.b],
            }
            for i, m in sorted(cubes.items())
        ]

    def on_path(msg: PathMsg) -> None:
        state["path"] = {
            "frame": msg.header.frame_id,
            "poses": [
                [
                    p.header.stamp.sec + p.header.stamp.nanosec * 1e-9,
                    p.pose.position.x,
                    p.pose.position.y,
                    p.pose.position.z,
                ]
                for p in msg.poses
            ],
        }

    def on_dynamic(msg: MarkerArray) -> None:
        state["dynamic"].append(
            [
                {
                    "ns": m.ns,
                    "id": m.id,
                    "type": m.type,
                    "action": m.action,
                    "frame": m.header.frame_id,
                    "stamp": m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                    "position": [m.pose.position.x, m.pose.position.y, m.pose.position.z],
                    "orientation": [
                        m.pose.orientation.x,
                        m.pose.orientation.y,
                        m.pose.orientation.z,
                        m.pose.orientation.w,
                    ],
                    "scale": [m.scale.x, m.scale.y, m.scale.z],
                    "colour": [m.color.r, m.color.g, m.color.b, m.color.a],
                    "lifetime": m.lifetime.sec + m.lifetime.nanosec * 1e-9,
                    "text": m.text,
                }
                for m in msg.markers
            ]
        )

    def on_status(msg: String) -> None:
        state["status"] = json.loads(msg.data)

    node.create_subscription(MarkerArray, "/semmap/landmarks", on_markers, latched)
    node.create_subscription(PathMsg, "/semmap/trajectory", on_path, latched)
    node.create_subscription(String, "/semmap/bridge_status", on_status, 10)
    dynamic = node.create_subscription(MarkerArray, "/semmap/dynamic", on_dynamic, RELIABLE)
    deadline = time.monotonic() + timeout_s
    done_at = None
    ready = out.with_suffix(".ready")
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
        if not ready.exists() and dynamic.get_publisher_count() > 0:
            ready.write_text("matched")  # the bridge's volatile topic reaches us: frames may start (see test)
        status = state["status"] or {}
        want = frames or max(status.get("frames_sent", 0), 1)  # 0: every frame the bridge sent
        if done_at is None and status.get("ended") and status.get("frames_done", 0) >= want:
            done_at = time.monotonic()
        if done_at is not None and time.monotonic() - done_at > 3.0:  # the last map update and path
            break
    out.write_text(json.dumps(state))
    node.destroy_node()
    rclpy.shutdown()
    return 0 if done_at is not None else 1


def camera(dataset: str, frames: int, out: Path, rate_hz: float, reliable: bool, start: int) -> int:
    """A live camera: `frames` frames from `start` on, frame i at t0 + i / rate_hz, never waiting for anyone."""
    rclpy.init()
    node = rclpy.create_node("semmap_test_live_camera")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
    pubs = {
        "colour": node.create_publisher(Image, COLOUR, qos),
        "depth": node.create_publisher(Image, DEPTH, qos),
        "info": node.create_publisher(CameraInfo, INFO, qos),
        "pose": node.create_publisher(Odometry, POSE, qos),
    }
    data = open_dataset(dataset)
    messages = []
    for i in range(start, start + frames):
        f = data[i]
        messages.append(
            (
                _info(f.stamp, f.intrinsics),
                _image(f.stamp, "rgb8", f.rgb),
                _image(f.stamp, "16UC1", _millimetres(f)),
                _odometry(f.stamp, f.gt_pose),
            )
        )
    deadline = time.monotonic() + 60
    while any(p.get_subscription_count() == 0 for p in pubs.values()):
        if time.monotonic() > deadline:
            print("no bridge subscribed within 60 s", file=sys.stderr)
            return 1
        rclpy.spin_once(node, timeout_sec=0.1)
    time.sleep(1.0)  # both sides have matched (discovery is symmetric but not simultaneous)
    period = 1.0 / rate_hz
    late = 0
    t0 = time.monotonic()
    for i, (info, colour, depth, pose) in enumerate(messages):
        wait = t0 + i * period - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        elif wait < -period:
            late += 1
        pubs["info"].publish(info)
        pubs["colour"].publish(colour)
        pubs["depth"].publish(depth)
        pubs["pose"].publish(pose)
    elapsed = time.monotonic() - t0
    time.sleep(0.5)
    out.write_text(
        json.dumps(
            {
                "sent": frames,
                "rate_hz": rate_hz,
                "elapsed_s": elapsed,
                "late_frames": late,
                "first_stamp": messages[0][1].header.stamp.sec + messages[0][1].header.stamp.nanosec * 1e-9,
                "profile": os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE", ""),
            }
        )
    )
    node.destroy_node()
    rclpy.shutdown()
    return 0


def count(out: Path, idle_s: float = 3.0, timeout_s: float = 120.0) -> int:
    """A subscriber that does nothing but count the camera's messages (best effort, depth 10)."""
    rclpy.init()
    node = rclpy.create_node("semmap_test_counter")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    counts = {"colour": 0, "depth": 0, "info": 0, "pose": 0}
    last = [None]

    def counter(name: str):  # noqa: ANN202
        def cb(_msg) -> None:  # noqa: ANN001
            counts[name] += 1
            last[0] = time.monotonic()

        return cb

    node.create_subscription(Image, COLOUR, counter("colour"), qos)
    node.create_subscription(Image, DEPTH, counter("depth"), qos)
    node.create_subscription(CameraInfo, INFO, counter("info"), qos)
    node.create_subscription(Odometry, POSE, counter("pose"), qos)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and (last[0] is None or time.monotonic() - last[0] < idle_s):
        rclpy.spin_once(node, timeout_sec=0.1)
    out.write_text(json.dumps(counts))
    node.destroy_node()
    rclpy.shutdown()
    return 0


def _option(name: str, default: str) -> str:
    return sys.argv[sys.argv.index(name) + 1] if name in sys.argv else default


if __name__ == "__main__":
    if sys.argv[1] == "camera":
        sys.exit(
            camera(
                sys.argv[2],
                int(sys.argv[3]),
                Path(sys.argv[4]),
                float(_option("--rate", "30")),
                "--reliable" in sys.argv,
                int(_option("--start", "0")),
            )
        )
    if sys.argv[1] == "count":
        sys.exit(count(Path(sys.argv[2]), float(_option("--idle", "3"))))
    if sys.argv[1] == "publish":
        sys.exit(publish(sys.argv[2], int(sys.argv[3]), "--bad" in sys.argv))
    sys.exit(listen(Path(sys.argv[2]), int(sys.argv[3])))
