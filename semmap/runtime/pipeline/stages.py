"""The per-frame pipeline as plain stage objects: tracker, associator and backend, free of I/O.

Each stage holds its algorithm and the per-frame policy around it; two drivers run them:
- the services (semmap/services/*/service.py): thin bus adapters (decode a message, call the stage, publish what
  it returns), with what only a bus needs (re-ordering, duplicates, journals, restarts: once, in
  semmap/runtime/transport/stage_service.py; metrics, logs);
- the in-process driver (semmap/runtime/pipeline/inprocess.py): the same stages in one process without a bus, in the
  order of a lockstep `semmap run`, so both give the same map and trajectory (tests/pipeline/test_closed_loop.py).

Lockstep order of one frame i: odometry(i) -> `TrackerStage.step` -> `AssociatorStage.process` (against the pose
book) -> `AssociatorStage.prior_step` (a prior map's relocalisation and statuses, if any) ->
`AssociatorStage.observations` (with the merges held back from the previous refine) ->
`BackendStage.step` (odometry and observations into the graph, one iSAM2 update, a loop closure from a keyframe,
the corrections delta) -> `AssociatorStage.corrected` -> `AssociatorStage.complete` (refine when due).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from semmap.algorithms.associator.mapper import LandmarkMapper, MapperParams, MapperStep
from semmap.algorithms.associator.pose_book import PoseBook
from semmap.algorithms.associator.prior_map import PriorParams, PriorSession
from semmap.algorithms.associator.revisit import Revisit, RevisitFinder
from semmap.algorithms.backend.corrections import CorrectionDelta, CorrectionPublisher, CorrectionsParams
from semmap.algorithms.backend.loop_closure import KeyframeCloud, LoopCloser, LoopClosure, LoopClosureParams
from semmap.algorithms.backend.pose_graph import BackendParams, PoseGraph
from semmap.algorithms.backend.prior_alignment import PriorAlignment
from semmap.algorithms.detector.onnx_detector import DetectedBox, depth_gate
from semmap.algorithms.relocalize import RelocResult
from semmap.algorithms.tracker.iou_tracker import (
    IouTracker,
    TrackerOutput,
    TrackerParams,
    depth_range,
    held_dynamic_box,
)
from semmap.core.messages import (
    CorrectedPoses,
    DepthPatch,
    Detection,
    Detections,
    DynamicBox,
    Frame,
    GroundTruthInstance,
    Landmark,
    MapAlignment,
    MessageError,
    Observations,
    OdometryPose,
    OdometryRefinement,
    PngImage,
)
from semmap.datasets.base import FrameData
from semmap.runtime.maps.map_store import MapStore
from semmap.runtime.maps.prior_keyframes import PriorKeyframes, load_prior_keyframes


def combined(a: MapperStep, b: MapperStep) -> MapperStep:
    """Two steps of one frame as one: later landmark states win, removals stay removed."""
    removed = list(dict.fromkeys(a.removed + b.removed))
    updated = {lm.id: lm for lm in a.updated + b.updated if lm.id not in removed}
    timing = {k: a.timing_ms.get(k, 0.0) + b.timing_ms.get(k, 0.0) for k in a.timing_ms.keys() | b.timing_ms.keys()}
    return MapperStep(
        updated=list(updated.values()),
        removed=removed,
        merges=a.merges + b.merges,
        observations=a.observations + b.observations,
        rejected=a.rejected + b.rejected,
        moving_tracks=a.moving_tracks + b.moving_tracks,
        moved=a.moved + b.moved,
        moved_why={**a.moved_why, **b.moved_why},
        kept_despite_motion=a.kept_despite_motion + b.kept_despite_motion,
        timing_ms=timing,
    )


# ------------------------------------------------------------------------------------------------ player, detector


def frame_message(robot: str, data: FrameData, depth_png: bool = False) -> Frame:
    """A dataset frame as a bus message. A JPEG colour file and a 16-bit PNG depth file of the camera's size travel
    as the dataset stores them (no decode and re-encode: ~6.5 ms less a frame for the player, and 140 KB instead
    of 690 KB for each subscriber on 7-Scenes); other images are encoded here (colour as JPEG; depth raw, or as a
    16-bit PNG with `depth_png`: ~3.5x smaller, ~10 ms more, for slow links)."""
    size = (data.intrinsics.width, data.intrinsics.height)
    rgb_file, depth_file = data.rgb_file, data.depth_file
    rgb = rgb_file.data if rgb_file is not None and rgb_file.fmt == "jpeg" and rgb_file.size == size else data.rgb
    as_png = depth_file is not None and depth_file.fmt == "png16" and depth_file.size == size
    frame = Frame.from_arrays(robot, data.index, data.stamp, rgb, PngImage(depth_file.data) if as_png else data.depth,
                              data.depth_scale, data.intrinsics, data.gt_pose,
                              [GroundTruthInstance(i.instance_id, i.class_name, tuple(i.box), i.visible_pixels,
                                                   i.moving) for i in data.instances])
    if depth_png and not as_png:
        frame.depth_as_png()
    return frame


def depth_detections(
    boxes: Iterable[DetectedBox],
    depth: np.ndarray,
    depth_scale: float,
    stride: int = 2,
    depth_min_m: float = 0.2,
    depth_max_m: float = 25.0,
) -> list[Detection]:
    """A frame's detections as the detector sends them: each box with the median depth of its central half
    (boxes without valid depth in range are dropped) and the strided depth patch under it."""
    out = []
    for b, d in depth_gate(boxes, depth, depth_scale, depth_min_m, depth_max_m):
        box = (b.x1, b.y1, b.x2, b.y2)
        out.append(Detection(box, b.class_name, float(b.score), float(d), DepthPatch.from_depth(depth, box, stride)))
    return out


# ------------------------------------------------------------------------------------------------ tracker


class TrackerStage:
    """IOU tracklets from one frame's detections. A skipped frame (not detected: stride, overload) only ages the
    tracklets, which may end them: the associator must hear of it; a frame with no stamp ages nothing.

    Also the frame's dynamic objects (`dynamic_objects`, for a front end that leaves them out of its depth): the
    boxes of tracklets of a dynamic class and of tracklets the associator saw moving (`saw_moving`), and the last
    box of such a tracklet still alive but not detected in this frame (a skipped frame, or a person the detector
    missed once: their depth would otherwise pull the odometry; Bonn crowd rgbd 0.153 -> 0.133 m ATE), grown by
    how far the object may have walked since it was detected (`held_dynamic_box`)."""

    def __init__(
        self, params: TrackerParams | None = None, first_track_id: int = 0, dynamic_classes: Iterable[str] = ()
    ) -> None:
        self.dynamic_classes = frozenset(dynamic_classes)
        self.tracker = IouTracker(params, first_track_id=first_track_id, dynamic_classes=self.dynamic_classes)
        self.moving: set[int] = set()  # track ids the associator rejected as moving
        # per dynamic tracklet alive, its last detected box and the stamp of the frame that detected it
        self.last_dynamic: dict[int, tuple[DynamicBox, float | None]] = {}

    @property
    def params(self) -> TrackerParams:
        return self.tracker.params

    def step(self, det: Detections) -> TrackerOutput:
        if det.skipped:
            return TrackerOutput(ended=self.tracker.skip(det.frame_id, det.stamp).ended if det.stamp >= 0 else [])
        return self.tracker.update(det.frame_id, det.stamp, det.detections, det.intrinsics, det.depth_scale)

    def saw_moving(self, track_ids: Iterable[int]) -> None:
        """Tracklets the associator rejected as moving (its map updates' `moving_tracks`)."""
        self.moving.update(track_ids)

    def dynamic_objects(self, det: Detections, out: TrackerOutput) -> list[DynamicBox]:
        """This frame's dynamic objects, after `step(det)` gave `out`: the detected ones, then the remembered
        boxes of dynamic tracklets still alive that this frame did not detect (by track id)."""
        alive = self.tracker.active_ids()
        boxes: list[DynamicBox] = []
        if not det.skipped:
            band = self.params.dynamic_depth_band_m
            for tb, d in zip(out.boxes, det.detections, strict=True):  # (one tracked box per detection, in order)
                reason = "class" if tb.class_name in self.dynamic_classes else (
                    "moving" if tb.track_id in self.moving else "")
                if reason:
                    lo, hi = depth_range(d, det.depth_scale, band)
                    boxes.append(DynamicBox(tb.track_id, tb.class_name, tb.box, lo, hi, reason))
        kept: dict[int, tuple[DynamicBox, float | None]] = {b.track_id: (b, det.stamp) for b in boxes}
        for t, (b, detected_at) in sorted(self.last_dynamic.items()):
            if t in alive and t not in kept:
                detected_at = det.stamp if detected_at is None else detected_at  # (a state saved without stamps)
                # (never longer than a tracklet lives undetected: a restored stamp cannot inflate it further)
                elapsed = min(det.stamp - detected_at, self.params.max_age_s)
                boxes.append(held_dynamic_box(b, elapsed, self.params.dynamic_hold_speed_mps, det.intrinsics))
                kept[t] = (b, detected_at)  # (grown from the box as detected each frame, not from the last grown one)
        self.last_dynamic = kept
        self.moving &= alive  # forget ended tracklets
        return boxes

    def state(self) -> dict:
        """The tracker's state plus what the dynamic objects depend on (plain data, msgpack-able)."""
        return {**self.tracker.state(), "moving": sorted(self.moving),
                "last_dynamic": [b.to_dict() for _, (b, _) in sorted(self.last_dynamic.items())],
                "last_dynamic_stamp": [[t, s] for t, (_, s) in sorted(self.last_dynamic.items()) if s is not None]}

    def restore(self, state: dict) -> None:
        """Continue from `state()` (a MessageError if it is not one; older states without the dynamic part
        restore the tracker alone)."""
        self.tracker = IouTracker.from_state(state, self.params, self.dynamic_classes)
        try:
            self.moving = {int(t) for t in state.get("moving", [])}
            detected_at = {int(t): float(s) for t, s in state.get("last_dynamic_stamp", [])}
            # (a state saved before the stamps were kept: its boxes are held as they are, grown from the next frame)
            self.last_dynamic = {b.track_id: (b, detected_at.get(b.track_id))
                                 for b in map(DynamicBox.from_dict, state.get("last_dynamic", []))}
        except (TypeError, ValueError) as exc:
            raise MessageError(f"not a tracker state: {exc}") from None


# ------------------------------------------------------------------------------------------------ associator


class AssociatorStage:
    """The landmark mapper against the pose book, with the associator's per-frame policy.

    - `process` associates a frame's candidates against the best known poses (the backend's corrected poses
      where it has them, odometry moved by the newest correction otherwise).
    - `observations` are what goes to the backend: the frame's landmark observations and merges, plus the
      merges a refine found after the previous frame's observations had left (they are carried over).
    - With `await_backend` (lockstep) a frame is held (`hold`) until the backend's corrected poses for it come
      (`corrected` hands it back), and only then refined (`complete`), so a replay gives the same map.
    - Refinement runs every `refine_every_n_frames` frames once there are landmarks.
    - A session started from a prior map (`load_prior`, docs/MAPS.md) maps in a provisional frame (its own
      odometry) until `prior_step` relocalises it against the prior's landmarks; from then on it maps in the
      prior's frame, the prior landmarks join the map, each with a status (seen again, missing), and the
      alignment goes to the backend with that frame's observations. Here, not in the service, so that the
      in-process driver runs prior maps as the services do.
    """

    def __init__(
        self,
        params: MapperParams | None = None,
        refine_every_n_frames: int = 10,
        await_backend: bool = True,
        mapper: LandmarkMapper | None = None,
        poses: PoseBook | None = None,
    ) -> None:
        self.mapper = mapper if mapper is not None else LandmarkMapper(params)
        self.poses = poses if poses is not None else PoseBook()
        self.refine_every = max(1, int(refine_every_n_frames))
        self.await_backend = await_backend
        self.pending_merges: list[tuple[int, int]] = []  # found by a refine after the frame's observations left
        self.awaiting: tuple[object, MapperStep] | None = None  # (the frame's input, its step) held for the backend
        self.prior: PriorSession | None = None  # the prior map this session relocalises against (`load_prior`)
        self.session_start: float | None = None  # the earliest stamp of this session (prior landmarks age from it)
        self.alignment: MapAlignment | None = None  # to go out with the current frame's observations
        self.revisits = RevisitFinder(self.mapper.params)  # places seen again after drift (revisit.py)
        self.last_revisit: Revisit | None = None  # the revisit the last `process` found (for the service's log)

    # -- a prior map
    def load_prior(self, path: Path, params: PriorParams | None = None) -> PriorSession:
        """Start from the map saved in `path` (a map.sqlite): its landmarks join the map once this session has
        relocalised against them; this session's new landmarks get ids after the prior's. ValueError when the
        file holds no map, MessageError (MapVersionError) when it holds one of another version."""
        state = MapStore.open_existing(path).load()
        if state is None:
            raise ValueError(f"the prior map {path} holds no map")
        prior = LandmarkMapper.from_state(state, self.mapper.params).map
        self.prior = PriorSession(prior, params)
        self.mapper.map.next_id = max(self.mapper.map.next_id, prior.next_id)
        return self.prior

    def saw_stamp(self, stamp: float) -> None:
        """A frame of this session arrived: the session starts at the earliest stamp seen."""
        if self.session_start is None or stamp < self.session_start:
            self.session_start = stamp

    def prior_step(self, frame_id: int, stamp: float, boxes: list | None, step: MapperStep) -> PriorFrame:
        """After `process`: relocalise against the prior map when due, then update the statuses of the prior
        landmarks (seen again, missing; `boxes` None: a skipped frame, no absence evidence). Without a prior map
        the step is returned as it is."""
        if self.prior is None:
            return PriorFrame(step)
        seen = [lm.id for lm in step.updated]
        frame = PriorFrame(step)
        if self.prior.due(frame_id):
            t0 = time.perf_counter()
            fit = self.prior.try_relocalize(self.mapper)
            frame.relocalize_ms = (time.perf_counter() - t0) * 1e3
            if fit is not None:
                self.poses.align(fit.transform, frame_id)
                adopted, self.alignment = self.prior.adopt(self.mapper, fit, frame_id,
                                                           self.session_start or stamp, self.poses)
                frame.step, frame.relocalised = combined(frame.step, adopted), fit
        changed = self.prior.update(self.mapper, frame_id, self.poses(frame_id), boxes, self.mapper._intrinsics,
                                    seen)
        if changed:
            ids = set(changed)
            frame.step.updated = [m for m in frame.step.updated if m.id not in ids] + [
                self.mapper.map[i].to_message() for i in sorted(ids) if i in self.mapper.map]
            frame.statuses_changed = True
        return frame

    def prior_counters(self) -> dict[str, int]:
        """The prior map's counters for stats.json (none without one)."""
        if self.prior is None:
            return {}
        status = self.prior.status.values()
        return {"prior_landmarks": len(self.prior.prior), "relocalize_attempts": self.prior.attempts,
                "prior_missing": sum(v == "missing" for v in status),
                "prior_seen_again": sum(v == "present" for v in status)}

    def relocalisation_record(self) -> dict[str, Any] | None:
        """The relocalisation's fit, for relocalization.json (None before it, or after a restart: the fit itself
        is not part of the saved state, only its transform)."""
        if self.prior is None or self.prior.fit is None:
            return None
        fit = self.prior.fit
        return {"frame_id": self.prior.aligned_at, "inliers": fit.inliers, "runner_up": fit.runner_up,
                "rms_m": fit.rms_m, "rotation_sigma_deg": fit.rotation_sigma_deg, "refined_on_clouds": fit.refined,
                "matches": [list(m) for m in fit.matches],
                "transform": [float(v) for v in fit.transform.reshape(16)], "attempts": self.prior.attempts}

    def landmarks(self) -> list[Landmark]:
        """The map as published and saved: with each prior landmark's status when a prior map is loaded."""
        return self.with_status(self.mapper.landmarks())

    def with_status(self, landmarks: list[Landmark]) -> list[Landmark]:
        return landmarks if self.prior is None else self.prior.with_status(landmarks)

    # -- inputs
    def odometry(self, frame_id: int, pose: np.ndarray) -> None:
        self.poses.odometry[frame_id] = pose

    def pose_known_or_lost(self, frame_id: int, lockstep: bool) -> bool:
        """Lockstep: wait for the frame's pose. Real time: a later pose means this one was dropped upstream;
        go on (the mapper keeps measurements without a pose for a while, then drops them)."""
        if frame_id in self.poses.odometry:
            return True
        return not lockstep and bool(self.poses.odometry) and max(self.poses.odometry) > frame_id

    # -- per frame
    def process(
        self, frame_id: int, stamp: float, candidates: list, ended: list[int], boxes: list | None
    ) -> MapperStep:
        """The mapper's step for one frame (`boxes` None: a skipped frame, no absence evidence), then, when due, the
        search for a revisit: a place seen again after drift, whose recent landmarks are fused into the old ones
        (the merges go to the backend with this frame's observations and close the loop there)."""
        step = self.mapper.process(frame_id, stamp, candidates, ended, self.poses, boxes=boxes)
        self.last_revisit = None
        if self.revisits.due(stamp):
            t0 = time.perf_counter()
            found = self.revisits.search(self.mapper.map.all(), stamp)
            step.timing_ms["revisit"] = (time.perf_counter() - t0) * 1e3
            if found is not None:
                for recent, old in found.pairs:
                    if recent in self.mapper.map and old in self.mapper.map and recent != old:
                        self.mapper.fuse(old, recent, step)
                        self.revisits.fused += 1
                self.last_revisit = found
        return step

    def take_merges(self, step: MapperStep) -> list[tuple[int, int]]:
        """The merges to send with this frame's observations: the carried-over ones first."""
        merges = self.pending_merges + list(step.merges)
        self.pending_merges = []
        return merges

    def observations(self, robot: str, frame_id: int, stamp: float, step: MapperStep) -> Observations:
        """What goes to the backend for this frame: its landmark observations, the merges (carried-over ones
        first), the landmarks retired as moved and, on the frame that relocalised, the prior-map alignment."""
        message = Observations(robot, frame_id, stamp, step.observations, self.take_merges(step),
                               alignment=self.alignment, retired=list(step.moved))
        self.alignment = None
        return message

    def hold(self, frame: object, step: MapperStep) -> bool:
        """After the observations left: hold the frame for the backend's answer (True) or complete it now."""
        if not self.await_backend:
            return False
        self.awaiting = (frame, step)
        return True

    def corrected(self, msg: CorrectedPoses) -> tuple[object, MapperStep] | None:
        """Apply the backend's corrected poses; returns the held frame (and its step) they answer, if any."""
        self.poses.set_corrected(msg)
        if self.awaiting is not None and msg.frame_id >= self.frame_of(self.awaiting[0]):
            held, self.awaiting = self.awaiting, None
            return held
        return None

    @staticmethod
    def frame_of(frame: object) -> int:
        return int(frame.frame_id)  # type: ignore[attr-defined]

    def refine_due(self, frame_id: int) -> bool:
        return frame_id % self.refine_every == 0 and len(self.mapper.landmarks()) > 0

    def complete(self, frame_id: int, stamp: float, step: MapperStep) -> tuple[MapperStep, float]:
        """After the backend's answer (lockstep): refine when due; returns the frame's whole step and the refine's
        time (ms, 0 when none ran). The refine's merges go out with the next frame's observations."""
        if not (self.await_backend and self.refine_due(frame_id)):
            return step, 0.0
        t0 = time.perf_counter()
        refined = self.mapper.refine(self.poses, stamp)
        refine_ms = (time.perf_counter() - t0) * 1e3
        self.pending_merges += list(refined.merges)
        return combined(step, refined), refine_ms

    # -- persistence
    def to_state(self) -> dict[str, Any]:
        """Everything a restarted associator needs to go on exactly as this one would (saved between frames, when
        none is held): the mapper, the pose book and the merges a refine found that still have to go out with
        the next frame's observations (lost, the backend would never join the two landmarks)."""
        return {**self.mapper.to_state(), "poses": self.poses.to_state(), "revisits": self.revisits.to_state(),
                "pending_merges": [[int(a), int(b)] for a, b in self.pending_merges],
                "session_start": self.session_start, "prior": None if self.prior is None else self.prior.to_state()}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from `to_state()` output (read back from the map store; a prior map, if any, is loaded
        first: its relocalisation and statuses are restored here)."""
        self.mapper = LandmarkMapper.from_state(state, self.mapper.params)
        self.revisits.restore(state.get("revisits"))
        self.poses = PoseBook.from_state(state.get("poses"))
        self.pending_merges = [(int(a), int(b)) for a, b in state.get("pending_merges") or []]
        self.awaiting = None
        if state.get("session_start") is not None:
            self.session_start = float(state["session_start"])
        if self.prior is not None:
            self.prior.restore(state.get("prior"))

    def refine_only(self) -> MapperStep:
        """Real time: a refine on a correction, outside any frame."""
        refined = self.mapper.refine(self.poses)
        self.pending_merges += list(refined.merges)
        return refined


@dataclass
class PriorFrame:
    """What `AssociatorStage.prior_step` did to one frame's step."""

    step: MapperStep
    relocalize_ms: float | None = None  # None: no relocalisation was due
    relocalised: RelocResult | None = None  # the fit, on the frame that relocalised
    statuses_changed: bool = False  # a prior landmark was seen again or went missing


# ------------------------------------------------------------------------------------------------ backend


@dataclass
class BackendStep:
    """What one frame did in the backend."""

    delta: CorrectionDelta
    update_ms: float
    closure: LoopClosure | None = None
    loop_closure_ms: float | None = None  # None: no keyframe cloud this frame
    realigned: bool = False  # the graph moved into a prior map's frame on this frame
    timing_ms: dict[str, float] = field(default_factory=dict)

    def message(self, robot: str, seq: int, frame_id: int, timing_ms: dict[str, float] | None = None) -> CorrectedPoses:
        return CorrectedPoses(
            robot,
            seq,
            frame_id,
            *self.delta.arrays(),
            self.timing_ms if timing_ms is None else timing_ms,
            full=self.delta.full,
            num_frames=self.delta.num_frames,
        )


REFINEMENT_MIN_CLOSURES = 3  # loop closures that must judge a front end's refinement at its end (`refine`)
REFINEMENT_MAX_T = 2.0  # ...and how much worse they may say it is (standard errors) before it is withheld


class BackendStage:
    """The pose graph with the backend's per-frame policy: a frame's odometry and observations (a frame that
    carries a prior-map alignment first moves the graph into the prior map's frame), one iSAM2 update, a loop
    closure search from a keyframe's cloud, then the delta of corrected poses to send."""

    def __init__(
        self,
        backend: BackendParams | None = None,
        loop_closure: LoopClosureParams | None = None,
        corrections: CorrectionsParams | None = None,
        expect_alignment: bool = False,
    ) -> None:
        self.graph = PoseGraph(backend or BackendParams())
        # a session that relocalises against a prior map (docs/MAPS.md); only such a session keeps its frames
        self.aligner = PriorAlignment(expected=expect_alignment)
        self.closer = LoopCloser(loop_closure)
        self.corrections = CorrectionPublisher(corrections or CorrectionsParams())

    def wants_cloud(self, frame_id: int) -> bool:
        return self.closer.wants(frame_id)

    def load_prior_keyframes(self, map_db: Path) -> PriorKeyframes:
        """The keyframes of the prior map's run (beside `map_db`), for this session's keyframes to register to
        once it has relocalised; returns what was read (and skipped) for the caller to report."""
        prior = load_prior_keyframes(map_db, self.closer.params.max_keyframes)
        self.closer.set_prior(prior.keyframes)
        return prior

    def add(self, pose: OdometryPose, obs: Observations) -> bool:
        """One frame into the graph (no update); True when its alignment moved the graph into the prior's frame."""
        realigned = False
        # (a backend not started for a prior map kept no frames to rebuild from: the service counts and logs it)
        if obs.alignment is not None and self.aligner.alignment is None and self.aligner.expected:
            self.graph = self.aligner.realign(self.graph, obs.alignment, obs.frame_id)
            realigned = True
        self.aligner.add(self.graph, pose, obs)
        return realigned

    def step(self, pose: OdometryPose, obs: Observations, cloud: KeyframeCloud | None) -> BackendStep:
        t0 = time.perf_counter()
        realigned = self.add(pose, obs)
        self.graph.update()
        update_ms = (time.perf_counter() - t0) * 1e3
        timing = {"update": update_ms}
        closure, closure_ms = None, None
        if cloud is not None:
            t0 = time.perf_counter()
            # once in the prior map's frame, the map's keyframes are registration targets too
            closure = self.closer.close(self.graph, cloud, against_prior=self.aligner.alignment is not None)
            closure_ms = (time.perf_counter() - t0) * 1e3
            timing["loop_closure"] = closure_ms
        t0 = time.perf_counter()
        delta = self.corrections.next(self.graph)
        timing["publish"] = (time.perf_counter() - t0) * 1e3
        return BackendStep(delta, update_ms, closure, closure_ms, realigned, timing)

    def refine(self, refinement: OdometryRefinement, updates: int = 3) -> tuple[int, str]:
        """The front end's refinement at its end (OdometryRefinement) into the graph unless semmap's own evidence
        is against it, optimised again (a few iSAM2 steps: every odometry factor may have changed at once, and one
        step is one linearisation). Returns the frames that took their refined pose, and why none did.

        The evidence: the loop closures, keyframes registered by semmap, which neither the tracked nor the refined
        odometry was fitted to. Each scores both (its squared whitened error); the refinement is withheld where the
        paired differences say it is worse by `REFINEMENT_MAX_T` standard errors, or where fewer than
        `REFINEMENT_MIN_CLOSURES` can say anything. Why a veto, not a vote: a closure's own error is larger than the
        difference between the two (7-Scenes: both about 30 a closure, 2 % apart either way), and the refinement
        is the SLAM's final word; why at all: ORB-SLAM3's local bundle adjustments do not always improve a short,
        fast-turning recording (the fr1_rpy window: refined 0.023-0.050 m, tracked 0.025-0.029 m)."""
        if refinement.withheld:
            return 0, refinement.withheld
        now, refined = self.graph.closure_agreement(refinement.frame_ids, refinement.poses)
        if len(now) < REFINEMENT_MIN_CLOSURES:
            return 0, f"{len(now)} loop closure(s) to judge it by (at least {REFINEMENT_MIN_CLOSURES} are needed)"
        worse = refined - now
        t = float(worse.mean() / max(worse.std(ddof=1) / math.sqrt(len(worse)), 1e-12))
        if t > REFINEMENT_MAX_T:
            return 0, f"the {len(now)} loop closures say it is worse (t = {t:.1f})"
        taken = self.graph.refine_odometry(refinement.frame_ids, refinement.poses)
        for _ in range(updates if taken else 0):
            self.graph.update()
        return taken, ""

    def restore(self, pose: OdometryPose, obs: Observations, keyframe: tuple | None) -> BackendStep:
        """A journalled frame again (after a crash): the same graph steps as `step` (the journalled closure
        instead of an ICP search), and the same corrections delta, which went out before the crash and is not
        sent again. Why the delta: the publisher remembers what it sent (the pose last sent per frame, the
        rolling refresh's cursor); a fresh one would make the next message full, and consumers would take
        poses the uninterrupted run never sent them (up to the tolerance off), so the associator's map drifted
        from the clean run's by up to a millimetre after a backend restart."""
        realigned = self.add(pose, obs)
        self.graph.update()
        closure = None
        if keyframe is not None:
            self.closer.restore(self.graph, *keyframe)
            closure = keyframe[1]
        delta = self.corrections.next(self.graph)
        return BackendStep(delta, 0.0, closure, None, realigned)
