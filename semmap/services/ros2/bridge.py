"""`semmap ros2`: a ROS 2 node that feeds a running semmap from a camera + SLAM and publishes the map back in ROS 2.

    semmap run external --out out/robot &          # the pipeline, waiting for a SLAM (it records its endpoint)
    semmap ros2 --run out/robot --ros-args -r /odom:=/rtabmap/odom -p pose_to_optical:=ros

In (defaults: the RealSense ROS 2 wrapper's names; remap any with `--ros-args -r FROM:=TO`):
  /camera/camera/color/image_raw                   sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8)
  /camera/camera/aligned_depth_to_color/image_raw  sensor_msgs/Image (16UC1 mm or 32FC1 m), aligned to colour
  /camera/camera/color/camera_info                 sensor_msgs/CameraInfo
  /odom                                            the camera pose: nav_msgs/Odometry (`pose_type:=odometry`),
                                                   geometry_msgs/PoseStamped (`pose`) or
                                                   PoseWithCovarianceStamped (`pose_with_covariance`)
Out:
  /semmap/landmarks               visualization_msgs/MarkerArray: a cube per landmark (its extent, a colour per
                                  class) and a text `class #id`; DELETE for merged and retired landmarks
  /semmap/trajectory              nav_msgs/Path: the backend's optimised camera trajectory (optical frame)
  /semmap/correction              geometry_msgs/TransformStamped: corrected world <- SLAM world (tf2_msgs, to put
                                  it on /tf, is not on PyPI)
  /semmap/landmark_observations   nav_msgs/Odometry, one per observation: child_frame_id `semmap_landmark_<id>`,
                                  the landmark's centroid in the camera frame with its covariance
  /semmap/dynamic                 visualization_msgs/MarkerArray per detected frame: a box per dynamic object
                                  (people, animals, things seen moving), a colour per track, a text label, a short
                                  lifetime (`dynamic_lifetime_s`) so that stale boxes vanish
  /semmap/bridge_status           std_msgs/String (JSON): counters of matched, skipped and sent messages, and
                                  `lost`: every frame lost between the camera and semmap, by reason

Frames go to semmap through its Zenoh keys exactly as an external SLAM sends them (semmap.runtime.client), one frame per
matched colour/depth/pose triple (semmap.services.ros2.sync). Parameters (`-p name:=value`): semmap/core/config/ros2.py.
"""

from __future__ import annotations

import argparse
import colorsys
import functools
import json
import logging
import math
import sys
import threading
import time
import zlib
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
from pydantic import ValidationError

from semmap.core import environment
from semmap.core.config.ros2 import Ros2BridgeConfig
from semmap.core.messages import CorrectedPoses, DynamicBox, DynamicObjects, Landmark, MapUpdate, Observations
from semmap.datasets.ros_convert import matrix_quaternion, parse_pose_to_optical
from semmap.services.ros2.sync import FrameSync, MatchedFrame, missing_at_ends
from semmap.services.ros2.transport import use_profile, write_profile

log = logging.getLogger("semmap.services.ros2")

COLOUR_TOPIC = "/camera/camera/color/image_raw"
DEPTH_TOPIC = "/camera/camera/aligned_depth_to_color/image_raw"
INFO_TOPIC = "/camera/camera/color/camera_info"
POSE_TOPIC = "/odom"
LANDMARKS_TOPIC = "/semmap/landmarks"
TRAJECTORY_TOPIC = "/semmap/trajectory"
CORRECTION_TOPIC = "/semmap/correction"
OBSERVATIONS_TOPIC = "/semmap/landmark_observations"
DYNAMIC_TOPIC = "/semmap/dynamic"
STATUS_TOPIC = "/semmap/bridge_status"

# its settings, each a ROS parameter (`-p name:=value`), are a configuration section: semmap/core/config/ros2.py
LOCKSTEP_QUEUE = 300  # frames held while semmap catches up in lockstep (~1.5 MB each at 640x480); then the ROS
# thread waits (the readers' histories fill, a reliable camera is slowed): nothing is dropped in lockstep
SENT_KEPT = 9000  # frames sent whose pose is kept for the outputs (5 min at 30 Hz; ~0.3 KB each, no images)
DYNAMIC_MIN_DEPTH_M = 0.05  # a dynamic box is at least this deep along the view (a one-surface depth range)


@dataclass(frozen=True)
class SentFrame:
    """What the outputs need of a frame sent to semmap: not its images (1.5 MB a frame at 640x480)."""

    stamp: float
    pose: np.ndarray  # optical camera -> world
    intrinsics: tuple[float, float, float, float, int, int]
    camera_frame: str


def track_colour(track_id: int) -> tuple[float, float, float]:
    """A distinct RGB colour per track (golden-ratio hue steps: neighbouring ids look different), fully saturated
    so that dynamic objects stand out from the landmarks' softer class colours."""
    hue = (track_id * 0.618033988749895) % 1.0
    return colorsys.hsv_to_rgb(hue, 1.0, 1.0)


