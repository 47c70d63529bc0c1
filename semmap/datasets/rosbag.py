"""ROS bags as datasets: a ROS 1 `.bag`, a rosbag2 folder (`.db3` or `.mcap` inside) or a single `.mcap` file.

Read with `rosbags` (pure Python, no ROS install). Topics are found by message type:
- colour: `sensor_msgs/Image` with a colour encoding (rgb8, bgr8, rgba8, bgra8, mono8) or `sensor_msgs/CompressedImage`;
- depth: `sensor_msgs/Image` 16UC1 (millimetres) or 32FC1 (metres), registered to the colour image;
- intrinsics: `sensor_msgs/CameraInfo` (the one beside the colour topic when there are several);
- camera pose: a `nav_msgs/Odometry`, `geometry_msgs/PoseStamped`, `PoseWithCovarianceStamped` or
  `TransformStamped` topic, else `/tf` (+ `/tf_static`) from `tf_parent` to `tf_child` (defaults: the root of
  the tree and the colour images' frame_id); `pose_to_optical` maps the pose's frame to the optical frame;
- ground truth: only from a topic named with `groundtruth=` (any pose type).
`topics="color=/a,depth=/b,camera_info=/c,pose=/d,groundtruth=/e"` overrides any role. When something is missing
or ambiguous the error lists every topic in the bag with its type.

Colour and depth are paired by header stamp (one-to-one, closest first, within `max_difference_s`, as TUM's
associate.py); each frame's pose is interpolated at its colour stamp between the two poses around it (no further
apart than `pose_max_gap_s`), and frames outside the pose stream are left out. Frames carry the ground truth as
`gt_pose` when a ground-truth topic is named, else the recorded camera pose: `--odometry gt` maps with the
recorded poses as they are, `file:PATH` with another trajectory.
"""

from __future__ import annotations

import bisect
import contextlib
import logging
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from semmap.datasets.ros_convert import (
    COLOUR_ENCODINGS,
    DEPTH_ENCODINGS,
    POSE_TYPES,
    TF_TYPE,
    ConversionError,
    camera_info_intrinsics,
    colour_to_rgb,
    compressed_to_rgb,
    depth_to_mm,
    parse_pose_to_optical,
    pose_at,
    pose_message,
    stamp_seconds,
    transform_matrix,
)

from .base import Dataset, DatasetError, EncodedImage, FrameData, Intrinsics
from .images import jpeg_size
from .tum import associate

log = logging.getLogger("semmap.datasets.rosbag")

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ROLES = ("color", "depth", "camera_info", "pose", "groundtruth")
DEPTH_SCALE = 0.001  # frames carry millimetres (32FC1 metres are converted)


def is_rosbag(path: Path) -> bool:
    """A ROS 1 .bag file, a single .mcap / .db3 file, or a rosbag2 folder (metadata.yaml beside its storage)."""
    if path.is_file():
        return path.suffix in (".bag", ".mcap", ".db3")
    return (
        path.is_dir() and (path / "metadata.yaml").is_file() and (any(path.glob("*.mcap")) or any(path.glob("*.db3")))
    )


def parse_topics(spec: str | dict | None) -> dict[str, str]:
    """'color=/cam/image,depth=/cam/depth' (or a dict) -> {role: topic}; unknown roles are errors."""
    if not spec:
        return {}
    if isinstance(spec, dict):
        items = [(str(k), str(v)) for k, v in spec.items()]
    else:
        items = []
        for part in filter(None, (p.strip() for p in str(spec).split(","))):
            role, sep, topic = part.partition("=")
            if not sep or not topic.strip():
                raise DatasetError(f"bad --topics entry {part!r}: expected role=/topic (roles: {', '.join(ROLES)})")
            items.append((role.strip(), topic.strip()))
    out = {}
    for role, topic in items:
        role = {"colour": "color", "rgb": "color", "info": "camera_info", "gt": "groundtruth"}.get(role, role)
        if role not in ROLES:
            raise DatasetError(f"unknown topic role {role!r} in --topics (roles: {', '.join(ROLES)})")
        out[role] = topic
    return out


def _cdr_header_stamp(raw: memoryview | bytes, ros2: bool) -> float:
    """The header stamp of a serialized message whose first field is std_msgs/Header, without deserializing the
    image behind it: CDR (4-byte encapsulation, then sec int32, nanosec uint32) or ROS 1 (seq, secs, nsecs)."""
    if ros2:
        endian = "<" if raw[1] == 1 else ">"
        sec, nsec = struct.unpack_from(endian + "iI", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec + nsec * 1e-9


@dataclass
class _Stream:
    """One image topic: the bag time (ns, for seeking) and header stamp of each message, in bag order."""

    topic: str
    msgtype: str
    connections: list[Any]
    log_ns: list[int] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)


