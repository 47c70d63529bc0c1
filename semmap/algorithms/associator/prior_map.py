"""A prior map that a new session relocalises against and then maps in (pure: no bus, no I/O).

`semmap run DATA --map PRIOR` hands the associator a saved mapper state. The session starts mapping in its own
(provisional) frame, since its odometry knows nothing of the prior map's. Every few frames, `try_relocalize`
matches the session's landmarks to the prior ones (semmap/algorithms/relocalize.py: class-consistent triples, rigid fit,
cloud refinement, refused unless certain). On success `adopt` puts the prior landmarks into the session's map
with their ids, views and clouds (their views frozen: frame and track ids made negative, so no pose lookup or
track of this session touches them), the pose book turns to the prior frame, every session landmark and
candidate is re-placed with it, and the session landmarks the fit matched are fused into their prior ones
(merges the backend applies too). From then on the session associates against the prior landmarks like any
others, and the `MapAlignment` that goes out with that frame's observations makes the backend anchor its
trajectory on them.

Status per landmark (map.json): `prior` until the session sees it again (`present`), `missing` once it should
have been seen (its centre projects well inside the image, between `missing_min_depth_m` and
`missing_max_depth_m`, its disk at least `missing_min_px` across, no other landmark in front of it, and looked at
from within `missing_max_view_angle_deg` of a direction it was detected from) in enough
detected frames in a row without a box on it of a class it was ever detected as (a detector calls one
microwave a tv or a laptop from some viewpoints): `missing_after_frames`, or more for a class
the detector often misses in plain view. That rate is learnt from this session's present landmarks of the
class (in plain view, a box on them or not; Beta(4, 1) before any evidence), and the run must be unlikely
(< `missing_miss_probability`) for an object still there: on 7-Scenes the detector boxes a dining table or the
microwave in few of the frames where it is in plain view, and with a fixed ten frames those that stood there
were marked missing. The rate is learnt from the first frame on, in the provisional frame too. Only the map
itself can tell occlusion here (the associator does not receive depth images): an object hidden behind
something that is no landmark can be marked missing, and comes back to `present` as soon as it is associated
again.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from semmap.algorithms.relocalize import MapObject, PriorIndex, RelocAttempt, RelocParams, RelocResult, relocalize
from semmap.core.config import PriorParams
from semmap.core.messages import Intrinsics, Landmark, MapAlignment, TrackedBox

from .geometry import inverse_transform
from .landmark_map import LandmarkMap, LandmarkState
from .mapper import LandmarkMapper, MapperStep
from .prior_anchor import PriorAnchor, registration_sigma

STATE_VERSION = 1


def _frozen(i: int) -> int:
    """A prior frame or track id, mapped where no id of this session can be (negative). One frozen already (a
    prior map that was itself a relocalised session's: its own prior's views) stays as it is: frozen twice, it
    came back positive, where the new session's poses re-placed it."""
    return int(i) if int(i) < 0 else -1 - int(i)