def dynamic_box_in_world(
    box: DynamicBox, intrinsics: tuple[float, float, float, float, int, int], pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(centre in the world, rotation world <- box axes, size x y z) of the 3D box of a dynamic object: its image box
    at the middle of its depth range, as wide and high as the image box spans there, as deep as the range (at least
    DYNAMIC_MIN_DEPTH_M), axes along the optical frame's (x right, y down, z forward). None without a depth range
    (0, 0: no valid depth in the box)."""
    if not box.depth_max_m > 0:
        return None
    fx, fy, cx, cy, _, _ = intrinsics
    x1, y1, x2, y2 = box.box
    z = 0.5 * (box.depth_min_m + box.depth_max_m)
    centre_cam = np.array([((x1 + x2) / 2 - cx) / fx * z, ((y1 + y2) / 2 - cy) / fy * z, z])
    size = np.array(
        [abs(x2 - x1) / fx * z, abs(y2 - y1) / fy * z, max(box.depth_max_m - box.depth_min_m, DYNAMIC_MIN_DEPTH_M)]
    )
    return pose[:3, :3] @ centre_cam + pose[:3, 3], pose[:3, :3].copy(), size


def class_colour(name: str) -> tuple[float, float, float]:
    """A stable RGB colour per class (the same in every run and every process)."""
    hue = (zlib.crc32(name.encode()) % 360) / 360.0
    return colorsys.hsv_to_rgb(hue, 0.75, 0.95)


class SemmapLink:
    """Sends matched frames to semmap over Zenoh on its own thread (publishing can wait; ROS callbacks must not)."""

    def __init__(
        self,
        client: Any,
        lockstep: bool,
        queue_size: int,
        sigmas: tuple[float, float],
        end_after_idle_s: float,
        counters: Counter,
    ) -> None:
        self.client = client
        self.lockstep = lockstep
        self.queue_size = LOCKSTEP_QUEUE if lockstep else max(1, int(queue_size))
        self.sigmas = sigmas
        self.end_after_idle_s = float(end_after_idle_s)
        self.counters = counters
        # the frames lost before semmap, by reason (set by the node): sent with end-of-stream, so that the run's
        # stats.json and summary show them
        self.report: Any = dict
        self.sent: OrderedDict[int, SentFrame] = OrderedDict()  # frame_id -> its pose etc. (the last SENT_KEPT)
        self.ready = False
        self.ended = False
        self.last_id = -1
        self.done_id = -1
        self._queue: deque[MatchedFrame] = deque()
        self._cv = threading.Condition()
        self._stopping = False
        self._last_frame_at = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="semmap-link", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def submit(self, frame: MatchedFrame) -> None:
        """Queue a frame for semmap. Real time: a full queue drops its oldest frame (`dropped_busy`). Lockstep:
        a full queue makes the caller (the ROS thread) wait: back-pressure, nothing dropped."""
        with self._cv:
            if self.ended:
                self.counters["after_end_of_stream"] += 1
                return
            while self.lockstep and len(self._queue) >= self.queue_size and not self._stopping:
                self._cv.wait(0.1)
            if len(self._queue) >= self.queue_size:
                self._queue.popleft()
                self.counters["dropped_busy"] += 1
            self._queue.append(frame)
            self.counters["frames_queued"] += 1
            self._cv.notify_all()

    def _wait_ready(self) -> bool:
        from semmap.runtime.client import SemmapTimeout

        waited = 0.0
        while not self._stopping:
            try:
                self.client.wait_ready(timeout=5.0)
                log.info("semmap is running: sending frames")
                return True
            except SemmapTimeout as exc:
                waited += 5.0
                if waited == 5.0 or waited % 30 == 0:
                    log.warning("waiting for semmap (start `semmap run external`): %s", exc)
        return False

    def _run(self) -> None:
        from semmap.runtime.client import SemmapTimeout

        if not self._wait_ready():
            return
        with self._cv:
            self.ready = True
        while True:
            with self._cv:
                while not self._queue and not self._stopping:
                    if self._idle_end_due():
                        break
                    self._cv.wait(0.1)
                if self._idle_end_due():
                    self._end_locked(f"no frame for {self.end_after_idle_s:.1f} s")
                    continue
                if not self._queue or (self._stopping and not self.lockstep):
                    self.counters["dropped_at_stop"] += len(self._queue)
                    self._queue.clear()
                    return
                frame = self._queue.popleft()
                self._cv.notify_all()  # a lockstep submit may be waiting for room
                frame_id = self.last_id + 1
            fx, fy, cx, cy, _, _ = frame.intrinsics
            self.client.publish_frame(frame_id, frame.stamp, frame.rgb, frame.depth_mm, 0.001, (fx, fy, cx, cy))
            self.client.publish_pose(
                frame_id,
                frame.stamp,
                frame.pose,
                sigma_translation=self.sigmas[0],
                sigma_rotation=self.sigmas[1],
                source="ros2",
            )
            with self._cv:
                self.sent[frame_id] = SentFrame(frame.stamp, frame.pose, frame.intrinsics, frame.camera_frame)
                if len(self.sent) > SENT_KEPT:
                    self.sent.popitem(last=False)
                self.last_id = frame_id
                self._last_frame_at = time.monotonic()
                self.counters["frames_sent"] += 1
            if self.lockstep:
                try:
                    self.client.wait_frame_done(frame_id, timeout=120.0)
                except SemmapTimeout as exc:
                    self.counters["frame_timeouts"] += 1
                    log.error("%s", exc)
            with self._cv:
                self.done_id = frame_id

    def _idle_end_due(self) -> bool:
        return (
            self.end_after_idle_s > 0
            and not self.ended
            and self.last_id >= 0
            and not self._queue
            and time.monotonic() - self._last_frame_at > self.end_after_idle_s
        )

    def _end_locked(self, why: str) -> None:
        if not self.ended and self.last_id >= 0:
            try:
                counters = self.report()
            except Exception:  # noqa: BLE001 (a report must never keep the stream from ending)
                log.exception("counting the frames lost")
                counters = {}
            self.client.end_of_stream(self.last_id, self.last_id + 1, counters)
            log.info("end of stream after frame %d (%s)", self.last_id, why)
        self.ended = True

    def stop(self, timeout: float = 30.0) -> None:
        """Lockstep: send what is queued first. Then end the stream, so semmap writes its files."""
        with self._cv:
            self._stopping = True
            self._cv.notify_all()
        self._thread.join(timeout if self.lockstep else 5.0)
        with self._cv:
            self.counters["dropped_at_stop"] += len(self._queue)  # lockstep: not sent within `timeout`
            self._queue.clear()
            self._end_locked("the bridge stops")

    def status(self) -> dict:
        processed = self.client.frames_done()  # what every pipeline service has finished (its Progress)
        with self._cv:
            return {
                "semmap_ready": self.ready,
                "frames_sent": self.last_id + 1,
                "frames_done": min(processed, self.last_id + 1),
                "queued": len(self._queue),
                "ended": self.ended,
                # the robot's poses not sent: the run poses the frames with its own front end (run file: front_end)
                "poses_not_sent": self.client.poses_not_sent,
            }


LOSS_REASONS = (  # sync counters that are a colour image (a frame) lost, in the order a frame meets them
    "bad_colour",
    "no_camera_info",
    "colour_without_depth",
    "colour_without_pose",
    "size_mismatch",
    "colour_unmatched_at_end",
)


def lost_frames(sync: Counter, link: Counter, gaps: dict, status: dict, camera_missing: int = 0) -> dict:
    """Every frame lost between the camera and semmap, by reason: `before_bridge` (colour images missing: frames
    whose camera info arrived without them, holes in the joint colour + camera-info stamps, holes in the colour
    stamps, images before / after the colour stream where depth and camera info went on; the largest of these
    estimates: lost in transport or by a full reader history), each sync reason (colour images that did
    not become a frame), the link's drops (`dropped_busy`: real time, semmap busy; `dropped_at_stop`,
    `after_end_of_stream`); `not_processed`: sent to semmap, not (yet) finished by every service. `total`: their
    sum, the frames the camera sent (as far as stamps tell) that did not reach the map."""
    colour = gaps.get("colour", {})
    at_ends = missing_at_ends(colour, [gaps.get("depth", {}), gaps.get("camera_info", {})])
    lost = {"before_bridge": max(int(colour.get("missing", 0)) + at_ends, int(camera_missing))}
    for reason in LOSS_REASONS:
        lost[reason] = int(sync.get(reason, 0))
    for reason in ("dropped_busy", "dropped_at_stop", "after_end_of_stream"):
        lost[reason] = int(link.get(reason, 0))
    lost["not_processed"] = max(0, int(status.get("frames_sent", 0)) - int(status.get("frames_done", 0)))
    lost = {k: v for k, v in lost.items() if v}
    lost["total"] = sum(lost.values())
    return lost


def auto_input_depth(rate_hz: float, latency_s: float) -> int:
    """Best-effort input history: what the camera sends while the bridge's ROS thread is `latency_s` behind."""
    return max(10, int(math.ceil(max(rate_hz, 1.0) * max(latency_s, 0.1))))


