"""The in-process driver: the pipeline's stages (semmap/runtime/pipeline/stages.py) in one process, without a bus.

    python -m semmap.runtime.pipeline.inprocess DATA [--odometry gt+drift] [--seed N] [--frames N] [--set
    sec.key=val]...
        [--map PRIOR] [--refresh-cache] [--cache-dir DIR] [--json-out FILE] [--out DIR] [-v]

DATA is a dataset folder (e.g. ../shared/data/7scenes-redkitchen) or `synthetic[:frames=N,seed=S]`;
`--set run.start_frame=N` plays it from frame N on, renumbered from 0, as `semmap run --start-frame N` does.
`--map PRIOR` (a run directory or its map.sqlite, as `semmap run --map`) starts from a saved map: the session
relocalises against it and then maps in its frame (docs/MAPS.md). `--out` writes map.sqlite too, so a run of this
driver can be the prior map of the next.
(`benchmarks/closed_loop.py` is the same command.)

It runs, frame by frame, the same stage objects as the services, in the order the dataflow table gives
(semmap.core.dataflow.lockstep_order, derived from the services' ports: detector, tracker, odometry, associator,
backend), then the feedback ports from the last writer up (the backend's corrected poses to the associator, which
completes the frame; its map update to the tracker): `LockstepDriver`.
Configuration comes from semmap.core.config (`semmap config show`) with the same `--set` overrides as `semmap run`, so
both drivers give the same map.json and optimised trajectory (tests/pipeline/test_closed_loop.py).

Detections are what the detector service would publish: the player's frame message (RGB through JPEG q90,
as on the bus), the ONNX detector (or the oracle on synthetic data), `depth_gate` and the strided depth
patches. They are computed once per (data, frames, detector settings) and cached as msgpack under
`.cache/closed_loop/` (never committed); `rgbd` odometry poses are cached the same way.

Reports ATE (evo, `semmap.algorithms.evaluation.ate_rmse`) of the odometry and of the optimised trajectory, landmarks,
observations sent and used, merges, and run times. Seconds instead of the pipeline's minutes.

`run_offline` is the tracker and mapper alone against given poses (no backend), for tests and benchmarks of the
mapping; `score_map` scores a map against a synthetic scene's objects.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import msgpack
import numpy as np

from semmap.algorithms.associator.mapper import LandmarkMapper, MapperParams, MapperStep
from semmap.algorithms.detector.onnx_detector import DetectedBox
from semmap.algorithms.evaluation import ate_rmse, write_json_atomic
from semmap.algorithms.odometry.frontends import OdometryInput, frame_offset, make_frontend
from semmap.algorithms.tracker.iou_tracker import IouTracker, TrackerParams
from semmap.core import dataflow
from semmap.core.config import Config, load_config
from semmap.core.messages import Detection, Detections, Message, MessageError, OdometryPose
from semmap.core.outputs import REPAIR_REPORT, SLAM_REFINED_TRAJECTORY, SLAM_TRAJECTORY
from semmap.datasets import open_dataset, platform_of
from semmap.datasets.base import FrameData, ObjectTruth, WindowDataset
from semmap.datasets.trajectory_io import write_tum
from semmap.runtime.maps.map_store import MapStore, write_map_json
from semmap.runtime.pipeline.stages import (
    AssociatorStage,
    BackendStage,
    TrackerStage,
    depth_detections,
    frame_message,
)

ROOT = Path(__file__).resolve().parents[2]
CACHE_DIR = ROOT / ".cache" / "closed_loop"
CACHE_VERSION = 1
ROBOT = "robot1"

DetectFn = Callable[[FrameData], Sequence[DetectedBox]]


# ------------------------------------------------------------------------------------------------ inputs


@dataclass
class Recording:
    """What the loop needs from a dataset: each frame's detector answer and ground truth."""

    name: str
    detections: list[Detections]
    gt: list[np.ndarray | None]
    objects: list[ObjectTruth] = field(default_factory=list)

    @property
    def stamps(self) -> list[float]:
        return [d.stamp for d in self.detections]


def _is_synthetic(data: str) -> bool:
    return data == "synthetic" or data.startswith("synthetic:")


def _cache_key(*parts: object) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


