"""The mapper's first stage, `proposal`: a candidate's measurements become views, and the candidate is validated.

A candidate is one tracklet (track id) the tracker proposed. Its measurements wait for their frame's pose (at
most `pose_wait_s`), are thinned in time (`min_view_interval_s`: 30 Hz frames are nearly the same view) and
back-projected into views (candidate.py); validation (candidate.py's tests over the recent window, then the
whole-track motion test) decides whether it may become or keep feeding a landmark.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np

from semmap.core.messages import Intrinsics, Measurement
from semmap.core.stamps import below, within

from .backproject import BackprojectParams
from .candidate import (
    PoseLookup,
    View,
    choose_surfaces,
    make_view,
    medoid,
    track_motion,
    validate,
)
from .landmark_map import LandmarkState
from .params import MapperParams

MOVING = ("motion", "track_motion")  # validation failures that mean the object moves (not just scatter)


@dataclass
class Candidate:
    track_id: int
    class_name: str
    views: list[View] = field(default_factory=list)
    frames: set[int] = field(default_factory=set)
    pending: list[Measurement] = field(default_factory=list)  # measurements whose pose is not known yet
    landmark_id: int | None = None
    held: bool = False
    since_validation: int = 0  # views added since the last validation
    skipped: int = 0  # measurements counted but not back-projected (min_view_interval_s)
    # the whole track's views as (stamp, world centroid, truncated, occluded) by frame id, for `track_motion` (views are
    # trimmed to the validation window; this is not)
    path: dict[int, tuple[float, np.ndarray, bool, bool]] = field(default_factory=dict)


def resolve_pending(
    cand: Candidate,
    stamp: float,
    pose: PoseLookup,
    lm: LandmarkState | None,
    bp: BackprojectParams,
    params: MapperParams,
    view_interval_s: float | None = None,
) -> tuple[list[View], Intrinsics | None]:
    """Turn pending measurements whose pose is known into views; drop those that waited too long. `lm` is the
    landmark the candidate feeds (its frames grow); view_interval_s: how close to a kept view a measurement is
    skipped (default `min_view_interval_s`; the mapper lowers it for a sparse detection cadence). Returns the
    new views and the camera of the latest measurement looked at (None when there was none)."""
    new_views: list[View] = []
    still: list[Measurement] = []
    intrinsics: Intrinsics | None = None
    expected = (lm.centroid, lm.size) if lm is not None and lm.size > 0 else None
    interval = params.min_view_interval_s if view_interval_s is None else view_interval_s
    kept = sorted(v.stamp for v in cand.views)
    for m in sorted(cand.pending, key=lambda m: (m.stamp, m.frame_id)):
        intrinsics = m.intrinsics
        cand.frames.add(m.frame_id)
        if lm is not None:
            lm.frames.add(m.frame_id)
        i = bisect.bisect_left(kept, m.stamp)
        gap = min(abs(m.stamp - kept[j]) for j in (i - 1, i) if 0 <= j < len(kept)) if kept else math.inf
        if below(gap, interval):
            cand.skipped += 1  # 30 Hz frames are nearly the same view: count it, do not back-project it
            continue
        T = pose(m.frame_id)
        if T is None:
            if within(stamp - m.stamp, params.pose_wait_s):
                still.append(m)
            continue
        v = make_view(m, T, cand.track_id, bp, params, expected)
        if v is not None:
            new_views.append(v)
            cand.path[v.frame_id] = (v.stamp, v.world.copy(), v.truncated, v.occluded)
            bisect.insort(kept, m.stamp)
    cand.pending = still
    cand.views.extend(new_views)
    late = new_views and len(cand.views) > len(new_views)
    if late and new_views[0].stamp < cand.views[-len(new_views) - 1].stamp:
        cand.views.sort(key=lambda v: (v.stamp, v.frame_id))  # late poses: keep views in time order
    window = max(params.validation_window, params.hold_max_views)
    if len(cand.views) > window:  # only recent views matter for validation; landmarks keep their own
        del cand.views[: len(cand.views) - window]
    return new_views, intrinsics


def validate_candidate(cand: Candidate, p: MapperParams) -> str:
    """Validation ('' = passed, else the reason); before association, first the multi-view choice of each
    view's surface (the background in a walking person's box walks along with them, so consensus cannot
    hide motion)."""
    cand.since_validation = 0
    if cand.landmark_id is None:
        choose_surfaces(cand.views[-p.validation_window :], p)
    return failure_reason(cand, p)


def failure_reason(cand: Candidate, p: MapperParams) -> str:
    """Why the candidate fails: the recent-window tests' reason, else the whole-track motion test's. A
    candidate feeding a landmark does not trust occluded views for motion (`View.shows_motion`)."""
    v = validate(cand.views, p, trust_occluded=cand.landmark_id is None)
    if not v.ok:
        return v.reason
    moving, _ = whole_track_motion(cand, p)
    return "track_motion" if moving else ""


def whole_track_motion(cand: Candidate, p: MapperParams, whole_only: bool = True) -> tuple[bool, float]:
    """`track_motion` over the candidate's whole track (the views still held as they are placed now)."""
    trust_occluded = cand.landmark_id is None
    for view in cand.views:
        cand.path[view.frame_id] = (view.stamp, view.world, view.truncated, view.occluded)
    entries = list(cand.path.values())
    size = float(np.percentile([x.size for x in cand.views], 80))
    return track_motion(
        np.array([e[0] for e in entries]),
        np.stack([e[1] for e in entries]),
        np.array([e[2] or (e[3] and not trust_occluded) for e in entries], dtype=bool),
        size,
        p,
        whole_only,
    )


