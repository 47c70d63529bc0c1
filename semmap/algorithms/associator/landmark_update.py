"""The mapper's last stage, `update_merge`: re-estimate touched landmarks and merge what overlaps.

A full re-estimate (batched MAP over each landmark's views, inlier views, fused voxel cloud, robust extent)
runs for new landmarks, after merges or rejections, once a quarter more views have arrived, or `full_refresh_s`
after the last one; in between, a new view is checked against the current MAP centroid and, if it agrees, its
points are voxel-merged into the cloud (cheap, same result in the limit). Same-class landmarks whose clouds
overlap merge into the older id; a co-located, overlapping landmark of a confusable class too (the class
becomes the majority vote).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .association import gate_floor
from .candidate import (
    MapProblem,
    View,
    inlier_limit,
    map_centroids,
    start_point,
    view_sigmas,
    whole_views,
    world_centroids,
)
from .geometry import robust_box, voxel_downsample
from .landmark_map import CentroidIndex, LandmarkMap, LandmarkState
from .params import MapperParams
from .prior_anchor import anchored_place


def confusable(a: LandmarkState, b: LandmarkState, groups: str) -> bool:
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


def views_cloud(views: list[View], p: MapperParams) -> np.ndarray:
    """The views' world points on the landmark voxel grid."""
    pts = np.concatenate([v.world_points() for v in views])
    return voxel_downsample(pts, p.voxel_m, p.cloud_max_points)


def set_cloud(lm: LandmarkState, cloud: np.ndarray, n_inliers: int, p: MapperParams) -> None:
    """The landmark's cloud, extent and centre from its inlier views' fused cloud; a prior map's landmark in a
    relocalised session keeps its prior place unless this session's evidence is worth more (prior_anchor.py)."""
    if len(cloud) >= 4:
        centre, extent = robust_box(cloud, p.extent_percentile)
    else:
        centre, extent = lm.map_centroid, np.full(3, float(np.median([v.size for v in lm.views])))
    lm.centroid = centre if n_inliers >= p.fused_min_views else lm.map_centroid
    lm.extent = extent
    lm.size = float(np.linalg.norm(extent))
    lm.set_cloud(cloud)
    if lm.anchor is not None:
        place = anchored_place(lm, lm.anchor, p)
        lm.centroid = place.centroid
        if place.moved and place.cloud is not None:  # it stands elsewhere now: its cloud is this session's
            lm.extent = robust_box(place.cloud, p.extent_percentile)[1]
            lm.size = float(np.linalg.norm(lm.extent))
            lm.set_cloud(place.cloud)
        lm.set_moved(place.moved)


def recompute(lms: list[LandmarkState], stamp: float, p: MapperParams, dirty: set[int]) -> None:
    """Full re-estimate: batched MAP over each landmark's views, then inliers, fused cloud, extent (each one
    leaves `dirty`)."""
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
        inl = d <= inlier_limit(lm.views, view_sigmas(lm.views, size, p), size, p)
        if not inl.any():
            inl = d <= np.median(d)
        for v, ok in zip(lm.views, inl, strict=True):
            v.inlier = bool(ok)
        lm.map_centroid = m
        set_cloud(lm, views_cloud([v for v in lm.views if v.inlier], p), int(inl.sum()), p)
        lm.views_at_full = len(lm.views)
        lm.added_since_full = 0
        lm.last_full = stamp
        dirty.discard(lm.id)


def incremental(lm: LandmarkState, new_views: list[View], p: MapperParams) -> None:
    """Cheap update with a few new views: inlier test against the MAP centroid, voxel-merge the points."""
    if not new_views:
        return
    sig = view_sigmas(new_views, lm.size, p)
    d = np.linalg.norm(world_centroids(new_views) - lm.map_centroid, axis=1)
    inl = d <= inlier_limit(new_views, sig, lm.size, p)
    added = []
    for v, ok in zip(new_views, inl, strict=True):
        v.inlier = bool(ok)
        if ok:
            added.append(v.world_points())
    if added:
        cloud = voxel_downsample(np.concatenate([lm.cloud, *added]), p.voxel_m, p.cloud_max_points)
        set_cloud(lm, cloud, sum(v.inlier for v in lm.views), p)