def _declare(node: Any) -> dict[str, Any]:
    from rcl_interfaces.msg import ParameterDescriptor

    values = {}
    for name, field in Ros2BridgeConfig.model_fields.items():
        values[name] = node.declare_parameter(name, field.default,
                                              ParameterDescriptor(description=field.description or "")).value
    try:
        return Ros2BridgeConfig.model_validate(values).model_dump()
    except ValidationError as exc:
        raise ValueError(f"bad ROS parameters: {exc}") from None


def run_bridge(
    robot: str, connect: str, zenoh_mode: str | None, ros_args: list[str], fastdds_profile: bool = True,
    check_slam: bool = False,
    front_end: str = "",
) -> int:
    """The bridge's process: rclpy node + Zenoh client until SIGINT / SIGTERM."""
    environment.set_default(environment.ROS_DISCOVERY_RANGE, "LOCALHOST")  # safe default: no multicast off-host
    # shared memory + large loopback buffers, unless the user set a profile of their own; it confines DDS to
    # this host, so not when the user asked for discovery beyond it (a camera on another computer)
    if fastdds_profile and environment.read(environment.ROS_DISCOVERY_RANGE) == "LOCALHOST":
        log.info("Fast DDS profile: %s", use_profile())
    try:
        import rclpy
        from rclpy.executors import ExternalShutdownException

        node_class = _make_node_class()
    except ImportError as exc:
        print(f"error: the ROS 2 bridge needs the ros2 extra (pip install 'semmap[ros2]'): {exc}", file=sys.stderr)
        return 2
    from semmap.runtime.client import SemmapClient

    rclpy.init(args=["semmap_ros2", *ros_args])
    client = None
    node = None
    try:
        client = SemmapClient(robot, connect, zenoh_mode, check_slam=check_slam, front_end=front_end)
        node = node_class(client)
        node.start()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:  # a bad parameter value
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        try:
            if node is not None:
                node.stop()
                node.destroy_node()
        finally:
            if client is not None:
                client.close()
            rclpy.try_shutdown()
    return 0


