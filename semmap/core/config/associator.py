"""The `associator:` section: every threshold of the landmark mapping (`MapperParams`, what `LandmarkMapper`
receives), the service's own settings and the prior-map settings (`prior_*`, see `PriorParams`).

Units are in the names (_m metres, _s seconds, _mps metres per second); bare factors are dimensionless and
multiply an object size s (the diagonal of the object's robust extent) unless the comment says otherwise.
"""

from __future__ import annotations

from pydantic import Field, create_model

from .base import AtLeastOne, Count, Fraction, Names, NonNegative, Positive, Probability, Section


class MapperParams(Section):
    """Settings of `LandmarkMapper` (paper values marked; the rest measured on the synthetic scene)."""

    # --- back-projection of a detection's depth patch (see backproject.py)
    depth_min_m: NonNegative = 0.2  # paper
    depth_max_m: Positive = 25.0  # paper
    band_factor: NonNegative = 0.6  # depth band half-width / metric box size
    band_min_m: NonNegative = 0.06
    band_max_m: Positive = 1.5
    gap_m: NonNegative = 0.04  # a depth gap wider than gap_m + gap_rel * depth separates surfaces
    gap_rel: NonNegative = 0.02
    view_points_max: AtLeastOne = 500  # foreground points per measurement used for its centroid
    stored_points_max: AtLeastOne = 96  # of which this many are kept per stored view (re-projection, clouds)
    min_view_interval_s: NonNegative = 0.1  # a track's measurements closer than this to its last view are counted,
    # not back-projected (30 Hz frames are nearly the same view); less half the run's detection cadence, so a
    # real-time run detecting every 2nd frame keeps every detection as lockstep keeps one per 0.1 s
    # (`LandmarkMapper.view_interval_s`)
    border_margin_px: NonNegative = 4.0  # a box this close to the image border saw only part of its object

    # --- candidate validation (dynamic / unstable objects)
    min_views: AtLeastOne = 3  # usable measurements before a candidate is judged at all
    min_track_span_s: NonNegative = 1.0  # a new candidate's views must span this long (and hold `motion_min_views`
    # whole views) before it becomes a landmark: motion needs time to show (a person crossing the view for
    # 0.5 s, or walking along the image border, must not become a landmark)
    untestable_span_s: NonNegative = 2.0  # without enough whole views (a table always cut by the image border),
    # a candidate must be stable for this long instead
    short_track_mad_factor: NonNegative = 0.1  # a tracklet ending younger than that needs MAD <= max(min, this x s)
    # (s capped at track_motion_size_cap_m) and its whole-track displacement (see track_motion_*) at most:
    short_track_motion_m: NonNegative = 0.25
    mad_min_m: NonNegative = 0.05  # trimmed mean absolute deviation of per-view centroids above
    mad_size_factor: NonNegative = 0.5  # max(mad_min_m, mad_size_factor * s_view) rejects the candidate
    mad_trim: Fraction = 0.3  # share of the largest deviations left out (wrong-surface views)
    min_consistent_fraction: Fraction = 0.5  # views whose centroid agrees with the median one, at least
    min_views_spread: AtLeastOne = 6  # the spread tests reject only with at least this many views
    max_speed_mps: NonNegative = 0.3  # centroid speed (first third -> last third of the views) above this ...
    min_motion_m: NonNegative = 0.2  # ... over more than max(min_motion_m, motion_size_factor * s_view) ...
    motion_size_factor: NonNegative = 0.4
    min_motion_span_s: NonNegative = 0.4  # ... seen for at least this long, moving steadily, rejects it
    motion_window_s: NonNegative = 1.5  # the motion test looks at this much of the most recent time
    motion_min_views: AtLeastOne = 9  # ... and needs this many views in it (three segments of three)
    surface_tol_size_factor: NonNegative = 0.5  # a box surface within max(inlier_min_m, this x s) is the object
    # (also the sigma of the multi-view surface consensus)
    # whole-track motion: the camera often follows a walking person, so the box keeps a high IOU and the
    # tracklet lives for seconds; its views' world centroids (all of them, before and after it became a
    # candidate) are binned by time and the track is moving once two bins' median centroids are further apart
    # than max(track_motion_min_m, track_motion_size_factor * min(s, track_motion_size_cap_m)): capped, so a
    # person's slack does not grow with its size (the MAD limit 0.5 x s would allow 0.9 m). 1 m, not 0.5 m: under
    # drifting odometry a static object's world centroid slides with the drift over a long track (the synthetic
    # room under `gt+drift` lost 2 of 17 objects at 0.5 m); people and animals are kept out by `dynamic_classes`
    track_motion_min_m: NonNegative = 1.0
    track_motion_size_factor: NonNegative = 0.5
    track_motion_size_cap_m: NonNegative = 1.0
    track_motion_bin_s: NonNegative = 0.5  # time bins of the whole-track test ...
    track_motion_bin_views: AtLeastOne = 3  # ... that count only with this many whole views
    # classes that move by nature (COCO: person and the animals): tracked and published as dynamic objects
    # (semmap/v1/<robot>/dynamic), never mapped; every other class is decided by geometry (parked cars map)
    dynamic_classes: Names = (
        "person",
        "bird",
        "cat",
        "dog",
        "horse",
        "sheep",
        "cow",
        "elephant",
        "bear",
        "zebra",
        "giraffe",
    )
    validation_window: AtLeastOne = 60  # most recent views a candidate keeps for validation
    validate_every: AtLeastOne = 3  # a candidate feeding a landmark is re-validated after this many new views

    # --- MAP centroid (seeded random-walk Metropolis over a robust Gaussian measurement model)
    sigma_base_m: Positive = 0.02  # per-view centroid sigma = base + depth_factor * depth + size_factor * s
    sigma_depth_factor: NonNegative = 0.01
    sigma_size_factor: NonNegative = 0.15
    outlier_floor: Fraction = 0.011  # likelihood floor (= a Gaussian at 3 sigma): wrong-surface views
    mc_chains: AtLeastOne = 16
    mc_steps: AtLeastOne = 16
    mc_polish_steps: Count = 3  # fixed-point steps from the best sample to the exact mode
    seed: int = 0

    # --- landmarks
    voxel_m: Positive = 0.03  # world cloud voxel size
    cloud_max_points: AtLeastOne = 3000
    max_views: AtLeastOne = 40  # stored per landmark; the most redundant viewpoint goes first
    inlier_sigmas: Positive = 3.0  # a view whose centroid is further than this many sigmas from the MAP ...
    inlier_min_m: NonNegative = 0.1  # ... and further than this is left out of the landmark's cloud
    fused_min_views: AtLeastOne = 3  # inlier views before the centroid comes from the fused cloud's robust box
    extent_percentile: NonNegative = 5.0  # robust extent: the 5-95 percentile box
    full_refresh_s: NonNegative = 1.0  # full re-estimate of a fed landmark at least this often ...
    full_growth: Fraction = 0.25  # ... or once its views grew by this share ...
    full_min_new_views: Count = 3  # ... but not before this many new views
    refine_tolerance_size_factor: NonNegative = 0.01  # a refine re-places a view only once its object's centre
    # moved by this x the object's size (at least refine_tolerance_min_m) from where the view put it: after a loop
    # closure iSAM2 keeps nudging every pose of the loop by millimetres, and re-estimating hundreds of street
    # landmarks for millimetres each refine made the per-frame cost grow with the map (KITTI 00: 0.3-0.6 s a refine)
    refine_tolerance_min_m: NonNegative = 0.002

    # --- association (paper: gate r = sqrt(dt / u * s))
    gate_u: Positive = 10.0  # paper
    gate_min_m: Positive = 0.1  # gate floor: max(gate_min_m, gate_size_factor * s) (r -> 0 when dt -> 0)
    gate_size_factor: NonNegative = 0.5
    clear_match_fraction: Fraction = 0.5  # one landmark closer than this share of the floor: no cloud check
    nn_accept_min_m: NonNegative = 0.05  # mean NN distance cloud-to-cloud accepted: max(min, factor * s, ...)
    nn_accept_size_factor: NonNegative = 0.15
    nn_trim: Fraction = 0.2  # share of the largest NN distances left out of the mean
    ambiguity_ratio: Fraction = 0.7  # best NN / second NN above this: ambiguous, hold the candidate back
    hold_max_views: AtLeastOne = 15  # views after which a held candidate is decided anyway
    covis_veto_frames: Count = 2  # landmark seen in this many of the candidate's frames: a different object

    # --- merging
    merge_tol_min_m: NonNegative = 0.04  # a point overlaps the other cloud within max(min, factor * s_small)
    merge_tol_size_factor: NonNegative = 0.1
    merge_overlap_min: Fraction = 0.5  # overlapping share of the smaller cloud that merges two landmarks
    merge_overlap_contained: Fraction = 0.85  # ... that merges them even when they were seen side by side
    class_merge: bool = True  # one object whose detected class flips between views becomes one landmark ...
    # ... when the classes are confusable (groups ';'-separated, classes '|'-separated), the centroids lie within
    # the gate floor of the smaller and the clouds overlap by merge_overlap_min; the class is the majority vote
    confusable_classes: str = (
        "laptop|tv|microwave|keyboard|oven;cup|bowl|vase|wine glass|bottle;chair|couch|bench;book|cell phone|remote"
    )

    # --- negative evidence (opt-in; needs the tracker's boxes of detected frames; see mapper._absence)
    absence_removal: bool = False
    absence_p: Probability = 1e-4  # a miss streak this improbable under the landmark's own detection rate removes it
    absence_min_frames: AtLeastOne = 8  # ... and never fewer detected frames in a row
    absence_margin: Fraction = 0.1  # in view: projects inside the image with this share of it kept clear
    absence_min_depth_m: NonNegative = 0.5
    absence_max_depth_m: NonNegative = 4.0  # beyond this, small objects are missed by detectors anyway
    absence_min_px: NonNegative = 12.0  # ... and so are objects whose sphere's radius is under this many pixels

    # --- observations for the backend
    observation_period_s: NonNegative = 1.0  # at most one observation per landmark every this many seconds. The
    # paper's 2 s (set 2.0 to reproduce it) leaves a 33 s 7-Scenes pass ~50 observations: one wrong chair
    # association then decides the result (optimised ATE worse than the odometry's on 2 of 10 drift seeds);
    # 1 s: 45-78 % lower than the odometry on all 10, weak drift 31-68 % lower; 0.5 s: about the same
    # for strong drift, a little worse for weak drift (correlated views), at twice the backend load
    observation_min_age_s: NonNegative = 1.0  # a landmark this young (moving things are rejected by then) is quiet
    observation_min_views: Count = 5
    observation_register: bool = False  # measure the landmark centre through an alignment of the view to the
    # landmark cloud instead of the view's own centre. Off: the translation-only ICP barely moves from where
    # the current pose estimate puts the view, so the "measurement" echoes the prediction. With ground-truth
    # poses that looks precise (7-Scenes: 1.4 cm median scatter vs 5.3 cm for view centres), but under drift
    # it hides the pose error from the backend (10 cm median error vs 5.2 cm; optimised ATE 0.13 m instead of
    # 0.07 m, worse than the odometry's 0.12 m, seed 0, observations every 0.1 s)
    obs_sigma_base_m: NonNegative = 0.02  # observation sigma = hypot(base + depth_factor * depth, size_factor * s)
    obs_sigma_depth_factor: NonNegative = 0.01
    obs_sigma_size_factor: NonNegative = 0.05
    obs_truncated_sigma_factor: NonNegative = 3.0  # ... times this for a view whose box touches the image border
    # (its centre slides with what is in view: 7-Scenes, 9-12 cm median error vs 3-5 cm for whole views)
    pose_wait_s: Positive = 5.0  # a measurement whose frame has no pose yet waits this long, then is dropped

    # --- revisits (revisit.py): a place seen again after drift beyond any gate, recognised by its objects, whose
    # recent landmarks are fused into the old ones (a loop closure through the backend's merge factor)
    revisit: bool = True
    revisit_every_s: NonNegative = 2.0  # search at most this often
    revisit_recent_s: Positive = 20.0  # the recent landmarks: first seen within this
    revisit_old_s: Positive = 60.0  # the old ones: last seen longer ago than this (a room re-associates its objects
    # through the gate all the time: they never get this old there)
    revisit_min_views: AtLeastOne = 5  # a recent landmark takes part once it has this many views
    revisit_min_inliers: AtLeastOne = 5  # objects that must agree (a row of parked cars agrees with many places)
    revisit_gate_size_factor: Positive = 0.33  # a recent landmark must land within this x the recent landmarks'
    # median size of an old one of its class, after the fit (cars: 1.5 m; a kitchen's objects: the floor below)
    revisit_gate_min_m: Positive = 0.15
    revisit_max_rotation_sigma_deg: Positive = 2.0  # the fit's rotation must be pinned this well (1 sigma)
    revisit_max_hypotheses: AtLeastOne = 20000  # placements tried per search (a street of 300 cars offers many)
    revisit_max_thirds: AtLeastOne = 4  # third landmarks tried per base pair, the furthest from its line


