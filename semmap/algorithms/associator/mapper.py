"""The landmark mapper: candidates in, landmarks, merges and backend observations out (pure, no bus, no I/O).

One `process()` per tracker output, in four timed stages named after the paper's runtime table (each in its own
module beside this one; this class holds the state and runs them in order):
- `proposal` (proposal.py): back-project the new measurements into views and validate each touched candidate
  (moving or unstable ones are rejected, and their contributions leave any landmark they already fed);
- `association` (association.py): a new (or held) candidate gets its MAP centroid and goes through the gate;
  a candidate already tied to a landmark (track id -> landmark id) just feeds it;
- `pointcloud`: the nearest-neighbour cloud comparisons inside the association (0 when none ran);
- `update_merge` (landmark_update.py, observation.py, absence.py): re-estimate every touched landmark and merge
  same-class landmarks whose clouds overlap, then emit backend observations. A full re-estimate (batched MAP
  over its views, inlier views, fused voxel cloud, robust extent) runs for new landmarks, after merges or
  rejections, once a quarter more views have arrived, or `full_refresh_s` after the last one; in between, a new
  view is checked against the current MAP centroid and, if it agrees, its points are voxel-merged into the cloud
  (cheap, same result in the limit).

`refine(pose)` takes the current poses of every stored view and re-estimates the landmarks whose views moved,
then merges what now overlaps; the service calls it (throttled) when the backend publishes corrected poses.
Views cache their world positions between refines: `process()` consults the pose lookup only for the new
measurements, so a corrected pose takes effect for old views at the next `refine()`.

Observations: at most one per landmark every `observation_period_s` of stamp time (default 1 s; the paper's
2 s is a setting), only from an inlier view of the frame being processed (the message is tied to that
frame), only for landmarks old enough that a moving object would have been rejected already. The observed
point is the view's own centre in its camera frame: what the depth data says, independent of any pose
estimate, so a pose error shows up in full in the backend's residual. A view whose box touches the image
border observes with `obs_truncated_sigma_factor` times the sigma (its centre slides with what is in view).
`observation_register` (off) measures the landmark centre through a translation-only ICP of the view to the
landmark cloud instead: object clouds are too smooth for it to recover an offset (a 10 cm offset is left at
5-8 cm), so it mostly returns the landmark as predicted through the current pose, an echo of the estimate
that hid half of any pose error from the backend (see params.py for the 7-Scenes figures).

Determinism: ids come from counters, iteration is in id / track-id / input order, and every random draw
comes from a generator seeded by (seed, purpose, id, view count).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from semmap.core.messages import CandidateUpdate, Intrinsics, Landmark, Measurement, Observation, TrackedBox
from semmap.core.stamps import below, reaches

from .absence import absent_landmarks
from .association import decide
from .candidate import (
    PoseLookup,
    View,
    backproject_params,
    map_centroids,
    map_problem,
    motion_testable,
)
from .geometry import robust_box, transform
from .landmark_map import LandmarkMap, LandmarkState, view_from_state, view_to_state
from .landmark_update import absorb, incremental, merge_pass, recompute, views_cloud
from .observation import observation
from .params import MapperParams
from .proposal import (
    MOVING,
    Candidate,
    failure_reason,
    left_its_landmark,
    motion_evidence,
    resolve_pending,
    short_but_static,
    validate_candidate,
    where_it_went,
)

__all__ = ["LandmarkMapper", "MapperParams", "MapperStep", "PoseLookup"]

STATE_VERSION = 1
TIMING_KEYS = ("proposal", "association", "pointcloud", "update_merge")


@dataclass
class MapperStep:
    """What one `process()` / `refine()` changed."""

    updated: list[Landmark] = field(default_factory=list)
    removed: list[int] = field(default_factory=list)  # includes the absorbed ids of `merges`
    merges: list[tuple[int, int]] = field(default_factory=list)  # (absorbed id, surviving id)
    observations: list[Observation] = field(default_factory=list)
    rejected: list[int] = field(default_factory=list)  # candidate track ids rejected by validation
    moving_tracks: list[int] = field(default_factory=list)  # of `rejected`: those seen moving
    moved: list[int] = field(default_factory=list)  # of `removed`: landmarks retired because their object moved
    # the evidence of a moving track (`motion_evidence`), for the log: of `moved`, and of the landmarks kept because
    # the track's motion stayed inside them (`kept_despite_motion`, `left_its_landmark`)
    moved_why: dict[int, str] = field(default_factory=dict)
    kept_despite_motion: list[int] = field(default_factory=list)
    timing_ms: dict[str, float] = field(default_factory=lambda: dict.fromkeys(TIMING_KEYS, 0.0))


CADENCE_WINDOW = 31  # detected frames the run's detection cadence is taken over
Touched = dict[int, list[View]]  # landmark id -> its new views this step, insertion-ordered


class LandmarkMapper:
    """Maps validated candidates to landmarks (see module docstring)."""

    def __init__(self, params: MapperParams | None = None) -> None:
        self.params = params or MapperParams()
        self.map = LandmarkMap()
        self._cands: dict[int, Candidate] = {}
        self._rejected: set[int] = set()
        self._bp = backproject_params(self.params)
        self._dirty: set[int] = set()  # landmarks needing a full re-estimate (views removed or re-chosen)
        self._intrinsics: Intrinsics | None = None  # the camera of the latest measurement (for absence checks)
        self._detected_stamps: deque[float] = deque(maxlen=CADENCE_WINDOW)  # frames detected lately (cadence)

    # ---- queries

    def landmarks(self) -> list[Landmark]:
        return self.map.landmarks()

    def track_landmark(self, track_id: int) -> int | None:
        """The landmark a candidate track feeds, if any."""
        cand = self._cands.get(track_id)
        return None if cand is None else cand.landmark_id

    # ---- main entry points

    def process(
        self,
        frame_id: int,
        stamp: float,
        candidates: list[CandidateUpdate],
        ended: list[int],
        pose: PoseLookup,
        boxes: Sequence[TrackedBox] | None = None,
    ) -> MapperStep:
        """One tracker output: the four stages of the module docstring, timed.

        boxes: the tracker's boxes of this frame when it was detected (None for a skipped frame); with them,
        landmarks in plain view that nothing detects are counted absent and removed once that is no longer
        explained by their own detection rate (`absence_*` settings).
        """
        step = MapperStep()
        touched: Touched = {}
        if boxes is not None and (not self._detected_stamps or stamp > self._detected_stamps[-1]):
            self._detected_stamps.append(stamp)
        t0 = time.perf_counter()
        fed = self._proposal(candidates, stamp, pose, step, touched)
        t1 = time.perf_counter()
        nn_ms = self._association(fed, ended, stamp, step, touched)
        t2 = time.perf_counter()
        self._update_merge(frame_id, stamp, pose, boxes, step, touched)
        t3 = time.perf_counter()
        step.timing_ms = {
            "proposal": (t1 - t0) * 1e3,
            "association": (t2 - t1) * 1e3 - nn_ms,
            "pointcloud": nn_ms,
            "update_merge": (t3 - t2) * 1e3,
        }
        return step

    def refine(self, pose: PoseLookup, stamp: float | None = None) -> MapperStep:
        """Re-place every stored view with the current poses, re-estimate the landmarks that moved, merge.

        stamp: the time of the correction (for the landmarks' refresh clock); default: their last sighting.
        """
        t0 = time.perf_counter()
        step = MapperStep()
        moved = []
        p = self.params
        for lm in self.map.all():
            tolerance = max(p.refine_tolerance_min_m, p.refine_tolerance_size_factor * lm.size)
            changed = [v.refresh(pose, tolerance) for v in lm.views]  # (before the candidates: they share views)
            if any(changed) or lm.id in self._dirty:
                moved.append(lm)
        for cand in self._cands.values():
            for v in cand.views:
                v.refresh(pose, p.refine_tolerance_min_m)
        now = stamp if stamp is not None else max((lm.last_seen for lm in moved), default=0.0)
        recompute(moved, now, self.params, self._dirty)
        touched: Touched = {lm.id: [] for lm in moved}
        self._merge_pass([lm.id for lm in moved], now, step, touched)
        step.updated = [self.map[i].to_message() for i in sorted(touched) if i in self.map]
        step.timing_ms["update_merge"] = (time.perf_counter() - t0) * 1e3
        return step

    def view_interval_s(self) -> float:
        """How close to a track's last view a measurement is counted but not back-projected: the view interval
        (`min_view_interval_s`) less half the run's detection cadence (the median time between detected frames),
        so the view kept is the detection nearest to one interval after the last.

        Why: at 30 Hz with every frame detected it keeps one view per 0.1 s as the bare interval does (frames lie
        33 ms apart: 83 ms or 100 ms keep the same ones), but a real-time run that detects every 2nd frame
        would otherwise keep every 2nd detection (a view per 133 ms), and an object seen for half a second
        would lack the views a short track needs (`short_but_static`) where the same object in lockstep has
        them. The run's cadence, not the track's: a track's own missed detections must not change its views."""
        interval = self.params.min_view_interval_s
        if len(self._detected_stamps) < 3:
            return interval
        cadence = float(np.median(np.diff(np.asarray(self._detected_stamps))))
        return interval - 0.5 * min(max(cadence, 0.0), interval)

    # ---- the stages of process()

    def _proposal(
        self, candidates: list[CandidateUpdate], stamp: float, pose: PoseLookup, step: MapperStep, touched: Touched
    ) -> list[tuple[Candidate, list[View]]]:
        """Views from the new measurements (and from older ones whose pose came), validation; returns the
        candidates that passed with their new views."""
        p = self.params
        work: list[Candidate] = []
        seen: set[int] = set()
        for cu in candidates:
            if cu.track_id in self._rejected or cu.track_id in seen or cu.class_name in p.dynamic_classes:
                continue  # (a dynamic class is published by the tracker as such, never mapped)
            seen.add(cu.track_id)
            cand = self._cands.get(cu.track_id)
            if cand is None:
                cand = self._cands[cu.track_id] = Candidate(cu.track_id, cu.class_name)
            cand.pending.extend(cu.measurements)
            work.append(cand)
        for tid, cand in self._cands.items():  # older candidates still waiting for a pose
            if cand.pending and tid not in seen:
                work.append(cand)
        fed: list[tuple[Candidate, list[View]]] = []
        interval = self.view_interval_s()  # (once a frame: the same for every candidate)
        for cand in work:
            lm = self.map.get(cand.landmark_id) if cand.landmark_id is not None else None
            new_views, intrinsics = resolve_pending(cand, stamp, pose, lm, self._bp, p, interval)
            if intrinsics is not None:
                self._intrinsics = intrinsics
            if not new_views or len(cand.views) < p.min_views:
                continue
            cand.since_validation += len(new_views)
            if cand.landmark_id is None or cand.since_validation >= p.validate_every:
                reason = validate_candidate(cand, p)
                if reason:
                    self._reject(cand, step, touched, reason)
                    continue
            fed.append((cand, new_views))
        return fed

    def _association(
        self,
        fed: list[tuple[Candidate, list[View]]],
        ended: list[int],
        stamp: float,
        step: MapperStep,
        touched: Touched,
    ) -> float:
        """Feed candidates tied to a landmark; gate the others (old enough to tell whether they move) and the
        ones whose tracklet ended; returns the time spent in cloud comparisons (ms)."""
        p = self.params
        nn_ms = 0.0
        for cand, new_views in fed:
            lm = self.map.get(cand.landmark_id) if cand.landmark_id is not None else None
            if lm is not None:
                lm.add_views(new_views, p.max_views)
                lm.measurements += cand.skipped
                lm.vote(cand.class_name, len(new_views) + cand.skipped)
                cand.skipped = 0
                lm.last_assoc = max(lm.last_assoc, stamp)
                touched.setdefault(lm.id, []).extend(new_views)
                continue
            cand.landmark_id = None
            span = cand.views[-1].stamp - cand.views[0].stamp
            if below(span, p.min_track_span_s) or (
                below(span, p.untestable_span_s) and not motion_testable(cand.views, p)
            ):
                continue  # too young to tell whether it moves (decided at its end if it ends young)
            nn_ms += self._associate(cand, stamp, touched, force=False)
        for tid in ended:
            cand = self._cands.get(tid)
            self._rejected.discard(tid)  # the tracker never reuses an id
            if cand is not None and cand.landmark_id is not None and cand.since_validation > 0:
                reason = failure_reason(cand, p)  # its last views were not validated yet
                if reason:
                    self._reject(cand, step, touched, reason)
                    self._rejected.discard(tid)
            cand = self._cands.pop(tid, None)
            if cand is None or cand.landmark_id is not None:
                continue
            if cand.held or short_but_static(cand, p):
                nn_ms += self._associate(cand, stamp, touched, force=True)
        return nn_ms

    def _update_merge(
        self,
        frame_id: int,
        stamp: float,
        pose: PoseLookup,
        boxes: Sequence[TrackedBox] | None,
        step: MapperStep,
        touched: Touched,
    ) -> None:
        """Re-estimate the touched landmarks (full or incremental), merge, observations, absence; the step's
        updated landmarks."""
        p = self.params
        full: list[LandmarkState] = []
        for lid, new_views in touched.items():
            lm = self.map.get(lid)
            if lm is None:
                continue
            lm.added_since_full += len(new_views)
            if (
                lid in self._dirty
                or lm.views_at_full == 0
                or reaches(stamp - lm.last_full, p.full_refresh_s)
                or lm.added_since_full >= max(p.full_min_new_views, p.full_growth * lm.views_at_full)
            ):
                full.append(lm)
            else:
                incremental(lm, new_views, p)
        recompute(full, stamp, p, self._dirty)
        self._merge_pass([lm.id for lm in full], stamp, step, touched)
        for lid in touched:
            lm = self.map.get(lid)
            if lm is None:
                continue
            obs = self._observation(lm, frame_id, stamp)
            if obs is not None:
                step.observations.append(obs)
        if boxes is not None and p.absence_removal:
            for lid in absent_landmarks(self.map.all(), frame_id, pose(frame_id), self._intrinsics, boxes, p):
                self._remove_landmark(lid, step, touched)
        step.updated = [self.map[i].to_message() for i in sorted(touched) if i in self.map]

    # ---- helpers

    def _reject(self, cand: Candidate, step: MapperStep, touched: Touched, reason: str = "") -> None:
        """Drop a candidate that failed validation (`reason`). One seen moving takes its landmark with it (retired:
        the object is no longer where the landmark is, whatever other tracks saw there before) when it left the
        landmark (`left_its_landmark`); one whose motion stayed inside it only stops feeding it."""
        moving = reason in MOVING
        step.rejected.append(cand.track_id)
        self._rejected.add(cand.track_id)
        self._cands.pop(cand.track_id, None)
        if moving:
            step.moving_tracks.append(cand.track_id)
        lm = self.map.get(cand.landmark_id) if cand.landmark_id is not None else None
        if lm is None:
            return
        if moving:
            went = where_it_went(cand, lm, self.params)  # (a failed candidate has views: min_views)
            step.moved_why[lm.id] = motion_evidence(cand, reason, lm, went, self.params)
            if left_its_landmark(went, lm):
                self._remove_landmark(lm.id, step, touched)
                step.moved.append(lm.id)
                return
            step.kept_despite_motion.append(lm.id)  # the track feeds it no more; what it gave stays, inside it
            return
        lm.remove_track(cand.track_id)
        if not lm.views:
            self._remove_landmark(lm.id, step, touched)
        else:
            self._dirty.add(lm.id)
            touched.setdefault(lm.id, [])

    def _associate(self, cand: Candidate, stamp: float, touched: Touched, force: bool) -> float:
        """Gate a validated, unassigned candidate; returns the time spent in cloud comparisons (ms)."""
        p = self.params
        problem = map_problem(cand.views, p, seed=(p.seed, 1, cand.track_id, len(cand.views)))
        centroid = map_centroids([problem], p)[0]
        cloud: list[np.ndarray] = []

        def cloud_fn() -> np.ndarray:
            if not cloud:
                cloud.append(views_cloud(cand.views, p))
            return cloud[0]

        size = float(np.percentile([v.size for v in cand.views], 80))
        decision = decide(
            centroid,
            size,
            cand.frames,
            cloud_fn,
            self.map.voted_for(cand.class_name),
            stamp,
            len(cand.views),
            p,
            force,
        )
        if decision.kind == "hold":
            cand.held = True
            return decision.nn_ms
        cand.held = False
        if decision.kind == "new":
            lm = self.map.create(cand.class_name, min(v.stamp for v in cand.views))
            c = cloud_fn()
            lm.map_centroid = lm.centroid = centroid
            _, extent = robust_box(c, p.extent_percentile) if len(c) >= 4 else (centroid, np.full(3, size))
            lm.extent, lm.size = extent, float(np.linalg.norm(extent))
            lm.set_cloud(c)
        else:
            assert decision.landmark_id is not None
            lm = self.map[decision.landmark_id]
            self._dirty.add(lm.id)
        lm.add_views(cand.views, p.max_views)
        lm.measurements += cand.skipped
        lm.vote(cand.class_name, len(cand.views) + cand.skipped)
        cand.skipped = 0
        lm.frames |= cand.frames
        lm.last_assoc = max(lm.last_assoc, stamp)
        lm.first_seen = min(lm.first_seen, min(v.stamp for v in cand.views))
        cand.landmark_id = lm.id
        touched.setdefault(lm.id, []).extend(cand.views)
        return decision.nn_ms

    def _merge_pass(self, ids: list[int], stamp: float, step: MapperStep, touched: Touched) -> None:
        for gone, keep in merge_pass(self.map, ids, stamp, self.params, self._dirty, self._absorb):
            step.merges.append((gone, keep))
            step.removed.append(gone)
            touched.pop(gone, None)
            touched.setdefault(keep, [])

    def _absorb(self, keep: LandmarkState, gone: LandmarkState) -> None:
        absorb(keep, gone, self.map, self.params, self._dirty)
        for cand in self._cands.values():
            if cand.landmark_id == gone.id:
                cand.landmark_id = keep.id

    def _remove_landmark(self, lid: int, step: MapperStep, touched: Touched) -> None:
        self.map.remove(lid)
        self._dirty.discard(lid)
        step.removed.append(lid)
        touched.pop(lid, None)
        for cand in self._cands.values():
            if cand.landmark_id == lid:  # a still running tracklet of it starts over as a new candidate
                cand.landmark_id = None

    def _observation(self, lm: LandmarkState, frame_id: int, stamp: float) -> Observation | None:
        return observation(lm, frame_id, stamp, self.params)

    # ---- a prior map (semmap/algorithms/associator/prior_map.py)

    def adopt_landmarks(self, landmarks: list[LandmarkState]) -> None:
        """Landmarks of a prior map join this map under their own ids (the session's ids start after them)."""
        for lm in landmarks:
            self.map.insert(lm)

    def move_frame(self, T: np.ndarray) -> None:
        """Take the whole map into another frame by the rigid `T` (every stored view's pose, landmarks' and
        candidates'); the next `refine` re-estimates every landmark there. Why: `semmap merge` re-places B's
        views with poses re-optimised in A's frame, and views no such pose reaches (a prior map's frozen ones)
        must be in A's frame too."""
        T = np.asarray(T, dtype=np.float64)
        moved: set[int] = set()  # (a restored candidate shares its views with its landmark)
        for views in [lm.views for lm in self.map.all()] + [c.views for c in self._cands.values()]:
            for v in views:
                if id(v) not in moved:
                    moved.add(id(v))
                    v.pose = T @ v.pose
                    v.alt_world = transform(v.pose, v.alt_centroids)
        for lm in self.map.all():  # a prior landmark's place moves with its views
            if lm.anchor is not None:
                lm.anchor.centroid = transform(T, lm.anchor.centroid[None, :])[0]
        self._dirty.update(lm.id for lm in self.map.all())

    def fuse(self, keep_id: int, gone_id: int, step: MapperStep) -> None:
        """One object twice (a session landmark and the prior landmark the relocalisation matched it to): fuse
        them into `keep_id`, as a merge."""
        keep, gone = self.map[keep_id], self.map[gone_id]
        self._absorb(keep, gone)
        recompute([keep], keep.last_seen, self.params, self._dirty)
        step.merges.append((gone_id, keep_id))
        step.removed.append(gone_id)
        step.updated = [m for m in step.updated if m.id not in (gone_id, keep_id)] + [keep.to_message()]

    # ---- persistence

    def to_state(self) -> dict[str, Any]:
        """Plain data (lists, numbers, bytes): the whole mapper, for SQLite / msgpack.

        A candidate tied to a landmark shares its View objects with it (validation re-chooses a shared view's
        surface, a landmark update marks it an inlier or not, for both); `shared` records, per candidate view,
        which landmark view it is, so that `from_state` links them again instead of making two copies that
        would drift apart after a restart."""
        where = {id(v): [lm.id, k] for lm in self.map.all() for k, v in enumerate(lm.views)}
        return {
            "version": STATE_VERSION,
            "map": self.map.to_state(),
            "rejected": sorted(self._rejected),
            "dirty": sorted(self._dirty),
            # the camera of the latest measurement: absence checks of the next frame use it
            "intrinsics": None if self._intrinsics is None else self._intrinsics.to_dict(),
            # the stamps of the frames detected lately: the run's detection cadence (`view_interval_s`)
            "detected_stamps": list(self._detected_stamps),
            "candidates": [
                {
                    "track_id": c.track_id,
                    "class": c.class_name,
                    "views": [view_to_state(v) for v in c.views],
                    "shared": [where.get(id(v)) for v in c.views],
                    "frames": sorted(c.frames),
                    "landmark_id": c.landmark_id,
                    "held": c.held,
                    "since_validation": c.since_validation,
                    "skipped": c.skipped,
                    "pending": [m.to_dict() for m in c.pending],
                    "path": [
                        [f, t, *(float(x) for x in w), bool(tr), bool(oc)] for f, (t, w, tr, oc) in c.path.items()
                    ],
                }
                for c in self._cands.values()
            ],
        }

    @classmethod
    def from_state(cls, state: dict[str, Any], params: MapperParams | None = None) -> LandmarkMapper:
        """A mapper that continues from `to_state()` output (same ids, same candidates)."""
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"mapper state version {state.get('version')!r}, expected {STATE_VERSION}")
        mapper = cls(params)
        mapper.map = LandmarkMap.from_state(state["map"])
        mapper._rejected = {int(t) for t in state["rejected"]}
        mapper._dirty = {int(t) for t in state["dirty"]}
        if state.get("intrinsics") is not None:
            mapper._intrinsics = Intrinsics.from_dict(state["intrinsics"])
        mapper._detected_stamps.extend(float(t) for t in state.get("detected_stamps") or ())  # (older: none)
        for d in state["candidates"]:
            shared = d.get("shared") or [None] * len(d["views"])
            c = Candidate(
                int(d["track_id"]),
                str(d["class"]),
                [
                    view_from_state(v) if ref is None else mapper.map[int(ref[0])].views[int(ref[1])]
                    for v, ref in zip(d["views"], shared, strict=True)
                ],
                {int(f) for f in d["frames"]},
                [Measurement.from_dict(m) for m in d["pending"]],
                None if d["landmark_id"] is None else int(d["landmark_id"]),
                bool(d["held"]),
                int(d["since_validation"]),
                int(d["skipped"]),
                {
                    int(e[0]): (float(e[1]), np.array(e[2:5], dtype=np.float64), bool(e[5]), len(e) > 6 and bool(e[6]))
                    for e in d.get("path", [])
                },
            )
            mapper._cands[c.track_id] = c
        return mapper
