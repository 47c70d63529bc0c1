"""The landmark mapper: candidates in, landmarks, merges and backend observations out (pure, no bus, no I/O).

One `process()` per tracker output, in four timed stages named after the paper's runtime table:
- `proposal`: back-project the new measurements into views and validate each touched candidate (moving or
  unstable ones are rejected, and their contributions leave any landmark they already fed);
- `association`: a new (or held) candidate gets its MAP centroid and goes through the gate (association.py);
  a candidate already tied to a landmark (track id -> landmark id) just feeds it;
- `pointcloud`: the nearest-neighbour cloud comparisons inside the association (0 when none ran);
- `update_merge`: re-estimate every touched landmark and merge same-class landmarks whose clouds overlap,
  then emit backend observations. A full re-estimate (batched MAP over its views, inlier views, fused voxel
  cloud, robust extent) runs for new landmarks, after merges or rejections, once a quarter more views have
  arrived, or `full_refresh_s` after the last one; in between, a new view is checked against the current MAP
  centroid and, if it agrees, its points are voxel-merged into the cloud (cheap, same result in the limit).

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

import bisect
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from semmap.messages import CandidateUpdate, Intrinsics, Landmark, Measurement, Observation, TrackedBox

from .association import decide, gate_floor, trimmed_mean
from .candidate import (
    MapProblem,
    PoseLookup,
    Validation,
    View,
    backproject_params,
    choose_surfaces,
    make_view,
    map_centroids,
    map_problem,
    motion_testable,
    start_point,
    track_motion,
    validate,
    view_sigmas,
    whole_views,
    world_centroids,
)
from .geometry import inverse_transform, robust_box, voxel_downsample
from .landmark_map import LandmarkMap, LandmarkState, view_from_state, view_to_state
from .params import MapperParams

__all__ = ["LandmarkMapper", "MapperParams", "MapperStep", "PoseLookup"]

STATE_VERSION = 1
MOVING = ("motion", "track_motion")  # validation failures that mean the object moves (not just scatter)
TIMING_KEYS = ("proposal", "association", "pointcloud", "update_merge")


def _confusable(a: LandmarkState, b: LandmarkState, groups: str) -> bool:
    """Whether the two landmarks' classes (or any class they were voted for) share a confusable group
    (`confusable_classes`: groups separated by ';', classes within a group by '|')."""
    names_a = {a.class_name, *a.class_votes}
    names_b = {b.class_name, *b.class_votes}
    if names_a & names_b:
        return True
    for group in groups.split(";"):
        members = {c.strip() for c in group.split("|") if c.strip()}
        if names_a & members and names_b & members:
            return True
    return False


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
    timing_ms: dict[str, float] = field(default_factory=lambda: dict.fromkeys(TIMING_KEYS, 0.0))


@dataclass
class _Candidate:
    track_id: int
    class_name: str
    views: list[View] = field(default_factory=list)
    frames: set[int] = field(default_factory=set)
    pending: list[Measurement] = field(default_factory=list)  # measurements whose pose is not known yet
    landmark_id: int | None = None
    held: bool = False
    since_validation: int = 0  # views added since the last validation
    skipped: int = 0  # measurements counted but not back-projected (min_view_interval_s)
    # the whole track's views as (stamp, world centroid, truncated) by frame id, for `track_motion` (views are
    # trimmed to the validation window; this is not)
    path: dict[int, tuple[float, np.ndarray, bool]] = field(default_factory=dict)


class LandmarkMapper:
    """Maps validated candidates to landmarks (see module docstring)."""

    def __init__(self, params: MapperParams | None = None) -> None:
        self.params = params or MapperParams()
        self.map = LandmarkMap()
        self._cands: dict[int, _Candidate] = {}
        self._rejected: set[int] = set()
        self._bp = backproject_params(self.params)
        self._dirty: set[int] = set()  # landmarks needing a full re-estimate (views removed or re-chosen)
        self._intrinsics: Intrinsics | None = (
            None  # the camera of the latest measurement (for absence checks)
        )

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
        """One tracker output: see the module docstring.

        boxes: the tracker's boxes of this frame when it was detected (None for a skipped frame); with them,
        landmarks in plain view that nothing detects are counted absent and removed once that is no longer
        explained by their own detection rate (`absence_*` settings).
        """
        p = self.params
        step = MapperStep()
        touched: dict[int, list[View]] = {}  # landmark id -> its new views, insertion-ordered

        # -- proposal: views and validation
        t0 = time.perf_counter()
        work: list[_Candidate] = []
        seen: set[int] = set()
        for cu in candidates:
            if cu.track_id in self._rejected or cu.track_id in seen or cu.class_name in p.dynamic_classes:
                continue  # (a dynamic class is published by the tracker as such, never mapped)
            seen.add(cu.track_id)
            cand = self._cands.get(cu.track_id)
            if cand is None:
                cand = self._cands[cu.track_id] = _Candidate(cu.track_id, cu.class_name)
            cand.pending.extend(cu.measurements)
            work.append(cand)
        for tid, cand in self._cands.items():  # older candidates still waiting for a pose
            if cand.pending and tid not in seen:
                work.append(cand)
        fed: list[tuple[_Candidate, list[View]]] = []
        for cand in work:
            new_views = self._resolve_pending(cand, stamp, pose)
            if not new_views or len(cand.views) < p.min_views:
                continue
            cand.since_validation += len(new_views)
            if cand.landmark_id is None or cand.since_validation >= p.validate_every:
                reason = self._validate(cand)
                if reason:
                    self._reject(cand, step, touched, moving=reason in MOVING)
                    continue
            fed.append((cand, new_views))
        t1 = time.perf_counter()

        # -- association
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
            if span < p.min_track_span_s or (
                span < p.untestable_span_s and not motion_testable(cand.views, p)
            ):
                continue  # too young to tell whether it moves (decided at its end if it ends young)
            nn_ms += self._associate(cand, stamp, touched, force=False)
        for tid in ended:
            cand = self._cands.get(tid)
            self._rejected.discard(tid)  # the tracker never reuses an id
            if cand is not None and cand.landmark_id is not None and cand.since_validation > 0:
                reason = self._reason(cand, validate(cand.views, p))  # its last views were not validated yet
                if reason:
                    self._reject(cand, step, touched, moving=reason in MOVING)
                    self._rejected.discard(tid)
            cand = self._cands.pop(tid, None)
            if cand is None or cand.landmark_id is not None:
                continue
            if cand.held or self._short_but_static(cand):
                nn_ms += self._associate(cand, stamp, touched, force=True)
        t2 = time.perf_counter()

        # -- landmark update & merge
        full: list[LandmarkState] = []
        for lid, new_views in touched.items():
            lm = self.map.get(lid)
            if lm is None:
                continue
            lm.added_since_full += len(new_views)
            if (
                lid in self._dirty
                or lm.views_at_full == 0
                or stamp - lm.last_full >= p.full_refresh_s
                or lm.added_since_full >= max(p.full_min_new_views, p.full_growth * lm.views_at_full)
            ):
                full.append(lm)
            else:
                self._incremental(lm, new_views)
        self._recompute(full, stamp)
        self._merge_pass([lm.id for lm in full], stamp, step, touched)
        for lid in touched:
            lm = self.map.get(lid)
            if lm is None:
                continue
            obs = self._observation(lm, frame_id, stamp)
            if obs is not None:
                step.observations.append(obs)
        if boxes is not None and p.absence_removal:
            self._absence(frame_id, pose(frame_id), boxes, step, touched)
        step.updated = [self.map[i].to_message() for i in sorted(touched) if i in self.map]
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
        for lm in self.map.all():
            changed = [v.refresh(pose) for v in lm.views]  # (before the candidates: they share views)
            if any(changed) or lm.id in self._dirty:
                moved.append(lm)
        for cand in self._cands.values():
            for v in cand.views:
                v.refresh(pose)
        now = stamp if stamp is not None else max((lm.last_seen for lm in moved), default=0.0)
        self._recompute(moved, now)
        touched: dict[int, list[View]] = {lm.id: [] for lm in moved}
        self._merge_pass([lm.id for lm in moved], now, step, touched)
        step.updated = [self.map[i].to_message() for i in sorted(touched) if i in self.map]
        step.timing_ms["update_merge"] = (time.perf_counter() - t0) * 1e3
        return step

    # ---- proposal helpers

    def _resolve_pending(self, cand: _Candidate, stamp: float, pose: PoseLookup) -> list[View]:
        """Turn pending measurements whose pose is known into views; drop those that waited too long."""
        new_views: list[View] = []
        still: list[Measurement] = []
        lm = self.map.get(cand.landmark_id) if cand.landmark_id is not None else None
        expected = (lm.centroid, lm.size) if lm is not None and lm.size > 0 else None
        kept = sorted(v.stamp for v in cand.views)
        for m in sorted(cand.pending, key=lambda m: (m.stamp, m.frame_id)):
            self._intrinsics = m.intrinsics
            cand.frames.add(m.frame_id)
            if lm is not None:
                lm.frames.add(m.frame_id)
            i = bisect.bisect_left(kept, m.stamp)
            gap = min(abs(m.stamp - kept[j]) for j in (i - 1, i) if 0 <= j < len(kept)) if kept else math.inf
            if gap < self.params.min_view_interval_s:
                cand.skipped += 1  # 30 Hz frames are nearly the same view: count it, do not back-project it
                continue
            T = pose(m.frame_id)
            if T is None:
                if stamp - m.stamp <= self.params.pose_wait_s:
                    still.append(m)
                continue
            v = make_view(m, T, cand.track_id, self._bp, self.params, expected)
            if v is not None:
                new_views.append(v)
                cand.path[v.frame_id] = (v.stamp, v.world.copy(), v.truncated)
                bisect.insort(kept, m.stamp)
        cand.pending = still
        cand.views.extend(new_views)
        late = new_views and len(cand.views) > len(new_views)
        if late and new_views[0].stamp < cand.views[-len(new_views) - 1].stamp:
            cand.views.sort(key=lambda v: (v.stamp, v.frame_id))  # late poses: keep views in time order
        window = max(self.params.validation_window, self.params.hold_max_views)
        if len(cand.views) > window:  # only recent views matter for validation; landmarks keep their own
            del cand.views[: len(cand.views) - window]
        return new_views

    def _validate(self, cand: _Candidate) -> str:
        """Validation ('' = passed, else the reason); before association, first the multi-view choice of each
        view's surface (the background in a walking person's box walks along with them, so consensus cannot
        hide motion)."""
        p = self.params
        cand.since_validation = 0
        if cand.landmark_id is None:
            choose_surfaces(cand.views[-p.validation_window :], p)
        return self._reason(cand, validate(cand.views, p))

    def _reason(self, cand: _Candidate, v: Validation) -> str:
        """Why the candidate fails: the recent-window tests' reason, else the whole-track motion test's."""
        if not v.ok:
            return v.reason
        moving, _ = self._track_motion(cand)
        return "track_motion" if moving else ""

    def _track_motion(self, cand: _Candidate, whole_only: bool = True) -> tuple[bool, float]:
        """`track_motion` over the candidate's whole track (the views still held as they are placed now)."""
        for view in cand.views:
            cand.path[view.frame_id] = (view.stamp, view.world, view.truncated)
        entries = list(cand.path.values())
        size = float(np.percentile([x.size for x in cand.views], 80))
        return track_motion(
            np.array([e[0] for e in entries]),
            np.stack([e[1] for e in entries]),
            np.array([e[2] for e in entries], dtype=bool),
            size,
            self.params,
            whole_only,
        )

    def _short_but_static(self, cand: _Candidate) -> bool:
        """A tracklet that ended before `min_track_span_s`: kept only if its views are tightly together
        (less time to show motion, so stronger evidence of standing still: a clock seen for 0.7 s at the
        image border yes, a person crossing the view no)."""
        p = self.params
        if (
            len(cand.views) < max(p.min_views, p.min_views_spread)
            or cand.views[-1].stamp - cand.views[0].stamp < p.min_motion_span_s
        ):
            return False
        if self._validate(cand) or self._track_motion(cand, whole_only=False)[1] > p.short_track_motion_m:
            return False
        v = validate(cand.views, p)
        size = min(float(np.percentile([x.size for x in cand.views], 80)), p.track_motion_size_cap_m)
        return v.spread_m <= max(p.mad_min_m, p.short_track_mad_factor * size)

    def _reject(
        self, cand: _Candidate, step: MapperStep, touched: dict[int, list[View]], moving: bool = False
    ) -> None:
        """Drop a candidate that failed validation. One seen moving takes its landmark with it (retired: the
        object is no longer where the landmark is, whatever other tracks saw there before)."""
        step.rejected.append(cand.track_id)
        self._rejected.add(cand.track_id)
        self._cands.pop(cand.track_id, None)
        if moving:
            step.moving_tracks.append(cand.track_id)
        lm = self.map.get(cand.landmark_id) if cand.landmark_id is not None else None
        if lm is None:
            return
        if moving:
            self._remove_landmark(lm.id, step, touched)
            step.moved.append(lm.id)
            return
        lm.remove_track(cand.track_id)
        if not lm.views:
            self._remove_landmark(lm.id, step, touched)
        else:
            self._dirty.add(lm.id)
            touched.setdefault(lm.id, [])

    # ---- association

    def _cloud(self, views: list[View]) -> np.ndarray:
        pts = np.concatenate([v.world_points() for v in views])
        return voxel_downsample(pts, self.params.voxel_m, self.params.cloud_max_points)

    def _associate(
        self, cand: _Candidate, stamp: float, touched: dict[int, list[View]], force: bool
    ) -> float:
        """Gate a validated, unassigned candidate; returns the time spent in cloud comparisons (ms)."""
        p = self.params
        problem = map_problem(cand.views, p, seed=(p.seed, 1, cand.track_id, len(cand.views)))
        centroid = map_centroids([problem], p)[0]
        cloud: list[np.ndarray] = []

        def cloud_fn() -> np.ndarray:
            if not cloud:
                cloud.append(self._cloud(cand.views))
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

    # ---- landmark update & merge

    def _inlier_limit(self, views: list[View], sig: np.ndarray, size: float) -> np.ndarray:
        """How far each view's centroid may be from the MAP centroid; a truncated view's centre may be off by
        up to half the object, so it gets that much slack."""
        p = self.params
        limit = np.maximum(p.inlier_min_m, p.inlier_sigmas * sig)
        return limit + 0.5 * size * np.array([v.truncated for v in views])

    def _set_cloud(self, lm: LandmarkState, cloud: np.ndarray, n_inliers: int) -> None:
        p = self.params
        if len(cloud) >= 4:
            centre, extent = robust_box(cloud, p.extent_percentile)
        else:
            centre, extent = lm.map_centroid, np.full(3, float(np.median([v.size for v in lm.views])))
        lm.centroid = centre if n_inliers >= p.fused_min_views else lm.map_centroid
        lm.extent = extent
        lm.size = float(np.linalg.norm(extent))
        lm.set_cloud(cloud)

    def _recompute(self, lms: list[LandmarkState], stamp: float) -> None:
        """Full re-estimate: batched MAP over each landmark's views, then inliers, fused cloud, extent."""
        p = self.params
        lms = [lm for lm in lms if lm.views]
        if not lms:
            return
        problems, sizes = [], []
        for lm in lms:
            size = lm.size if lm.size > 0 else float(np.percentile([v.size for v in lm.views], 80))
            use = whole_views(lm.views, 3)
            c = world_centroids(use)
            problems.append(
                MapProblem(
                    c,
                    view_sigmas(use, size, p),
                    start_point(use, c),
                    (p.seed, 2, lm.id, len(lm.views)),
                    prior_sigma=1.0 + size,
                )
            )
            sizes.append(size)
        for lm, size, m in zip(lms, sizes, map_centroids(problems, p), strict=True):
            c = world_centroids(lm.views)
            d = np.linalg.norm(c - m, axis=1)
            inl = d <= self._inlier_limit(lm.views, view_sigmas(lm.views, size, p), size)
            if not inl.any():
                inl = d <= np.median(d)
            for v, ok in zip(lm.views, inl, strict=True):
                v.inlier = bool(ok)
            lm.map_centroid = m
            self._set_cloud(lm, self._cloud([v for v in lm.views if v.inlier]), int(inl.sum()))
            lm.views_at_full = len(lm.views)
            lm.added_since_full = 0
            lm.last_full = stamp
            self._dirty.discard(lm.id)

    def _incremental(self, lm: LandmarkState, new_views: list[View]) -> None:
        """Cheap update with a few new views: inlier test against the MAP centroid, voxel-merge the points."""
        if not new_views:
            return
        sig = view_sigmas(new_views, lm.size, self.params)
        d = np.linalg.norm(world_centroids(new_views) - lm.map_centroid, axis=1)
        inl = d <= self._inlier_limit(new_views, sig, lm.size)
        added = []
        for v, ok in zip(new_views, inl, strict=True):
            v.inlier = bool(ok)
            if ok:
                added.append(v.world_points())
        if added:
            cloud = voxel_downsample(
                np.concatenate([lm.cloud, *added]), self.params.voxel_m, self.params.cloud_max_points
            )
            self._set_cloud(lm, cloud, sum(v.inlier for v in lm.views))

    def _overlap(self, a: LandmarkState, b: LandmarkState) -> float:
        """Share of one cloud lying within a tolerance of the other (the larger of the two directions)."""
        p = self.params
        if len(a.cloud) == 0 or len(b.cloud) == 0:
            return 0.0
        tol = max(p.merge_tol_min_m, p.merge_tol_size_factor * min(a.size, b.size))
        da, _ = b.tree().query(a.cloud, k=1, distance_upper_bound=tol)
        db, _ = a.tree().query(b.cloud, k=1, distance_upper_bound=tol)
        return max(float(np.mean(np.isfinite(da))), float(np.mean(np.isfinite(db))))

    def _same_object_other_class(self, a: LandmarkState, b: LandmarkState) -> bool:
        """Two landmarks of confusable classes that are one object: the detector's class flipped between
        views (a laptop as tv or microwave; with class-wise NMS even two boxes in one frame, so co-visibility
        says nothing here). Co-located (centroids within the gate floor of the smaller) and overlapping clouds;
        two different objects side by side (a keyboard in front of a screen) do not overlap."""
        p = self.params
        if not p.class_merge or not _confusable(a, b, p.confusable_classes):
            return False
        if float(np.linalg.norm(a.centroid - b.centroid)) > gate_floor(min(a.size, b.size), p):
            return False
        return self._overlap(a, b) >= p.merge_overlap_min

    def _merge_pass(
        self, ids: list[int], stamp: float, step: MapperStep, touched: dict[int, list[View]]
    ) -> None:
        """Merge each listed landmark with overlapping same-class ones into the older id (repeatedly), and with
        a co-located, overlapping landmark of a confusable class (the class becomes the majority vote)."""
        p = self.params
        queue = sorted(set(ids))
        while queue:
            a = self.map.get(queue.pop(0))
            if a is None:
                continue
            for b in self.map.all():
                if b.id == a.id or float(np.linalg.norm(a.centroid - b.centroid)) > a.radius + b.radius:
                    continue
                if b.class_name != a.class_name:
                    if not self._same_object_other_class(a, b):
                        continue
                else:
                    covis = len(a.frames & b.frames)
                    if covis >= p.covis_veto_frames and p.merge_overlap_contained > 1.0:
                        continue
                    overlap = self._overlap(a, b)
                    if not (
                        (overlap >= p.merge_overlap_min and covis < p.covis_veto_frames)
                        or overlap >= p.merge_overlap_contained
                    ):
                        continue
                keep, gone = (a, b) if a.id < b.id else (b, a)
                self._absorb(keep, gone)
                step.merges.append((gone.id, keep.id))
                step.removed.append(gone.id)
                touched.pop(gone.id, None)
                touched.setdefault(keep.id, [])
                self._recompute([keep], stamp)
                queue = sorted(set(queue) - {gone.id} | {keep.id})
                break

    def _absorb(self, keep: LandmarkState, gone: LandmarkState) -> None:
        keep.views.extend(gone.views)
        keep.views.sort(key=lambda v: (v.stamp, v.frame_id, v.track_id))
        while len(keep.views) > self.params.max_views:
            keep._drop_redundant_view()
        keep.tracks.extend(t for t in gone.tracks if t not in keep.tracks)
        keep.frames |= gone.frames
        keep.measurements += gone.measurements
        keep.absorb_votes(gone.class_votes)
        keep.first_seen = min(keep.first_seen, gone.first_seen)
        keep.last_seen = max(keep.last_seen, gone.last_seen)
        keep.last_assoc = max(keep.last_assoc, gone.last_assoc)
        keep.last_obs_sent = max(keep.last_obs_sent, gone.last_obs_sent)
        self.map.remove(gone.id)
        self._dirty.discard(gone.id)
        for cand in self._cands.values():
            if cand.landmark_id == gone.id:
                cand.landmark_id = keep.id

    # ---- negative evidence

    def _absence(
        self,
        frame_id: int,
        T: np.ndarray | None,
        boxes: Sequence[TrackedBox],
        step: MapperStep,
        touched: dict[int, list[View]],
    ) -> None:
        """Count landmarks that should be visible in this detected frame but are not detected.

        In view: the centroid projects into the image's central part (`absence_margin` kept clear) at a
        depth in [absence_min_depth_m, absence_max_depth_m], its sphere spans at least `absence_min_px`
        pixels, and no other landmark's sphere lies in front of it on the line of sight (occlusion, judged
        from the map itself). Detected: a box of its class (tentative tracklets too) meets its projected
        disk. A landmark is removed when its current streak
        of in-view misses has become improbable under its own detection rate r = (n_seen + 1) /
        (n_seen + n_missed + 2): (1 - r)^streak < absence_p, and streak >= absence_min_frames. A person who
        stood still long enough to be mapped and walked off goes within a few frames of looking there again;
        a table that the detector finds in one frame of five needs a long, unexplained absence.
        Off by default: occluders that are not landmarks (a wall edge, a person) and objects a detector
        finds only from some sides make absence evidence unsafe within one pass over a scene; it pays in
        long sessions with revisits.
        """
        p = self.params
        k = self._intrinsics
        lms = [lm for lm in self.map.all() if lm.views]
        if T is None or k is None or not lms:
            return
        c = np.stack([lm.centroid for lm in lms])
        cam = inverse_transform(np.asarray(T, dtype=np.float64), c)
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam[:, 0] / z * k.fx + k.cx
            v = cam[:, 1] / z * k.fy + k.cy
        mu, mv = p.absence_margin * k.width, p.absence_margin * k.height
        radius = np.array([lm.radius for lm in lms])
        visible = (
            (z >= p.absence_min_depth_m)
            & (z <= p.absence_max_depth_m)
            & (u >= mu)
            & (u <= k.width - mu)
            & (v >= mv)
            & (v <= k.height - mv)
            & (radius * k.fx >= p.absence_min_px * z)
        )
        if not visible.any():
            return
        dist = np.linalg.norm(cam, axis=1)
        dirs = cam / np.maximum(dist, 1e-9)[:, None]
        along = dirs @ cam.T  # along[i, j]: depth of landmark j along the line of sight to landmark i
        perp = np.sqrt(np.maximum(np.square(np.linalg.norm(cam, axis=1))[None, :] - along**2, 0.0))
        blocks = (
            (perp < radius[None, :])
            & (along + radius[None, :] < dist[:, None] - radius[:, None])
            & (along > 0)
        )
        np.fill_diagonal(blocks, False)
        for i, lm in enumerate(lms):
            if not visible[i] or frame_id in lm.frames or blocks[i].any():
                continue
            r_px = max(2.0, lm.radius * k.fx / z[i])  # its disk on the image meets a box of its class
            seen = any(
                b.class_name == lm.class_name
                and b.box[0] - r_px <= u[i] <= b.box[2] + r_px
                and b.box[1] - r_px <= v[i] <= b.box[3] + r_px
                for b in boxes
            )
            if seen:
                lm.absent_streak = 0
                continue
            lm.absent_streak += 1
            lm.absent_total += 1
            rate = (lm.measurements + 1.0) / (lm.measurements + lm.absent_total + 2.0)
            needed = max(p.absence_min_frames, math.log(p.absence_p) / math.log(max(1.0 - rate, 1e-9)))
            if lm.absent_streak >= needed:
                self._remove_landmark(lm.id, step, touched)

    def _remove_landmark(self, lid: int, step: MapperStep, touched: dict[int, list[View]]) -> None:
        self.map.remove(lid)
        self._dirty.discard(lid)
        step.removed.append(lid)
        touched.pop(lid, None)
        for cand in self._cands.values():
            if cand.landmark_id == lid:  # a still running tracklet of it starts over as a new candidate
                cand.landmark_id = None

    # ---- observations for the backend

    def _observation(self, lm: LandmarkState, frame_id: int, stamp: float) -> Observation | None:
        p = self.params
        if (
            stamp - lm.last_obs_sent < p.observation_period_s
            or stamp - lm.first_seen < p.observation_min_age_s
        ):
            return None
        if sum(v.inlier for v in lm.views) < p.observation_min_views:
            return None
        view = None
        for v in lm.views:
            if v.frame_id == frame_id and v.inlier:
                view = v
        if view is None:
            return None
        point = self._measure_centre(lm, view) if p.observation_register else None
        if point is None:
            point = view.centroid
        depth = float(np.linalg.norm(point))
        sigma = math.hypot(
            p.obs_sigma_base_m + p.obs_sigma_depth_factor * depth, p.obs_sigma_size_factor * lm.size
        )
        if view.truncated:
            sigma *= p.obs_truncated_sigma_factor
        lm.last_obs_sent = stamp
        return Observation(
            lm.id, lm.class_name, (float(point[0]), float(point[1]), float(point[2])), sigma, float(lm.size)
        )

    def _measure_centre(self, lm: LandmarkState, view: View) -> np.ndarray | None:
        """The landmark centre in the view's camera frame, through a translation-only alignment of the view's
        points to the landmark cloud (trimmed ICP, 4 iterations); None when the alignment is not credible."""
        if len(lm.cloud) < 10:
            return None
        pts = view.world_points()
        tree = lm.tree()
        shift = np.zeros(3)
        keep = max(3, int(len(pts) * 0.7))
        residual = float("inf")
        for _ in range(4):
            d, idx = tree.query(pts + shift, k=1)
            order = np.argsort(d, kind="stable")[:keep]
            shift = shift + np.mean(lm.cloud[idx[order]] - (pts[order] + shift), axis=0)
            residual = trimmed_mean(d, 0.3)
        limit = max(2 * self.params.voxel_m, 0.1 * lm.size)
        if residual > limit or np.linalg.norm(shift) > 0.1 + 0.5 * lm.size:
            return None
        return inverse_transform(view.pose, lm.centroid - shift)

    # ---- a prior map (services/associator/prior_map.py)

    def adopt_landmarks(self, landmarks: list[LandmarkState]) -> None:
        """Landmarks of a prior map join this map under their own ids (the session's ids start after them)."""
        for lm in landmarks:
            self.map.insert(lm)

    def fuse(self, keep_id: int, gone_id: int, step: MapperStep) -> None:
        """One object twice (a session landmark and the prior landmark the relocalisation matched it to): fuse
        them into `keep_id`, as a merge."""
        keep, gone = self.map[keep_id], self.map[gone_id]
        self._absorb(keep, gone)
        self._recompute([keep], keep.last_seen)
        step.merges.append((gone_id, keep_id))
        step.removed.append(gone_id)
        step.updated = [m for m in step.updated if m.id not in (gone_id, keep_id)] + [keep.to_message()]

    # ---- persistence

    def to_state(self) -> dict[str, Any]:
        """Plain data (lists, numbers, bytes): the whole mapper, for SQLite / msgpack."""
        return {
            "version": STATE_VERSION,
            "map": self.map.to_state(),
            "rejected": sorted(self._rejected),
            "dirty": sorted(self._dirty),
            "candidates": [
                {
                    "track_id": c.track_id,
                    "class": c.class_name,
                    "views": [view_to_state(v) for v in c.views],
                    "frames": sorted(c.frames),
                    "landmark_id": c.landmark_id,
                    "held": c.held,
                    "since_validation": c.since_validation,
                    "skipped": c.skipped,
                    "pending": [m.to_dict() for m in c.pending],
                    "path": [[f, t, *(float(x) for x in w), bool(tr)] for f, (t, w, tr) in c.path.items()],
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
        for d in state["candidates"]:
            c = _Candidate(
                int(d["track_id"]),
                str(d["class"]),
                [view_from_state(v) for v in d["views"]],
                {int(f) for f in d["frames"]},
                [Measurement.from_dict(m) for m in d["pending"]],
                None if d["landmark_id"] is None else int(d["landmark_id"]),
                bool(d["held"]),
                int(d["since_validation"]),
                int(d["skipped"]),
                {int(e[0]): (float(e[1]), np.array(e[2:5], dtype=np.float64), bool(e[5])) for e in d.get("path", [])},
            )
            mapper._cands[c.track_id] = c
        return mapper