@functools.cache
def _ros() -> SimpleNamespace:
    """rclpy, SciPy's rotations and the ROS message classes the node uses, imported on first use: only the bridge
    needs them (ImportError without the ros2 extra)."""
    from builtin_interfaces.msg import Duration, Time
    from geometry_msgs.msg import (
        Point,
        Pose,
        PoseStamped,
        PoseWithCovarianceStamped,
        Quaternion,
        TransformStamped,
        Vector3,
    )
    from nav_msgs.msg import Odometry, Path
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image
    from std_msgs.msg import ColorRGBA, String
    from visualization_msgs.msg import Marker, MarkerArray

    return SimpleNamespace(
        Duration=Duration,
        Time=Time,
        Point=Point,
        Pose=Pose,
        PoseStamped=PoseStamped,
        PoseWithCovarianceStamped=PoseWithCovarianceStamped,
        Quaternion=Quaternion,
        TransformStamped=TransformStamped,
        Vector3=Vector3,
        Odometry=Odometry,
        Path=Path,
        Node=Node,
        DurabilityPolicy=DurabilityPolicy,
        HistoryPolicy=HistoryPolicy,
        QoSProfile=QoSProfile,
        ReliabilityPolicy=ReliabilityPolicy,
        Rotation=Rotation,
        CameraInfo=CameraInfo,
        CompressedImage=CompressedImage,
        Image=Image,
        ColorRGBA=ColorRGBA,
        String=String,
        Marker=Marker,
        MarkerArray=MarkerArray,
    )


# pose_type: (the ROS type name, its class's name in `_ros()`)
POSE_TYPES = {
    "odometry": ("nav_msgs/msg/Odometry", "Odometry"),
    "pose": ("geometry_msgs/msg/PoseStamped", "PoseStamped"),
    "pose_with_covariance": ("geometry_msgs/msg/PoseWithCovarianceStamped", "PoseWithCovarianceStamped"),
}


def input_qos(p: dict) -> Any:
    """The inputs' QoS (see `input_depth`): reliable input keeps all by default (the bridge's reader never
    drops; lockstep's back-pressure reaches the camera), best effort keeps rate x latency messages."""
    ros = _ros()
    reliable = bool(p["reliable_input"])
    reliability = ros.ReliabilityPolicy.RELIABLE if reliable else ros.ReliabilityPolicy.BEST_EFFORT
    depth = int(p["input_depth"])
    if depth > 0:
        return ros.QoSProfile(depth=depth, reliability=reliability)
    if reliable:
        return ros.QoSProfile(history=ros.HistoryPolicy.KEEP_ALL, reliability=reliability)
    return ros.QoSProfile(
        depth=auto_input_depth(float(p["camera_rate_hz"]), float(p["input_latency_s"])), reliability=reliability
    )


