"""Backend observations (the end of the mapper's `update_merge` stage): at most one per landmark every
`observation_period_s`, from an inlier view of the frame being processed (see mapper.py's module docstring)."""

from __future__ import annotations

import math

import numpy as np

from semmap.core.messages import Observation
from semmap.core.stamps import below

from .association import trimmed_mean
from .candidate import View
from .geometry import inverse_transform
from .landmark_map import LandmarkState
from .params import MapperParams


def observation(lm: LandmarkState, frame_id: int, stamp: float, p: MapperParams) -> Observation | None:
    """The landmark's observation from this frame, if one is due (it then counts as sent)."""
    if below(stamp - lm.last_obs_sent, p.observation_period_s) or below(stamp - lm.first_seen, p.observation_min_age_s):
        return None
    if sum(v.inlier for v in lm.views) < p.observation_min_views:
        return None
    view = None
    for v in lm.views:
        if v.frame_id == frame_id and v.inlier:
            view = v
    if view is None:
        return None
    point = measure_centre(lm, view, p) if p.observation_register else None
    cloud = inverse_transform(view.pose, lm.cloud)  # the landmark's fused cloud in this camera's frame
    points = view.points if point is None else cloud  # what the centre comes from
    if point is None:
        point = view.centroid
    unseen = depth_unseen(points, cloud, point, p.extent_percentile)
    depth = float(np.linalg.norm(point))
    sigma = math.hypot(p.obs_sigma_base_m + p.obs_sigma_depth_factor * depth, p.obs_sigma_size_factor * lm.size)
    if view.truncated:
        sigma *= p.obs_truncated_sigma_factor
    lm.last_obs_sent = stamp
    return Observation(lm.id, lm.class_name, (float(point[0]), float(point[1]), float(point[2])), sigma,
                       float(lm.size), unseen)


def extent_along_across(points_camera: np.ndarray, centre: np.ndarray, q: float) -> tuple[float, float]:
    """How deep along the ray to `centre` the points lie, and how wide across it, horizontally (camera frame, y
    down): each the spread between the q and 100-q percentiles, scaled as `robust_box` scales an extent (a
    uniformly covered length L reports L)."""
    norm = float(np.linalg.norm(centre))
    if len(points_camera) < 2 or norm <= 0.0:
        return 0.0, 0.0
    ray = np.asarray(centre, float) / norm
    across = np.cross(np.array([0.0, 1.0, 0.0]), ray)  # horizontal, perpendicular to the ray
    across_norm = float(np.linalg.norm(across))
    pts = np.asarray(points_camera, float)
    scale = 1.0 - 2.0 * q / 100.0
    lo, hi = np.percentile(pts @ ray, (q, 100.0 - q))
    depth = float(hi - lo) / scale
    if across_norm < 1e-6:  # looking straight up or down: no horizontal direction across the ray
        return depth, 0.0
    lo, hi = np.percentile(pts @ (across / across_norm), (q, 100.0 - q))
    return depth, float(hi - lo) / scale


def depth_unseen(points: np.ndarray, cloud: np.ndarray, centre: np.ndarray, q: float) -> float:
    """How much of the object's depth along the ray the view may not have seen (metres; camera frame), bounded by
    the object's footprint: its largest horizontal extent, along or across the ray, in the view's points and in
    the landmark's fused cloud. A view cannot tell how deep an object is behind what it shows, so the bound is the
    whole footprint: a parked car 4.5 m, a chair 0.6-0.8 m. (Less what the view shows of it was tried and was not
    enough: cars along a street are mostly seen at a slant, whose visible side spans metres of depth while their
    centre is still behind it; docs/RESULTS.md.)"""
    depth, width = extent_along_across(points, centre, q)
    along, across = extent_along_across(cloud, centre, q) if len(cloud) >= 4 else (0.0, 0.0)
    return max(depth, width, along, across)


def measure_centre(lm: LandmarkState, view: View, p: MapperParams) -> np.ndarray | None:
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
    limit = max(2 * p.voxel_m, 0.1 * lm.size)
    if residual > limit or np.linalg.norm(shift) > 0.1 + 0.5 * lm.size:
        return None
    return inverse_transform(view.pose, lm.centroid - shift)