class _TfTree:
    """Transforms from /tf and /tf_static: each child frame has one parent; dynamic edges are interpolated."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.static: dict[str, np.ndarray] = {}
        self.dynamic: dict[str, tuple[list[float], list[np.ndarray]]] = {}

    def add(self, msg: Any, static: bool) -> None:
        for t in msg.transforms:
            child, parent = str(t.child_frame_id).lstrip("/"), str(t.header.frame_id).lstrip("/")
            try:
                matrix = transform_matrix(t.transform.translation, t.transform.rotation)
            except ConversionError:
                continue
            self.parent[child] = parent
            if static:
                self.static[child] = matrix
            else:
                stamps, poses = self.dynamic.setdefault(child, ([], []))
                stamp = stamp_seconds(t.header.stamp)
                i = bisect.bisect_right(stamps, stamp)
                stamps.insert(i, stamp)
                poses.insert(i, matrix)

    @property
    def frames(self) -> set[str]:
        return set(self.parent) | set(self.parent.values())

    def chain(self, parent: str, child: str) -> list[str]:
        """Frames from `child` up to `parent` ("" = the root), child first; [] when not connected."""
        path, frame = [child], child
        while frame != parent:
            if frame not in self.parent:
                return path if not parent else []
            frame = self.parent[frame]
            if frame in path:  # a loop in a broken tree
                return []
            path.append(frame)
        return path

    def edge(self, child: str, t: float, max_gap: float) -> np.ndarray | None:
        if child in self.static:
            return self.static[child]
        stamps, poses = self.dynamic[child]
        return pose_at(stamps, poses, t, max_gap)

    def lookup(self, chain: list[str], t: float, max_gap: float) -> np.ndarray | None:
        out = np.eye(4)
        for child in chain[:-1]:
            edge = self.edge(child, t, max_gap)
            if edge is None:
                return None
            out = edge @ out
        return out


class RosbagDataset(Dataset):
    """Frames of one ROS bag (see the module docstring); depth in millimetres (scale 0.001)."""

    name = "rosbag"
    depth_scale = DEPTH_SCALE

    def __init__(
        self,
        path: str | Path,
        topics: str | dict | None = None,
        tf_parent: str = "",
        tf_child: str = "",
        pose_to_optical: str = "identity",
        max_difference_s: float = 0.02,
        pose_max_gap_s: float = 0.5,
    ) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.name = f"rosbag/{self.path.name}"
        self.max_difference_s = float(max_difference_s)
        self.pose_max_gap_s = float(pose_max_gap_s)
        try:
            self.pose_to_optical = parse_pose_to_optical(pose_to_optical)
        except ValueError as exc:
            raise DatasetError(str(exc)) from None
        wanted = parse_topics(topics)
        try:
            self.reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self.reader.open()
        except (AnyReaderError, OSError, ValueError, KeyError) as exc:
            raise DatasetError(f"cannot open ROS bag {self.path}: {exc}") from None
        try:
            self._index(wanted, tf_parent.strip().lstrip("/"), tf_child.strip().lstrip("/"))
        except BaseException:
            self.close()
            raise

    # -- discovery ---------------------------------------------------------------------------------------------
    def _listing(self) -> str:
        lines = []
        for topic, info in sorted(self.reader.topics.items()):
            extra = f" ({self._encodings[topic]})" if topic in self._encodings else ""
            lines.append(f"  {topic}  {info.msgtype}{extra}  {info.msgcount} messages")
        return "\n".join(lines) or "  (none)"

    def _missing(self, what: str, hint: str) -> DatasetError:
        return DatasetError(
            f"{self.path}: {what}. Topics in the bag:\n{self._listing()}\n{hint} "
            f"(e.g. --topics color=/camera/color/image_raw,depth=/camera/aligned_depth_to_color/"
            f"image_raw,camera_info=/camera/color/camera_info,pose=/odom)"
        )

    def _first(self, topic: str) -> Any:
        conns = [c for c in self.reader.connections if c.topic == topic]
        for conn, _, raw in self.reader.messages(connections=conns):
            return self.reader.deserialize(raw, conn.msgtype)
        return None

    def _pick(self, role: str, candidates: list[str], keywords: Iterable[str], what: str) -> str | None:
        if not candidates:
            return None
        if len(candidates) == 1:
            return candidates[0]
        for word in keywords:
            named = [t for t in candidates if word in t.lower()]
            if len(named) == 1:
                return named[0]
        raise self._missing(f"several {what} topics ({', '.join(candidates)})", f"choose one with --topics {role}=")

    def _index(self, wanted: dict[str, str], tf_parent: str, tf_child: str) -> None:
        types = {topic: info.msgtype for topic, info in self.reader.topics.items()}
        self._encodings: dict[str, str] = {}
        for role, topic in wanted.items():
            if topic not in types:
                raise self._missing(f"the {role} topic {topic} is not in the bag", "check the names")
        for topic, msgtype in types.items():
            if msgtype == IMAGE:
                first = self._first(topic)
                self._encodings[topic] = str(first.encoding) if first is not None else "empty"
        colours = [
            t for t, m in types.items() if (m == IMAGE and self._encodings[t] in COLOUR_ENCODINGS) or m == COMPRESSED
        ]
        depths = [t for t, m in types.items() if m == IMAGE and self._encodings[t] in DEPTH_ENCODINGS]
        colour = wanted.get("color") or self._pick("color", colours, ("color", "rgb"), "colour image")
        if colour is None:
            raise self._missing(
                "no colour image topic (sensor_msgs/Image rgb8/bgr8/rgba8/bgra8/mono8 or CompressedImage)",
                "name it with --topics color=",
            )
        depth = wanted.get("depth") or self._pick("depth", depths, ("aligned", "registered", "depth"), "depth image")
        if depth is None:
            raise self._missing(
                "no depth image topic (sensor_msgs/Image 16UC1 or 32FC1)", "name it with --topics depth="
            )
        infos = [t for t, m in types.items() if m == CAMERA_INFO]
        prefix = colour.rsplit("/", 1)[0]
        beside = [t for t in infos if t.startswith(prefix + "/")]
        info = wanted.get("camera_info") or self._pick("camera_info", beside or infos, ("color", "rgb"), "camera info")
        if info is None:
            raise self._missing(
                "no sensor_msgs/CameraInfo topic (the colour camera's intrinsics)", "name it with --topics camera_info="
            )
        for role, topic, allowed in (
            ("color", colour, (IMAGE, COMPRESSED)),
            ("depth", depth, (IMAGE,)),
            ("camera_info", info, (CAMERA_INFO,)),
        ):
            if types[topic] not in allowed:
                raise self._missing(
                    f"the {role} topic {topic} is a {types[topic]}, not {' or '.join(allowed)}", "choose another"
                )
        self.topics = {"color": colour, "depth": depth, "camera_info": info}
        pose_topics = [t for t, m in types.items() if m in POSE_TYPES]
        pose = wanted.get("pose")
        if pose is None and pose_topics:
            pose = self._pick("pose", pose_topics, ("odom", "pose", "slam"), "pose")
        if pose is None and any(m == TF_TYPE for t, m in types.items() if t.lstrip("/") == "tf"):
            pose = next(t for t, m in types.items() if m == TF_TYPE and t.lstrip("/") == "tf")
        if pose is None:
            raise self._missing(
                "no camera pose (no nav_msgs/Odometry, geometry_msgs/PoseStamped, "
                "PoseWithCovarianceStamped or TransformStamped topic, no /tf)",
                "name it with --topics pose=",
            )
        if types[pose] not in (*POSE_TYPES, TF_TYPE):
            raise self._missing(f"the pose topic {pose} is a {types[pose]}", "choose a pose type or /tf")
        self.topics["pose"] = pose
        if "groundtruth" in wanted:
            self.topics["groundtruth"] = wanted["groundtruth"]
            if types[wanted["groundtruth"]] not in POSE_TYPES:
                raise self._missing(
                    f"the ground-truth topic {wanted['groundtruth']} is a {types[wanted['groundtruth']]}",
                    "choose a pose type",
                )
        self._read(types, tf_parent, tf_child)

    # -- one pass over everything but the images' pixels -------------------------------------------------------
    def _read(self, types: dict[str, str], tf_parent: str, tf_child: str) -> None:
        reader = self.reader
        streams = {
            role: _Stream(
                self.topics[role],
                types[self.topics[role]],
                [c for c in reader.connections if c.topic == self.topics[role]],
            )
            for role in ("color", "depth")
        }
        by_topic = {s.topic: s for s in streams.values()}
        pose_series: dict[str, tuple[list[float], list[np.ndarray]]] = {"pose": ([], []), "groundtruth": ([], [])}
        pose_roles = {self.topics[r]: r for r in ("pose", "groundtruth") if r in self.topics}
        tf = _TfTree()
        intrinsics = None
        colour_frame = ""
        self.skipped: dict[str, int] = {}
        for conn, log_ns, raw in reader.messages():
            topic = conn.topic
            if topic in by_topic:
                stream = by_topic[topic]
                try:
                    stamp = _cdr_header_stamp(memoryview(raw), reader.is2)
                except struct.error:
                    self.skipped[topic] = self.skipped.get(topic, 0) + 1
                    continue
                stream.log_ns.append(log_ns)
                stream.stamps.append(stamp)
                if not colour_frame and topic == self.topics["color"]:
                    colour_frame = str(reader.deserialize(raw, conn.msgtype).header.frame_id).lstrip("/")
            elif topic == self.topics["camera_info"] and intrinsics is None:
                try:
                    intrinsics = camera_info_intrinsics(reader.deserialize(raw, conn.msgtype))
                except ConversionError:
                    self.skipped[topic] = self.skipped.get(topic, 0) + 1
            elif topic in pose_roles and conn.msgtype in POSE_TYPES:
                try:
                    stamp, _, matrix = pose_message(reader.deserialize(raw, conn.msgtype), conn.msgtype)
                except ConversionError:
                    self.skipped[topic] = self.skipped.get(topic, 0) + 1
                    continue
                stamps, poses = pose_series[pose_roles[topic]]
                i = bisect.bisect_right(stamps, stamp)
                stamps.insert(i, stamp)
                poses.insert(i, matrix @ self.pose_to_optical)
            elif conn.msgtype == TF_TYPE and topic.lstrip("/") in ("tf", "tf_static"):
                tf.add(reader.deserialize(raw, conn.msgtype), static=topic.lstrip("/") == "tf_static")
        if intrinsics is None:
            raise self._missing(f"no valid message on {self.topics['camera_info']}", "check the camera info topic")
        fx, fy, cx, cy, width, height = intrinsics
        self.intrinsics = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)
        colour, depth = streams["color"], streams["depth"]
        if not colour.stamps or not depth.stamps:
            raise self._missing("no colour or no depth message could be read", "check the image topics")
        pairs = associate(colour.stamps, depth.stamps, self.max_difference_s)
        if not pairs:
            raise DatasetError(
                f"{self.path}: no colour/depth pair within {self.max_difference_s} s on "
                f"{colour.topic} and {depth.topic} (check the stamps)"
            )
        self._colour, self._depth = colour, depth

        def series_at(role: str) -> list[np.ndarray | None]:
            stamps, poses = pose_series[role]
            return [pose_at(stamps, poses, colour.stamps[i], self.pose_max_gap_s) for i, _ in pairs]

        if types[self.topics["pose"]] == TF_TYPE:
            poses = self._tf_poses(tf, [colour.stamps[i] for i, _ in pairs], tf_parent, tf_child or colour_frame)
        else:
            poses = series_at("pose")
        truth = series_at("groundtruth") if "groundtruth" in self.topics else poses
        keep = [k for k, p in enumerate(poses) if p is not None]
        if not keep:
            raise DatasetError(
                f"{self.path}: no frame lies within the pose stream {self.topics['pose']} "
                f"(gaps over {self.pose_max_gap_s} s are not interpolated)"
            )
        if len(keep) < len(pairs):
            log.info(
                "%s: %d of %d frames have no pose (before the first or after the last one, or in a gap): left out",
                self.path,
                len(pairs) - len(keep),
                len(pairs),
            )
        self._pairs = [pairs[k] for k in keep]
        self._poses = [poses[k] for k in keep]
        self._truth = [truth[k] for k in keep]
        self._stamps = [colour.stamps[i] for i, _ in self._pairs]
        span = self._stamps[-1] - self._stamps[0]
        self.rate_hz = (len(self._stamps) - 1) / span if len(self._stamps) > 1 and span > 0 else 30.0

    def _tf_poses(self, tf: _TfTree, stamps: list[float], parent: str, child: str) -> list[np.ndarray | None]:
        frames = sorted(tf.frames)
        if child not in tf.parent:
            raise self._missing(
                f"camera frame {child or '(none)'} not in /tf (frames: {', '.join(frames)})",
                "name it with --set rosbag.tf_child=FRAME",
            )
        chain = tf.chain(parent, child)
        if not chain:
            raise self._missing(
                f"no /tf path from {parent} to {child} (frames: {', '.join(frames)})",
                "name the world frame with --set rosbag.tf_parent=FRAME",
            )
        if not any(c in tf.dynamic for c in chain[:-1]):
            raise self._missing(
                f"/tf from {chain[-1]} to {child} never moves (static only)",
                "name the moving frames with rosbag.tf_parent / tf_child",
            )
        log.info("%s: camera pose from /tf %s -> %s", self.path, chain[-1], child)
        out = []
        for t in stamps:
            pose = tf.lookup(chain, t, self.pose_max_gap_s)
            out.append(None if pose is None else pose @ self.pose_to_optical)
        return out

    # -- frames ------------------------------------------------------------------------------------------------
    def _message(self, stream: _Stream, index: int) -> Any:
        log_ns, stamp = stream.log_ns[index], stream.stamps[index]
        for conn, _, raw in self.reader.messages(connections=stream.connections, start=log_ns, stop=log_ns + 1):
            if abs(_cdr_header_stamp(memoryview(raw), self.reader.is2) - stamp) < 1e-9:
                return self.reader.deserialize(raw, conn.msgtype)
        raise DatasetError(f"{self.path}: message at {log_ns} ns on {stream.topic} could not be read again")

    def __len__(self) -> int:
        return len(self._pairs)

    def __getitem__(self, index: int) -> FrameData:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range 0..{len(self) - 1}")
        index %= len(self)
        ci, di = self._pairs[index]
        colour = self._message(self._colour, ci)
        depth = self._message(self._depth, di)
        k = self.intrinsics
        try:
            if self._colour.msgtype == COMPRESSED:
                rgb = self._compressed(index, str(colour.format), bytes(memoryview(colour.data).cast("B")))
            else:
                rgb = colour_to_rgb(
                    str(colour.encoding), int(colour.height), int(colour.width), int(colour.step), colour.data
                )
            mm = depth_to_mm(
                str(depth.encoding),
                int(depth.height),
                int(depth.width),
                int(depth.step),
                depth.data,
                bool(depth.is_bigendian),
            )
        except ConversionError as exc:
            raise DatasetError(f"{self.path}: frame {index} ({self._stamps[index]:.3f} s): {exc}") from None
        width, height = rgb.size if isinstance(rgb, EncodedImage) else (rgb.shape[1], rgb.shape[0])
        if (height, width) != (k.height, k.width) or mm.shape != (height, width):
            raise DatasetError(
                f"{self.path}: frame {index}: colour {width}x{height}, depth "
                f"{mm.shape[1]}x{mm.shape[0]} and camera info {k.width}x{k.height} differ "
                "(depth must be aligned to colour)"
            )
        truth = self._truth[index]
        return FrameData(
            index=index,
            stamp=self._stamps[index],
            rgb=rgb,
            depth=mm,
            depth_scale=self.depth_scale,
            intrinsics=k,
            gt_pose=None if truth is None else truth.copy(),
        )

    def _compressed(self, index: int, fmt: str, data: bytes) -> np.ndarray | EncodedImage:
        """A CompressedImage's colour: a complete-looking JPEG stays encoded (decoded where needed, and sent as it
        was recorded); anything else is decoded now."""
        size = jpeg_size(data) if "compressedDepth" not in fmt else None
        if size is None:
            return compressed_to_rgb(fmt, data)

        def decode() -> np.ndarray:
            try:
                return compressed_to_rgb(fmt, data)
            except ConversionError as exc:
                raise DatasetError(f"{self.path}: frame {index} ({self._stamps[index]:.3f} s): {exc}") from None

        return EncodedImage(data, "jpeg", size, decode)

    @property
    def has_groundtruth(self) -> bool:
        return any(p is not None for p in self._truth)

    def groundtruth(self) -> list[tuple[float, np.ndarray]]:
        return [(s, p.copy()) for s, p in zip(self._stamps, self._truth, strict=True) if p is not None]

    def recorded_poses(self) -> list[tuple[float, np.ndarray]]:
        """The camera pose the bag recorded (pose topic or /tf) at every frame, optical frame."""
        return [(s, p.copy()) for s, p in zip(self._stamps, self._poses, strict=True)]

    def close(self) -> None:
        if getattr(self, "reader", None) is not None and self.reader.stack is not None:
            self.reader.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at interpreter shutdown
            self.close()
