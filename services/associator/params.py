"""Every threshold of the landmark mapping, in one dataclass: the field names are the YAML `associator:` keys.

Units are in the names (_m metres, _s seconds, _mps metres per second); bare factors are dimensionless and
multiply an object size s (the diagonal of the object's robust extent) unless the comment says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any


@dataclass
class MapperParams:
    """Settings of `LandmarkMapper` (paper values marked; the rest measured on the synthetic scene)."""

    # --- back-projection of a detection's depth patch (see backproject.py)
    depth_min_m: float = 0.2  # paper
    depth_max_m: float = 25.0  # paper
    band_factor: float = 0.6  # depth band half-width / metric box size
    band_min_m: float = 0.06
    band_max_m: float = 1.5
    gap_m: float = 0.04  # a depth gap wider than gap_m + gap_rel * depth separates surfaces
    gap_rel: float = 0.02
    view_points_max: int = 500  # foreground points per measurement used for its centroid
    stored_points_max: int = 96  # of which this many are kept per stored view (re-projection, clouds)
    min_view_interval_s: float = 0.1  # a track's measurements closer than this to its last view are counted,
    # not back-projected (30 Hz frames are nearly the same view)
    border_margin_px: float = 4.0  # a box this close to the image border saw only part of its object

    # --- candidate validation (dynamic / unstable objects)
    min_views: int = 3  # usable measurements before a candidate is judged at all
    min_track_span_s: float = 1.0  # a new candidate's views must span this long (and hold `motion_min_views`
    # whole views) before it becomes a landmark: motion needs time to show (a person crossing the view for
    # 0.5 s, or walking along the image border, must not become a landmark)
    untestable_span_s: float = 2.0  # without enough whole views (a table always cut by the image border),
    # a candidate must be stable for this long instead
    short_track_mad_factor: float = 0.1  # a tracklet ending younger than that needs MAD <= max(min, this x s)
    # (s capped at track_motion_size_cap_m) and its whole-track displacement (see track_motion_*) at most:
    short_track_motion_m: float = 0.25
    mad_min_m: float = 0.05  # trimmed mean absolute deviation of per-view centroids above
    mad_size_factor: float = 0.5  # max(mad_min_m, mad_size_factor * s_view) rejects the candidate
    mad_trim: float = 0.3  # share of the largest deviations left out (wrong-surface views)
    min_consistent_fraction: float = 0.5  # views whose centroid agrees with the median one, at least
    min_views_spread: int = 6  # the spread tests reject only with at least this many views
    max_speed_mps: float = 0.3  # centroid speed (first third -> last third of the views) above this ...
    min_motion_m: float = 0.2  # ... over more than max(min_motion_m, motion_size_factor * s_view) ...
    motion_size_factor: float = 0.4
    min_motion_span_s: float = 0.4  # ... seen for at least this long, moving steadily, rejects it
    motion_window_s: float = 1.5  # the motion test looks at this much of the most recent time
    motion_min_views: int = 9  # ... and needs this many views in it (three segments of three)
    surface_tol_size_factor: float = 0.5  # a box surface within max(inlier_min_m, this x s) is the object
    # (also the sigma of the multi-view surface consensus)
    # whole-track motion: the camera often follows a walking person, so the box keeps a high IOU and the
    # tracklet lives for seconds; its views' world centroids (all of them, before and after it became a
    # candidate) are binned by time and the track is moving once two bins' median centroids are further apart
    # than max(track_motion_min_m, track_motion_size_factor * min(s, track_motion_size_cap_m)): capped, so a
    # person's slack does not grow with its size (the MAD limit 0.5 x s would allow 0.9 m). 1 m, not 0.5 m: under
    # drifting odometry a static object's world centroid slides with the drift over a long track (the synthetic
    # room under `gt+drift` lost 2 of 17 objects at 0.5 m); people and animals are kept out by `dynamic_classes`
    track_motion_min_m: float = 1.0
    track_motion_size_factor: float = 0.5
    track_motion_size_cap_m: float = 1.0
    track_motion_bin_s: float = 0.5  # time bins of the whole-track test ...
    track_motion_bin_views: int = 3  # ... that count only with this many whole views
    # classes that move by nature (COCO: person and the animals): tracked and published as dynamic objects
    # (semmap/v1/<robot>/dynamic), never mapped; every other class is decided by geometry (parked cars map)
    dynamic_classes: tuple[str, ...] = ("person", "bird", "cat", "dog", "horse", "sheep", "cow", "elephant", "bear",
                                        "zebra", "giraffe")
    validation_window: int = 60  # most recent views a candidate keeps for validation
    validate_every: int = 3  # a candidate feeding a landmark is re-validated after this many new views

    # --- MAP centroid (seeded random-walk Metropolis over a robust Gaussian measurement model)
    sigma_base_m: float = 0.02  # per-view centroid sigma = base + depth_factor * depth + size_factor * s
    sigma_depth_factor: float = 0.01
    sigma_size_factor: float = 0.15
    outlier_floor: float = 0.011  # likelihood floor (= a Gaussian at 3 sigma): wrong-surface views
    mc_chains: int = 16
    mc_steps: int = 16
    mc_polish_steps: int = 3  # fixed-point steps from the best sample to the exact mode
    seed: int = 0

    # --- landmarks
    voxel_m: float = 0.03  # world cloud voxel size
    cloud_max_points: int = 3000
    max_views: int = 40  # stored per landmark; the most redundant viewpoint goes first
    inlier_sigmas: float = 3.0  # a view whose centroid is further than this many sigmas from the MAP ...
    inlier_min_m: float = 0.1  # ... and further than this is left out of the landmark's cloud
    fused_min_views: int = 3  # inlier views before the centroid comes from the fused cloud's robust box
    extent_percentile: float = 5.0  # robust extent: the 5-95 percentile box
    full_refresh_s: float = 1.0  # full re-estimate of a fed landmark at least this often ...
    full_growth: float = 0.25  # ... or once its views grew by this share ...
    full_min_new_views: int = 3  # ... but not before this many new views

    # --- association (paper: gate r = sqrt(dt / u * s))
    gate_u: float = 10.0  # paper
    gate_min_m: float = 0.1  # gate floor: max(gate_min_m, gate_size_factor * s) (r -> 0 when dt -> 0)
    gate_size_factor: float = 0.5
    clear_match_fraction: float = 0.5  # one landmark closer than this share of the floor: no cloud check
    nn_accept_min_m: float = 0.05  # mean NN distance cloud-to-cloud accepted: max(min, factor * s, ...)
    nn_accept_size_factor: float = 0.15
    nn_trim: float = 0.2  # share of the largest NN distances left out of the mean
    ambiguity_ratio: float = 0.7  # best NN / second NN above this: ambiguous, hold the candidate back
    hold_max_views: int = 15  # views after which a held candidate is decided anyway
    covis_veto_frames: int = 2  # landmark seen in this many of the candidate's frames: a different object

    # --- merging
    merge_tol_min_m: float = 0.04  # a point overlaps the other cloud within max(min, factor * s_small)
    merge_tol_size_factor: float = 0.1
    merge_overlap_min: float = 0.5  # overlapping share of the smaller cloud that merges two landmarks
    merge_overlap_contained: float = 0.85  # ... that merges them even when they were seen side by side
    class_merge: bool = True  # one object whose detected class flips between views becomes one landmark ...
    # ... when the classes are confusable (groups ';'-separated, classes '|'-separated), the centroids lie within
    # the gate floor of the smaller and the clouds overlap by merge_overlap_min; the class is the majority vote
    confusable_classes: str = (
        "laptop|tv|microwave|keyboard|oven;cup|bowl|vase|wine glass|bottle;chair|couch|bench;book|cell phone|remote"
    )

    # --- negative evidence (opt-in; needs the tracker's boxes of detected frames; see mapper._absence)
    absence_removal: bool = False
    absence_p: float = (
        1e-4  # a miss streak this improbable under the landmark's own detection rate removes it
    )
    absence_min_frames: int = 8  # ... and never fewer detected frames in a row
    absence_margin: float = 0.1  # in view: projects inside the image with this share of it kept clear
    absence_min_depth_m: float = 0.5
    absence_max_depth_m: float = 4.0  # beyond this, small objects are missed by detectors anyway
    absence_min_px: float = 12.0  # ... and so are objects whose sphere's radius is under this many pixels

    # --- observations for the backend
    observation_period_s: float = 1.0  # at most one observation per landmark every this many seconds. The
    # paper's 2 s (set 2.0 to reproduce it) leaves a 33 s 7-Scenes pass ~50 observations: one wrong chair
    # association then decides the result (optimised ATE worse than the odometry's on 2 of 10 drift seeds);
    # 1 s: 45-78 % lower than the odometry on all 10, weak drift 31-68 % lower; 0.5 s: about the same
    # for strong drift, a little worse for weak drift (correlated views), at twice the backend load
    observation_min_age_s: float = 1.0  # a landmark this young (moving things are rejected by then) is quiet
    observation_min_views: int = 5
    observation_register: bool = False  # measure the landmark centre through an alignment of the view to the
    # landmark cloud instead of the view's own centre. Off: the translation-only ICP barely moves from where
    # the current pose estimate puts the view, so the "measurement" echoes the prediction. With ground-truth
    # poses that looks precise (7-Scenes: 1.4 cm median scatter vs 5.3 cm for view centres), but under drift
    # it hides the pose error from the backend (10 cm median error vs 5.2 cm; optimised ATE 0.13 m instead of
    # 0.07 m, worse than the odometry's 0.12 m, seed 0, observations every 0.1 s)
    obs_sigma_base_m: float = 0.02  # observation sigma = hypot(base + depth_factor * depth, size_factor * s)
    obs_sigma_depth_factor: float = 0.01
    obs_sigma_size_factor: float = 0.05
    obs_truncated_sigma_factor: float = 3.0  # ... times this for a view whose box touches the image border
    # (its centre slides with what is in view: 7-Scenes, 9-12 cm median error vs 3-5 cm for whole views)
    pose_wait_s: float = 5.0  # a measurement whose frame has no pose yet waits this long, then is dropped

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> MapperParams:
        """Build from a YAML section; unknown keys are an error (a typo must not silently do nothing)."""
        d = dict(d or {})
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise ValueError(f"associator: unknown settings {unknown}; known: {sorted(known)}")
        values: dict[str, Any] = {}
        for key, raw in d.items():
            default = getattr(cls, key)
            if isinstance(default, tuple):
                items = raw.split(",") if isinstance(raw, str) else raw
                if not isinstance(items, list | tuple) or not all(isinstance(x, str) for x in items):
                    raise ValueError(f"associator.{key} must be a list of names, got {raw!r}")
                values[key] = tuple(x.strip() for x in items if x.strip())
            elif isinstance(default, bool):
                values[key] = (
                    raw if isinstance(raw, bool) else str(raw).strip().lower() in ("1", "true", "yes", "on")
                )
            elif isinstance(default, int):
                values[key] = int(raw)
            elif isinstance(default, str):
                values[key] = str(raw)
            else:
                values[key] = float(raw)
        return cls(**values)