def ros_time(t: float) -> Any:
    """A stamp in seconds as a builtin_interfaces/Time."""
    ros = _ros()
    sec = math.floor(t)
    return ros.Time(sec=int(sec), nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


def ros_pose(matrix: np.ndarray) -> Any:
    """A 4x4 rigid transform as a geometry_msgs/Pose."""
    ros = _ros()
    x, y, z, w = matrix_quaternion(matrix[:3, :3])
    t = matrix[:3, 3]
    return ros.Pose(
        position=ros.Point(x=float(t[0]), y=float(t[1]), z=float(t[2])), orientation=ros.Quaternion(x=x, y=y, z=z, w=w)
    )


class _BridgeNodeMethods:
    """The bridge node's input side: its parameters, subscriptions, matching, the Zenoh link to semmap and its
    status (see the module docstring). A plain class, so that rclpy is imported only when the node class is made
    (`_make_node_class` joins it with `_BridgeOutputs` and rclpy's Node)."""

    def __init__(self, client: Any) -> None:
        super().__init__("semmap_bridge")  # (rclpy's Node, after this class in the node class's bases)
        p = _declare(self)
        if p["pose_type"] not in POSE_TYPES:
            raise ValueError(f"pose_type must be one of {', '.join(POSE_TYPES)}, got {p['pose_type']!r}")
        self.params = p
        self.client = client
        self.counters: Counter[str] = Counter()
        self.sync = FrameSync(
            p["sync_tolerance_s"],
            p["pose_max_gap_s"],
            p["max_wait_s"],
            parse_pose_to_optical(str(p["pose_to_optical"])),
        )
        self.link = SemmapLink(
            client,
            bool(p["lockstep"]),
            int(p["queue_size"]),
            (float(p["sigma_translation_m"]), math.radians(float(p["sigma_rotation_deg"]))),
            float(p["end_after_idle_s"]),
            self.counters,
        )
        self.link.report = self._lost_before_semmap
        self.lock = threading.Lock()  # the map and trajectory state is updated from Zenoh threads
        self.landmarks: dict[int, Landmark] = {}
        self.arrivals: Counter[str] = Counter()
        self.warned: dict[str, float] = {}
        pose_name = self._subscribe_inputs(p)
        self._declare_outputs()
        self.started = time.monotonic()
        self.last_input = time.monotonic()
        self.quiet_seen = False
        self.create_timer(1.0, self._tick)
        self.create_timer(0.1, self._flush_if_quiet)
        self.deleted: set[int] = set()
        self.map_dirty = False
        # the optimised trajectory, kept by applying each `poses/corrected` delta (semmap.corrected_poses/2)
        self.poses: dict[int, np.ndarray] = {}
        self.stamps: dict[int, float] = {}
        self.trajectory_dirty = False
        self.create_timer(float(p["output_period_s"]), self._publish_outputs)
        client.on_map_update(self._on_map_update)
        client.on_corrected_poses(self._on_corrected)
        client.on_observations(self._on_observations)
        client.on_dynamic(self._on_dynamic)
        self.get_logger().info(
            f"in: {self._topic('colour')}, {self._topic('depth')}, {self._topic('camera_info')}, "
            f"{self._topic('pose')} ({pose_name}); out: {LANDMARKS_TOPIC}, {TRAJECTORY_TOPIC}, "
            f"{CORRECTION_TOPIC}, {OBSERVATIONS_TOPIC}, {DYNAMIC_TOPIC}; "
            f"{'lockstep' if p['lockstep'] else 'real time'}, "
            f"tolerance {p['sync_tolerance_s']} s, ROS_AUTOMATIC_DISCOVERY_RANGE="
            f"{environment.read(environment.ROS_DISCOVERY_RANGE)}"
        )

    def _subscribe_inputs(self, p: dict[str, Any]) -> str:
        """The camera and pose subscriptions (`self.inputs`, by role, with the type each expects); returns the
        pose topic's type name."""
        ros = _ros()
        qos = input_qos(p)
        self.input_history = "keep all" if qos.history == ros.HistoryPolicy.KEEP_ALL else f"keep last {qos.depth}"
        pose_name, pose_class_name = POSE_TYPES[p["pose_type"]]
        pose_class = getattr(ros, pose_class_name)
        self.inputs = {
            "colour": (self.create_subscription(ros.Image, COLOUR_TOPIC, self._on_colour, qos), "sensor_msgs/Image"),
            "depth": (self.create_subscription(ros.Image, DEPTH_TOPIC, self._on_depth, qos), "sensor_msgs/Image"),
            "camera_info": (
                self.create_subscription(ros.CameraInfo, INFO_TOPIC, self._on_info, qos),
                "sensor_msgs/CameraInfo",
            ),
            "pose": (
                self.create_subscription(pose_class, POSE_TOPIC, lambda m: self._on_pose(m, pose_name), qos),
                pose_name,
            ),
        }
        # a compressed colour stream is taken too when that is what the camera sends
        self.create_subscription(ros.CompressedImage, COLOUR_TOPIC + "/compressed", self._on_compressed, qos)
        return pose_name

    def _declare_outputs(self) -> None:
        """The publishers: the map, trajectory and correction latched (a late RViz gets the latest)."""
        ros = _ros()
        latched = ros.QoSProfile(
            depth=1, reliability=ros.ReliabilityPolicy.RELIABLE, durability=ros.DurabilityPolicy.TRANSIENT_LOCAL
        )
        self.markers_pub = self.create_publisher(ros.MarkerArray, LANDMARKS_TOPIC, latched)
        self.path_pub = self.create_publisher(ros.Path, TRAJECTORY_TOPIC, latched)
        self.correction_pub = self.create_publisher(ros.TransformStamped, CORRECTION_TOPIC, latched)
        self.observations_pub = self.create_publisher(ros.Odometry, OBSERVATIONS_TOPIC, 100)
        self.dynamic_pub = self.create_publisher(ros.MarkerArray, DYNAMIC_TOPIC, 10)
        self.status_pub = self.create_publisher(ros.String, STATUS_TOPIC, 10)

    def _topic(self, role: str) -> str:
        return self.inputs[role][0].topic_name

    def start(self) -> None:
        self.link.start()

    def stop(self) -> None:
        """After rclpy's shutdown (SIGINT / SIGTERM): nothing can be published any more; the counters go to
        the log."""
        self._forward(self.sync.finish())  # the last frame of a recording is sent, the rest counted
        self.link.stop()
        log.info("stopped: %s", json.dumps(self._status()))

    # -- inputs ------------------------------------------------------------------------------------------
    def _forward(self, frames: list[MatchedFrame]) -> None:
        for frame in frames:
            self.link.submit(frame)  # lockstep: may wait for room
        self.last_input = time.monotonic()
        self.quiet_seen = False

    def _flush_if_quiet(self) -> None:
        """No input for `flush_after_s`: frames held for a closer depth image or a newer pose go with what
        there is (the last frame of a recording), or are counted. Quiet must be seen by two ticks in a row
        with no input between them: after a stall of the ROS thread the executor runs a due timer before the
        messages that waited, which must not be mistaken for the end."""
        quiet = time.monotonic() - self.last_input > float(self.params["flush_after_s"])
        if not (quiet and self.sync.pending()):
            self.quiet_seen = False
            return
        if not self.quiet_seen:
            self.quiet_seen = True
            return
        self.quiet_seen = False
        self._forward(self.sync.flush())

    def _on_colour(self, msg: Any) -> None:
        self.arrivals["colour"] += 1
        self._forward(self.sync.add_colour(msg))

    def _on_compressed(self, msg: Any) -> None:
        self.arrivals["colour"] += 1
        self._forward(self.sync.add_colour(msg, compressed=True))

    def _on_depth(self, msg: Any) -> None:
        self.arrivals["depth"] += 1
        self._forward(self.sync.add_depth(msg))

    def _on_info(self, msg: Any) -> None:
        self.arrivals["camera_info"] += 1
        self._forward(self.sync.add_camera_info(msg))

    def _on_pose(self, msg: Any, msgtype: str) -> None:
        self.arrivals["pose"] += 1
        self._forward(self.sync.add_pose(msg, msgtype))

    def _tick(self) -> None:
        """Once a second: report inputs that never arrived, publish the counters."""
        ros = _ros()
        now = time.monotonic()
        timeout = float(self.params["topic_timeout_s"])
        for role, (sub, kind) in self.inputs.items():
            quiet = now - self.warned.get(role, -1e9) > 30
            if self.arrivals[role] == 0 and now - self.started >= timeout and quiet:
                self.warned[role] = now
                self.get_logger().warning(
                    f"no message on {sub.topic_name} ({kind}) after {now - self.started:.0f} s: is it published? "
                    f"remap with --ros-args -r {sub.topic_name}:=/your/topic"
                )
        self.status_pub.publish(ros.String(data=json.dumps(self._status())))

    def _status(self) -> dict:
        missing = [self.inputs[r][0].topic_name for r in self.inputs if self.arrivals[r] == 0]
        gaps = {role: g.as_dict() for role, g in self.sync.gaps.items()}
        link = self.link.status()
        return {
            "received": dict(self.arrivals),
            "sync": dict(self.sync.counters),
            "link": dict(self.counters),
            "gaps": gaps,
            **link,
            "lost": lost_frames(
                self.sync.counters, self.counters, gaps, link, self.sync.camera_frames.colour_missing()
            ),
            "camera_frames": self.sync.camera_frames.frames(),
            "input_history": self.input_history,
            "missing_topics": missing,
        }

    def _lost_before_semmap(self) -> dict[str, int]:
        """What end-of-stream reports to the run: frames lost between the camera and semmap, by reason."""
        gaps = {role: g.as_dict() for role, g in self.sync.gaps.items()}
        lost = lost_frames(self.sync.counters, self.counters, gaps, {}, self.sync.camera_frames.colour_missing())
        lost.pop("total", None)
        return {**lost, "total": sum(lost.values())}



class _BridgeOutputs:
    """The bridge node's output side: what semmap sends back (map updates, corrected poses, dynamic objects,
    landmark observations) as ROS 2 messages, published from the node's timer and Zenoh threads under its lock."""

    def _frame_id(self) -> str:
        return str(self.params["map_frame"]) or self.sync.world_frame or "map"

    def _on_map_update(self, update: MapUpdate) -> None:
        """(Zenoh thread) Keep the map; the timer publishes it (at most every `output_period_s`)."""
        with self.lock:
            before = set(self.landmarks)
            if update.full:
                self.landmarks = {lm.id: lm for lm in update.landmarks}
            else:
                for lm in update.landmarks:
                    self.landmarks[lm.id] = lm
                for gone in [*update.removed, *(absorbed for absorbed, _ in update.merges)]:
                    self.landmarks.pop(gone, None)
            self.deleted |= before - set(self.landmarks)
            self.map_dirty = True

    def _on_corrected(self, corrected: CorrectedPoses) -> None:
        """(Zenoh thread) Keep the newest estimate; the timer publishes it (a 1000-pose Path takes ~20 ms to
        build: not for every frame)."""
        with self.lock:
            if corrected.full:
                self.stamps.clear()
            corrected.apply_to(self.poses)
            self.stamps.update(
                zip((int(f) for f in corrected.frame_ids), (float(t) for t in corrected.stamps), strict=True)
            )
            self.trajectory_dirty = True

    def _publish_outputs(self) -> None:
        """(ROS timer) The latest map and trajectory, if they changed."""
        with self.lock:
            markers = self._markers(sorted(self.deleted)) if self.map_dirty else None
            self.deleted, self.map_dirty = set(), False
            trajectory = None
            if self.trajectory_dirty:
                ids = sorted(self.poses)
                trajectory = (ids, [self.stamps[i] for i in ids], np.array([self.poses[i] for i in ids]))
                self.trajectory_dirty = False
        if markers is not None:
            self.markers_pub.publish(markers)
        if trajectory is not None and trajectory[0]:
            self._publish_trajectory(*trajectory)

    def _markers(self, deleted: list[int]) -> Any:
        ros = _ros()
        frame = self._frame_id()
        out = ros.MarkerArray()
        for lid in deleted:
            for ns in ("landmarks", "labels"):
                out.markers.append(ros.Marker(ns=ns, id=lid, action=ros.Marker.DELETE))
                out.markers[-1].header.frame_id = frame
        for lm in sorted(self.landmarks.values(), key=lambda x: x.id):
            r, g, b = class_colour(lm.class_name)
            pose = ros.Pose(
                position=ros.Point(x=float(lm.centroid[0]), y=float(lm.centroid[1]), z=float(lm.centroid[2])),
                orientation=ros.Quaternion(w=1.0),
            )
            cube = ros.Marker(
                ns="landmarks",
                id=lm.id,
                type=ros.Marker.CUBE,
                action=ros.Marker.ADD,
                pose=pose,
                scale=ros.Vector3(
                    x=max(float(lm.extent[0]), 0.02),
                    y=max(float(lm.extent[1]), 0.02),
                    z=max(float(lm.extent[2]), 0.02),
                ),
                color=ros.ColorRGBA(r=r, g=g, b=b, a=0.6),
            )
            label = ros.Marker(
                ns="labels",
                id=lm.id,
                type=ros.Marker.TEXT_VIEW_FACING,
                action=ros.Marker.ADD,
                pose=pose,
                scale=ros.Vector3(z=0.08),
                color=ros.ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0),
                text=f"{lm.class_name} #{lm.id}",
            )
            for marker in (cube, label):
                marker.header.frame_id = frame  # stamp 0: RViz draws with the latest transform
                out.markers.append(marker)
        return out

    def _publish_trajectory(self, ids: list[int], stamps: list[float], poses: np.ndarray) -> None:
        ros = _ros()
        frame = self._frame_id()
        path = ros.Path()
        path.header.frame_id = frame
        limit = max(2, int(self.params["path_max_poses"]))
        keep = np.unique(np.linspace(0, len(ids) - 1, min(limit, len(ids))).round().astype(int))  # newest kept
        quats = ros.Rotation.from_matrix(poses[keep, :3, :3]).as_quat()
        items = []
        for k, q in zip(keep, quats, strict=True):
            pose = poses[k]
            item = ros.PoseStamped()
            item.header.frame_id = frame
            item.header.stamp = ros_time(float(stamps[k]))
            position, orientation = item.pose.position, item.pose.orientation
            position.x, position.y, position.z = float(pose[0, 3]), float(pose[1, 3]), float(pose[2, 3])
            orientation.x, orientation.y, orientation.z, orientation.w = (float(v) for v in q)
            items.append(item)
        path.poses = items
        path.header.stamp = ros_time(float(stamps[-1]))
        self.path_pub.publish(path)
        sent = self.link.sent
        for fid, pose in zip(ids[::-1], poses[::-1], strict=True):
            frame_sent = sent.get(int(fid))
            if frame_sent is not None:  # corrected <- SLAM world: T = P_corrected @ inv(P_slam)
                correction = pose @ np.linalg.inv(frame_sent.pose)
                msg = ros.TransformStamped()
                msg.header.frame_id = str(self.params["corrected_frame"])
                msg.header.stamp = ros_time(frame_sent.stamp)
                msg.child_frame_id = frame
                q = ros_pose(correction)
                msg.transform.translation = ros.Vector3(x=q.position.x, y=q.position.y, z=q.position.z)
                msg.transform.rotation = q.orientation
                self.correction_pub.publish(msg)
                break

    def _on_dynamic(self, objects: DynamicObjects) -> None:
        """(Zenoh thread) A detected frame's dynamic objects as boxes in the world, published at once (they are
        about now; each lives `dynamic_lifetime_s`, so an object that left vanishes). A frame that was not
        detected repeats older boxes: nothing is published for it, the boxes of the last detected frame live on
        until their lifetime ends."""
        ros = _ros()
        if objects.skipped:
            return
        sent = self.link.sent.get(objects.frame_id)
        if sent is None:
            self.counters["dynamic_unknown_frame"] += 1
            return
        frame = self._frame_id()
        stamp = ros_time(objects.stamp)
        lifetime = max(float(self.params["dynamic_lifetime_s"]), 0.0)
        life = ros.Duration(sec=int(lifetime), nanosec=int(round((lifetime % 1.0) * 1e9)))
        out = ros.MarkerArray()
        for box in objects.boxes:
            placed = dynamic_box_in_world(box, sent.intrinsics, sent.pose)
            if placed is None:
                self.counters["dynamic_without_depth"] += 1
                continue
            centre, rotation, size = placed
            x, y, z, w = matrix_quaternion(rotation)
            r, g, b = track_colour(box.track_id)
            position = ros.Point(x=float(centre[0]), y=float(centre[1]), z=float(centre[2]))
            cube = ros.Marker(
                ns="dynamic",
                id=box.track_id,
                type=ros.Marker.CUBE,
                action=ros.Marker.ADD,
                pose=ros.Pose(position=position, orientation=ros.Quaternion(x=x, y=y, z=z, w=w)),
                scale=ros.Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])),
                color=ros.ColorRGBA(r=r, g=g, b=b, a=0.5),
                lifetime=life,
            )
            why = " moving" if box.reason == "moving" else ""
            label = ros.Marker(
                ns="dynamic_labels",
                id=box.track_id,
                type=ros.Marker.TEXT_VIEW_FACING,
                action=ros.Marker.ADD,
                pose=ros.Pose(position=ros.Point(x=position.x, y=position.y, z=position.z),
                              orientation=ros.Quaternion(w=1.0)),
                scale=ros.Vector3(z=0.1),
                color=ros.ColorRGBA(r=r, g=g, b=b, a=1.0),
                text=f"{box.class_name}{why} (track {box.track_id})",
                lifetime=life,
            )
            for marker in (cube, label):
                marker.header.frame_id = frame
                marker.header.stamp = stamp
                out.markers.append(marker)
        if out.markers:
            self.counters["dynamic_boxes"] += len(out.markers) // 2
            with self.lock:
                self.dynamic_pub.publish(out)

    def _on_observations(self, observations: Observations) -> None:
        ros = _ros()
        sent = self.link.sent.get(observations.frame_id)
        camera_frame = sent.camera_frame if sent is not None else "camera_color_optical_frame"
        for obs in observations.observations:
            msg = ros.Odometry(child_frame_id=f"semmap_landmark_{obs.landmark_id}")
            msg.header.frame_id = camera_frame
            msg.header.stamp = ros_time(observations.stamp)
            msg.pose.pose.position = ros.Point(
                x=float(obs.point_camera[0]), y=float(obs.point_camera[1]), z=float(obs.point_camera[2])
            )
            msg.pose.pose.orientation = ros.Quaternion(w=1.0)
            # position: the observation's isotropic sigma; orientation: unconstrained (an object centroid)
            msg.pose.covariance = [float(v) for v in np.diag([obs.sigma**2] * 3 + [1e6] * 3).reshape(36)]
            msg.twist.covariance[0] = -1.0  # no twist (the REP 145 "unknown" marker)
            with self.lock:
                self.observations_pub.publish(msg)


