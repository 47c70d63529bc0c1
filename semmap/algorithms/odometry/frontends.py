"""Odometry front ends: stand-ins for an external SLAM, each turning frames into camera-to-world poses.

- `gt`: the dataset's ground truth (with a tight declared covariance).
- `gt+drift`: ground-truth motion with seeded random-walk noise on translation and on yaw about gravity, plus a
  constant yaw bias: drift that grows like a real visual odometry's (defaults give ~0.1-0.3 m ATE on 7-Scenes).
- `rgbd`: Open3D multi-scale RGB-D odometry between consecutive frames; the depth inside the frame's dynamic
  objects (people, animals, anything seen moving: `semmap/v1/<robot>/dynamic`) is left out, because people
  who fill the view drag a frame-to-frame registration with them (Bonn "crowd": 1.07 m -> 0.09 m ATE).
- `file:PATH`: a TUM-format trajectory (or a KITTI pose file) written by any SLAM, matched to frames by timestamp.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from semmap.core.config import OdometryConfig
from semmap.datasets.trajectory_io import KITTI_RATE_HZ, read_trajectory

from .base import FrontEnd, OdometryError, OdometryInput
from .base import flat as _flat
from .base import unflat as _unflat
from .checked import CheckedSlam, SlamReading
from .motion import MotionParams
from .refinement import OutputStep, Refinement, refine_outputs
from .registration import PairRegistration
from .repair import RepairParams

__all__ = ["FrontEnd", "OdometryError", "OdometryInput", "PairRegistration", "make_frontend", "frame_offset"]


def _require_gt(frame: OdometryInput) -> np.ndarray:
    if frame.gt_pose is None:
        raise OdometryError(f"frame {frame.frame_id} has no ground-truth pose: use --odometry rgbd or file:PATH")
    return frame.gt_pose


class GroundTruthOdometry(FrontEnd):
    def __init__(self, sigma_translation_m: float, sigma_rotation_deg: float) -> None:
        self.sigmas = (sigma_translation_m, math.radians(sigma_rotation_deg))

    def estimate(self, frame: OdometryInput) -> np.ndarray:
        return _require_gt(frame).copy()


class DriftingOdometry(FrontEnd):
    """GT relative motion composed with seeded noise; yaw noise and bias act about the world's up axis.

    Declared sigmas: the backend adds per-frame variances over the frames between two of its nodes (a random
    walk), but a constant bias b grows linearly: over n frames the yaw error is n*b, not sqrt(n)*b. The
    declared rotation sigma is therefore sqrt(yaw_sigma^2 + bias_horizon_frames * b^2): a random walk that
    matches the bias's error over `bias_horizon_frames` frames (the order of the gap between two landmark
    constraints), so the odometry does not claim to be tighter than it is over that horizon and landmarks can
    pull. 1 is the plain hypot(yaw_sigma, bias) per frame.

    `per_metre` (the `vehicle` profile): the three figures are per metre driven instead of per frame (translation
    noise a share of the step's length, yaw noise per sqrt(metre), yaw bias per metre), as a car's odometry drifts:
    a hand-held camera's 0.05 deg a frame turned KITTI 00's 4541 frames into 227 degrees of heading error (ATE
    219 m), which no odometry on a car comes near. The declared sigmas then follow each step's length.
    """

    def __init__(self, seed: int, translation_sigma_m: float, yaw_sigma_deg: float, yaw_bias_deg: float,
                 up: np.ndarray | None = None, bias_horizon_frames: float = 1.0, per_metre: bool = False) -> None:
        self.rng = np.random.default_rng(seed)
        self.t_sigma = translation_sigma_m
        self.yaw_sigma = math.radians(yaw_sigma_deg)
        self.yaw_bias = math.radians(yaw_bias_deg)
        self.up = None if up is None else np.asarray(up, float) / np.linalg.norm(up)
        self.horizon = max(float(bias_horizon_frames), 1.0)
        self.per_metre = per_metre
        self.sigmas = self._declared(1.0)
        self._prev_gt: np.ndarray | None = None
        self._est: np.ndarray | None = None

    def _declared(self, metres: float) -> tuple[float, float]:
        """(translation m, rotation rad) sigmas of one step (`metres` long; per frame: the settings themselves)."""
        scale_t, scale_r, scale_b = (metres, math.sqrt(metres), metres) if self.per_metre else (1.0, 1.0, 1.0)
        declared = math.sqrt((self.yaw_sigma * scale_r) ** 2 + self.horizon * (self.yaw_bias * scale_b) ** 2)
        return max(self.t_sigma * scale_t, 1e-4), max(declared, 1e-4)

    def estimate(self, frame: OdometryInput) -> np.ndarray:
        gt = _require_gt(frame)
        if self._est is None or self._prev_gt is None:
            self._est = gt.copy()
            if self.up is None:  # image y points down, so the first camera's -y is "up" for handheld data
                self.up = -gt[:3, 1]
        else:
            delta = np.linalg.inv(self._prev_gt) @ gt
            est = self._est @ delta
            metres = float(np.linalg.norm(delta[:3, 3]))
            if self.per_metre:
                yaw = self.rng.normal(0.0, self.yaw_sigma * math.sqrt(metres)) + self.yaw_bias * metres
                t_sigma = self.t_sigma * metres
                self.sigmas = self._declared(metres)
            else:
                yaw = self.rng.normal(0.0, self.yaw_sigma) + self.yaw_bias
                t_sigma = self.t_sigma
            rot = Rotation.from_rotvec(self.up * yaw).as_matrix()
            est[:3, :3] = rot @ est[:3, :3]
            # rotate the motion of this step, not the whole past: position moves by the rotated step
            step = est[:3, 3] - self._est[:3, 3]
            est[:3, 3] = self._est[:3, 3] + rot @ step + self.rng.normal(0.0, t_sigma, 3)
            self._est = est
        self._prev_gt = gt
        return self._est.copy()

    def state(self) -> dict:
        # the generator's state holds 128-bit integers: JSON text travels where msgpack integers cannot
        return {"rng": json.dumps(self.rng.bit_generator.state), "est": _flat(self._est),
                "prev_gt": _flat(self._prev_gt), "up": _flat(self.up)}

    def restore(self, state: dict) -> None:
        self.rng.bit_generator.state = json.loads(state["rng"])
        self._est = _unflat(state["est"], (4, 4))
        self._prev_gt = _unflat(state["prev_gt"], (4, 4))
        self.up = _unflat(state["up"], (3,))


class RgbdOdometry(FrontEnd):
    """Frame-to-frame Open3D RGB-D odometry (tensor, multi-scale); starts at the first GT pose if known.

    A pair Open3D cannot register, or registers on less than `min_fitness` of its pixels (the fraction with a
    correspondence: people left out of the depth, motion blur, a view of a blank wall), is not trusted: the previous
    step is repeated (constant velocity; none yet: standing still), and counted. Why: on the Bonn crowd window the
    few pairs with fitness below 0.1 (median 0.5) carried 5-8 cm jumps of a camera that moves 1-3 mm a frame, and
    those jumps were most of the front end's error (0.153 -> 0.108 m ATE with the gate)."""

    needs_images = True

    def __init__(
        self, sigma_translation_m: float, sigma_rotation_deg: float, dynamic_mask: str = "box", min_fitness: float = 0.0
    ) -> None:
        self.registration = PairRegistration(dynamic_mask)
        self.dynamic_mask = dynamic_mask
        self.uses_dynamic = dynamic_mask != "none"
        self.min_fitness = min_fitness
        self.sigmas = (sigma_translation_m, math.radians(sigma_rotation_deg))
        self._pose: np.ndarray | None = None
        self._step = np.eye(4)  # the last trusted frame-to-frame motion
        self.counters = {"pairs_failed": 0, "pairs_low_fitness": 0}

    def estimate(self, frame: OdometryInput) -> np.ndarray:
        chained = self.registration.has_previous
        relative, fitness = self.registration.register(frame)
        if self._pose is None:
            self._pose = frame.gt_pose.copy() if frame.gt_pose is not None else np.eye(4)
        elif chained:
            if relative is None:
                self.counters["pairs_failed"] += 1
                relative = self._step  # the backend's landmarks can still pull it back
            elif fitness < self.min_fitness:
                self.counters["pairs_low_fitness"] += 1
                relative = self._step
            else:
                self._step = relative
            self._pose = self._pose @ relative
        return self._pose.copy()

    def state(self) -> dict:
        return {"pose": _flat(self._pose), "step": _flat(self._step)}

    def restore(self, state: dict) -> None:
        """The previous image is not kept: the next frame starts a new frame-to-frame chain at the saved pose."""
        self._pose = _unflat(state["pose"], (4, 4))
        step = _unflat(state.get("step"), (4, 4))
        self._step = step if step is not None else np.eye(4)
        self.registration.reset()


FILE_MATCH_S = 0.05  # a frame and a trajectory pose further apart than this do not match
FILE_MIN_MATCHED = 0.5  # fewer matched frames than this fraction: the two clocks disagree, refuse the run


def match_trajectory(traj_stamps: np.ndarray, frame_stamps: np.ndarray, offset_s: float = 0.0,
                     max_difference_s: float = FILE_MATCH_S) -> tuple[np.ndarray, np.ndarray]:
    """For each frame, the index of the trajectory pose nearest in time (trajectory stamp + offset_s) and
    whether it lies within `max_difference_s`. `traj_stamps` sorted ascending."""
    shifted = np.asarray(traj_stamps, float) + offset_s
    frames = np.asarray(frame_stamps, float)
    right = np.clip(np.searchsorted(shifted, frames), 0, len(shifted) - 1)
    left = np.clip(right - 1, 0, len(shifted) - 1)
    nearest = np.where(np.abs(shifted[left] - frames) <= np.abs(shifted[right] - frames), left, right)
    return nearest, np.abs(shifted[nearest] - frames) <= max_difference_s


def check_trajectory_overlap(path: str | Path, frame_stamps: list[float], offset_s: float = 0.0,
                             max_difference_s: float = FILE_MATCH_S, min_fraction: float = FILE_MIN_MATCHED,
                             rate_hz: float = KITTI_RATE_HZ) -> str:
    """Refuse a trajectory file whose stamps do not cover the frames (a TUM file in Unix time on a dataset
    timed from 0 would otherwise give every frame the same nearest pose). Returns a one-line report."""
    poses = read_trajectory(path, rate_hz=rate_hz)
    if not poses:
        raise OdometryError(f"trajectory file {path} holds no poses")
    stamps = np.sort(np.array([t for t, _ in poses]))
    _, matched = match_trajectory(stamps, np.asarray(frame_stamps, float), offset_s, max_difference_s)
    n, total = int(matched.sum()), len(frame_stamps)
    if total and n < max(1, min_fraction * total):
        lo, hi = stamps[0] + offset_s, stamps[-1] + offset_s
        raise OdometryError(
            f"trajectory {path} matches only {n} of {total} frames within {max_difference_s} s: its poses span "
            f"{lo:.3f} .. {hi:.3f} s (with --time-offset {offset_s:g}), the frames span {min(frame_stamps):.3f} .. "
            f"{max(frame_stamps):.3f} s. Pass --time-offset SECONDS (added to the trajectory's stamps), e.g. "
            f"--time-offset {min(frame_stamps) - stamps[0]:.3f} to start both together")
    return f"odometry {path}: {n} of {total} frames matched a pose within {max_difference_s} s"


class CheckedSlamFrontEnd(FrontEnd):
    """A SLAM's poses, each step checked by semmap (checked.py) unless the check is off: what `file:`,
    `external` and `orbslam3` share. A subclass hands `checked_pose` its SLAM's pose of each frame; the SLAM's own
    poses are kept as `slam_trajectory` (written as `trajectory_slam.tum`), the decisions in `counters` and
    `judged` (written to `odometry_repair.json`)."""

    def __init__(self, fixed_sigmas: tuple[float, float], check: CheckedSlam) -> None:
        self.sigmas = self.fixed_sigmas = fixed_sigmas
        self.check = check
        self.needs_images = self.uses_dynamic = check.checks
        self.counters: dict[str, int] = {}
        self.slam_trajectory: list[tuple[float, np.ndarray]] = []  # the SLAM's own poses, before the repair
        # a SLAM that refines its trajectory at its end (ORB-SLAM3): every measured frame's output and whose step it
        # took, for `refinement`
        self.refines_at_end = False
        self.refined_trajectory: list[tuple[float, np.ndarray]] = []  # ...its refined poses, once it has closed
        self._outputs: list[OutputStep] = []

    def checked_pose(self, frame: OdometryInput, slam_pose: np.ndarray | None = None, slam_weak: bool = False,
                     same_map: bool | None = None, track: Callable[[], SlamReading] | None = None) -> np.ndarray:
        """The frame's pose from the SLAM's (or from `track`, its tracking run beside semmap's measurement)."""
        if track is not None:
            inner = track

            def track() -> SlamReading:  # (and keep what it said, in the SLAM's own trajectory)
                reading = inner()
                if reading[0] is not None:
                    self.slam_trajectory.append((float(frame.stamp), reading[0].copy()))
                return reading
        elif slam_pose is not None:
            self.slam_trajectory.append((float(frame.stamp), slam_pose.copy()))
        pose = self.check.pose(frame, slam_pose, slam_weak, same_map, track)
        if self.refines_at_end and not self.bridged:
            self._outputs.append(OutputStep(int(frame.frame_id), float(frame.stamp), pose.copy(),
                                            self.check.repair.took_slam_step))
        self.sigmas = self.check.repair.declared_sigmas(self.fixed_sigmas)
        self.counters.update({**self.check.counters(), **_declared_counters(self.sigmas)})
        return pose

    @property
    def bridged(self) -> bool:
        """The SLAM had no pose of this frame: its pose is a stand-in (OdometryPose.bridged)."""
        return self.check.repair.bridged

    @property
    def step_source(self) -> str:
        """Whose step this frame's pose took: slam | semmap | motion (the motion model) | copied (no check)."""
        return self.check.repair.last_winner if self.check.checks else "copied"

    def overruled(self) -> list[tuple[int, int]]:
        return self.check.repair.report.spans()

    def refinement(self) -> Refinement | None:
        """After `close`: the output with the SLAM's own steps as it refined them at its end (refinement.py), or
        None where the SLAM does not refine at its end (or that is turned off)."""
        if not self.refines_at_end:
            return None
        report = self.check.repair.report
        return refine_outputs(self._outputs, self.refined_trajectory, len(self.check.moving.seen_moving),
                              report.overruled + report.implausible)

    def judged(self) -> list[dict]:
        return list(self.check.repair.report.judged)

    def repair_report(self, mode: str) -> dict:
        """Where semmap overruled the SLAM and why, as `odometry_repair.json` holds it (the summary reads it):
        counters, frame spans and, per disagreement, the evidence and who won."""
        return {"schema": "semmap.repair/2", "mode": mode, "counters": dict(self.counters),
                "overruled_spans": [list(span) for span in self.overruled()], "judged": self.judged()}

    def state(self) -> dict:
        return self.check.state()

    def restore(self, state: dict) -> None:
        self.check.restore(state)


class FileOdometry(CheckedSlamFrontEnd):
    """Poses from a TUM trajectory file (or a KITTI pose file, pose i at i / `rate_hz`), matched to each frame by
    the nearest timestamp (+ a time offset).

    With `repair` (the default) each of the file's steps is checked by semmap (checked.py): the front end then
    needs the frames' images and their dynamic objects. A frame with no pose within `FILE_MATCH_S` counts as one
    the SLAM had none for. Without `repair` the file's poses are copied as they are."""

    def __init__(self, path: str | Path, sigma_translation_m: float, sigma_rotation_deg: float,
                 time_offset_s: float = 0.0, repair: bool = False, dynamic_mask: str = "box",
                 repair_gates: RepairParams | None = None, rate_hz: float = KITTI_RATE_HZ,
                 measured_sigmas_after: int = 0, motion: MotionParams | None = None) -> None:
        poses = sorted(read_trajectory(path, rate_hz=rate_hz), key=lambda p: p[0])
        if not poses:
            raise OdometryError(f"trajectory file {path} holds no poses")
        super().__init__((sigma_translation_m, math.radians(sigma_rotation_deg)),
                         CheckedSlam(repair_gates, dynamic_mask, repair, motion, measured_sigmas_after))
        self.stamps = np.array([t for t, _ in poses])
        self.poses = [p for _, p in poses]
        self.time_offset_s = float(time_offset_s)
        self.far_matches = 0

    def estimate(self, frame: OdometryInput) -> np.ndarray:
        nearest, matched = match_trajectory(self.stamps, np.array([frame.stamp]), self.time_offset_s)
        if not matched[0]:
            self.far_matches += 1
        pose = self.poses[int(nearest[0])].copy()
        if not self.check.checks:
            return pose
        return self.checked_pose(frame, pose if matched[0] else None)


class ExternalSlamOdometry(CheckedSlamFrontEnd):
    """A live external SLAM's poses (the client's or the ROS 2 bridge's, on the `slam` key), each step checked
    by semmap like `file:` (checked.py); `odometry.repair=false` copies them. The run's odometry is then the
    repaired trajectory; the SLAM's own poses are kept as `trajectory_slam.tum`."""

    needs_slam = True

    def __init__(self, sigma_translation_m: float, sigma_rotation_deg: float, repair: bool = True,
                 dynamic_mask: str = "box", repair_gates: RepairParams | None = None,
                 measured_sigmas_after: int = 0, motion: MotionParams | None = None) -> None:
        super().__init__((sigma_translation_m, math.radians(sigma_rotation_deg)),
                         CheckedSlam(repair_gates, dynamic_mask, repair, motion, measured_sigmas_after))

    def estimate(self, frame: OdometryInput) -> np.ndarray:
        slam = frame.slam_pose
        if slam is not None and (slam.shape != (4, 4) or not np.all(np.isfinite(slam))):
            slam = None
        return self.checked_pose(frame, slam)


def _declared_counters(sigmas: tuple[float, float]) -> dict[str, int]:
    """The per-frame sigmas a SLAM's front end declares now (measured or fixed), as counters (stats.json)."""
    return {"declared_sigma_translation_um": round(sigmas[0] * 1e6),
            "declared_sigma_rotation_mdeg": round(math.degrees(sigmas[1]) * 1e3)}


def make_frontend(mode: str, config: OdometryConfig) -> FrontEnd:
    """The front end for `--odometry MODE` with the `odometry` config section (the registry in
    semmap/algorithms/odometry/__init__.py; an unknown mode is a ConfigError naming `odometry.mode`)."""
    from semmap.algorithms.odometry import create_frontend

    return create_frontend(mode, config)


def frame_offset(values: object) -> np.ndarray:
    """`odometry.frame_offset` [x, y, z (m), roll, pitch, yaw (deg)] as the 4x4 transform from the session's
    frame to the dataset's: the front end publishes inv(offset) @ pose, so a session starts in a frame of its
    own (what relocalisation against a prior map must undo; identity by default)."""
    if not isinstance(values, list | tuple) or len(values) != 6:
        raise OdometryError(f"odometry.frame_offset must be 6 numbers [x, y, z, roll, pitch, yaw], got {values!r}")
    try:
        v = [float(x) for x in values]
    except (TypeError, ValueError):
        raise OdometryError(f"odometry.frame_offset must hold numbers, got {values!r}") from None
    if not all(math.isfinite(x) for x in v):
        raise OdometryError("odometry.frame_offset must be finite")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", v[3:], degrees=True).as_matrix()
    T[:3, 3] = v[:3]
    return T
