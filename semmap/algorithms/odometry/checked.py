"""semmap's check of a SLAM's poses, frame by frame: the one place the pieces of the repair meet.

- motion.py says whether an object in view is seen moving: only then (and `hold_s` after) is the SLAM's step
  doubted at all;
- registration.py measures the step itself, with the dynamic objects left out, only where that is asked: inside
  the scope, where the SLAM has no pose, and on every `witness_every`-th frame where the SLAM's precision is being
  measured (a registration costs 40-100 ms; a static scene needs none);
- arbiter.py judges a disagreement on the static scene's evidence over the last few frames (and, in real time
  while the front end is behind the video, where asked, measures every n-th step over the n frames since the last);
- repair.py decides the step and chains the output.

The `file:`, `external` and `orbslam3` front ends each hand it their SLAM's pose of every frame.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .arbiter import StepArbiter, Verdict
from .base import OdometryError, OdometryInput
from .motion import MotionParams, MovingObjects
from .registration import PairRegistration
from .repair import RepairParams, SlamRepair

# what a SLAM says of a frame: its camera-to-world pose (None: none), whether it calls that pose weak, and whether a
# pose after a gap is in the map it left (None: it does not say)
SlamReading = tuple[np.ndarray | None, bool, bool | None]
POSES_KEPT = 128  # frames whose poses place dynamic objects that come late (real time: the tracker lags)


class CheckedSlam:
    """`pose(frame, slam_pose)` -> the repaired camera-to-world pose (see module docstring). With `check` off the
    SLAM's poses are copied (frames it has none for carried at constant velocity) and no image is looked at."""

    def __init__(self, params: RepairParams | None = None, dynamic_mask: str = "box", check: bool = True,
                 motion: MotionParams | None = None, measured_sigmas_after: int = 0) -> None:
        self.params = params or RepairParams()
        self.repair = SlamRepair(self.params, measured_sigmas_after=measured_sigmas_after if check else 0)
        self.registration = PairRegistration(dynamic_mask, self.params.registration_scale) if check else None
        self.arbiter = StepArbiter(self.params.arbiter, self.params.behind_check_every) if check else None
        self.moving = MovingObjects(motion)
        self.registrations = 0  # pairs registered (the rest were only remembered)
        self.skipped_behind = 0  # real time: checks left out while the front end was behind the video
        self.checked_behind = 0  # ... and the steps checked meanwhile (`_measure_over`)
        self._behind_run = 0  # frames in a row that wanted a check while the front end was behind
        self._by_depth = False  # this frame's judgement leaves people out by their depth band (`_measure_over`)
        self.sparse_steps = 0  # steps measured on the static matches where the dense registration was not trusted
        self.dynamic_unplaced = 0  # real time: frames' dynamic objects the motion test could not place (no pose kept)
        self._frames = 0
        self._tracker: ThreadPoolExecutor | None = None  # the SLAM's tracking beside semmap's registration
        self._poses: OrderedDict[int, np.ndarray] = OrderedDict()  # recent frames' repaired poses (`dynamic_seen`)

    @property
    def checks(self) -> bool:
        return self.registration is not None

    def pose(self, frame: OdometryInput, slam_pose: np.ndarray | None = None, slam_weak: bool = False,
             same_map: bool | None = None, track: Callable[[], SlamReading] | None = None) -> np.ndarray:
        """The repaired pose of `frame` given the SLAM's (`slam_pose`, `slam_weak`: its own word that the pose is
        weak, `same_map`: whether a pose after a gap is in the map it left). Or `track`: the SLAM's tracking of
        the frame, called in a second thread while semmap registers the frame pair, so a frame costs the longer
        of the two, not their sum (ORB-SLAM3 and a registration take about as long)."""
        if self.registration is None or self.arbiter is None:
            if track is not None:
                slam_pose, slam_weak, same_map = track()
            return self.repair.copy(frame.frame_id, slam_pose)
        if frame.rgb is None or frame.depth is None or frame.intrinsics is None:
            raise OdometryError("checking a SLAM's steps needs RGB, depth and intrinsics")
        boxes = list(frame.dynamic or [])
        moving = self.moving.moving(boxes)
        undecided = self.moving.undecided(boxes)
        self._frames += 1
        wanted = (self.repair.in_scope(moving, frame.stamp, undecided)
                  or (self.repair.measured_sigmas and self._frames % max(1, self.params.witness_every) == 0))
        skipped = wanted and frame.behind
        over = 0  # real time, behind: this frame's check spans this many frames (`_measure_over`)
        if skipped:  # (real time, frames queued up: the SLAM's step, unchecked, and counted; every n-th checked)
            wanted = False
            self._behind_run += 1
            every = self.params.behind_check_every
            if every > 0 and self._behind_run >= every:
                over, skipped, self._behind_run = every, False, 0
            else:
                self.skipped_behind += 1
        else:
            self._behind_run = 0
        tracking = None
        if track is not None:
            if self._tracker is None:
                self._tracker = ThreadPoolExecutor(1, thread_name_prefix="slam-track")
            tracking = self._tracker.submit(track)
        self.arbiter.push(frame.frame_id, frame.rgb, frame.depth, frame.depth_scale, frame.intrinsics, boxes)
        step, fitness, fitted = self._measure(frame) if wanted else (None, 0.0, False)
        self._by_depth = frame.behind  # (real time: the boxes lag their frames; the wall behind a person stays)
        if over:
            step, fitness, fitted = self._measure_over(over)
            skipped = step is None  # (no fit: unchecked, as any step while behind; not the motion model's to judge)
        if tracking is not None:
            slam_pose, slam_weak, same_map = tracking.result()
        if not wanted:
            if slam_pose is None and not frame.behind:  # (no SLAM pose: semmap's registration carries the frame)
                step, fitness, fitted = self._measure(frame)
            else:
                self.registration.remember(frame)
        # behind: nothing judged either (the static scene's ORB matches cost a frame's time: Bonn crowd in real
        # time judged 270 of 377 frames it had no time to check, and dropped 99 frames)
        pose = self.repair.update(frame.frame_id, slam_pose, step, fitness, moving, float(frame.stamp),
                                  judge=None if skipped else self._judge, slam_weak=slam_weak, undecided=undecided,
                                  same_map=same_map, fitted_to_scene=fitted, unchecked=skipped,
                                  judge_rejoin=self._judge)
        if self.repair.anchor_frame == frame.frame_id:  # (where the output last took the SLAM's step: kept)
            self.arbiter.pin(frame.frame_id)
        if self.repair.slam_last_frame == frame.frame_id:  # (the SLAM's last pose: where a gap would start)
            self.arbiter.pin(frame.frame_id, "gap")
        self._poses[frame.frame_id] = pose
        while len(self._poses) > POSES_KEPT:
            self._poses.popitem(last=False)
        k = np.asarray(frame.intrinsics, float)
        seen = [(frame.frame_id, float(frame.stamp), boxes)] if frame.dynamic_seen is None else frame.dynamic_seen
        for frame_id, stamp, seen_boxes in seen:  # (each at its own frame's pose: a box placed by a later pose is
            at = self._poses.get(frame_id)        # off by the camera's motion in between)
            if at is None:  # (a frame the front end never posed, or posed too long ago: counted)
                self.dynamic_unplaced += 1
                continue
            self.moving.observe(stamp, seen_boxes, at, k[0, 0], k[1, 1], k[0, 2], k[1, 2],
                                frame.depth.shape[1], frame.depth.shape[0])
        return pose

    def _measure(self, frame: OdometryInput) -> tuple[np.ndarray | None, float, bool]:
        """semmap's step to this frame, its fitness and whether it was fitted to the static scene's matches: the
        dense registration, or where too few pixels are left to trust it (or with the `sparse` witness: always),
        the step fitted to the static scene's ORB matches (`StepArbiter.sparse_step`) if enough of them agree on it
        (it then counts as a registration at the bar: `min_fitness`)."""
        assert self.registration is not None and self.arbiter is not None
        self.registrations += 1
        if self.params.witness == "sparse":
            self.registration.remember(frame)
            step, fitness = None, 0.0
        else:
            step, fitness = self.registration.register(frame)
        if step is not None and fitness >= self.params.min_fitness:
            return step, fitness, False
        sparse, inliers = self.arbiter.sparse_step()
        if sparse is None or inliers < self.params.arbiter.sparse_min_inliers:
            return step, fitness, False
        self.sparse_steps += 1
        return sparse, self.params.min_fitness, True

    def _measure_over(self, steps: int) -> tuple[np.ndarray | None, float, bool]:
        """Real time, the front end behind: the camera's motion over the last `steps` frames fitted to the static
        scene's ORB matches between their ends, as the step from the previous frame's output pose that puts this
        frame where that motion says (so the repair weighs it as one step against the SLAM's, and the arbiter
        judges both over the same frames). Why: a check per frame costs 20-45 ms beside ORB-SLAM3 on two cores,
        so without this a front end behind the video checks none, and walkers drag the SLAM unopposed (Bonn crowd
        in real time: 417 of 424 steps unchecked); the fit is ~10 ms every n-th frame, and a drag over n frames is
        n times larger against the same matching noise (`odometry.repair_behind_check_every`; its cost and what it
        gains: docs/PERFORMANCE.md)."""
        assert self.arbiter is not None
        ref_id, prev_id = self.arbiter.held_back(steps), self.arbiter.held_back(1)
        if ref_id is None or prev_id is None or ref_id not in self._poses or prev_id not in self._poses:
            self.skipped_behind += 1
            return None, 0.0, False
        self.registrations += 1
        motion, inliers = self.arbiter.sparse_step(steps, by_depth=True)
        if motion is None or inliers < self.params.arbiter.sparse_min_inliers:  # (no fit: left unchecked, counted)
            self.skipped_behind += 1
            return None, 0.0, False
        self.checked_behind += 1
        self.sparse_steps += 1
        step = np.linalg.inv(self._poses[prev_id]) @ self._poses[ref_id] @ motion
        return step, self.params.min_fitness, True

    def close(self) -> None:
        if self._tracker is not None:
            self._tracker.shutdown(wait=True)
            self._tracker = None

    def _judge(self, slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
               from_frame: int | None = None) -> Verdict:
        assert self.arbiter is not None
        if from_frame is None and self.arbiter.frames_held < steps + 1:  # (a window that a restart cut short)
            return Verdict(0.0, 0, math.nan, math.nan)
        return self.arbiter.judge(slam_motion, semmap_motion, steps, from_frame, by_depth=self._by_depth)

    def counters(self) -> dict[str, int]:
        return {**self.repair.report.counters(), "repair_registrations": self.registrations,
                "repair_skipped_behind": self.skipped_behind,
                "repair_checked_behind": self.checked_behind, "repair_sparse_steps": self.sparse_steps,
                "repair_judged": 0 if self.arbiter is None else self.arbiter.judged,
                "moving_objects": len(self.moving.seen_moving), "dynamic_unplaced": self.dynamic_unplaced}

    def break_chain(self) -> None:
        self.repair.break_chain()
        if self.arbiter is not None:
            self.arbiter.reset()

    def state(self) -> dict:
        return {"repair": self.repair.state(), "moving": self.moving.state()}

    def restore(self, state: dict) -> None:
        if "repair" in state:
            self.repair.restore(state["repair"])
        self.moving.restore(state.get("moving", {}))
        if self.registration is not None:
            self.registration.reset()
        if self.arbiter is not None:
            self.arbiter.reset()