def where_it_went(cand: Candidate, lm: LandmarkState, p: MapperParams) -> float:
    """How far a track's last views (the medoid of its last `track_motion_bin_views`) stand from its landmark's
    centroid (m)."""
    last = np.stack([v.world for v in cand.views[-p.track_motion_bin_views :]])
    return float(np.linalg.norm(medoid(last) - lm.centroid))


def left_its_landmark(went_m: float, lm: LandmarkState) -> bool:
    """Has a track that failed as moving taken its object out of its landmark? Its last views stand `went_m`
    (`where_it_went`) beyond the landmark's radius from its centroid. Why ask: a track whose box hops between
    neighbouring chairs of a row (the IOU tracker follows overlapping boxes of one class) or slides over a large
    object's surfaces "moves" a metre while every object it saw stands still; the landmark then still holds what it
    was built on, and only the track is dropped. An object carried away ends outside."""
    return went_m > lm.radius


def motion_evidence(cand: Candidate, reason: str, lm: LandmarkState, went_m: float, p: MapperParams) -> str:
    """Why a track failed as moving, in words for the log: which track, how it moved (the test's reason,
    displacement and speed), and where its last views stand from its landmark (`went_m`). A user who sees a static
    object retired, or a landmark kept, can tell a real move from a track that switched objects. (Only for a track
    that fed a landmark: the test is run again here, off the per-frame path.)"""
    views = cand.views
    if reason == "motion":
        v = validate(views, p, trust_occluded=False)
        how = f"moved {v.displacement_m:.2f} m at {v.speed_mps:.2f} m/s over the last {p.motion_window_s:g} s"
    else:
        _, displacement = whole_track_motion(cand, p)
        how = f"its track's time bins lie {displacement:.2f} m apart"
    span = views[-1].stamp - views[0].stamp
    return (f"track {cand.track_id} ({cand.class_name}, {len(views)} views over {span:.1f} s) {how}; its last views "
            f"{went_m:.2f} m from the landmark's centre (radius {lm.radius:.2f} m, {lm.measurements} measurements)")


def short_but_static(cand: Candidate, p: MapperParams) -> bool:
    """A tracklet that ended before `min_track_span_s`: kept only if its views are tightly together
    (less time to show motion, so stronger evidence of standing still: a clock seen for 0.7 s at the
    image border yes, a person crossing the view no)."""
    if (
        len(cand.views) < max(p.min_views, p.min_views_spread)
        or below(cand.views[-1].stamp - cand.views[0].stamp, p.min_motion_span_s)
    ):
        return False
    if validate_candidate(cand, p) or whole_track_motion(cand, p, whole_only=False)[1] > p.short_track_motion_m:
        return False
    v = validate(cand.views, p)
    size = min(float(np.percentile([x.size for x in cand.views], 80)), p.track_motion_size_cap_m)
    return v.spread_m <= max(p.mad_min_m, p.short_track_mad_factor * size)
