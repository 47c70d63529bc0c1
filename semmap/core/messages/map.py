"""The map and what the backend needs of it: `Landmark`s in `MapUpdate` (key `map/updates`), per-frame
`Observations` (key `observations`) with an optional `MapAlignment`, and the same as RTAB-Map-style
`TagDetections` (key `observations/tags`)."""

from __future__ import annotations

from typing import Annotated

import msgspec
import numpy as np

from .base import (
    Finite,
    Id,
    Merge,
    Message,
    MessageError,
    NonNegativeInt,
    Part,
    Pose,
    Positive,
    RobotName,
    Timings,
    Vector3,
    as_matrix,
    as_vector3,
    decoding,
    flat_matrix,
    validate_pose,
)

LANDMARK_STATUSES = ("present", "prior", "missing")
# a str checked by Landmark (not a Literal): map files are edited by hand, and their error should list the choices
LandmarkStatus = Annotated[str, msgspec.Meta(extra_json_schema={"enum": list(LANDMARK_STATUSES)})]


class Landmark(Part):
    """A mapped object. `centroid` and `extent` in the world frame (metres); `radius` is its sphere's."""

    id: Id
    class_name: str = msgspec.field(name="class")
    centroid: Vector3
    radius: Finite
    extent: Vector3
    observations: NonNegativeInt
    first_seen: Finite
    last_seen: Finite
    # "present" (mapped or seen again this session), "prior" (from a loaded map, not seen again yet) or
    # "missing" (from a loaded map, in plain view for several frames and not detected); see docs/MAPS.md
    status: LandmarkStatus = "present"

    def __post_init__(self) -> None:
        if decoding():
            if self.status not in LANDMARK_STATUSES:
                raise MessageError(f"landmark status must be one of {', '.join(LANDMARK_STATUSES)}, "
                                   f"got {self.status!r}")
        else:
            self.centroid = as_vector3(self.centroid)
            self.extent = as_vector3(self.extent)


class Observation(Part):
    """A landmark seen from one frame: its centroid in that camera's frame, for the backend."""

    landmark_id: Id
    class_name: str = msgspec.field(name="class")
    point_camera: Vector3
    sigma: Positive  # 1-sigma isotropic, metres
    size: Finite
    # how much of the object's depth along the ray this view may not have seen, metres (None: not measured, an older
    # sender); the backend loosens the range by it (pose_graph.py `_observation_range_sigma`)
    depth_unseen: Finite | None = None

    def __post_init__(self) -> None:
        self.point_camera = as_vector3(self.point_camera)


class MapAlignment(Part):
    """A session relocalised against a prior map (docs/MAPS.md): from the frame that carries it on, the session's
    poses belong in the prior map's frame. `transform` takes the session's (odometry) frame to the prior frame;
    `anchors` are prior landmarks (id, position in the prior frame) that the backend holds within `anchor_sigma_m`;
    the fit's own figures (`inliers`, `rms_m`) travel along for the record."""

    transform: Pose
    anchors: list[tuple[Id, Vector3]]
    anchor_sigma_m: Positive
    inliers: NonNegativeInt
    rms_m: Finite

    def __post_init__(self) -> None:
        if decoding():
            self.transform = validate_pose(self.transform, "transform")
        else:
            self.transform = as_matrix(self.transform, 4, "transform")
            self.anchors = [(int(i), as_vector3(p)) for i, p in self.anchors]


class Observations(Message, tag="semmap.observations/1"):
    """The associator's landmark observations for one frame (at most one per landmark every 2 s), and merges.

    `merges` are (absorbed id, surviving id): the backend joins the two landmark variables. `alignment` (once per
    session, optional): the session relocalised against a prior map at this frame. `retired` are landmarks whose
    object was seen moving: the backend drops their factors (they must stop pulling the trajectory towards where
    the object was). Optional on the wire (absent = none).
    """

    robot: RobotName
    frame_id: NonNegativeInt
    stamp: Finite
    observations: list[Observation] = msgspec.field(default_factory=list)
    merges: list[Merge] = msgspec.field(default_factory=list)
    sent_at: Finite = 0.0
    alignment: MapAlignment | None = None
    retired: list[Id] = msgspec.field(default_factory=list)


class TagDetection(Part):
    """An observation in the AprilTag-like form RTAB-Map consumes: id, size, camera-frame pose, 6x6 covariance.

    Objects carry no orientation: the rotation is identity and its covariance large (rotation unconstrained).
    """

    id: Id
    size: Finite
    pose: Pose  # 4x4 in the camera frame
    covariance: flat_matrix(6, "covariance of (x, y, z, roll, pitch, yaw)")

    def __post_init__(self) -> None:
        self.covariance = as_matrix(self.covariance, 6, "covariance")
        if decoding():
            self.pose = validate_pose(self.pose)
            if np.any(np.diag(self.covariance) < 0):
                raise MessageError("covariance must have a non-negative diagonal")
        else:
            self.pose = as_matrix(self.pose, 4, "pose")

    @classmethod
    def from_observation(cls, obs: Observation, rotation_sigma_rad: float = 1e3) -> TagDetection:
        pose = np.eye(4)
        pose[:3, 3] = obs.point_camera
        cov = np.diag([obs.sigma**2] * 3 + [rotation_sigma_rad**2] * 3)
        return cls(obs.landmark_id, obs.size, pose, cov)


class TagDetections(Message, tag="semmap.landmark_tags/1"):
    """The frame's landmark observations as tag detections (key `observations/tags`)."""

    robot: RobotName
    frame_id: NonNegativeInt
    stamp: Finite
    detections: list[TagDetection] = msgspec.field(default_factory=list)
    sent_at: Finite = 0.0


class MapUpdate(Message, tag="semmap.map_update/1"):
    """Landmarks that changed (or all, when `full`), removed ids and merges, after processing `frame_id`."""

    robot: RobotName
    seq: NonNegativeInt
    frame_id: NonNegativeInt
    stamp: Finite
    landmarks: list[Landmark] = msgspec.field(default_factory=list)
    removed: list[int] = msgspec.field(default_factory=list)
    merges: list[Merge] = msgspec.field(default_factory=list)
    full: bool = False
    rejected_candidates: list[int] = msgspec.field(default_factory=list)
    timing_ms: Timings = msgspec.field(default_factory=dict)
    frame_sent_at: Finite = 0.0
    sent_at: Finite = 0.0
    moved: list[Id] = msgspec.field(default_factory=list)  # of `removed`: retired because their object moved
    moving_tracks: list[Id] = msgspec.field(default_factory=list)  # of `rejected_candidates`: rejected as moving