class PriorSession:
    """The prior map's landmarks, the relocalisation and the status of each prior landmark."""

    def __init__(self, prior: LandmarkMap, params: PriorParams | None = None, reloc: RelocParams | None = None) -> None:
        self.params = params or PriorParams()
        self.reloc_params = reloc or RelocParams(
            min_inliers=self.params.relocalize_min_inliers,
            max_rotation_sigma_deg=self.params.relocalize_max_rotation_sigma_deg,
        )
        self.prior = prior
        self.prior_ids = {lm.id for lm in prior.all()}
        self.next_id = prior.next_id
        self.index = PriorIndex(
            [MapObject(lm.id, lm.class_name, lm.centroid.copy(), lm.cloud.copy()) for lm in prior.all()]
        )
        self.fit: RelocResult | None = None
        self.transform: np.ndarray | None = None
        self.aligned_at: int | None = None
        self.status: dict[int, str] = dict.fromkeys(self.prior_ids, "prior")
        self.streak: dict[int, int] = dict.fromkeys(self.prior_ids, 0)
        self.attempts = 0
        self.last_attempt: RelocAttempt | None = None
        self.class_seen: dict[str, list[int]] = {}  # class -> [frames boxed, frames in plain view], present ones

    @property
    def relocalised(self) -> bool:
        return self.transform is not None

    # ---- relocalisation

    def due(self, frame_id: int) -> bool:
        return not self.relocalised and frame_id % max(1, self.params.relocalize_every_n_frames) == 0

    def try_relocalize(self, mapper: LandmarkMapper) -> RelocResult | None:
        """Match the session's landmarks (provisional frame) to the prior map's; None unless certain."""
        query = [
            MapObject(lm.id, lm.class_name, lm.centroid.copy(), _view_cloud(lm))
            for lm in mapper.map.all()
            if lm.id not in self.prior_ids and len(lm.views) >= self.params.relocalize_min_views
        ]
        if len(query) < self.reloc_params.min_inliers:
            return None
        self.attempts += 1
        self.last_attempt = relocalize(query, self.index, self.reloc_params)
        return self.last_attempt.result

    def adopt(
        self, mapper: LandmarkMapper, fit: RelocResult, frame_id: int, session_start: float, pose
    ) -> tuple[MapperStep, MapAlignment]:  # noqa: ANN001 - a PoseLookup already in the prior frame
        """Bring the prior landmarks in, re-place the session in the prior frame, fuse the matched landmarks.

        pose: the pose lookup already turned to the prior frame. Returns the map changes (merges included)
        and the alignment for the backend."""
        self.fit, self.transform, self.aligned_at = fit, fit.transform.copy(), frame_id
        stamps = [lm.last_seen for lm in self.prior.all()] + [lm.last_assoc for lm in self.prior.all()]
        shift = min(0.0, session_start - 1.0 - max(stamps, default=0.0))  # the prior session ends before this one
        adopted = [_freeze(lm, shift, self._anchor(lm, fit)) for lm in self.prior.all()]
        mapper.adopt_landmarks(adopted)
        step = mapper.refine(pose)
        for session_id, prior_id in fit.matches:
            if session_id in mapper.map and prior_id in mapper.map:
                mapper.fuse(prior_id, session_id, step)
        # a prior landmark that absorbed one of this session's (a fit match, or one the re-placed session now
        # overlaps) was seen again: it is present, and its misses from now on are the detector's
        for gone, kept in step.merges:
            if kept in self.status and gone not in self.prior_ids:
                self.status[kept] = "present"
        alignment = MapAlignment(
            fit.transform.copy(),
            [(lm.id, (float(lm.centroid[0]), float(lm.centroid[1]), float(lm.centroid[2]))) for lm in adopted],
            self.params.anchor_sigma_m,
            fit.inliers,
            # what the transform is known to: the surfaces' residual where it was fitted on them (the backend holds
            # the first pose within twice this), not the centres', which are off by the viewpoint (12 cm on 7-Scenes)
            float(fit.cloud_rms_m if fit.refined and fit.cloud_rms_m is not None else fit.rms_m),
        )
        return step, alignment

    def _anchor(self, lm: LandmarkState, fit: RelocResult) -> PriorAnchor:
        """The prior landmark's place and class, held against this session's views (prior_anchor.py), which are
        worth what the fit's residual and rotation uncertainty leave at its distance from the fit's landmarks."""
        matched = [self.prior[prior_id].centroid for _, prior_id in fit.matches if prior_id in self.prior]
        centre = np.mean(matched, axis=0) if matched else lm.centroid
        residual = float(fit.cloud_rms_m if fit.refined and fit.cloud_rms_m is not None else fit.rms_m)
        p = self.params
        return PriorAnchor(
            lm.centroid.copy(),
            lm.class_name,
            p.anchor_sigma_m,
            registration_sigma(lm.centroid, centre, residual, fit.rotation_sigma_deg, p.registration_sigma_m),
            p.moved_sigmas,
            p.moved_min_views,
        )

    # ---- changes

    def update(
        self,
        mapper: LandmarkMapper,
        frame_id: int,
        T: np.ndarray | None,
        boxes: Sequence[TrackedBox] | None,
        intrinsics: Intrinsics | None,
        touched: Sequence[int],
    ) -> list[int]:
        """After a frame: prior landmarks seen again are present; those in plain view and not detected count
        towards missing. Returns the ids whose status changed. Before the relocalisation (no prior landmark in
        the map yet) it only learns how often each class is detected in plain view."""
        changed = []
        for lid in touched:
            if lid in self.status and self.status[lid] != "present":
                self.status[lid] = "present"
                changed.append(lid)
            if lid in self.streak:
                self.streak[lid] = 0
        if boxes is None or T is None or intrinsics is None:
            return changed
        lms = [lm for lm in mapper.map.all() if lm.views]
        candidates = [i for i, lm in enumerate(lms) if self.status.get(lm.id, "present") != "missing"]
        if not candidates:
            return changed
        touched_set = set(touched)
        for i, seen in self._in_plain_view(lms, candidates, T, intrinsics, boxes):
            lm = lms[i]
            seen = seen or lm.id in touched_set
            if self.status.get(lm.id, "present") == "present":  # there: its misses are the detector's
                stats = self.class_seen.setdefault(lm.class_name, [0, 0])
                stats[0] += int(seen)
                stats[1] += 1
                continue
            if not self.relocalised:
                continue
            if seen:
                self.streak[lm.id] = 0
                continue
            self.streak[lm.id] += 1
            if self.streak[lm.id] >= self.missing_after(lm.class_name):
                self.status[lm.id] = "missing"
                changed.append(lm.id)
        return changed

    def missing_after(self, class_name: str) -> int:
        """Undetected plain-view frames in a row that make a prior landmark of this class missing: a run of
        misses that an object still there would give with probability below `missing_miss_probability`, at the
        class's detection rate in plain view (this session's present landmarks; Beta(4, 1) prior)."""
        hits, trials = self.class_seen.get(class_name, (0, 0))
        rate = min((hits + 4.0) / (trials + 5.0), 0.999)
        runs = math.log(self.params.missing_miss_probability) / math.log(1.0 - rate)
        return max(self.params.missing_after_frames, math.ceil(runs))

    def _in_plain_view(
        self, lms: list[LandmarkState], candidates: list[int], T: np.ndarray, k: Intrinsics, boxes: Sequence[TrackedBox]
    ) -> list[tuple[int, bool]]:
        """Of `candidates` (indices into lms), those that should be visible, each with whether a box of its class
        meets it."""
        p = self.params
        c = np.stack([lm.centroid for lm in lms])
        cam = inverse_transform(np.asarray(T, dtype=np.float64), c)
        z = cam[:, 2]
        radius = np.array([lm.radius for lm in lms])
        dist = np.linalg.norm(cam, axis=1)
        out = []
        for i in candidates:
            if not (p.missing_min_depth_m <= z[i] <= p.missing_max_depth_m):
                continue
            u = cam[i, 0] / z[i] * k.fx + k.cx
            v = cam[i, 1] / z[i] * k.fy + k.cy
            mu, mv = p.missing_margin * k.width, p.missing_margin * k.height
            if not (mu <= u <= k.width - mu and mv <= v <= k.height - mv):
                continue
            if 2 * radius[i] * k.fx / z[i] < p.missing_min_px:
                continue
            ray = cam[i] / max(dist[i], 1e-9)
            along = cam @ ray
            perp = np.linalg.norm(cam - along[:, None] * ray[None, :], axis=1)
            blocked = (perp < radius) & (along + radius < dist[i] - radius[i]) & (along > 0)
            blocked[i] = False
            if blocked.any():
                continue
            lm = lms[i]
            if not self._seen_from_here(lm, np.asarray(T, dtype=np.float64)[:3, 3]):
                continue
            r_px = max(2.0, radius[i] * k.fx / z[i])
            names = lm.class_votes.keys() | {lm.class_name}  # a box of any class it was detected as
            seen = any(
                b.class_name in names
                and b.box[0] - r_px <= u <= b.box[2] + r_px
                and b.box[1] - r_px <= v <= b.box[3] + r_px
                for b in boxes
            )
            out.append((i, seen))
        return out

    def _seen_from_here(self, lm: LandmarkState, camera: np.ndarray) -> bool:
        """Is the camera looking at the landmark from a direction it was detected from (within
        `missing_max_view_angle_deg`)? Only there does a miss say something about the object."""
        if not lm.views:
            return False
        here = lm.centroid - camera
        here = here / max(float(np.linalg.norm(here)), 1e-9)
        seen = lm.centroid[None, :] - np.stack([v.pose[:3, 3] for v in lm.views])
        seen = seen / np.maximum(np.linalg.norm(seen, axis=1), 1e-9)[:, None]
        return bool((seen @ here).max() >= math.cos(math.radians(self.params.missing_max_view_angle_deg)))

    def with_status(self, landmarks: list[Landmark]) -> list[Landmark]:
        return [lm if lm.id not in self.status else _status(lm, self.status[lm.id]) for lm in landmarks]

    # ---- persistence (with the associator's map state)

    def to_state(self) -> dict[str, Any]:
        return {
            "version": STATE_VERSION,
            "transform": None if self.transform is None else [float(v) for v in self.transform.reshape(16)],
            "aligned_at": self.aligned_at,
            "status": {str(k): v for k, v in self.status.items()},
            "streak": {str(k): v for k, v in self.streak.items()},
            "attempts": self.attempts,
            "class_seen": {k: list(v) for k, v in self.class_seen.items()},
        }

    def restore(self, state: dict[str, Any] | None) -> None:
        if not state:
            return
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"prior-map state version {state.get('version')!r}, expected {STATE_VERSION}")
        if state["transform"] is not None:
            self.transform = np.array(state["transform"], dtype=np.float64).reshape(4, 4)
            self.aligned_at = state["aligned_at"]
        self.status = {int(k): str(v) for k, v in state["status"].items()}
        self.streak = {int(k): int(v) for k, v in state["streak"].items()}
        self.attempts = int(state["attempts"])
        self.class_seen = {str(k): [int(v[0]), int(v[1])] for k, v in state.get("class_seen", {}).items()}


