"""The configuration sections of the run and of every service but the associator (see associator.py).

Each field is a YAML key with its default and, where it needs one, a description (`semmap config show` prints
them as comments). Defaults are the paper's "Applied system configuration" where it gives one.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from semmap.core.keys import Keys

from .base import (
    AtLeastOne,
    Count,
    Float,
    Fraction,
    Names,
    NonNegative,
    Numbers6,
    OptionalFile,
    Positive,
    Probability,
    Section,
)


class RunConfig(Section):
    """How `semmap run` plays the dataset."""

    robot: str = Field("robot1", min_length=1, description="robot name in the key expressions")
    mode: Literal["lockstep", "realtime"] = Field(
        "lockstep", description="lockstep (deterministic, as fast as the machine allows) | realtime (dataset rate)"
    )
    speed: Positive = Field(1.0, description="real-time playback speed factor")
    realtime_map_niceness: Count = Field(
        5, description="real time: the tracker, associator and backend lower their CPU priority by this much (nice), "
        "so the front end poses every frame first; they answer later instead (0: equal shares)")
    max_frames: Count = Field(0, description="0 = all")
    start_frame: Count = Field(
        0, description="begin at this frame of the dataset (renumbered from 0): a later session of it"
    )
    loops: AtLeastOne = Field(1, description="play the dataset this many times (soak tests)")
    depth_encoding: Literal["raw", "png"] = Field(
        "raw", description="raw (670 KB a 7-Scenes frame) | png (190 KB, ~10 ms to encode): for slow links"
    )
    start_timeout_s: Positive = Field(60.0, description="how long services may take to come up")
    frame_timeout_s: Positive = Field(
        30.0,
        description="lockstep: longest wait for one frame before the run fails (not counting time a "
        "waited-for service is down, e.g. restarting; down longer than start_timeout_s fails)",
    )
    deadline_s: NonNegative = Field(
        0.0, description="the whole run's time limit (0 = none; `semmap run --deadline S`): then it fails"
    )
    min_free_mb: NonNegative = Field(200.0, description="pre-flight: free disk space --out must have")
    gt_max_gap_s: NonNegative = Field(
        0.1,
        description="TUM layout: a frame without a ground-truth sample within 20 ms gets a pose interpolated "
        "(SE(3)) between samples at most this far apart; with `--odometry gt` or `gt+drift` a frame left without "
        "one is announced unreadable and skipped",
    )

    @field_validator("robot")
    @classmethod
    def _robot(cls, value: str) -> str:
        Keys(value)  # a name that keeps the key expressions narrow (InvalidNameError says which characters)
        return value


class SecurityConfig(Section):
    """Checks on an open bus (docs/SECURITY.md)."""

    max_frame_gap: AtLeastOne = Field(
        300, description="frame ids further than this from the newest seen on a stream are refused (counted)"
    )
    max_rate_hz: Positive = Field(
        5000.0, description="messages a second one subscription takes (bursts of as many); more are refused"
    )


class RosbagConfig(Section):
    """ROS bags as datasets (semmap/datasets/rosbag.py, docs/ROS2.md)."""

    topics: str = Field(
        "",
        description="role=/topic,... overrides (`semmap run BAG --topics ...`): color, depth, "
        'camera_info, pose, groundtruth; "" = found by message type',
    )
    tf_parent: str = Field("", description='pose from /tf: the world frame ("" = the root of the camera\'s tf tree)')
    tf_child: str = Field("", description='... and the camera frame ("" = the colour images\' frame_id)')
    pose_to_optical: str = Field(
        "identity", description='pose frame -> optical frame: identity | ros (REP 103 x forward) | "x y z qx qy qz qw"'
    )
    max_difference_s: Positive = Field(0.02, description="colour/depth pairing tolerance (header stamps)")
    pose_max_gap_s: Positive = Field(
        0.5, description="longest gap between two poses that a frame's pose is interpolated over"
    )


class DetectorConfig(Section):
    """The detector service (semmap/algorithms/detector)."""

    kind: str = Field(
        "auto",
        min_length=1,
        description="auto (oracle on synthetic data, ONNX otherwise) | onnx | "
        "oracle: a back end registered in semmap/algorithms/detector (checked before a run starts)",
    )
    model: OptionalFile = Field(
        "", description='ONNX model file; "" = the converted YOLOv5s from `semmap models fetch` (see precision)'
    )
    precision: Literal["auto", "fp32", "int8", "int8w7"] = Field(
        "auto",
        description="auto (real time: the configuration measured on this machine, among those agreeing with fp32 "
        "at full size, `semmap models doctor`; fp32 otherwise) | fp32 | int8 (~2x faster on CPUs with VNNI; "
        "without VNNI its 8-bit products saturate and it disagrees) | int8w7 (int8 with 7-bit weights: agrees "
        "without VNNI too, at int8's speed); `semmap models quantize DATASET` makes both copies, ./dev.sh does",
    )
    input_size: str = Field(
        "auto",
        pattern=r"^(auto|[1-9][0-9]*x[1-9][0-9]*)$",
        description="letterbox WxH (multiples of 32, e.g. 512x384) | auto (real time with precision auto: the "
        "measured choice; the model's own size, 640x480, otherwise)",
    )
    names: OptionalFile = Field("", description="class names file for a bring-your-own model")
    confidence: Probability = Field(0.4, description="paper")
    class_confidence: dict[str, Probability] = Field(
        default_factory=lambda: {"person": 0.25},
        description="per-class thresholds that replace `confidence` for those classes. person 0.25: people are "
        "never mapped, only left out of the odometry's depth and the SLAM's features (the `dynamic` key), where a "
        "person missed (motion-blurred, half in view) drags the trajectory and a false one costs a few pixels. Bonn "
        "crowd, ORB-SLAM3 run 1 as file: 0.4 -> 0.047 m, 0.3 -> 0.046, 0.25 -> 0.044, 0.2 -> 0.042, 0.15 -> 0.106 "
        "(false people covering whole frames; docs/RESULTS.md); {} = `confidence` for all",
    )
    iou: Probability = 0.45
    depth_min_m: NonNegative = Field(0.2, description="paper")
    depth_max_m: Positive = Field(25.0, description="paper")
    threads: Count = Field(0, description="intra-op CPU threads; 0 = auto (the measured choice in real time "
                           "with precision auto, 2 otherwise)")
    classes: Names = Field((), description="allow list (empty = all)")
    exclude: Names = Field((), description="deny list")
    every_n_frames: Count = Field(
        0,
        description="detect every n-th frame (others are passed on as skipped); 0 = auto: every frame in lockstep, "
        "in real time the cadence the frame budget allows (measured detector cost, cores shared with the others)",
    )
    depth_patch_stride: AtLeastOne = Field(2, description="subsampling of the depth pixels sent with each detection")
    queue: AtLeastOne = Field(
        1,
        description="real time: frames waiting per replica before the oldest is dropped (1: a free detector "
        "takes the newest frame; the older ones are answered as dropped)",
    )
    realtime_niceness: Count = Field(
        10,
        description="real time: the detector lowers its CPU priority by this much (nice), so the front end and "
        "the other services get a core first and the detector takes what they leave (0: equal shares)",
    )
    oracle_seed: int = 0
    oracle_miss_rate: Fraction = 0.05
    oracle_false_positive_rate: NonNegative = Field(0.02, description="expected spurious boxes per frame (Poisson)")
    oracle_confusion_rate: Fraction = 0.0

    @model_validator(mode="after")
    def _depth_range(self) -> DetectorConfig:
        if not self.depth_min_m < self.depth_max_m:
            raise ValueError("depth_min_m must be below depth_max_m")
        return self


class TrackerParams(Section):
    """The tracker service (semmap/algorithms/tracker/iou_tracker.py)."""

    sigma_iou: Probability = Field(0.2, description="paper: least IOU that continues a tracklet")
    min_length: AtLeastOne = Field(5, description="paper: measurements before a tracklet becomes a candidate")
    max_age_s: NonNegative = Field(0.5, description="paper: longest time since the last detection")
    dynamic_depth_band_m: Positive = Field(
        0.5, description="a dynamic object's depth range: its box's valid depths this close to its median"
    )
    dynamic_hold_speed_mps: NonNegative = Field(
        1.5,
        description="a dynamic object alive but not detected in a frame keeps its last box, grown on every side by "
        "how far it may have moved since at this speed (a brisk walk; semmap/algorithms/tracker/iou_tracker.py, "
        "held_dynamic_box); 0: the last box as it was",
    )
    occlusion_min_overlap: Probability = Field(
        0.1,
        description="a box this much covered (intersection / its area) by a box of a dynamic class "
        "(associator.dynamic_classes) in the same frame is marked occluded: the associator's motion tests leave "
        "it out (a person passing in front of or behind a chair is not the chair moving)",
    )
    occlusion_depth_margin_m: NonNegative = Field(
        1.0, description="...when that box's median depth is at most this much beyond the covered box's (further "
        "behind, its depth is outside the object's band)"
    )


class OdometryConfig(Section):
    """The odometry service (semmap/algorithms/odometry/frontends.py)."""

    mode: str = Field(
        "auto",
        min_length=1,
        description="auto | orbslam3 | rgbd | file:PATH | gt | gt+drift: a front end registered in "
        "semmap/algorithms/odometry (checked before a run starts). auto: orbslam3 where the pyorbslam3 wheel and a "
        "vocabulary are at hand, else rgbd (a real front end); the synthetic world's own simulated odometry "
        "(gt+drift) on synthetic data. gt and gt+drift simulate odometry from ground truth: only when asked",
    )
    seed: int = 0
    keyframe_every: AtLeastOne = Field(
        10, description="every n-th frame is a keyframe: a pose-graph node (frames between ride on the previous one)")
    frame_offset: Numbers6 = Field(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        description="x y z (m) roll pitch yaw (deg): every pose is given in a frame "
        "moved by this (a session that starts in an unknown frame; docs/MAPS.md)",
    )
    drift_translation_sigma_m: NonNegative = Field(0.003, description="per frame")
    drift_yaw_sigma_deg: NonNegative = Field(0.3, description="per frame, about gravity")
    drift_yaw_bias_deg: Float = Field(
        0.05, description="per frame: what makes drift grow (about 0.1-0.2 m ATE on 7-Scenes)"
    )
    drift_bias_horizon_frames: NonNegative = Field(
        100.0,
        description="declared yaw sigma = sqrt(sigma^2 + horizon * bias^2): a bias grows linearly, a "
        "declared random walk only with sqrt(frames) (frontends.py)",
    )
    drift_profile: Literal["auto", "handheld", "vehicle"] = Field(
        "auto",
        description="gt+drift: `handheld` drifts per frame (the drift_* settings above), `vehicle` per metre "
        "driven (drift_vehicle_*: a car's odometry); auto: the data's platform (street world, KITTI: vehicle)",
    )
    drift_vehicle_translation_sigma: NonNegative = Field(
        0.01, description="vehicle: translation noise per step, as a share of the step's length (1 %)"
    )
    drift_vehicle_yaw_sigma_deg: NonNegative = Field(0.02, description="vehicle: yaw noise per sqrt(metre) driven")
    drift_vehicle_yaw_bias_deg: Float = Field(
        0.004, description="vehicle: yaw bias per metre driven (15 deg over KITTI 00's 3.7 km)"
    )
    gt_sigma_translation_m: Positive = Field(0.0002, description="the covariance the `gt` front end declares (tight)")
    gt_sigma_rotation_deg: Positive = 0.01
    rgbd_sigma_translation_m: Positive = 0.01
    rgbd_sigma_rotation_deg: Positive = 0.5
    rgbd_min_fitness: Fraction = Field(
        0.15,
        description="rgbd: a frame pair registered on less than this fraction of its pixels is not trusted: the "
        "previous step is repeated (counted as pairs_low_fitness; 0 = trust every pair)",
    )
    dynamic_mask: Literal["box", "range", "none"] = Field(
        "box",
        description="rgbd: leave out the depth of the frame's dynamic objects (people, animals, things seen "
        "moving; semmap/v1/<robot>/dynamic): box (whole box) | range (only the object's depth range in it) | none. "
        "Lockstep waits for each frame's boxes",
    )
    dynamic_wait_s: NonNegative = Field(
        10.0, description="lockstep: longest wait for a frame's dynamic objects, then without them"
    )
    realtime_queue_s: Positive = Field(
        2.0,
        description="real time: how much video (at 30 fps) the front end queues through a stall before it drops "
        "the oldest frames (a SLAM fed every 4th frame of a hand-held camera loses track; ORB-SLAM3 on 2 cores "
        "takes about a frame's time a frame, so its backlog wanders: Bonn crowd dropped 19-64 frames with 1 s, "
        "0-30 with 2 s, at ~100 MB more memory and up to 2 s more latency)",
    )
    registration_resolution: Literal["auto", "full", "half"] = Field(
        "auto",
        description="semmap's own frame-to-frame registration on the full images or on half their size (a quarter "
        "of the pixels, ~4x cheaper) | auto: half in real time (the front end must keep up with the video), full "
        "in lockstep",
    )
    repair_witness: Literal["dense", "sparse"] = Field(
        "dense",
        description="repair: what measures a checked step: dense (the RGB-D registration above; the step fitted to "
        "the static ORB matches where it has too few pixels) or sparse (that fit alone: a third of a full-size "
        "registration's cost; Bonn crowd in lockstep 0.07-0.11 m where dense gives 0.05-0.10 m: "
        "benchmarks/bench_witness.py)",
    )
    file_sigma_translation_m: Positive = Field(
        0.01, description="what `file:PATH` (and `external`) declares for a trajectory of unknown quality"
    )
    file_sigma_rotation_deg: Positive = 0.5
    file_sigma_measured: bool = Field(
        True,
        description="file:PATH and external, with repair: a frame whose step is the SLAM's own declares sigmas "
        "measured from the SLAM's consistency, never looser than file_sigma_*: per axis, the larger of its steps' "
        "roughness (second difference) and their disagreement with semmap's trusted registrations (90th percentile "
        "/ 2.5; repair.py, StepAgreement; KITTI 00 ORB: 7.3 mm, 0.071 deg); false: file_sigma_* always",
    )
    file_sigma_measured_after: AtLeastOne = Field(
        50, description="...once this many of the SLAM's steps were witnessed (file_sigma_* until then)"
    )
    file_time_offset_s: Float = Field(
        0.0, description="added to a `file:PATH` trajectory's stamps before matching (--time-offset)"
    )
    file_rate_hz: Positive = Field(
        10.0, description="a `file:PATH` in KITTI's format (12 numbers a line, no stamps): pose i is at i / rate"
    )
    repair: bool = Field(
        True,
        description="orbslam3 and file:PATH: check each of the SLAM's steps against semmap's own people-masked "
        "RGB-D registration and overrule the wrong ones (semmap/algorithms/odometry/repair.py; needs the frames' "
        "images); false: copy the SLAM's poses as they are",
    )
    repair_translation_m: Positive = Field(
        0.005, description="repair: a SLAM step further than this from semmap's own measurement of it is overruled"
    )
    repair_rotation_deg: Positive = Field(0.5, description="repair: ...or turned further than this (deg)")
    repair_min_fitness: Fraction = Field(
        0.15,
        description="repair: semmap's registration witnesses a step only where it registered this fraction of the "
        "pixels; elsewhere the SLAM's step must agree with the recent motion (the same gate)",
    )
    repair_scope: Literal["moving", "always"] = Field(
        "moving",
        description="repair: check the SLAM's steps only while an object is seen moving (motion_*) and "
        "repair_hold_s after (moving: a person sitting still or a false person box is no reason to doubt a SLAM, and "
        "on a static scene a SLAM beats frame-to-frame registration), or always",
    )
    repair_hold_s: NonNegative = Field(
        2.0, description="repair: seconds after the last moving object left the view that steps are still checked"
    )
    repair_gap_half_life_s: Positive = Field(
        0.25,
        description="repair: where the SLAM has no pose and nothing measured the step, the motion model's speed "
        "halves every this many seconds (a hand-held camera's motion over seconds is no straight line); a slower "
        "stream (a car at 10 Hz) keeps its speed; inf: constant velocity",
    )
    repair_witness_every: AtLeastOne = Field(
        5,
        description="file:PATH and external: outside the scope, register every n-th frame pair only to measure the "
        "SLAM's precision (file_sigma_measured); the other pairs cost nothing",
    )
    repair_behind_check_every: Count = Field(
        3,
        description="real time, while the front end is behind the video (frames queued): every n-th step is still "
        "checked, over the n frames since the last, on the static scene's ORB matches with people left out by their "
        "depth band (~12 ms where a check a frame costs 20-45); 0: none while behind (the SLAM's steps as they "
        "are). Only where an object is seen moving (the repair's scope). Bonn crowd, 24 real-time runs: 18 within "
        "0.08 m (none with 0), but ORB-SLAM3 posed 73-89 % of the frames instead of 77-98 (docs/PERFORMANCE.md)",
    )
    motion_window_s: Positive = Field(
        1.0, description="a dynamic object moves when its centroids over this long scatter by more than ..."
    )
    motion_min_spread_m: Positive = Field(
        0.10,
        description="... this (median absolute deviation from their median, in the world of the repaired poses: "
        "the associator's MAD test applied to people; a walker covers a metre a second, a seated person's box "
        "centre stays within centimetres)",
    )
    motion_min_views: AtLeastOne = Field(5, description="...from at least this many detected views (paper: 5)")
    motion_persist_views: AtLeastOne = Field(
        3, description="...for this many views in a row (semmap/algorithms/odometry/motion.py says which views count)"
    )
    arbiter_window_frames: AtLeastOne = Field(
        3,
        description="repair: where the SLAM's step and semmap's registration disagree, both motions over this many "
        "frames are scored on the static scene's ORB matches between the window's ends (a dragged SLAM drifts frame "
        "after frame; one frame pair's noise hides it)",
    )
    arbiter_long_window_frames: Count = Field(
        0, description="repair: ... and again over this many frames (a SLAM dragged slowly shows over half a second)"
    )
    arbiter_min_t: Positive = Field(
        3.0,
        description="repair: semmap's step replaces the SLAM's only when its motion explains the matches better by "
        "this many standard errors; weaker evidence keeps the SLAM's step",
    )
    arbiter_min_matches: AtLeastOne = Field(40, description="repair: fewer static matches are weak evidence")
    arbiter_sparse_min_inliers: AtLeastOne = Field(
        80, description="repair: where too few pixels are left to trust semmap's dense registration, a step fitted to "
        "the static scene's ORB matches witnesses instead if this many of them agree on it")
    orbslam3_vocabulary: str = Field(
        "",
        description="orbslam3: the ORB vocabulary (ORBvoc.txt, or `semmap models vocabulary IMAGES --out FILE`); "
        '"" = orbvoc.txt in the model dir ($SEMMAP_MODEL_DIR or ~/.cache/semmap/models) if there. Never downloaded',
    )
    orbslam3_settings: str = Field(
        "", description='orbslam3: your own ORB-SLAM3 settings file; "" = written from the frames\' camera'
    )
    orbslam3_features: AtLeastOne = Field(1000, description="orbslam3: ORB features per image")
    orbslam3_realtime_features: AtLeastOne = Field(
        800,
        description="orbslam3 in real time, where orbslam3_features is left at its default: fewer features, so that "
        "it tracks every frame on its share of two cores (7-Scenes on a 2-core EPYC: 1000 posed 80 % of the frames, "
        "800 95 % at the same ATE; 600 lost track for seconds on Bonn crowd)",
    )
    orbslam3_mask: Literal["range", "box", "none"] = Field(
        "range",
        description="orbslam3: blank the frame's dynamic objects before it tracks: range (the pixels of a box in "
        "the object's depth band), box (the whole box), none",
    )
    orbslam3_weak_points: Count = Field(
        30,
        description="orbslam3: a frame ORB-SLAM3 tracked on fewer map points than this is a weak pose of its own "
        "account; semmap's registration replaces its step where the two disagree",
    )
    orbslam3_refinement: bool = Field(
        True,
        description="orbslam3: at the end of a run where no walker dragged it, its own steps as it refined them "
        "(the trajectory it saves) replace its steps as tracked in semmap's result (docs/ORBSLAM3.md)",
    )
    orbslam3_sigma_translation_m: Positive = Field(0.005, description="what orbslam3 declares per frame")
    orbslam3_sigma_rotation_deg: Positive = 0.3


RobustKernel = Literal["huber", "cauchy", "none"]  # semmap/algorithms/backend/factors.py


class BackendParams(Section):
    """The backend's pose graph (semmap/algorithms/backend/pose_graph.py). Sigmas are 1-sigma; the observation
    sigma used is max(message sigma, floor + per_m_depth * depth + size_factor * size), because per-view object
    centroids scatter 3-14 cm with the viewpoint (more for big objects) whatever the associator believes; along the
    ray (the range) it may be loosened further by the object's size (`observation_range_sigma_size_factor`)."""

    prior_sigma_translation_m: Positive = 0.001
    prior_sigma_rotation_deg: Positive = 0.01
    observation_sigma_floor_m: NonNegative = Field(
        0.02, description="sigma used = max(msg sigma, floor + per_m_depth*z + size_factor*size)"
    )
    observation_sigma_per_m_depth: NonNegative = 0.01
    observation_sigma_size_factor: NonNegative = 0.05
    observation_range_sigma_size_factor: NonNegative = Field(
        0.0,
        description="range sigma = hypot(sigma, factor * size); the bearing's stays sigma / range; 0: isotropic. A "
        "view's centre is its visible surface's, in front of the object's centre along the ray (street world, KITTI "
        "00's parked cars: by 0.33 x size on average, 0.19 x size scatter; across the ray the sigma holds), and every "
        "view from that side shares the offset. 1.0 takes the KITTI 00 ORB row 1.51 -> 1.21 m, but on Bonn crowd "
        "(ORB-SLAM3 run 1 as file:) 0.058 -> 0.068-0.076 m (docs/RESULTS.md); off by default. Only for observations "
        "without depth_unseen (older senders): observation_range_sigma_unseen_factor takes its place",
    )
    observation_range_sigma_unseen_factor: NonNegative = Field(
        1.0,
        description="range sigma = hypot(sigma, factor * depth_unseen) for an observation that carries the "
        "associator's depth_unseen (the depth the view may not have seen, bounded by the object's footprint: a "
        "parked car ~4.5 m, a chair ~0.7 m); the bearing keeps sigma. KITTI 00 street, ORB estimate: 1.51 -> 1.19 m "
        "(alone 1.30); Bonn crowd and 7-Scenes unchanged (docs/RESULTS.md). 0: the isotropic model "
        "(observation_range_sigma_size_factor x size, for messages without it too)",
    )
    observation_min_range_m: NonNegative = 0.05
    robust_kernel: RobustKernel = Field(
        "cauchy",
        description="landmark observations: huber | cauchy | none (cauchy: a wrong association pulls less "
        "and less; 7-Scenes closed loop, 10 drift seeds: lower ATE than huber everywhere)",
    )
    robust_k: Positive = 1.345
    relative_pose_kernel: RobustKernel = Field(
        "huber",
        description="relative-pose constraints (loop closures arrive with large residuals, which cauchy "
        "would all but ignore)",
    )
    min_observations_per_landmark: AtLeastOne = Field(
        3, description="a landmark constrains the graph from its 3rd observation on"
    )
    landmark_constraints: bool = Field(
        True, description="false: odometry (+ loop closures) only, for comparison (bench_matrix.py --ablation)"
    )
    merge_sigma_m: Positive = 0.001
    relinearize_threshold: Positive = 0.001
    relinearize_skip: AtLeastOne = 1
    active_window_nodes: Count = Field(
        300,
        description="pose nodes iSAM2 keeps solving; older ones are settled (their estimate kept, their factors "
        "turned into priors on what stays) so an update costs the same after hours as after a minute; 0 = never",
    )
    settle_batch_nodes: AtLeastOne = Field(
        100, description="nodes settled at once, when the window holds this many more (the graph is rebuilt then)"
    )