@functools.lru_cache(maxsize=2)
def _open(data: str, start_frame: int = 0):  # noqa: ANN202 - a semmap Dataset
    """Opened once per run (the synthetic scene builds its meshes on opening); from `run.start_frame` on,
    renumbered from 0, as the player plays it."""
    ds = open_dataset(data)
    return WindowDataset(ds, int(start_frame)) if start_frame > 0 else ds


def _frame_count(ds, frames: int) -> int:  # noqa: ANN001
    return min(len(ds), frames) if frames > 0 else len(ds)


def make_detections(
    frame: FrameData, boxes: Iterable[DetectedBox], stride: int = 2, depth_min_m: float = 0.2, depth_max_m: float = 25.0
) -> list[Detection]:
    """A dataset frame's detections as the detector service makes them (`depth_detections`)."""
    return depth_detections(boxes, frame.depth, frame.depth_scale, stride, depth_min_m, depth_max_m)


WireMessage = TypeVar("WireMessage", bound=Message)


def on_the_wire(message: WireMessage) -> WireMessage:
    """The message as a subscriber decodes it."""
    return type(message).decode(message.encode())


def detect_recording(
    data: str, frames: int, config: Config, cache_dir: Path = CACHE_DIR, refresh: bool = False, verbose: bool = True
) -> Recording:
    """Every frame's `Detections` as the detector service makes them (cached; see module docstring)."""
    from semmap.algorithms.detector import resolve_kind

    det_cfg = config.detector.model_dump()
    synthetic = _is_synthetic(data)
    kind = resolve_kind(det_cfg["kind"], synthetic)
    ds = _open(data, config.run.start_frame)
    n = _frame_count(ds, frames)
    model = None
    if kind == "onnx":
        from semmap.runtime.models.model_store import packaged_model

        precision = "fp32" if det_cfg["precision"] == "auto" else det_cfg["precision"]  # (lockstep: fp32's figures)
        model = Path(det_cfg["model"] or packaged_model(precision))
    model_id = None if model is None else (str(model), model.stat().st_size, int(model.stat().st_mtime))
    setup = None
    if kind == "onnx" and not det_cfg["model"]:  # the packaged model, resized to `detector.input_size` as the
        from semmap.runtime.models.detector_choice import resolve_setup  # detector service resizes it

        setup = resolve_setup(det_cfg["precision"], int(det_cfg["threads"]), det_cfg["input_size"], realtime=False)
        model_id = (*model_id, "letterbox", setup.hw)  # (before: detections at the model's own size whatever was set)
    # the model file stands for `precision`; threads and queueing do not change detections
    key = _cache_key(
        CACHE_VERSION,
        str(Path(data).resolve()) if not synthetic else data,
        n,
        config.run.start_frame,
        kind,
        model_id,
        {k: det_cfg[k] for k in sorted(det_cfg) if k not in ("threads", "queue", "precision")},
    )
    path = cache_dir / f"detections-{key}.msgpack"
    objects = ds.objects()
    if path.is_file() and not refresh:
        raw = msgpack.unpackb(path.read_bytes(), raw=False)
        dets = [Detections.decode(b) for b in raw["detections"]]
        gt = [None if g is None else np.array(g, dtype=np.float64).reshape(4, 4) for g in raw["gt"]]
        return Recording(raw["name"], dets, gt, objects)

    # built as the detector service builds it (the oracle with the allow / deny lists; the packaged model resized
    # to `detector.input_size`)
    from semmap.algorithms.detector import create_detector
    from semmap.runtime.models.detector_choice import load_detector_model

    detector = create_detector(kind, config.detector, load_detector_model(setup) if setup is not None else model)
    every = max(1, int(det_cfg["every_n_frames"]))
    stride = max(1, int(det_cfg["depth_patch_stride"]))
    dets, gt = [], []
    t0 = time.perf_counter()
    for i in range(n):
        data_i = ds[i]
        frame = on_the_wire(frame_message(ROBOT, data_i))
        gt.append(frame.gt_pose)
        if i % every:
            dets.append(Detections(ROBOT, i, frame.stamp, frame.intrinsics, frame.depth_scale, [], "stride"))
            continue
        boxes = detector.detect_frame(frame)
        # the dataset's depth is what a subscriber decodes (the same file or array; 65535 read as 0 either way)
        detections = make_detections(data_i, boxes, stride, det_cfg["depth_min_m"], det_cfg["depth_max_m"])
        dets.append(Detections(ROBOT, i, frame.stamp, frame.intrinsics, frame.depth_scale, detections))
        if verbose and (i + 1) % 100 == 0:
            print(f"  detected {i + 1}/{n} frames ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    encoded = [d.encode() for d in dets]
    dets = [Detections.decode(b) for b in encoded]  # exactly what a subscriber decodes
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(
        msgpack.packb(
            {
                "name": ds.name,
                "detections": encoded,
                "gt": [None if g is None else np.asarray(g).reshape(16).tolist() for g in gt],
            },
            use_bin_type=True,
        )
    )
    tmp.replace(path)
    return Recording(ds.name, dets, gt, objects)


def rgbd_poses(
    data: str, frames: int, config: Config, cache_dir: Path = CACHE_DIR, refresh: bool = False, verbose: bool = True
) -> list[np.ndarray]:
    """The `rgbd` front end's poses for every frame (Open3D, slow: cached)."""
    ds = _open(data, config.run.start_frame)
    n = _frame_count(ds, frames)
    cfg = config.odometry
    code = hashlib.sha1(Path(make_frontend.__code__.co_filename).read_bytes()).hexdigest()  # the front end's code
    key = _cache_key(
        CACHE_VERSION,
        "rgbd",
        str(Path(data).resolve()),
        n,
        config.run.start_frame,
        code,
        {k: v for k, v in cfg.model_dump().items() if k.startswith("rgbd_")},
    )
    path = cache_dir / f"rgbd-{key}.npy"
    if path.is_file() and not refresh:
        return list(np.load(path))
    front = make_frontend("rgbd", cfg)
    poses = []
    t0 = time.perf_counter()
    for i in range(n):
        frame = on_the_wire(frame_message(ROBOT, ds[i]))
        poses.append(
            front.estimate(
                OdometryInput(
                    i,
                    frame.stamp,
                    frame.gt_pose,
                    frame.rgb(),
                    frame.depth(),
                    frame.depth_scale,
                    frame.intrinsics.matrix,
                )
            )
        )
        if verbose and (i + 1) % 100 == 0:
            print(f"  rgbd odometry {i + 1}/{n} frames ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    cache_dir.mkdir(parents=True, exist_ok=True)
    np.save(path, np.stack(poses))
    return poses


# ------------------------------------------------------------------------------------------------ the loop


@dataclass
class LoopResult:
    ate_odometry: float
    ate_optimized: float
    landmarks: int
    observations: int  # sent by the mapper
    observation_factors: int  # that became factors in the graph
    graph_landmarks: int
    merges: int
    frames: int
    wall_s: float
    classes: dict[str, int]
    mapper_ms_p50: float = 0.0  # mapper.process (+ refine) per frame
    loop_closures: dict[str, int] = field(default_factory=dict)  # the backend's loop closer's counters
    graph_counters: dict[str, int] = field(default_factory=dict)  # the pose graph's (e.g. qr_refactorisations)
    backend_ms_p50: float = 0.0  # odometry + observations + iSAM2 update per frame
    mapper: LandmarkMapper | None = None
    optimized: list[tuple[float, np.ndarray]] = field(default_factory=list)
    odometry: list[tuple[float, np.ndarray]] = field(default_factory=list)
    frontend_counters: dict[str, int] = field(default_factory=dict)  # e.g. the repair's overruled steps
    slam_trajectory: list = field(default_factory=list)  # a checked SLAM's own poses, (stamp, 4x4)
    slam_refined: list = field(default_factory=list)  # ...as the SLAM refined them at its end (ORB-SLAM3)
    ate_slam: float | None = None  # an external SLAM's own poses, before semmap's repair (orbslam3, file:)
    ate_slam_refined: float | None = None  # ...refined by the SLAM at its end (orbslam3: what it alone saves)
    repair_report: dict | None = None  # where semmap overruled a checked SLAM and why (odometry_repair.json)
    refinement_withheld: str | None = None  # why the SLAM's refinement was not taken ("": taken; None: none)
    associator: AssociatorStage | None = None  # the map with its prior landmarks' statuses, its saved state

    @property
    def improvement_pct(self) -> float:
        """How much of the odometry's error the optimisation removed (0 when the odometry had none to remove:
        ground truth, where a percentage of a rounding error would read as nonsense)."""
        if self.ate_odometry < 1e-3:
            return 0.0
        return 100.0 * (self.ate_odometry - self.ate_optimized) / self.ate_odometry

    def summary(self) -> dict:
        return {
            "ate_odometry_m": self.ate_odometry,
            "ate_optimized_m": self.ate_optimized,
            "ate_slam_m": self.ate_slam,
            "ate_slam_refined_m": self.ate_slam_refined,
            "refinement_withheld": self.refinement_withheld,
            "improvement_pct": self.improvement_pct,
            "landmarks": self.landmarks,
            "observations": self.observations,
            "observation_factors": self.observation_factors,
            "graph_landmarks": self.graph_landmarks,
            "merges": self.merges,
            "frames": self.frames,
            "wall_s": self.wall_s,
            "mapper_ms_p50": self.mapper_ms_p50,
            "backend_ms_p50": self.backend_ms_p50,
            "classes": self.classes,
            "loop_closures": self.loop_closures,
            "frontend": self.frontend_counters,
        }

    def write_outputs(self, out: Path) -> None:
        """map.json, map.sqlite, relocalization.json (after a prior map's relocalisation), the trajectories, and
        with a checked SLAM its own poses and odometry_repair.json, as the services write them."""
        out.mkdir(parents=True, exist_ok=True)
        assert self.mapper is not None
        landmarks = self.associator.landmarks() if self.associator is not None else self.mapper.landmarks()
        write_map_json(out / "map.json", landmarks)
        if self.associator is not None:  # (a later session's prior map)
            MapStore(out / "map.sqlite").save(self.associator.to_state())
            record = self.associator.relocalisation_record()
            if record is not None:
                (out / "relocalization.json").write_text(json.dumps(record, indent=1))
        write_tum(out / "trajectory_optimized.tum", self.optimized)
        write_tum(out / "trajectory_odometry.tum", self.odometry)
        if self.slam_trajectory:  # (a checked SLAM's own poses, as the odometry service writes them)
            write_tum(out / SLAM_TRAJECTORY, self.slam_trajectory)
        if self.slam_refined:  # (...and refined by it at its end)
            write_tum(out / SLAM_REFINED_TRAJECTORY, self.slam_refined)
        if self.repair_report is not None:
            write_json_atomic(out / REPAIR_REPORT, self.repair_report)


def prior_stages(config: Config, prior_map: Path | None) -> tuple[AssociatorStage, BackendStage]:
    """The associator and backend stages of a lockstep run, from the sections their services read; with a prior
    map (a map.sqlite) the associator relocalises against it and the backend registers keyframes to its run's."""
    associator = AssociatorStage(config.associator, config.associator.refine_every_n_frames, await_backend=True)
    backend = BackendStage(config.backend, config.loop_closure, config.corrections,
                           expect_alignment=prior_map is not None)
    if prior_map is not None:
        associator.load_prior(prior_map, config.associator.prior())
        if backend.closer.params.enabled:
            backend.load_prior_keyframes(prior_map)
    return associator, backend


def odometry_message(front, frame_id: int, stamp: float, pose: np.ndarray, keyframe: bool, odometry: str,  # noqa: ANN001
                     estimated: bool) -> OdometryPose:
    """A frame's pose as the odometry service publishes it (`estimated`: by the front end now, not cached)."""
    return OdometryPose(ROBOT, frame_id, stamp, pose, keyframe=keyframe,
                        sigma_translation=front.sigmas[0],  # (read per frame: a vehicle's drift declares per step)
                        sigma_rotation=front.sigmas[1], source=odometry,
                        bridged=estimated and bool(getattr(front, "bridged", False)),
                        step=str(getattr(front, "step_source", "")) if estimated else "")


class LockstepDriver:
    """One frame at a time through the stages, in the order the dataflow table gives (semmap.core.dataflow:
    `lockstep_order`, derived from the services' ports), then its feedback ports from the last writer up
    (`feedback_ports`): the backend's corrected poses reach the associator, whose map update reaches the tracker.
    Each stage and each feedback port is one method here, found by the node's name; a node the table adds without
    a method here is refused at once (ValueError), never skipped."""

    STAGES = {"detector": "detector", "tracker": "tracker", "odometry": "odometry", "associator": "associator",
              "backend": "backend"}
    FEEDBACK = {("associator", "poses/corrected"): "associator_corrected", ("tracker", "map/updates"): "tracker_moving"}

    def __init__(self, rec: Recording, config: Config, odometry: str, odometry_poses: list[np.ndarray] | None,
                 depth_frames, prior_map: Path | None) -> None:  # noqa: ANN001 - a semmap Dataset
        self.order = dataflow.lockstep_order()
        self.feedback = dataflow.feedback_ports()
        missing = [n for n in self.order if n not in self.STAGES] + [
            f"{n} <- {p.topic}" for n, p in self.feedback if (n, p.topic) not in self.FEEDBACK]
        if missing:
            raise ValueError(f"the in-process driver has no step for {missing} (semmap/core/dataflow.py)")
        self.rec, self.odometry_mode = rec, odometry
        self.odometry_poses, self.depth_frames = odometry_poses, depth_frames
        self.front = make_frontend(odometry, config.odometry)  # with cached poses only for what it declares
        self.keyframe_every = config.odometry.keyframe_every
        # a session in a frame of its own (`odometry.frame_offset`), as the odometry service expresses its poses
        offset = frame_offset(config.odometry.frame_offset)
        self.to_session = None if np.array_equal(offset, np.eye(4)) else np.linalg.inv(offset)
        # the sections each service reads (semmap/services/*/service.py)
        self.tracker_stage = TrackerStage(config.tracker, dynamic_classes=config.associator.dynamic_classes)
        self.associator_stage, self.backend_stage = prior_stages(config, prior_map)
        self.n_obs = self.n_merges = 0
        self.odo_traj: list[tuple[float, np.ndarray]] = []
        self.mapper_ms: list[float] = []
        self.backend_ms: list[float] = []

    def run_frame(self, seq: int, det: Detections) -> None:
        self.seq, self.det = seq, det
        for name in self.order:
            getattr(self, self.STAGES[name])()
        for name, port in self.feedback:
            getattr(self, self.FEEDBACK[(name, port.topic)])()

    def detector(self) -> None:
        """(the detections come from the recording's cache: what the detector service would have sent)"""

    def tracker(self) -> None:
        self.out = self.tracker_stage.step(self.det)
        self.dynamic = self.tracker_stage.dynamic_objects(self.det, self.out)

    def odometry(self) -> None:
        det, front = self.det, self.front
        i, stamp = det.frame_id, det.stamp
        if self.odometry_poses is not None:
            pose = np.asarray(self.odometry_poses[i], dtype=np.float64)
        else:
            data = OdometryInput(i, stamp, self.rec.gt[i], depth_scale=det.depth_scale,
                                 intrinsics=det.intrinsics.matrix)
            if front.needs_images:
                if self.depth_frames is None:
                    raise ValueError(f"odometry {self.odometry_mode} needs the recording's images (depth_frames)")
                frame = on_the_wire(frame_message(ROBOT, self.depth_frames[i]))
                data.rgb, data.depth = frame.rgb(), frame.depth()
            if front.uses_dynamic:
                data.dynamic = self.dynamic
            pose = front.estimate(data)
        if self.to_session is not None:
            pose = self.to_session @ pose
        self.odo = odometry_message(front, i, stamp, pose, i % self.keyframe_every == 0, self.odometry_mode,
                                    self.odometry_poses is None)
        if not self.odo.bridged:  # (a stand-in pose is no measurement: the trajectory lists what was measured)
            self.odo_traj.append((stamp, pose.copy()))

    def associator(self) -> None:
        """With the prior map's relocalisation and statuses, when there is one; held for the backend's answer."""
        det, stage = self.det, self.associator_stage
        i, stamp = det.frame_id, det.stamp
        stage.odometry(i, self.odo.pose)
        stage.saw_stamp(stamp)
        t0 = time.perf_counter()
        boxes = None if det.skipped else self.out.boxes
        step = stage.process(i, stamp, self.out.candidates, self.out.ended, boxes)
        self.mapper_ms.append((time.perf_counter() - t0) * 1e3)
        step = stage.prior_step(i, stamp, boxes, step).step
        self.obs_msg = stage.observations(ROBOT, i, stamp, step)
        self.n_obs += len(step.observations)
        self.n_merges += len(self.obs_msg.merges)
        stage.hold(det, step)

    def backend(self) -> None:
        i, stamp = self.det.frame_id, self.det.stamp
        cloud = None
        if self.depth_frames is not None and self.backend_stage.wants_cloud(i):
            frame = self.depth_frames[i]
            k = frame.intrinsics
            cloud = self.backend_stage.closer.cloud_from_depth(i, stamp, frame.depth, frame.depth_scale, k.fx, k.fy,
                                                               k.cx, k.cy, self.dynamic)
        self.done = self.backend_stage.step(self.odo, self.obs_msg, cloud)
        self.backend_ms.append(self.done.update_ms + (self.done.loop_closure_ms or 0.0))

    def associator_corrected(self) -> None:
        """The backend's answer for the frame: the associator applies it and completes the held frame."""
        held = self.associator_stage.corrected(self.done.message(ROBOT, self.seq, self.det.frame_id))
        assert held is not None and held[0] is self.det
        t0 = time.perf_counter()
        self.completed, _ = self.associator_stage.complete(self.det.frame_id, self.det.stamp, held[1])
        self.mapper_ms[-1] += (time.perf_counter() - t0) * 1e3

    def tracker_moving(self) -> None:
        """The frame's map update: the tracklets the associator saw moving."""
        self.tracker_stage.saw_moving(self.completed.moving_tracks)

    def _take_refinement(self) -> str | None:
        """After the front end closed: its SLAM's refinement at its end into the graph, as the backend service
        takes it (the same message, through the wire). Returns why it was withheld ("" where it was taken; None:
        the front end does not refine at its end)."""
        refine = getattr(self.front, "refinement", None)
        refinement = refine() if refine is not None and self.odometry_poses is None else None
        if refinement is None:
            return None
        message = on_the_wire(refinement.message(ROBOT, self.odometry_mode, self.to_session))
        return self.backend_stage.refine(message)[1]

    def result(self, t_start: float) -> LoopResult:
        associator, front = self.associator_stage, self.front
        slam = getattr(front, "slam_trajectory", None)
        report = getattr(front, "repair_report", None)
        if (close := getattr(front, "close", None)) is not None:
            close()
        refined = getattr(front, "refined_trajectory", None) or []  # (after close: the SLAM refines at its end)
        withheld = self._take_refinement()
        graph = self.backend_stage.graph
        _, stamps, corrected = graph.measured_poses()  # (not the stand-ins of frames no front end measured)
        optimized = [(float(t), p) for t, p in zip(stamps, corrected, strict=True)]
        gt = [(s, g) for s, g in zip(self.rec.stamps, self.rec.gt, strict=True) if g is not None]
        landmarks = associator.mapper.landmarks()
        return LoopResult(
            ate_odometry=ate_rmse(gt, self.odo_traj), ate_optimized=ate_rmse(gt, optimized), landmarks=len(landmarks),
            observations=self.n_obs, observation_factors=graph.counters["observation_factors"],
            graph_landmarks=graph.num_landmarks, merges=self.n_merges, frames=len(self.rec.detections),
            wall_s=time.perf_counter() - t_start, classes=dict(Counter(lm.class_name for lm in landmarks)),
            mapper=associator.mapper, optimized=optimized, odometry=self.odo_traj,
            frontend_counters=dict(getattr(front, "counters", {})),
            ate_slam=ate_rmse(gt, slam) if slam and len(slam) >= 3 else None, slam_trajectory=list(slam or []),
            slam_refined=list(refined), ate_slam_refined=ate_rmse(gt, refined) if len(refined) >= 3 else None,
            repair_report=None if report is None else report(self.odometry_mode), refinement_withheld=withheld,
            mapper_ms_p50=float(np.median(self.mapper_ms)) if self.mapper_ms else 0.0,
            loop_closures=dict(self.backend_stage.closer.counters),
            graph_counters={**graph.counters, **associator.revisits.counters()},
            backend_ms_p50=float(np.median(self.backend_ms)) if self.backend_ms else 0.0, associator=associator)


def run_loop(
    rec: Recording,
    config: Config,
    odometry: str,
    odometry_poses: list[np.ndarray] | None = None,
    verbose: bool = False,
    depth_frames=None,
    prior_map: Path | None = None,
) -> LoopResult:  # noqa: ANN001 - a semmap Dataset
    """The pipeline's stages in lockstep order (`LockstepDriver`) over a recording. `depth_frames` (the dataset)
    feeds the backend's loop closer with keyframe depth, as the frames key does in the services; `prior_map` (a
    map.sqlite) is the map the session starts from."""
    t_start = time.perf_counter()
    driver = LockstepDriver(rec, config, odometry, odometry_poses, depth_frames, prior_map)
    for seq, det in enumerate(rec.detections, start=1):
        driver.run_frame(seq, det)
        if verbose and (det.frame_id + 1) % 100 == 0:
            print(f"  frame {det.frame_id + 1}: {len(driver.associator_stage.mapper.landmarks())} landmarks, "
                  f"{driver.n_obs} observations ({time.perf_counter() - t_start:.0f} s)", file=sys.stderr)
    return driver.result(t_start)


def closed_loop(
    data: str,
    odometry: str = "gt+drift",
    seed: int = 0,
    frames: int = 0,
    overrides: list[str] | None = None,
    cache_dir: Path = CACHE_DIR,
    refresh: bool = False,
    verbose: bool = False,
    prior_map: Path | None = None,
) -> tuple[LoopResult, Recording]:
    """Load config (defaults + overrides, as `semmap run`), detections (cached) and run the loop (from the prior
    map `prior_map`, a map.sqlite, if given)."""
    over = [*(overrides or []), f"odometry.mode={odometry}", f"odometry.seed={seed}"]
    config = load_config(None, over)
    if config.odometry.drift_profile == "auto":  # pinned to the data's platform, as `semmap run` does
        config = load_config(None, [*over, f"odometry.drift_profile={platform_of(data)}"])
    rec = detect_recording(data, frames, config, cache_dir, refresh, verbose)
    # `rgbd` poses are cached unless the front end leaves out dynamic objects: then they depend on the tracker and
    # the associator (moving tracklets) and are estimated in the loop, frame by frame, as the services do
    cached = odometry == "rgbd" and not make_frontend(odometry, config.odometry).uses_dynamic
    odo_poses = rgbd_poses(data, frames, config, cache_dir, refresh, verbose) if cached else None
    depth_frames = _open(data, config.run.start_frame)
    return run_loop(rec, config, odometry, odo_poses, verbose, depth_frames=depth_frames, prior_map=prior_map), rec


# ------------------------------------------------------------------------------------------------ tracker + mapper


@dataclass
class OfflineRun:
    """Everything a tracker + mapper run produced."""

    tracker: IouTracker
    mapper: LandmarkMapper
    steps: list[MapperStep] = field(default_factory=list)
    tracker_ms: list[float] = field(default_factory=list)
    detections: int = 0
    frames: int = 0


def run_offline(
    frames: Iterable[FrameData],
    detect: DetectFn,
    poses: dict[int, np.ndarray],
    tracker_params: TrackerParams | None = None,
    mapper_params: MapperParams | None = None,
    stride: int = 2,
) -> OfflineRun:
    """Feed every frame (its index is the frame id) through detection, the tracker stage and the mapper against
    fixed poses (no backend): for tests and benchmarks of the mapping alone."""
    mapper = LandmarkMapper(mapper_params)
    tracker = TrackerStage(tracker_params, dynamic_classes=mapper.params.dynamic_classes)
    run = OfflineRun(tracker.tracker, mapper)
    lookup = poses.get
    for frame in frames:
        dets = make_detections(frame, detect(frame), stride)
        message = Detections(ROBOT, frame.index, frame.stamp, frame.intrinsics, frame.depth_scale, dets)
        t0 = time.perf_counter()
        out = tracker.step(message)
        run.tracker_ms.append((time.perf_counter() - t0) * 1e3)
        run.steps.append(run.mapper.process(frame.index, frame.stamp, out.candidates, out.ended, lookup, out.boxes))
        run.detections += len(dets)
        run.frames += 1
    return run


@dataclass
class MapScore:
    """A map against ground-truth objects (synthetic scenes)."""

    recall: float  # static objects with exactly one or more landmark of their class nearby
    mapped: int
    static_objects: int
    duplicates: int  # extra same-class landmarks on an already mapped object
    false_landmarks: int  # landmarks on no object of their class (includes moving objects)
    on_moving: int  # unmatched landmarks of a moving object's class (a person: no static ones here)
    errors: dict[int, float]  # instance id -> centroid error of its landmark (metres)

    @property
    def median_error(self) -> float:
        return float(np.median(list(self.errors.values()))) if self.errors else float("inf")


def score_map(landmarks: Sequence, objects: Sequence[ObjectTruth], max_dist: float = 0.5) -> MapScore:
    """Match landmarks to static objects of the same class (each landmark to its nearest object within
    max(max_dist, object half-diagonal)); count duplicates, false landmarks and those of a moving class."""
    static = [o for o in objects if not o.moving]
    moving_classes = {o.class_name for o in objects if o.moving}
    assigned: dict[int, list[tuple[float, int]]] = {o.instance_id: [] for o in static}
    false_lms = on_moving = 0
    for lm in landmarks:
        c = np.asarray(lm.centroid)
        best, best_d = None, float("inf")
        for o in static:
            if o.class_name != lm.class_name:
                continue
            d = float(np.linalg.norm(c - np.asarray(o.centroid)))
            if d < best_d and d <= max(max_dist, 0.5 * float(np.linalg.norm(o.extent))):
                best, best_d = o, d
        if best is None:
            false_lms += 1
            on_moving += lm.class_name in moving_classes
            continue
        assigned[best.instance_id].append((best_d, lm.id))
    errors = {i: min(v)[0] for i, v in assigned.items() if v}
    duplicates = sum(max(0, len(v) - 1) for v in assigned.values())
    return MapScore(
        len(errors) / max(1, len(static)), len(errors), len(static), duplicates, false_lms, on_moving, errors
    )


# ------------------------------------------------------------------------------------------------ command


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m semmap.runtime.pipeline.inprocess",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("data")
    ap.add_argument("--odometry", default="gt+drift")
    ap.add_argument("--seed", type=int, default=0, help="seed of the drifting odometry")
    ap.add_argument("--seeds", default=None, help="several seeds, comma-separated (overrides --seed)")
    ap.add_argument("--frames", type=int, default=0, help="0 = all")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--cache-dir", type=Path, default=CACHE_DIR)
    ap.add_argument("--refresh-cache", action="store_true")
    ap.add_argument("--json-out", type=Path, default=None)
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="write map.json and trajectory_optimized.tum here (a subfolder per seed with --seeds)",
    )
    ap.add_argument(
        "--map",
        type=Path,
        default=None,
        metavar="PRIOR",
        help="start from a saved map (a run directory or its map.sqlite): relocalise against it (docs/MAPS.md)",
    )
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)

    prior_map = None if args.map is None else args.map / "map.sqlite" if args.map.is_dir() else args.map
    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else [args.seed]
    rows = []
    for seed in seeds:
        try:
            res, rec = closed_loop(
                args.data,
                args.odometry,
                seed,
                args.frames,
                args.overrides,
                args.cache_dir,
                args.refresh_cache,
                args.verbose,
                prior_map,
            )
        except (ValueError, MessageError) as exc:  # (MessageError: a prior map of another version)
            print(f"error: {f'--map {args.map}: ' if args.map else ''}{exc}", file=sys.stderr)
            return 2
        if args.out is not None:
            res.write_outputs(args.out / f"seed{seed}" if args.seeds else args.out)
        row = {"data": args.data, "odometry": args.odometry, "seed": seed, **res.summary()}
        if res.associator is not None and res.associator.prior is not None:
            row["relocalised_at_frame"] = res.associator.prior.aligned_at
        if rec.objects:
            score = score_map(res.mapper.landmarks(), rec.objects)
            row.update(
                recall=score.recall,
                duplicates=score.duplicates,
                false_landmarks=score.false_landmarks,
                on_moving=score.on_moving,
                median_centroid_error_m=score.median_error,
            )
        rows.append(row)
        extra = ""
        if "on_moving" in row:
            extra = (
                f"  recall {row['recall']:.2f} dup {row['duplicates']} false {row['false_landmarks']} "
                f"on_moving {row['on_moving']}"
            )
        slam = "" if res.ate_slam is None else f"SLAM alone {res.ate_slam:.4f} m, " + (
            "" if res.ate_slam_refined is None else f"refined at its end {res.ate_slam_refined:.4f} m "
            f"({'taken' if not res.refinement_withheld else 'not taken: ' + res.refinement_withheld}), ")
        print(
            f"{args.odometry:9s} seed {seed}: {slam}ATE odometry {res.ate_odometry:.4f} m, optimised "
            f"{res.ate_optimized:.4f} m ({res.improvement_pct:+.1f} %), landmarks {res.landmarks}, observations "
            f"{res.observations} ({res.observation_factors} factors, {res.graph_landmarks} in graph), merges "
            f"{res.merges}, loop closures {res.loop_closures.get('accepted', 0)}/"
            f"{res.loop_closures.get('registered', 0)}, revisits {res.graph_counters.get('revisits', 0)} "
            f"({res.graph_counters.get('revisit_fused_landmarks', 0)} landmarks), {res.wall_s:.0f} s{extra}",
            flush=True,
        )
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