def _view_cloud(lm: LandmarkState, max_points: int = 2000) -> np.ndarray | None:
    """A session landmark's surface for relocalisation: its inlier views' points through their current poses.
    The landmark's own cloud grows incrementally and keeps points placed with the poses of their time, which the
    backend has corrected since (on 7-Scenes the stale cloud left the cloud fit 4-6 degrees off, this one 1-2)."""
    parts = [v.world_points() for v in lm.views if v.inlier and len(v.points)]
    if not parts:
        return lm.cloud if len(lm.cloud) else None
    pts = np.concatenate(parts)
    return pts[:: max(1, len(pts) // max_points)]


def _status(lm: Landmark, status: str) -> Landmark:
    from msgspec.structs import replace

    return replace(lm, status=status)


def _freeze(lm: LandmarkState, shift: float, anchor: PriorAnchor) -> LandmarkState:
    """A prior landmark for the session's map: its views keep their (prior-frame) poses for good, its place and
    class are held (`anchor`: this session's views move it only as far as they are worth), and its stamps move
    before the session's start (the association gate grows with the time since it was seen)."""
    lm.anchor = anchor
    for v in lm.views:
        v.frame_id = _frozen(v.frame_id)
        v.track_id = _frozen(v.track_id)
        v.stamp += shift
    lm.tracks = [_frozen(t) for t in lm.tracks]
    lm.frames = {_frozen(f) for f in lm.frames}
    lm.first_seen += shift
    lm.last_seen += shift
    lm.last_assoc += shift
    lm.last_obs_sent = float("-inf")
    lm.last_full += shift
    return lm
