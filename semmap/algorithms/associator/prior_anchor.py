"""Where a prior landmark stands, and what it is, in a session that relocalised against its map (pure).

A prior map's landmark joins a relocalised session with its stored views frozen in the prior frame, and the
session's own views of it are placed by the session's poses. Where both kinds of view feed one fused cloud,
whose robust box gives the centre, on 7-Scenes (frames 0-499, then 500-999 in a frame moved by a few metres and
up to 40 degrees) a table, a book and the wall screen move 10-14 cm from their session-1 places although nothing
has moved. Two causes add up: the centre of a partly seen object moves with the viewpoint
(the second session's views alone put the table 40-43 cm, the screen 19-23 cm, a book 16-18 cm from the first
session's centres, from the other side of the room), and the second session's views carry its registration error
(1-2 degrees, a few cm). A landmark keeps a bounded number of views, the newest winning, so the first session's
views would also be thinned out.

So a prior landmark holds its prior place as a prior (`PriorAnchor`), and the session's evidence moves it only
as far as that evidence is worth:

- the prior place is known to `sigma_m` (the prior map's anchor sigma, `associator.prior_anchor_sigma_m`, the
  same the backend holds prior landmarks with);
- the session's own estimate (its views alone, those that agree with their median, fused and boxed as the prior
  centre was made: `session_estimate`) is known to `hypot(registration, viewpoint)`: registration = the
  relocalisation's residual and its rotation uncertainty at the landmark's distance from the fit's landmarks, at
  least `registration_sigma_m` (`associator.prior_registration_sigma_m`); viewpoint = the mapper's
  `sigma_size_factor` times the object's size (how far a partial view's centre strays with the viewpoint).
  Neither shrinks with the session's view count: both are shared by all its views (they all stand on the
  session's side);
- the two are fused precision-weighted; but when the session's estimate lies more than `moved_sigmas` of their
  combined sigma from the prior place, from at least `moved_min_views` of its views, the evidence says the object
  moved and the landmark takes the session's place, cloud and extent (and may change class, below).

Class: a detector's class for one object depends on the viewpoint (the 7-Scenes microwave is boxed as a laptop
from most of the second session's places), so a majority over both sessions' boxes measures where the second session
stood rather than what the object is: it turns the microwave into a laptop and the class is gone from the
map. A prior landmark in its place keeps its prior class (the votes still grow, so boxes of the other classes
keep joining it); one the evidence says moved is elected by its votes like any landmark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .candidate import inlier_limit, view_sigmas, world_centroids
from .geometry import fast_median, robust_box, voxel_downsample
from .params import MapperParams

if TYPE_CHECKING:
    from .landmark_map import LandmarkState


@dataclass
class PriorAnchor:
    """A prior landmark's place and class in the prior map, and how much this session's views may move it."""

    centroid: np.ndarray  # (3,) its place in the prior map (the prior frame)
    class_name: str  # its class there
    sigma_m: float  # how well the prior map knows that place
    registration_sigma_m: float  # how well the session's views are placed in the prior frame, at this landmark
    moved_sigmas: float = 3.0  # the session's estimate this many combined sigmas away: the object moved
    moved_min_views: int = 5  # ... from at least this many of the session's views
    moved: bool = False  # the session's evidence says it moved: it follows the session (derived, per update)
    session_offset_m: float = 0.0  # |session's estimate - prior place| at the last update (diagnostics)

    def to_state(self) -> dict[str, Any]:
        return {
            "centroid": [float(x) for x in self.centroid],
            "class": self.class_name,
            "sigma_m": self.sigma_m,
            "registration_sigma_m": self.registration_sigma_m,
            "moved_sigmas": self.moved_sigmas,
            "moved_min_views": self.moved_min_views,
            "moved": self.moved,
            "session_offset_m": self.session_offset_m,
        }

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> PriorAnchor:
        return cls(
            np.array(d["centroid"], dtype=np.float64),
            str(d["class"]),
            float(d["sigma_m"]),
            float(d["registration_sigma_m"]),
            float(d["moved_sigmas"]),
            int(d["moved_min_views"]),
            bool(d["moved"]),
            float(d.get("session_offset_m", 0.0)),
        )


def registration_sigma(
    centroid: np.ndarray, fit_centre: np.ndarray, residual_m: float, rotation_sigma_deg: float, floor_m: float
) -> float:
    """How far the session's poses may put a view of this landmark from where it is: the fit's residual and its
    rotation uncertainty times the landmark's distance from the fit's landmarks (the lever arm), at least
    `floor_m` (the fit's own sigma is optimistic: on 7-Scenes 0.3-0.7 degrees, against 1.2-3.4 off the truth)."""
    lever = float(np.linalg.norm(np.asarray(centroid) - np.asarray(fit_centre)))
    return max(floor_m, math.hypot(residual_m, math.radians(rotation_sigma_deg) * lever))


@dataclass
class AnchoredPlace:
    """Where a prior landmark stands after an update: its centre, whether it moved, and this session's own cloud
    of it (None without enough of this session's views)."""

    centroid: np.ndarray
    moved: bool
    cloud: np.ndarray | None = None


def session_estimate(lm: LandmarkState, p: MapperParams) -> tuple[np.ndarray, np.ndarray, int] | None:
    """(centre, cloud, views) from this session's views alone: those whose centre agrees with their median (as a
    landmark's inlier views agree with its MAP centre), fused and boxed as a landmark's centre is made; None with
    fewer than `fused_min_views`. Not the landmark's inlier flags: they are judged against a centre of both
    sessions' views, which for an object that moved is its old place. This session's views are those with
    non-negative frame ids: a prior map's views are frozen to negative ones (prior_map.py)."""
    views = [v for v in lm.views if v.frame_id >= 0 and len(v.points)]
    if len(views) < p.fused_min_views:
        return None
    centres = world_centroids(views)
    size = lm.size if lm.size > 0 else float(np.percentile([v.size for v in views], 80))
    near = np.linalg.norm(centres - fast_median(centres), axis=1) <= inlier_limit(
        views, view_sigmas(views, size, p), size, p
    )
    views = [v for v, ok in zip(views, near, strict=True) if ok]
    if len(views) < p.fused_min_views:
        return None
    cloud = voxel_downsample(np.concatenate([v.world_points() for v in views]), p.voxel_m, p.cloud_max_points)
    if len(cloud) < 4:
        return None
    return robust_box(cloud, p.extent_percentile)[0], cloud, len(views)


def held_place(
    prior: np.ndarray,
    prior_sigma: float,
    estimate: np.ndarray,
    estimate_sigma: float,
    moved_sigmas: float,
    may_move: bool = True,
) -> tuple[np.ndarray, bool]:
    """(the place, whether it moved): a prior place and a later estimate of it fused by their sigmas, or the
    estimate alone once it lies more than `moved_sigmas` of their combined sigma away (and `may_move`: evidence
    enough to say so). Shared by the relocalised session (`anchored_place`) and `semmap merge`, so that a map
    merged from two sessions places a landmark where the second session relocalised against the first does."""
    prior, estimate = np.asarray(prior, dtype=np.float64), np.asarray(estimate, dtype=np.float64)
    combined = math.hypot(prior_sigma, estimate_sigma)
    offset = estimate - prior
    if may_move and float(np.linalg.norm(offset)) > moved_sigmas * combined:
        return estimate.copy(), True
    return prior + prior_sigma**2 / combined**2 * offset, False  # the estimate's share: its precision's


def estimate_sigma(registration_sigma_m: float, size: float, p: MapperParams) -> float:
    """How far a later session's estimate of a landmark's centre may lie from the prior place of an object that
    stood still: its registration, and a partial view's centre moving with the viewpoint (the mapper's per-view
    `sigma_size_factor` times the size; not averaged down by more views: they all stand on that session's side)."""
    return math.hypot(registration_sigma_m, p.sigma_size_factor * size)


def anchored_place(lm: LandmarkState, anchor: PriorAnchor, p: MapperParams) -> AnchoredPlace:
    """The landmark's place: its prior place and this session's estimate fused by their sigmas, or the session's
    estimate alone once it lies beyond `moved_sigmas` from enough views (module docstring)."""
    got = session_estimate(lm, p)
    if got is None:
        anchor.session_offset_m = 0.0
        return AnchoredPlace(anchor.centroid.copy(), False)
    estimate, cloud, n_views = got
    anchor.session_offset_m = float(np.linalg.norm(estimate - anchor.centroid))
    sigma = estimate_sigma(anchor.registration_sigma_m, lm.size, p)
    centre, moved = held_place(
        anchor.centroid, anchor.sigma_m, estimate, sigma, anchor.moved_sigmas, n_views >= anchor.moved_min_views
    )
    return AnchoredPlace(centre, moved, cloud)
