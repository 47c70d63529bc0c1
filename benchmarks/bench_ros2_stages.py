"""Per-message cost of the ROS 2 bridge (`semmap ros2`) for 30 Hz 640x480 RGB-D input; prints p50 / p95.

    python benchmarks/bench_ros2_stages.py [--frames 300] [--data ../shared/data/7scenes-redkitchen]

Stages, per frame, measured on real rclpy messages and a real Zenoh session (loopback, a subscriber taking the
frames as semmap's services would):
  camera   publish() of colour (rgb8) + depth (16UC1) + pose (Odometry): the camera node's serialisation
  dds      from there until the bridge's callbacks have them (transport, deserialisation into rclpy messages);
           both nodes in this process, on one executor
  convert  the bridge's conversion and approximate-time matching (semmap.services.ros2.sync.FrameSync)
  send     to semmap: JPEG encoding of the colour image, msgpack, Zenoh put of frame and pose (semmap.runtime.client)
  markers  a MarkerArray of 50 landmarks built and published (at most every output_period_s, 1 s)
  path     a Path of 1000 optimised poses (thinned to path_max_poses, 500) + the correction (likewise)
  dynamic  a frame's dynamic objects (3 people) as a MarkerArray on /semmap/dynamic (per detected frame, on the
           Zenoh side)
The bridge keeps up with 30 Hz when each of its two threads stays under 33.3 ms a frame at p95: the ROS side
(dds + convert) and the Zenoh side (send); they run in parallel.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(150 + os.getpid() % 50))

PROJECT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PROJECT))


def _pct(values: list[float]) -> str:
    values = sorted(values)
    p95 = values[min(len(values) - 1, int(round(0.95 * (len(values) - 1))))]
    return f"p50 {statistics.median(values):6.2f} ms   p95 {p95:6.2f} ms   (n={len(values)})"


def _frames(data: str | None, count: int) -> list:
    from semmap.datasets import find_data_root, open_dataset

    root = Path(data) if data else (find_data_root() or Path("/nonexistent")) / "7scenes-redkitchen"
    if root.exists():
        dataset = open_dataset(root)
        return [dataset[i % len(dataset)] for i in range(min(count, 60))]
    print(f"({root} absent: synthetic 640x480 frames)", file=sys.stderr)
    return [open_dataset("synthetic:frames=30,size=640x480")[i] for i in range(30)]


def _loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--data", default=None)
    args = parser.parse_args(argv)

    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from semmap.core.messages import CorrectedPoses, DynamicBox, DynamicObjects, Frame, Landmark, MapUpdate
    from semmap.runtime.client import SemmapClient
    from semmap.runtime.orchestrator import free_loopback_port
    from semmap.runtime.transport.bus import Bus, BusConfig
    from semmap.services.ros2.bridge import SentFrame, _make_node_class
    from tests.ros2.ros_nodes import _image, _odometry

    load_before = _loadavg()
    frames = _frames(args.data, args.frames)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = Bus(BusConfig(mode="router", listen=[endpoint]), "bench")
    received = threading.Event()
    got = {"n": 0}

    def on_frame(frame: Frame) -> None:
        got["n"] += 1
        received.set()

    sink = Bus(BusConfig(mode="client", connect=[endpoint], listen=[]), "bench")
    sink.subscribe(sink.keys.frames, Frame, on_frame)
    client = SemmapClient("bench", endpoint, "client")

    rclpy.init()
    node = _make_node_class()(client)  # the bridge's node, its link not started: sends are timed below
    camera = rclpy.create_node("bench_camera")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {
        "colour": camera.create_publisher(Image, "/camera/camera/color/image_raw", qos),
        "depth": camera.create_publisher(Image, "/camera/camera/aligned_depth_to_color/image_raw", qos),
        "pose": camera.create_publisher(Odometry, "/odom", qos),
    }
    inbox: list = []
    node.link.submit = inbox.append  # what the ROS callbacks hand to the Zenoh thread
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(camera)
    deadline = time.monotonic() + 20
    while any(p.get_subscription_count() == 0 for p in pubs.values()) and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    node.sync.intrinsics = (585.0, 585.0, 320.0, 240.0, 640, 480)
    messages = [
        (
            _image(f.stamp + k * 2.0, "rgb8", f.rgb),
            _image(f.stamp + k * 2.0, "16UC1", f.depth),
            _odometry(f.stamp + k * 2.0, f.gt_pose),
        )
        for k in range(2)
        for f in frames[:30]
    ]

    dds, convert, send, camera_side = [], [], [], []
    original = {"colour": node._on_colour, "depth": node._on_depth}
    timing = {"convert": 0.0}

    def timed(fn):
        def wrapper(msg):
            t0 = time.perf_counter()
            fn(msg)
            timing["convert"] += time.perf_counter() - t0

        return wrapper

    node._on_colour_timed = timed(original["colour"])
    for sub in node.subscriptions:  # time the bridge's own callbacks
        cb = sub.callback
        sub.callback = timed(cb)
    period = 1.0 / 30.0
    next_at = time.monotonic()
    for i in range(args.frames):
        colour, depth, pose = messages[i % len(messages)]
        stamp = 1000.0 + i * period
        for m in (colour, depth, pose):
            m.header.stamp.sec, m.header.stamp.nanosec = int(stamp), int(round((stamp % 1) * 1e9))
        timing["convert"] = 0.0
        before = len(inbox)
        t0 = time.perf_counter()
        pubs["colour"].publish(colour)
        pubs["depth"].publish(depth)
        pubs["pose"].publish(pose)
        camera_side.append((time.perf_counter() - t0) * 1e3)
        while len(inbox) == before and time.perf_counter() - t0 < 2.0:
            executor.spin_once(timeout_sec=0.01)
        total = time.perf_counter() - t0
        if len(inbox) == before:
            continue
        dds.append((total - timing["convert"]) * 1e3 - camera_side[-1])
        convert.append(timing["convert"] * 1e3)
        matched = inbox[-1]
        received.clear()
        t1 = time.perf_counter()
        fx, fy, cx, cy, _, _ = matched.intrinsics
        client.publish_frame(i, matched.stamp, matched.rgb, matched.depth_mm, 0.001, (fx, fy, cx, cy))
        client.publish_pose(i, matched.stamp, matched.pose)
        send.append((time.perf_counter() - t1) * 1e3)
        received.wait(2.0)
        next_at += period
        time.sleep(max(0.0, next_at - time.monotonic()))

    rng = np.random.default_rng(0)
    landmarks = [
        Landmark(i, ["cup", "chair", "tv", "book"][i % 4], tuple(rng.normal(size=3)), 0.1, (0.1, 0.2, 0.3), 5, 0.0, 1.0)
        for i in range(50)
    ]
    markers, path = [], []
    for k in range(50):
        update = MapUpdate("bench", k, k, float(k), landmarks, removed=[100 + k], full=False)
        t0 = time.perf_counter()
        node._on_map_update(update)
        node._publish_outputs()
        markers.append((time.perf_counter() - t0) * 1e3)
    poses = np.repeat(np.eye(4)[None], 1000, axis=0)
    if inbox:
        last = inbox[-1]
        node.link.sent[999] = SentFrame(last.stamp, last.pose, last.intrinsics, last.camera_frame)
    for k in range(20):
        corrected = CorrectedPoses("bench", k, 999, np.arange(1000), np.arange(1000) / 30.0, poses)
        t0 = time.perf_counter()
        node._on_corrected(corrected)
        node._publish_outputs()
        path.append((time.perf_counter() - t0) * 1e3)

    dynamic = []
    if inbox:
        boxes = [
            DynamicBox(k, "person", (100.0 + 150 * k, 80.0, 220.0 + 150 * k, 460.0), 1.5, 2.1, "class")
            for k in range(3)
        ]
        for _ in range(100):
            objects = DynamicObjects("bench", 999, node.link.sent[999].stamp, boxes)
            t0 = time.perf_counter()
            node._on_dynamic(objects)
            dynamic.append((time.perf_counter() - t0) * 1e3)

    print(
        f"ROS 2 bridge, 640x480 rgb8 + 16UC1 + Odometry at 30 Hz, {len(dds)} frames "
        f"({len(frames)} distinct 7-Scenes frames), {os.cpu_count()} CPUs:"
    )
    print(f"  camera   {_pct(camera_side)}   (the publisher's serialisation: the camera node's cost)")
    print(f"  dds      {_pct(dds)}   (transport and deserialisation into the bridge's callbacks)")
    print(f"  convert  {_pct(convert)}")
    print(f"  send     {_pct(send)}   (frames received by the Zenoh subscriber: {got['n']})")
    print(f"  markers  {_pct(markers)}   (50 landmarks, at most once a second)")
    print(f"  path     {_pct(path)}   (1000 poses -> 500, at most once a second)")
    if dynamic:
        print(f"  dynamic  {_pct(dynamic)}   (3 boxes, per detected frame, Zenoh side)")
    print(f"  load average before / after: {load_before} / {_loadavg()}")
    ros_side = [a + b for a, b in zip(dds, convert, strict=True)]
    worst = max(sorted(ros_side)[int(0.95 * (len(ros_side) - 1))], sorted(send)[int(0.95 * (len(send) - 1))])
    print(f"  per frame: ROS side {_pct(ros_side)}; Zenoh side {_pct(send)}")
    print(
        f"  keeps up with 30 Hz (33.3 ms a frame): {'yes' if worst < 33.3 else 'NO'} (p95 of the slower side "
        f"{worst:.1f} ms); unmatched or skipped: {dict(node.sync.counters)}"
    )
    executor.shutdown()
    camera.destroy_node()
    node.destroy_node()
    rclpy.try_shutdown()
    client.close()
    sink.close()
    router.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