def overlap(a: LandmarkState, b: LandmarkState, p: MapperParams) -> float:
    """Share of one cloud lying within a tolerance of the other (the larger of the two directions)."""
    if len(a.cloud) == 0 or len(b.cloud) == 0:
        return 0.0
    tol = max(p.merge_tol_min_m, p.merge_tol_size_factor * min(a.size, b.size))
    da, _ = b.tree().query(a.cloud, k=1, distance_upper_bound=tol)
    db, _ = a.tree().query(b.cloud, k=1, distance_upper_bound=tol)
    return max(float(np.mean(np.isfinite(da))), float(np.mean(np.isfinite(db))))


def same_object_other_class(a: LandmarkState, b: LandmarkState, p: MapperParams) -> bool:
    """Two landmarks of confusable classes that are one object: the detector's class flipped between
    views (a laptop as tv or microwave; with class-wise NMS even two boxes in one frame, so co-visibility
    says nothing here). Co-located (centroids within the gate floor of the smaller) and overlapping clouds;
    two different objects side by side (a keyboard in front of a screen) do not overlap."""
    if not p.class_merge or not confusable(a, b, p.confusable_classes):
        return False
    if float(np.linalg.norm(a.centroid - b.centroid)) > gate_floor(min(a.size, b.size), p):
        return False
    return overlap(a, b, p) >= p.merge_overlap_min


def absorb(keep: LandmarkState, gone: LandmarkState, landmarks: LandmarkMap, p: MapperParams, dirty: set[int]) -> None:
    """`gone` joins `keep` (views, tracks, frames, votes, clocks) and leaves the map."""
    keep.views.extend(gone.views)
    keep.views.sort(key=lambda v: (v.stamp, v.frame_id, v.track_id))
    while keep.over_cap(p.max_views):
        keep._drop_redundant_view()
    keep.tracks.extend(t for t in gone.tracks if t not in keep.tracks)
    keep.frames |= gone.frames
    keep.measurements += gone.measurements
    keep.absorb_votes(gone.class_votes)
    keep.first_seen = min(keep.first_seen, gone.first_seen)
    keep.last_seen = max(keep.last_seen, gone.last_seen)
    keep.last_assoc = max(keep.last_assoc, gone.last_assoc)
    keep.last_obs_sent = max(keep.last_obs_sent, gone.last_obs_sent)
    landmarks.remove(gone.id)
    dirty.discard(gone.id)


def merge_pass(
    landmarks: LandmarkMap,
    ids: list[int],
    stamp: float,
    p: MapperParams,
    dirty: set[int],
    absorb_fn: Callable[[LandmarkState, LandmarkState], None],
) -> list[tuple[int, int]]:
    """Merge each listed landmark with overlapping same-class ones into the older id (repeatedly), and with
    a co-located, overlapping landmark of a confusable class (the class becomes the majority vote).
    `absorb_fn(keep, gone)` does the merge; returns the merges (absorbed id, surviving id) in order."""
    merges: list[tuple[int, int]] = []
    queue = sorted(set(ids))
    index = CentroidIndex(landmarks.all()) if queue else None
    while queue:
        a = landmarks.get(queue.pop(0))
        if a is None or index is None:
            continue
        # only landmarks whose spheres can touch a's (every pair would be quadratic in the map's size)
        for b in index.within(a.centroid, a.radius + index.max_radius):
            if b.id == a.id or float(np.linalg.norm(a.centroid - b.centroid)) > a.radius + b.radius:
                continue
            if b.class_name != a.class_name:
                if not same_object_other_class(a, b, p):
                    continue
            else:
                covis = len(a.frames & b.frames)
                if covis >= p.covis_veto_frames and p.merge_overlap_contained > 1.0:
                    continue
                share = overlap(a, b, p)
                if not (
                    (share >= p.merge_overlap_min and covis < p.covis_veto_frames) or share >= p.merge_overlap_contained
                ):
                    continue
            keep, gone = (a, b) if a.id < b.id else (b, a)
            absorb_fn(keep, gone)
            merges.append((gone.id, keep.id))
            recompute([keep], stamp, p, dirty)
            queue = sorted(set(queue) - {gone.id} | {keep.id})
            index = CentroidIndex(landmarks.all())  # keep moved, gone left
            break
    return merges
