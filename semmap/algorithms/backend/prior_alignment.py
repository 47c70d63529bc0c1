"""The backend's side of relocalisation against a prior map (pure: no bus, no I/O).

Until the associator relocalises the session, the graph lives in the session's own (provisional) frame. The
frame whose observations carry a `MapAlignment` moves it into the prior map's frame: the graph is rebuilt from
every frame handled so far with each odometry pose taken through the alignment's transform, the first pose's
prior loosened to the fit's uncertainty, and the prior landmarks named in the alignment added as variables held
in place by a prior factor (`anchor_sigma_m`). From then on every odometry pose goes through the transform on
its way in, and the session's observations of prior landmarks tie its trajectory to the prior map: the anchors
correct what the fit left (a few cm, a degree) as well as the drift. Loop closures found before the alignment
are not carried into the rebuilt graph (the closer finds revisits again against the new estimate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np

from semmap.algorithms.backend.pose_graph import PoseGraph
from semmap.algorithms.relocalize import rotation_angle_deg
from semmap.core.messages import MapAlignment, Observations, OdometryPose

FIRST_PRIOR_MIN_M = 0.05
FIRST_PRIOR_ROTATION_DEG = 3.0


@dataclass
class FinalAlignment:
    frame_id: int
    transform: np.ndarray  # session frame -> map frame, as the final estimate has it at frame_id
    object_fit: np.ndarray  # ... and as the relocalisation's fit had it
    correction_deg: float  # the rotation between the two
    correction_m: float  # how far they place that frame's camera apart


class PriorAlignment:
    """Keeps the frames handled so far (odometry + observations, ~1 KB each) to rebuild once: only in a session
    started from a prior map (`expected`); any other run would keep every frame's messages for nothing."""

    def __init__(self, expected: bool = True) -> None:
        self.expected = expected
        self.alignment: MapAlignment | None = None
        self.aligned_at: int | None = None  # the frame whose alignment moved the graph into the prior's frame
        self.handled: list[tuple[OdometryPose, Observations]] = []

    def add(self, graph: PoseGraph, pose: OdometryPose, obs: Observations) -> None:
        if self.alignment is None and self.expected:
            self.handled.append((pose, obs))
        graph.add_odometry_message(self._aligned(pose))
        graph.add_observations_message(obs)

    def realign(self, graph: PoseGraph, alignment: MapAlignment, frame_id: int | None = None) -> PoseGraph:
        """A new graph in the prior map's frame holding every frame handled so far, and the anchors; `frame_id`:
        the frame that carried the alignment."""
        self.alignment, self.aligned_at = alignment, frame_id
        fresh = PoseGraph(graph.params)
        fresh.first_prior = (max(FIRST_PRIOR_MIN_M, 2.0 * alignment.rms_m), math.radians(FIRST_PRIOR_ROTATION_DEG))
        for landmark_id, position in alignment.anchors:
            fresh.anchor_landmark(landmark_id, np.asarray(position, float), alignment.anchor_sigma_m)
        for pose, obs in self.handled:
            fresh.add_odometry_message(self._aligned(pose))
            fresh.add_observations_message(obs)
        self.handled = []
        if fresh.num_frames:
            fresh.update()
        return fresh

    def final(self, graph: PoseGraph) -> FinalAlignment | None:
        """The session-to-map transform the graph's current estimate implies at the frame that relocalised, and
        how far it moved the fit (None before a relocalisation)."""
        if self.alignment is None or self.aligned_at is None:
            return None
        f, fit = self.aligned_at, np.asarray(self.alignment.transform, dtype=np.float64)
        # the graph holds the odometry through the fit's transform A: corrected @ inv(A @ odom) @ A
        transform = graph.corrected_pose(f) @ np.linalg.inv(graph.odometry_pose(f)) @ fit
        # that frame's camera in the session's own frame, placed by the fit and by the final transform
        camera = (np.linalg.inv(fit) @ graph.odometry_pose(f))[:3, 3]
        moved = transform[:3, :3] @ camera + transform[:3, 3] - (fit[:3, :3] @ camera + fit[:3, 3])
        return FinalAlignment(f, transform, fit, rotation_angle_deg((np.linalg.inv(fit) @ transform)[:3, :3]),
                              float(np.linalg.norm(moved)))

    def _aligned(self, pose: OdometryPose) -> OdometryPose:
        if self.alignment is None:
            return pose
        return msgspec.structs.replace(pose, pose=self.alignment.transform @ pose.pose)