class PriorParams(Section):
    """Starting from a saved map (`semmap run --map`): relocalisation and the prior landmarks' status. In the
    `associator:` section each key is prefixed `prior_` (e.g. `associator.prior_anchor_sigma_m`)."""

    relocalize_every_n_frames: AtLeastOne = 5
    relocalize_min_views: AtLeastOne = 5  # a session landmark takes part once it has this many views
    relocalize_min_inliers: AtLeastOne = 4  # semmap/algorithms/relocalize.py RelocParams.min_inliers
    relocalize_max_rotation_sigma_deg: Positive = 1.5  # RelocParams.max_rotation_sigma_deg
    anchor_sigma_m: Positive = 0.03  # how firmly the backend and the associator (prior_anchor.py) hold a prior landmark
    # a relocalised session's views of a prior landmark move it only as far as they are worth: their registration
    # (the fit's residual and rotation uncertainty at the landmark, at least this: on 7-Scenes the fit's own sigma
    # said 0.3-0.7 degrees, the truth was 1.7-1.8 off) and the object's size (a partial view's centre moves with
    # the viewpoint); the session's estimate this many combined sigmas away, from enough views: the object moved
    registration_sigma_m: Positive = 0.05
    moved_sigmas: Positive = 3.0
    moved_min_views: AtLeastOne = 5
    missing_after_frames: AtLeastOne = 10  # at least; more for a class the detector often misses (below)
    missing_miss_probability: Fraction = 0.01  # how unlikely the run of misses must be for an object still there
    missing_min_depth_m: NonNegative = 0.5
    missing_max_depth_m: Positive = 4.0
    missing_margin: Fraction = 0.1  # share of the image width / height kept clear at each border
    missing_min_px: NonNegative = 12.0
    # ... and only from a viewing direction within this of one it was detected from (detectors find many objects
    # from some sides only: on 7-Scenes a microwave and a table boxed in the first session are never boxed from the
    # second session's)
    missing_max_view_angle_deg: Positive = 30.0


class _AssociatorBase(MapperParams):
    refine_every_n_frames: AtLeastOne = Field(
        10, description="lockstep: re-project landmarks with the corrected poses every n-th frame"
    )

    def prior(self) -> PriorParams:
        """The `prior_*` keys as the prior map's parameters."""
        return PriorParams(**{name: getattr(self, f"prior_{name}") for name in PriorParams.model_fields})


# the MapperParams fields, the service's own and PriorParams' under `prior_` (one definition of each default)
AssociatorConfig = create_model(
    "AssociatorConfig",
    __base__=_AssociatorBase,
    __doc__="The associator service: the landmark mapper's settings (MapperParams) and the service's own.",
    **{f"prior_{name}": (field.annotation, field) for name, field in PriorParams.model_fields.items()},
)
