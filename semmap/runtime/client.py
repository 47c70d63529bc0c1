"""A small Python client for an external SLAM: publish frames and poses, get corrected poses and the map back.

    from semmap.runtime.client import SemmapClient
    with SemmapClient(robot="robot1", connect="tcp/127.0.0.1:7447") as client:
        client.wait_ready()
        for i, (stamp, rgb, depth, pose) in enumerate(my_slam()):
            client.publish_frame(i, stamp, rgb, depth, depth_scale=0.001, intrinsics=(fx, fy, cx, cy))
            client.publish_pose(i, stamp, pose)
            client.wait_frame_done(i)             # lockstep; leave out to stream in real time
        client.end_of_stream(i)
        poses = client.corrected_trajectory()     # {frame_id: 4x4}, from the semmap.corrected_poses/2 deltas

Everything here is plain `semmap.core.messages` on `semmap.core.keys`: a SLAM in another language does the same with its
own Zenoh and msgpack bindings (docs/INTERFACE.md).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable

import numpy as np

from semmap.core.messages import (
    Control,
    CorrectedPoses,
    DynamicObjects,
    Frame,
    GroundTruthInstance,
    Intrinsics,
    Landmark,
    MapUpdate,
    Observations,
    OdometryPose,
    Progress,
    ServiceStatus,
    TagDetections,
)
from semmap.runtime.maps.map_query import MapQuery, ask_live_map
from semmap.runtime.transport.bus import Bus, BusConfig

PIPELINE_SERVICES = ("detector", "tracker", "associator", "backend")
# what semmap's own front ends mark as keyframes: `odometry.keyframe_every`'s default, written out because the
# light client ships without the configuration (tests/client/test_client_defaults.py keeps the two equal)
DEFAULT_KEYFRAME_EVERY = 10


class SemmapTimeout(TimeoutError):
    pass


class SemmapClient:
    """One robot's connection to a running semmap (see module docstring)."""

    def __init__(self, robot: str = "robot1", connect: str | None = None, mode: str | None = None,
                 keyframe_every: int = DEFAULT_KEYFRAME_EVERY, check_slam: bool = False,
                 front_end: str = "") -> None:
        """`check_slam`: publish the SLAM's poses on the `slam` key for semmap to check against its own
        registration before they become odometry (the run started with `semmap run external --check-slam`);
        otherwise they are the odometry as they are. `front_end`: the run poses the frames itself (`semmap run
        external --odometry orbslam3`): poses given to `publish_pose` are not sent (counted in `poses_not_sent`)."""
        if keyframe_every < 1:  # refused before a session opens, so nothing is left behind
            raise ValueError(f"keyframe_every must be at least 1, got {keyframe_every}")
        self.keyframe_every = int(keyframe_every)
        self.bus = Bus(BusConfig.from_env(connect, mode), robot)
        self.robot = robot
        self._frames = self.bus.publisher(self.bus.keys.frames)
        self.check_slam = bool(check_slam)
        self.front_end = str(front_end)
        self.poses_not_sent = 0
        self._poses = self.bus.publisher(self.bus.keys.slam if check_slam else self.bus.keys.odometry)
        self._control = self.bus.publisher(self.bus.keys.control)
        self._cv = threading.Condition()
        self._progress: dict[str, int] = {}
        self._running: dict[str, set[str]] = {}
        self._corrected: CorrectedPoses | None = None
        self._trajectory: dict[int, np.ndarray] = {}  # the corrected deltas applied, frame id -> pose
        self._landmarks: dict[int, np.ndarray] = {}
        self._callbacks: dict[str, list[Callable]] = {"corrected": [], "observations": [], "map": [], "tags": [],
                                                      "dynamic": []}
        self.bus.subscribe(self.bus.keys.progress_all, Progress, self._on_progress)
        self.bus.subscribe(self.bus.keys.status_all, ServiceStatus, self._on_status)
        self.bus.subscribe(self.bus.keys.corrected_poses, CorrectedPoses, self._on_corrected)
        self.bus.subscribe(self.bus.keys.observations, Observations, lambda m: self._emit("observations", m))
        self.bus.subscribe(self.bus.keys.map_updates, MapUpdate, lambda m: self._emit("map", m))
        self.bus.subscribe(self.bus.keys.landmark_tags, TagDetections, lambda m: self._emit("tags", m))
        self.bus.subscribe(self.bus.keys.dynamic, DynamicObjects, lambda m: self._emit("dynamic", m))

    @classmethod
    def attach(cls, robot: str | None = None, run_dir: str | None = None, mode: str | None = None,
               keyframe_every: int = DEFAULT_KEYFRAME_EVERY) -> SemmapClient:
        """A client of the run a `semmap run external` on this host recorded (semmap.runtime.transport.run_registry):
        the
        one whose out dir is `run_dir`, else the only live run of `robot` (of any robot when None). Raises
        RunNotFound when there is none or more than one. A run started with `--check-slam` gets the poses on the
        `slam` key (checked), as its run file says."""
        from semmap.runtime.transport.run_registry import find_run

        info = find_run(run_dir, None if run_dir else robot)
        return cls(info.robot, info.endpoint, mode, keyframe_every, check_slam=info.check_slam,
                   front_end=info.front_end)

    # -- inbound ----------------------------------------------------------------------------------------------
    def _emit(self, kind: str, message: object) -> None:
        for callback in list(self._callbacks[kind]):
            callback(message)

    def _on_progress(self, p: Progress) -> None:
        with self._cv:
            self._progress[p.service] = max(self._progress.get(p.service, -1), p.frame_id)
            self._cv.notify_all()

    def _on_status(self, s: ServiceStatus) -> None:
        with self._cv:
            members = self._running.setdefault(s.service, set())
            (members.add if s.state == "running" else members.discard)(s.instance)
            self._cv.notify_all()

    def _on_corrected(self, msg: CorrectedPoses) -> None:
        with self._cv:
            self._corrected = msg
            msg.apply_to(self._trajectory, self._landmarks)
        self._emit("corrected", msg)

    def on_corrected_poses(self, callback: Callable[[CorrectedPoses], None]) -> None:
        self._callbacks["corrected"].append(callback)

    def on_observations(self, callback: Callable[[Observations], None]) -> None:
        """Landmark observations as camera-frame points (what a pose-graph back end can add as factors)."""
        self._callbacks["observations"].append(callback)

    def on_landmark_tags(self, callback: Callable[[TagDetections], None]) -> None:
        """The same observations as AprilTag-like id + pose detections (the form RTAB-Map's landmarks take)."""
        self._callbacks["tags"].append(callback)

    def on_map_update(self, callback: Callable[[MapUpdate], None]) -> None:
        self._callbacks["map"].append(callback)

    def on_dynamic(self, callback: Callable[[DynamicObjects], None]) -> None:
        """Each frame's dynamic objects (people, animals, things seen moving): boxes with a depth range, for a
        SLAM to leave out of its features or depth, as dynamic SLAM systems do. One message per frame."""
        self._callbacks["dynamic"].append(callback)

    def latest_corrected(self) -> CorrectedPoses | None:
        """The newest message as received: a delta (the poses that moved), see `corrected_trajectory`."""
        with self._cv:
            return self._corrected

    def corrected_trajectory(self) -> dict[int, np.ndarray]:
        """Every frame's corrected camera-to-world pose received so far (the deltas applied; a copy)."""
        with self._cv:
            return dict(self._trajectory)

    def corrected_landmarks(self) -> dict[int, np.ndarray]:
        """Every landmark's position in the backend's graph received so far (a copy)."""
        with self._cv:
            return dict(self._landmarks)

    # -- outbound ---------------------------------------------------------------------------------------------
    def _wanted(self, services: Iterable[str]) -> list[str]:
        """The services to wait for: these, and the odometry service where the run has one (checking the SLAM's
        poses, or posing the frames itself)."""
        own = self.check_slam or bool(self.front_end)
        return list(services) + (["odometry"] if own and "odometry" not in services else [])

    def wait_ready(self, services: Iterable[str] = PIPELINE_SERVICES, timeout: float = 60.0) -> None:
        """Block until each service reports running and our frames have a subscriber."""
        wanted = self._wanted(services)
        deadline = time.monotonic() + timeout
        with self._cv:
            while not all(self._running.get(s) for s in wanted):
                left = deadline - time.monotonic()
                if left <= 0:
                    missing = [s for s in wanted if not self._running.get(s)]
                    raise SemmapTimeout(f"semmap services not running after {timeout:g} s: {', '.join(missing)}")
                self._cv.wait(min(left, 0.1))
        if not self._frames.wait_matching(max(0.1, deadline - time.monotonic())):
            raise SemmapTimeout("nothing subscribes to frames")
        if self.check_slam and not self._poses.wait_matching(max(0.1, deadline - time.monotonic())):
            raise SemmapTimeout("nothing subscribes to the slam key: was the run started with --check-slam?")

    def publish_frame(self, frame_id: int, stamp: float, rgb: np.ndarray, depth: np.ndarray, depth_scale: float,
                      intrinsics: Intrinsics | tuple[float, float, float, float],
                      instances: list[GroundTruthInstance] | None = None) -> None:
        """An RGB (uint8 HxWx3) + registered depth (uint16 HxW, `depth_scale` m per unit) frame."""
        if not isinstance(intrinsics, Intrinsics):
            fx, fy, cx, cy = intrinsics
            intrinsics = Intrinsics(fx, fy, cx, cy, rgb.shape[1], rgb.shape[0])
        self._frames.put(Frame.from_arrays(self.robot, frame_id, stamp, rgb, depth, depth_scale, intrinsics,
                                           None, instances))

    def publish_pose(self, frame_id: int, stamp: float, pose: np.ndarray, keyframe: bool | None = None,
                     sigma_translation: float = 0.01, sigma_rotation: float = 0.005, source: str = "external") -> None:
        """The camera-to-world pose of frame `frame_id`, with per-frame motion sigmas (m, rad).

        `keyframe`: whether the frame becomes a pose-graph node (your SLAM's keyframes); None marks every
        `keyframe_every`-th frame, as semmap's own front ends do (`odometry.keyframe_every`)."""
        if self.front_end:  # (the run's own front end poses the frames)
            self.poses_not_sent += 1
            return
        if keyframe is None:
            keyframe = frame_id % self.keyframe_every == 0
        self._poses.put(OdometryPose(self.robot, frame_id, stamp, np.asarray(pose, float), bool(keyframe),
                                     sigma_translation, sigma_rotation, source))

    def wait_frame_done(self, frame_id: int, services: Iterable[str] = PIPELINE_SERVICES,
                        timeout: float = 60.0) -> None:
        """Lockstep: block until every service has finished frame `frame_id`."""
        wanted = self._wanted(services)
        deadline = time.monotonic() + timeout
        with self._cv:
            while min((self._progress.get(s, -1) for s in wanted), default=frame_id) < frame_id:
                left = deadline - time.monotonic()
                if left <= 0:
                    late = [s for s in wanted if self._progress.get(s, -1) < frame_id]
                    raise SemmapTimeout(f"frame {frame_id} not done after {timeout:g} s by {', '.join(late)}")
                self._cv.wait(min(left, 0.1))

    def frames_done(self, services: Iterable[str] = PIPELINE_SERVICES) -> int:
        """How many frames (ids 0..n-1) every one of `services` has finished, from their progress messages (a run
        in real time reports it at most every 0.1 s: up to that much behind)."""
        with self._cv:
            return min((self._progress.get(s, -1) for s in services), default=-1) + 1

    def end_of_stream(self, last_frame_id: int, frames: int | None = None,
                      counters: dict[str, int] | None = None) -> None:
        """No more frames: services write their outputs (map.json, trajectories). `frames`: how many this client
        sent (default last_frame_id + 1); `counters`: what it counted on its side (e.g. frames it lost, by
        reason), kept in the run's stats.json as "source"."""
        self._control.put(Control(self.robot, "end_of_stream", last_frame_id,
                                  last_frame_id + 1 if frames is None else frames, counters=dict(counters or {})))

    def query_map(self, query: MapQuery | None = None, timeout: float = 3.0) -> list[Landmark]:
        query = query or MapQuery()
        params = query.to_parameters()
        selector = self.bus.keys.map_query + (f"?{params}" if params else "")
        found = ask_live_map(self.bus.session, selector, timeout)  # (asks again until one answers)
        if found is None:
            raise SemmapTimeout(f"no map service answered within {timeout:g} s")
        return found

    def close(self) -> None:
        self.bus.close()

    def __enter__(self) -> SemmapClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