def _make_node_class() -> type:
    """The node class (rclpy's Node with the bridge's methods), made here so that rclpy and the message packages
    are imported only by the bridge."""
    return type("_BridgeNode", (_BridgeNodeMethods, _BridgeOutputs, _ros().Node), {})


def main(argv: list[str] | None = None) -> int:
    """`semmap ros2 [--robot R] [--connect EP] [--ros-args ...]` (also `python -m semmap.services.ros2.bridge`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args: list[str] = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i:]
    parser = argparse.ArgumentParser(
        prog="semmap ros2", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    return run(args, ros_args)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--robot",
        default=None,
        help="semmap robot name (key space semmap/v1/<robot>); without --connect, the live run of this robot is "
        "served (default: the only live run on this host, whatever its robot)",
    )
    parser.add_argument(
        "--run",
        metavar="OUT_DIR",
        default=None,
        help="serve the run whose out dir this is (its run.json: endpoint, robot, run id)",
    )
    parser.add_argument(
        "--connect",
        default=None,
        help="semmap's Zenoh endpoint, e.g. tcp/HOST:7447 (env SEMMAP_ZENOH_CONNECT); default: found from the "
        "run's own record (--run, else the only live run of --robot on this host)",
    )
    parser.add_argument("--zenoh-mode", default=None, choices=("peer", "client"))
    parser.add_argument(
        "--no-fastdds-profile",
        action="store_true",
        help="do not load semmap's Fast DDS profile (shared memory + large loopback buffers; loaded by default "
        "unless FASTDDS_DEFAULT_PROFILES_FILE is set)",
    )
    parser.add_argument(
        "--write-fastdds-profile",
        metavar="PATH",
        default=None,
        help="write that profile to PATH and exit: export FASTDDS_DEFAULT_PROFILES_FILE=PATH for your camera node",
    )
    parser.add_argument(
        "--check-slam",
        action="store_true",
        help="send the SLAM's poses to be checked against semmap's own registration (a run started with "
        "`semmap run external --check-slam`; found by --run / --robot, this follows the run by itself)",
    )
    parser.add_argument("-v", "--verbose", action="store_true")


def run(args: argparse.Namespace, ros_args: list[str]) -> int:
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s"
    )
    if args.write_fastdds_profile:
        print(write_profile(args.write_fastdds_profile))
        return 0
    from semmap.runtime.transport.run_registry import RunNotFound, find_run

    connect = args.connect or environment.read(environment.ZENOH_CONNECT)
    robot = args.robot
    check_slam = bool(args.check_slam)
    front_end = ""  # (a run that poses the frames itself says so in its run file)
    if args.run or not connect:
        try:
            info = find_run(args.run, None if args.run else robot)
        except (RunNotFound, OSError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if robot and info.robot != robot:
            print(f"error: the run in {args.run} maps robot {info.robot!r}, not {robot!r}", file=sys.stderr)
            return 2
        connect = connect if args.connect else info.endpoint
        robot = info.robot
        check_slam = check_slam or info.check_slam  # (the run says whether it checks the SLAM's poses)
        front_end = info.front_end
        log.info("serving run %s (robot %s, %s, out %s)", info.run_id, info.robot, connect, info.out_dir)
    return run_bridge(
        robot or "robot1",
        connect,
        args.zenoh_mode,
        ros_args,
        not args.no_fastdds_profile,
        check_slam,
        front_end,
    )


if __name__ == "__main__":
    sys.exit(main())