class LoopClosureParams(Section):
    """Whole-depth-frame ICP at revisits (semmap/algorithms/backend/loop_closure.py): breaks the ~5 cm floor
    that per-view object centroids leave (README, Table 1)."""

    enabled: bool = True
    every_n_frames: AtLeastOne = Field(10, description="keyframes whose depth cloud is kept and registered")
    min_gap_s: NonNegative = Field(
        3.0,
        description="only against keyframes at least this much older (not the last frames). 3 s rather than a "
        "true revisit's 10 s: a real front end's errors are abrupt (a person walks through), and closures to "
        "the keyframes of a few seconds before catch them while they are small (Bonn crowd, in-process: rgbd "
        "0.077 -> 0.061 m, live ORB-SLAM3 median 0.082 -> 0.064 m; 7-Scenes rgbd 8.3 -> 8.0 cm; simulated "
        "gt+drift, 4 cases: mean 3.39 cm either way; docs/RESULTS.md)",
    )
    max_distance_m: Positive = Field(0.4, description="search radius around the current corrected pose ...")
    max_angle_deg: Positive = Field(20.0, description="... and viewing-direction difference")
    candidates: AtLeastOne = Field(
        3, description="keyframes in that radius tried, nearest first, until one passes the tests below (Bonn crowd: "
        "1 accepted 8-12 closures of 33 searches, 3 accepted 16, 6 no more)"
    )
    depth_stride: AtLeastOne = Field(6, description="every n-th depth pixel, then")
    depth_min_m: NonNegative = 0.3
    depth_max_m: NonNegative = 4.0
    voxel_m: Positive = Field(0.02, description="one point per voxel")
    dynamic_mask: Literal["box", "range", "none"] = Field(
        "none",
        description="leave the keyframe's dynamic objects (the tracker's boxes: people, things seen moving) out "
        "of its cloud: box | range (only the object's depth band in its box) | none. Lockstep then waits for each "
        "keyframe's boxes. Off by default: measured on Bonn crowd (rgbd, in process) it gave no reliable gain "
        "(box: 0.058 / 0.058 / 0.087 / 0.087 m optimised ATE; none: 0.061 / 0.063 / 0.063 m; docs/RESULTS.md)",
    )
    normal_radius_m: Positive = 0.08
    coarse_distance_m: Positive = Field(0.1, description="ICP correspondence distance, coarse pass")
    fine_distance_m: Positive = Field(0.03, description="... and fine pass")
    max_iterations: AtLeastOne = 30
    min_fitness: Probability = Field(0.5, description="accept: share of points with a correspondence")
    max_rmse_m: Positive = Field(0.02, description="accept: RMS correspondence distance")
    min_constraint: NonNegative = Field(
        0.02, description="accept: smallest eigenvalue of the normals' scatter (0 = a plane: slides)"
    )
    max_correction_m: Positive = Field(
        0.3, description="accept: how far ICP may move the keyframe from the current estimate"
    )
    sigma_translation_m: Positive = Field(
        0.01, description="noise of the relative-pose factor (robust: backend.relative_pose_kernel)"
    )
    sigma_rotation_deg: Positive = 0.5
    max_keyframes: AtLeastOne = Field(1000, description="clouds kept (~80-160 KB each); the oldest go first")

    @model_validator(mode="after")
    def _depth_range(self) -> LoopClosureParams:
        if not self.depth_min_m < self.depth_max_m:
            raise ValueError("depth_min_m must be below depth_max_m")
        return self


class CorrectionsParams(Section):
    """What the backend sends on poses/corrected (semmap/algorithms/backend/corrections.py)."""

    tolerance_m: NonNegative = Field(
        0.001, description="a frame's pose goes out again once it moved this far from what was last sent ..."
    )
    tolerance_deg: NonNegative = Field(0.05, description="... or turned this much")
    refresh_frames: Count = Field(
        32, description="plus this many consecutive frames per message, cycling: late joiners catch up"
    )


class VizConfig(Section):
    """The Rerun sink (semmap/services/viz)."""

    enabled: bool = True
    images: bool = Field(True, description="log camera images (JPEG as received)")
    depth_every: Count = Field(30, description="log every n-th depth image (0 = none; 30: once a second at 30 Hz): "
                               "each is a 16-bit PNG to decode and 600 KB in run.rrd, a third of the viewer's CPU "
                               "at every 10th")
