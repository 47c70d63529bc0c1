"""Repair, not copy: an external SLAM's motion checked step by step against what semmap measures itself.

A visual SLAM that walking people corrupt does not fail loudly: it tracks features on the people, and its pose
moves with them (ORB-SLAM3 on the Bonn "crowd" window: an estimated path of 10.8 m for a camera that moved 1 m).
semmap sees the same frames, knows where the people are (the tracker's dynamic boxes) and can register two
consecutive frames with their depth left out (`rgbd` odometry, 40-100 ms a pair). `SlamRepair` compares each of
the SLAM's frame-to-frame steps with that registration and, where they disagree by more than a gate, asks the
static scene which of the two is right (arbiter.py: sparse features over the last few frames, evidence neither was
fitted to). Only where that evidence clearly favours semmap's registration does the output **overrule** the SLAM:
it takes semmap's step and re-anchors the SLAM's later poses onto the repaired path, so the SLAM's own later motion
still counts. Where the evidence is weak, the SLAM keeps its step. Where the SLAM has no pose (lost, not
initialised) semmap's step carries the trajectory alone.

Where it checks (the scope): only while an object is *seen to move* (motion.py) and `hold_s` after. A person who
sits still, or a false person box, is no reason to doubt the SLAM; on a static scene a SLAM beats semmap's
frame-to-frame registration (7-Scenes: ORB-SLAM3 3.5 cm, checked everywhere 7.3 cm; TUM fr1_rpy, fast rotation:
registration steps 25 mm off, the SLAM's 4 mm).

Why step by step and not poses: a wrong step is local (a person crossing the view for a second), but it shifts
every later pose; comparing steps finds it where it happened, and replacing one step moves the rest with it.
The registration is a witness only where it registered enough of the image (`fitness`) and agreed with itself
(finite, not a jump beyond `max_step_*`); otherwise the SLAM's step stands if it continues the recent motion.

Everything here is pure: steps in, poses and counters out (the front ends in frontends.py feed it).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from semmap.core.geometry import rotation_exp, rotation_log

from .arbiter import ArbiterParams, Verdict


class Judge(Protocol):
    """The static scene's verdict on two motions over the last `steps` frames, or from frame `from_frame` (one the
    caller was told to hold, see `SlamRepair.anchor_frame`) to the newest; `t` > 0 favours `semmap_motion`."""

    def __call__(self, slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
                 from_frame: int | None = None) -> Verdict: ...


@dataclass(frozen=True)
class RepairParams:
    """Gates of the step check (the `odometry.repair_*` settings)."""

    translation_m: float = 0.005  # steps further apart than this (m) disagree
    rotation_deg: float = 0.5  # ...or turned further apart than this (deg)
    min_fitness: float = 0.15  # semmap's registration must cover this fraction of the pixels to overrule
    max_step_m: float = 0.3  # a registration step longer than this (m per frame) is itself not trusted
    max_step_deg: float = 15.0
    scope: str = "moving"  # check steps only while an object is seen moving (and `hold_s` after); "always"
    hold_s: float = 2.0  # a SLAM that mapped a person keeps those points a while after the person left the view
    arbiter: ArbiterParams = field(default_factory=ArbiterParams)  # who is right where the two disagree
    # outside the scope a frame is registered only to measure the SLAM's precision (StepAgreement), every n-th
    witness_every: int = 5
    # real time, the front end behind the video: every n-th wanted check still made, over the n frames since the
    # last (`CheckedSlam._measure_over`); 0: none while behind (see `odometry.repair_behind_check_every`)
    behind_check_every: int = 3
    registration_scale: int = 1  # semmap's registration on images downscaled by this (real time: 2)
    # what measures a checked step: "dense" (the RGB-D registration; the static ORB matches' fit where it has too
    # few pixels) or "sparse" (that fit alone: 12 ms a frame pair where a full-size registration takes 38-43; Bonn
    # crowd in lockstep, ORB-SLAM3 0.15-0.26 m alone: sparse 0.07-0.11 m, dense 0.05-0.10 m, a half-size registration
    # 0.15-0.20 m; benchmarks/bench_witness.py). Real time keeps dense at half size: its checks there, few and far
    # between, were no better sparse.
    witness: str = "dense"
    # the gates above are for a camera at `gate_rate_hz`; a step of a slower stream may change by more under the
    # same acceleration (the change grows with the frame interval squared: a car at 10 Hz, not a hand at 30)
    gate_rate_hz: float = 30.0
    # the motion model carries at most this long in a row, then the SLAM's steps count; off (inf) by default: on
    # Bonn crowd a SLAM dragged by people stays wrong for seconds, and 1 s let it back in (1.16 m stayed 1.27 m)
    max_coast_s: float = float("inf")
    motion_steps: int = 5  # the motion model is the mean of the last steps taken (a sixth of a second at 30 Hz)
    # where the SLAM has no pose and nothing measured the step (real time, the front end behind), the motion
    # model's speed halves every this many seconds at the gates' rate: a hand-held camera's motion over seconds is
    # no straight line (Bonn crowd in real time: ORB-SLAM3 lost for 4 s, carried at its old speed, ended 1.3 m off
    # where the SLAM alone, in two maps, was 0.7 m); a slower stream (a car) keeps its speed
    gap_half_life_s: float = 0.25
    rejoin_m: float = 0.1  # a SLAM back after a gap continues from its own motion over it if that agrees this well
    rejoin_deg: float = 10.0
    # without a witness a step breaks the recent motion only if it also differs by this share of the step's length:
    # a SLAM's jitter on a car's metre-long steps is centimetres, a person dragging a hand-held camera doubles them
    jump_share: float = 0.25
    # a registration whose step breaks the recent motion by more than this many gates (and twice `jump_share` of
    # the step) witnesses nothing: ICP that slid along a featureless road says "stopped" to a car at 7 m/s
    check_jump_gates: float = 4.0


@dataclass
class RepairReport:
    """How often and where semmap overruled the SLAM (stats.json, the summary)."""

    steps: int = 0
    overruled: int = 0  # the SLAM's step replaced by semmap's
    slam_missing: int = 0  # the SLAM gave no pose: semmap's step carried the trajectory
    unchecked: int = 0  # no trustworthy registration: the SLAM's step stands (it agreed with the recent motion)
    static: int = 0  # no dynamic object in view for `hold_s`: the SLAM's step stands unchecked (its own ground)
    implausible: int = 0  # no trustworthy registration and the SLAM's step broke the recent motion: replaced
    coast_limit: int = 0  # ...but the motion model had carried `max_coast_s` already: the SLAM's step taken
    outvoted: int = 0  # the registration disagreed, but the SLAM's step continued the recent motion and it did not
    kept: int = 0  # the registration disagreed, but the static scene did not clearly favour it: the SLAM's step
    slam_weak: int = 0  # the registration disagreed and the SLAM itself said its tracking was weak: overruled
    gaps_rejoined: int = 0  # the SLAM came back after frames without a pose, in the same map: re-anchored
    rejoined_from_anchor: int = 0  # ... measured from its last step the output took, not its last pose (see update)
    rejoin_by_motion: int = 0  # ... where the static scene could not say, the motion model could (`_rejoin`)
    overruled_frames: list[int] = field(default_factory=list)  # frame ids (the first `max_listed`)
    max_listed: int = 200
    # per judged step (the first `max_judged`): what disagreed, the evidence and who won (odometry_repair.json)
    judged: list[dict] = field(default_factory=list)
    max_judged: int = 5000

    # the counted fields; older saved states listed the first eight as a plain list, in this order
    COUNTED = ("steps", "overruled", "slam_missing", "unchecked", "implausible", "static", "coast_limit", "outvoted",
               "kept", "slam_weak", "gaps_rejoined", "rejoined_from_anchor", "rejoin_by_motion")

    def counters(self) -> dict[str, int]:
        return {f"repair_{name}": getattr(self, name) for name in self.COUNTED}

    def set_counters(self, saved: dict | list | None) -> None:
        """From `counters()` as saved; a state saved before they were named (a list) is read by position."""
        if isinstance(saved, list):
            saved = {f"repair_{name}": v for name, v in zip(self.COUNTED, saved, strict=False)}
        for name in self.COUNTED:
            setattr(self, name, int((saved or {}).get(f"repair_{name}", 0)))

    def note_judgement(self, frame_id: int, winner: str, difference: tuple[float, float], verdict: Verdict | None,
                       fitness: float, rejoin_from: int | None = None) -> None:
        """One judged step; `rejoin_from`: a SLAM back after a gap, judged from that frame (its winner `slam`: its
        motion over the gap, `anchor`: its motion from the anchor)."""
        if len(self.judged) < self.max_judged:
            record = {"frame": int(frame_id), "winner": winner, "differ_mm": round(difference[0] * 1e3, 2),
                      "differ_deg": round(difference[1], 3), "fitness": round(float(fitness), 3)}
            if rejoin_from is not None:
                record["rejoin_from"] = int(rejoin_from)
            if verdict is not None:
                record.update(t=round(verdict.t, 2), t_long=round(verdict.t_long, 2), matches=verdict.matches,
                              slam_px=_rounded(verdict.slam_px), semmap_px=_rounded(verdict.semmap_px))
            self.judged.append(record)

    def spans(self) -> list[tuple[int, int]]:
        """The overruled frames as [first, last] runs of consecutive ids: where the SLAM went wrong."""
        out: list[tuple[int, int]] = []
        for f in self.overruled_frames:
            if out and f == out[-1][1] + 1:
                out[-1] = (out[-1][0], f)
            else:
                out.append((f, f))
        return out


# new samples before the measured sigmas are recomputed (a percentile of windows of up to 2000: one sample more
# moves it by nothing that matters, and recomputing it every frame cost the front end a share of its frame time)
SIGMAS_EVERY = 10
# the 90th percentile of the length of a 3-vector of independent N(0, s^2) components is 2.50 s (chi, 3 degrees)
CHI3_Q90 = 2.500
# a second difference s[i+1] - 2 s[i] + s[i-1] of steps with independent noise s has sqrt(1 + 4 + 1) times its sigma
SECOND_DIFFERENCE_GAIN = math.sqrt(6.0)


class StepAgreement:
    """The SLAM's declared uncertainty measured, not assumed: how consistent its steps are.

    A trajectory file (or a live SLAM's poses) comes without a covariance; `file:` declared a fixed 1 cm and 0.5 deg
    a frame for any of them, six times looser in rotation than KITTI 00's ORB estimate, so landmark factors biased
    by metres (a street's partly seen parked cars) bent a trajectory that had closed its own loops (ATE 1.30 m ->
    42.99 m). Two witnesses of the SLAM's step noise, each per axis from the 90th percentile of a 3-vector's length
    / 2.50 (what it is for a Gaussian 3-vector: robust to a tenth of outliers, not blind to a heavy tail as a median
    would be), over the last `window` samples, once there are `min_samples`:

    - **roughness**: the second difference of the SLAM's consecutive steps (rotation vectors, translations) / sqrt 6.
      True motion is smooth at a frame's scale (a car's), the SLAM's step noise is not: it shows. A lower bound: a
      smooth drift (scale, a slow bias) does not show, nor is a shaking hand told from noise (it only loosens).
    - **agreement**: where semmap's registration witnessed the step (trusted: enough fitness, no jump; on static
      scenes too, whatever the repair's scope), the difference between the two measurements of the same motion.
      An upper bound (it holds the registration's noise too); a car at 10 Hz gets none (its metre steps are beyond
      what the registration is trusted with, `max_step_m`), a hand-held camera many.

    `sigmas` is the larger of the two that are known (the upper bound where there is one): None before
    `min_samples` of either (the fixed sigmas stand)."""

    def __init__(self, min_samples: int = 50, window: int = 2000) -> None:
        self.min_samples = max(1, int(min_samples))
        self.window = window
        self.agreement: tuple[deque[float], deque[float]] = (deque(maxlen=window), deque(maxlen=window))
        self.roughness: tuple[deque[float], deque[float]] = (deque(maxlen=window), deque(maxlen=window))
        self._steps: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=3)  # the SLAM's last steps (rotvec, t)
        self._restored: tuple[float, float] | None = None  # the sigmas before a restart, until the windows refill
        self._added = 0  # samples taken so far: `sigmas` is recomputed every `SIGMAS_EVERY` new ones
        self._cached: tuple[int, tuple[float, float] | None] | None = None

    def add_slam_step(self, slam_step: np.ndarray | None) -> None:
        """The SLAM's step of this frame (None: it had none, the chain of consecutive steps breaks)."""
        if slam_step is None:
            self._steps.clear()
            return
        rotvec = rotation_log(slam_step[:3, :3])
        self._steps.append((rotvec, np.asarray(slam_step[:3, 3], float).copy()))
        if len(self._steps) == 3:
            (r0, t0), (r1, t1), (r2, t2) = self._steps
            self.roughness[0].append(float(np.linalg.norm(t2 - 2.0 * t1 + t0)) / SECOND_DIFFERENCE_GAIN)
            self.roughness[1].append(float(np.linalg.norm(r2 - 2.0 * r1 + r0)) / SECOND_DIFFERENCE_GAIN)
            self._added += 1

    def add_witnessed(self, slam_step: np.ndarray, check_step: np.ndarray) -> None:
        """A step semmap's registration witnessed: the two measurements of the same motion."""
        dt, dr = step_difference(slam_step, check_step)
        self.agreement[0].append(dt)
        self.agreement[1].append(math.radians(dr))
        self._added += 1

    def _measured(self, samples: tuple[deque[float], deque[float]]) -> tuple[float, float] | None:
        if len(samples[0]) < self.min_samples:
            return None
        t, r = (float(np.quantile(np.fromiter(q, float), 0.9)) / CHI3_Q90 for q in samples)
        return max(t, 1e-4), max(r, math.radians(1e-3))

    def sigmas(self) -> tuple[float, float] | None:
        """Per-axis (translation m, rotation rad) sigmas of one step, or None before `min_samples`."""
        if self._cached is None or (self._added - self._cached[0] >= SIGMAS_EVERY or self._cached[1] is None
                                    and self._added != self._cached[0]):
            known = [m for m in (self._measured(self.agreement), self._measured(self.roughness)) if m is not None]
            value = (max(m[0] for m in known), max(m[1] for m in known)) if known else None
            self._cached = (self._added, value)
        return self._restored if self._cached[1] is None else self._cached[1]

    def state(self) -> list[float] | None:
        """The measured sigmas only (the front end's state is journalled every frame: no window of samples)."""
        sigmas = self.sigmas()
        return None if sigmas is None else [float(v) for v in sigmas]

    def restore(self, state: list[float] | None) -> None:
        for q in (*self.agreement, *self.roughness):
            q.clear()
        self._steps.clear()
        self._cached = None
        self._restored = None if not state else (float(state[0]), float(state[1]))


def _rounded(value: float) -> float | None:
    return None if not math.isfinite(value) else round(float(value), 2)


def step_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg) between two relative motions."""
    d = np.linalg.inv(a) @ b
    cos = (np.trace(d[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])), math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def _rotation_deg(t: np.ndarray) -> float:
    cos = (np.trace(t[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


class SlamRepair:
    """Per frame: `update(frame_id, slam_pose, check_step, fitness)` -> the repaired camera-to-world pose.

    `slam_pose` is the SLAM's camera-to-world pose (None where it has none); `check_step` semmap's registration
    of the previous frame to this one as the relative motion T_prev^-1 T_cur (None where it has none). The output
    starts at the first SLAM pose (or at `start`), in the SLAM's world frame.

    It keeps the last `arbiter.window_frames` steps of both estimates (the SLAM's poses, semmap's own steps) so
    that a disagreement is judged over that window (`judge`, arbiter.py) rather than on one noisy frame pair.
    """

    def __init__(self, params: RepairParams | None = None, start: np.ndarray | None = None,
                 measured_sigmas_after: int = 0) -> None:
        self.params = params or RepairParams()
        self.report = RepairReport()
        self._start = None if start is None else np.asarray(start, float)
        self._pose: np.ndarray | None = None  # the last repaired pose
        self._slam_prev: np.ndarray | None = None  # the SLAM's previous pose (None: it had none)
        # the SLAM's last pose in its current map and the output pose of that frame: a SLAM back after a gap
        # continues from there
        self._slam_last: np.ndarray | None = None
        self._out_at_slam_last: np.ndarray | None = None
        # ... and its frame: a SLAM back after a gap whose anchor is too far back to judge from is judged from there
        self.slam_last_frame: int | None = None
        # the last frame whose step the output took from the SLAM, its SLAM pose and output pose: where the two last
        # agreed. A SLAM dragged before a gap and relocalised after it is measured from there (`_rejoin`)
        self.anchor_frame: int | None = None
        self._slam_at_anchor: np.ndarray | None = None
        self._out_at_anchor: np.ndarray | None = None
        # the last steps taken: their mean is the camera's recent motion (the motion model), not the last step
        # alone, which is often the glitch that precedes a SLAM losing track (TUM fr1_rpy: a 2 cm step carried
        # on over 5 lost frames put them 10-18 cm off)
        self._recent: deque[np.ndarray] = deque(maxlen=max(1, self.params.motion_steps))
        self._velocity_cache: tuple[tuple[np.ndarray, ...], np.ndarray] | None = None  # (`_velocity`)
        self._dynamic_seen: float | None = None  # stamp of the last frame with a dynamic object in view
        self._stamp: float | None = None  # of the previous frame (the gates scale with the frame interval)
        self._coast_since: float | None = None  # stamp where the motion model began to carry the chain
        self._bridged = 0  # frames in a row without a SLAM pose
        self._velocity_at_slam_last = np.eye(4)  # the motion model where the SLAM's last pose was
        self._gap_start: float | None = None  # the stamp of the SLAM's last pose before the gap
        # the SLAM's steps against the trusted registrations: the declared sigmas (0: the fixed ones, always)
        self.agreement = StepAgreement(max(1, measured_sigmas_after))
        self.measured_sigmas = measured_sigmas_after > 0
        self.took_slam_step = False  # this frame's step is the SLAM's own (not semmap's, not the motion model's)
        self.last_winner = "slam"  # whose step this frame took: slam | semmap | motion (the motion model)
        self.bridged = False  # this frame had no SLAM pose: its pose is a stand-in
        self._walker = False
        # the static scene's verdicts over the recent disagreements, summed with a fading memory (> 0: semmap's)
        self.evidence = 0.0
        self._verdict: Verdict | None = None  # the last verdict weighed
        # the window the arbiter judges: the SLAM's last poses and semmap's own last steps (its registration where
        # it was a witness, else the step taken), newest last
        window = max(1, self.params.arbiter.window_frames, self.params.arbiter.long_window_frames)
        self._slam_window: deque[np.ndarray | None] = deque(maxlen=window)  # poses of the frames before this one
        self._semmap_window: deque[np.ndarray] = deque(maxlen=window - 1)  # steps between them

    def copy(self, frame_id: int, slam_pose: np.ndarray | None) -> np.ndarray:
        """No check (`odometry.repair` off): the SLAM's steps as they are; a frame without a SLAM pose repeats the
        last step (constant velocity) and the chain resumes from the SLAM's next pose."""
        if self._pose is None:
            return self.update(frame_id, slam_pose, None)
        r = self.report
        r.steps += 1
        if slam_pose is not None and not np.all(np.isfinite(slam_pose)):
            slam_pose = None
        self.bridged = slam_pose is None
        self.took_slam_step = slam_pose is not None and (self._slam_prev is not None or self._slam_last is not None)
        if slam_pose is not None and self._slam_prev is None and self._slam_last is not None:
            r.gaps_rejoined += 1  # (back after a gap in the same map: its motion over the gap, see `update`)
            self._pose = self._out_at_slam_last @ np.linalg.inv(self._slam_last) @ slam_pose
        elif slam_pose is None or self._slam_prev is None:
            r.slam_missing += 1
            self._pose = self._pose @ self._velocity()
        else:
            step = np.linalg.inv(self._slam_prev) @ slam_pose
            self._recent.append(step)
            self._pose = self._pose @ step
        self._remember_slam(slam_pose, None, frame_id)
        return self._pose.copy()

    def declared_sigmas(self, fixed: tuple[float, float]) -> tuple[float, float]:
        """This frame's (translation m, rotation rad) sigmas to declare: where its step is the SLAM's own, measured
        from the SLAM's consistency (`StepAgreement`) once enough steps were seen, never looser than `fixed` (the
        settings': what a trajectory of unknown quality is declared); else `fixed` (a step semmap's registration or
        the motion model gave says nothing of the SLAM's precision: Bonn crowd, 85 % of the steps overruled)."""
        measured = self.agreement.sigmas() if self.measured_sigmas and self.took_slam_step else None
        return fixed if measured is None else (min(fixed[0], measured[0]), min(fixed[1], measured[1]))

    def _note(self, frame_id: int) -> None:
        if len(self.report.overruled_frames) < self.report.max_listed:
            self.report.overruled_frames.append(int(frame_id))

    def _trusted(self, step: np.ndarray | None, fitness: float, scale: float, fitted_to_scene: bool = False) -> bool:
        p = self.params
        if not (step is not None and bool(np.all(np.isfinite(step))) and fitness >= p.min_fitness
                and float(np.linalg.norm(step[:3, 3])) <= p.max_step_m and _rotation_deg(step) <= p.max_step_deg):
            return False
        if fitted_to_scene and scale > 1.0:
            # (at a slower stream a step fitted to the static matches is no witness: frames a metre apart on a car,
            # its PnP on a far scene was 5-12 cm off where the SLAM's steps were 0.3-2 cm, and the street along
            # KITTI 00 went from 1.26 to 4.08 m)
            return False
        if self.report.steps <= 1 or scale <= 1.0:  # (at the gates' own rate the registration is the witness)
            return True
        dt, dr = step_difference(step, self._velocity())
        length = max(float(np.linalg.norm(step[:3, 3])), float(np.linalg.norm(self._velocity()[:3, 3])))
        return (dt <= max(p.check_jump_gates * p.translation_m * scale, 2.0 * p.jump_share * length)
                and dr <= p.check_jump_gates * p.rotation_deg * scale)

    def _gate_scale(self, stamp: float | None) -> float:
        """How much wider the gates are for this frame's interval than for one at `gate_rate_hz`: 1 for a stream at
        about that rate (a frame interval under 1.5 of the gates': a 30 Hz camera's jitter, a dropped frame), the
        interval's ratio squared for a slower one (a car at 10 Hz: 9). Only a slower stream gets the rules for metre
        steps (a registration that breaks the recent motion is no witness, two witnesses outvote it, a step may
        differ from the last by `jump_share` of its length); at the gates' rate the registration is the witness."""
        if stamp is None or self._stamp is None or stamp <= self._stamp:
            return 1.0
        ratio = (stamp - self._stamp) * self.params.gate_rate_hz
        return ratio**2 if ratio >= 1.5 else 1.0

    def in_scope(self, moving_in_view: bool, stamp: float | None, undecided: bool = False) -> bool:
        """Whether this frame's step is checked: with scope `moving`, while an object is seen moving and `hold_s`
        seconds (by `stamp`) after, and while one is in view whose motion is not known yet (no hold after);
        always with scope `always`."""
        if moving_in_view and stamp is not None:
            self._dynamic_seen = stamp
        return self.params.scope == "always" or moving_in_view or undecided or (
            stamp is not None and self._dynamic_seen is not None and stamp - self._dynamic_seen <= self.params.hold_s)

    def update(self, frame_id: int, slam_pose: np.ndarray | None, check_step: np.ndarray | None,
               fitness: float = 1.0, moving_in_view: bool = True, stamp: float | None = None,
               judge: Judge | None = None, slam_weak: bool = False, undecided: bool = False,
               same_map: bool | None = None, fitted_to_scene: bool = False, unchecked: bool = False,
               judge_rejoin: Judge | None = None) -> np.ndarray:
        """`moving_in_view`: an object in this frame is seen moving (motion.py); with scope `moving` a step is
        checked only then and for `hold_s` seconds (by `stamp`) after. `judge` weighs the static scene's evidence
        where the two estimates disagree (without one the evidence is weak and the SLAM keeps its step);
        `slam_weak`: the SLAM said its own tracking of this frame was weak (few tracked points); `undecided`: an
        object is in view whose motion is not known yet (checked too, see `in_scope`); `same_map`: the SLAM says
        whether a pose after a gap is in the map it left (None: it does not say, see `_rejoins`);
        `fitted_to_scene`: `check_step` was fitted to the static scene's ORB matches (`StepArbiter.sparse_step`): a
        witness at the gates' rate only. `unchecked`: the step could not be checked (real time, the front end
        behind the video): a SLAM step taken then says nothing of where the two agree, so the anchor stays where
        they last did (`_rejoin`); `judge_rejoin`: where `judge` is None, a SLAM back after a gap is still judged by
        this one (a rare frame, where the output's corrections meet the SLAM's relocalisation)."""
        r = self.report
        in_scope = self.in_scope(moving_in_view, stamp, undecided)
        # a walker seen in view (or within `hold_s`) is itself evidence against the SLAM's step
        self._walker = in_scope and self.params.scope != "always" and not undecided or moving_in_view
        if slam_pose is not None and not np.all(np.isfinite(slam_pose)):
            slam_pose = None
        self.bridged = slam_pose is None
        if self._pose is None:  # the first frame: the anchor
            if slam_pose is not None:
                self._pose = slam_pose.copy() if self._start is None else self._start.copy()
            elif self._start is not None:
                self._pose = self._start.copy()
            else:
                self._pose = np.eye(4)
            self._remember_slam(slam_pose, stamp, frame_id)
            self._slam_window.append(self._slam_prev)
            if slam_pose is not None:
                self._set_anchor(frame_id)
            return self._pose.copy()
        r.steps += 1
        scale = self._gate_scale(stamp)
        trusted = self._trusted(check_step, fitness, scale, fitted_to_scene)
        slam_step = None
        if slam_pose is not None and self._slam_prev is None and self._rejoins(slam_pose, same_map):
            # back after a gap, in the same map: the SLAM's motion over the whole gap replaces the steps that
            # bridged it (a gap is never one step, and what carried it was a stand-in)
            r.gaps_rejoined += 1
            self._pose = self._rejoin(frame_id, slam_pose, judge if judge is not None else judge_rejoin)
            self._remember_slam(slam_pose, stamp, frame_id)
            self.took_slam_step, self.last_winner = True, "slam"
            self._set_anchor(frame_id)
            self._slam_window.append(self._slam_prev)
            self._semmap_window.append(self._velocity())
            return self._pose.copy()
        if slam_pose is None or self._slam_prev is None:
            # no SLAM step (lost, or the first pose of a new map: its origin says nothing)
            r.slam_missing += 1
            self.agreement.add_slam_step(None)
            if self._bridged == 0:  # (the gap's first frame: the camera's motion where the SLAM left)
                self._velocity_at_slam_last, self._gap_start = self._velocity(), self._stamp
            step = check_step if trusted else self._coasting(stamp, scale)
        else:
            slam_step = np.linalg.inv(self._slam_prev) @ slam_pose
            self.agreement.add_slam_step(slam_step)
            if trusted:  # (in scope or not: the SLAM's consistency is measured wherever semmap witnessed it)
                self.agreement.add_witnessed(slam_step, check_step)
            if not in_scope:
                r.static += 1
                self.evidence = 0.0  # (what the scene said of an earlier scope says nothing of the next one)
                step = slam_step
            elif not trusted:
                step = self._without_witness(frame_id, slam_pose, slam_step, stamp, scale, judge)
            else:
                step = self._arbitrate(frame_id, slam_pose, slam_step, check_step, fitness, scale, judge, slam_weak)
        self.took_slam_step = slam_step is not None and step is slam_step
        self.last_winner = "slam" if self.took_slam_step else ("semmap" if trusted and step is check_step else "motion")
        self._slam_window.append(None if slam_pose is None else slam_pose.copy())
        self._semmap_window.append(np.asarray(check_step if trusted else step, float).copy())
        self._recent.append(np.asarray(step, float).copy())
        self._pose = self._pose @ step
        self._remember_slam(slam_pose, stamp, frame_id)
        if self.took_slam_step and slam_pose is not None and not unchecked:
            self._set_anchor(frame_id)
        return self._pose.copy()

    def _set_anchor(self, frame_id: int) -> None:
        """After `_remember_slam`: this frame's SLAM pose (its copy there) and output pose are the anchor (no
        further copies: both are replaced each frame, never changed in place)."""
        self.anchor_frame = int(frame_id)
        self._slam_at_anchor, self._out_at_anchor = self._slam_prev, self._pose

    def _rejoin(self, frame_id: int, slam_pose: np.ndarray, judge: Judge | None) -> np.ndarray:
        """The output pose of a SLAM back in its map after a gap: its motion over the gap continues the output from
        its last pose before the gap. Unless the output had stopped taking its steps before the gap (a walker
        dragged it) and the static scene says its motion since the anchor, the last frame whose step the output
        took from it, is the better one: a SLAM that relocalised in its map has left the drag behind, and its
        motion over the gap then contains the drag's undoing (Bonn crowd, ORB-SLAM3 lost 3-4 frames among
        people: its motion over the gap 10-25 cm off, its motion from the anchor 1.6 cm)."""
        assert self._slam_last is not None and self._out_at_slam_last is not None
        over_gap = self._out_at_slam_last @ np.linalg.inv(self._slam_last) @ slam_pose
        if (judge is None or self._out_at_anchor is None or self._slam_at_anchor is None or self.anchor_frame is None
                or np.array_equal(self._slam_at_anchor, self._slam_last)):
            return over_gap
        from_anchor = self._out_at_anchor @ np.linalg.inv(self._slam_at_anchor) @ slam_pose
        start = np.linalg.inv(self._out_at_anchor)
        verdict = judge(start @ over_gap, start @ from_anchor, 0, from_frame=self.anchor_frame)
        judged_from = self.anchor_frame
        if not verdict.favours_semmap(self.params.arbiter) and not verdict.favours_slam(self.params.arbiter) \
                and self.slam_last_frame is not None and self.slam_last_frame != self.anchor_frame:
            # the anchor too far back for the scene to say (a drag over seconds): judged from the gap's start,
            # whose output pose the checks held (Bonn crowd in real time: a drag the checks held to 6-9 cm, then
            # ORB-SLAM3 lost 15-56 frames and relocalised; over the gap, its motion put the output 0.4-0.9 m off)
            start = np.linalg.inv(self._out_at_slam_last)
            verdict = judge(start @ over_gap, start @ from_anchor, 0, from_frame=self.slam_last_frame)
            judged_from = self.slam_last_frame
        won = verdict.favours_semmap(self.params.arbiter)
        if not won and not verdict.favours_slam(self.params.arbiter) \
                and step_difference(over_gap, from_anchor)[0] > self.params.rejoin_m \
                and self._off_motion(from_anchor) < self._off_motion(over_gap):
            won = True  # (the scene silent: the camera's own motion over the gap tells them apart)
            self.report.rejoin_by_motion += 1
        self.report.note_judgement(frame_id, "anchor" if won else "slam", step_difference(over_gap, from_anchor),
                                   verdict, 0.0, rejoin_from=judged_from)
        if not won:
            return over_gap
        self.report.rejoined_from_anchor += 1
        return from_anchor

    def _motion_over_gap(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera's motion over the gap from where the SLAM left, as the motion model has it: what bridged the
        gap (slowed to a stop, see `_coasting`), and the speed where the SLAM left, kept (a camera that kept going
        is as likely)."""
        assert self._out_at_slam_last is not None and self._pose is not None
        bridge = np.linalg.inv(self._out_at_slam_last) @ self._pose @ self._velocity()
        return bridge, np.linalg.matrix_power(self._velocity_at_slam_last, self._bridged + 1)

    def _bridge_agrees(self, pose: np.ndarray) -> bool:
        """Whether `pose`, the SLAM's first frame back after a gap, continues the output from where the SLAM left as
        the camera's motion would have (`_motion_over_gap`: within `rejoin_m` or half that motion, and
        `rejoin_deg`)."""
        assert self._out_at_slam_last is not None
        motion = np.linalg.inv(self._out_at_slam_last) @ pose
        p = self.params

        def agrees(model: np.ndarray) -> bool:
            dt, dr = step_difference(motion, model)
            return dt <= max(p.rejoin_m, 0.5 * float(np.linalg.norm(model[:3, 3]))) and dr <= p.rejoin_deg

        return any(agrees(model) for model in self._motion_over_gap())

    def _off_motion(self, pose: np.ndarray) -> float:
        """How far (m) `pose`, a candidate for the SLAM's first frame back after a gap, is from where the camera's
        motion over the gap would have put it (the nearer of `_motion_over_gap`'s two). Why: where people fill the
        view over the gap, the static scene has too few matches between its ends to judge (Bonn crowd in real time:
        8-17 over a second), yet its two candidates differ by the whole drag the checks held off (0.4-1.0 m); where
        the scene could judge a pair over 0.25 m apart, it took the motion from the anchor 6 times of 7."""
        assert self._out_at_slam_last is not None
        motion = np.linalg.inv(self._out_at_slam_last) @ pose
        return min(step_difference(motion, model)[0] for model in self._motion_over_gap())

    def _rejoins(self, slam_pose: np.ndarray, same_map: bool | None) -> bool:
        """Whether the SLAM, back after a gap, is back in the map it left: where it says so (`same_map`, ORB-SLAM3
        after RECENTLY_LOST), else where its motion over the gap roughly agrees with what bridged it (within
        `rejoin_m` or half the bridge's length, and `rejoin_deg`). A SLAM that started a new map (a trajectory file
        whose later part has its own origin) does not, and its first pose says nothing of the step."""
        if self._slam_last is None or self._out_at_slam_last is None or self._pose is None or same_map is False:
            return False
        if same_map:
            return True
        # its motion over the gap, continuing the output from where it left (the bridge slowed to a stop, see
        # `_coasting`, but a camera that kept going is as likely: both count)
        return self._bridge_agrees(self._out_at_slam_last @ np.linalg.inv(self._slam_last) @ slam_pose)

    def _velocity(self) -> np.ndarray:
        """The motion model: the mean of the last steps taken (identity before any). Kept until the steps change
        (compared by identity): a frame asks for it up to six times, on the front end's critical path."""
        cached = self._velocity_cache
        if cached is None or len(cached[0]) != len(self._recent) or any(
                kept is not step for kept, step in zip(cached[0], self._recent, strict=True)):
            if not self._recent:
                mean = np.eye(4)
            elif len(self._recent) == 1:
                mean = np.array(self._recent[0], dtype=float)
            else:
                steps = np.stack(self._recent)
                mean = np.eye(4)
                mean[:3, :3] = rotation_exp(rotation_log(steps[:, :3, :3]).mean(axis=0))
                mean[:3, 3] = steps[:, :3, 3].mean(axis=0)
            self._velocity_cache = (tuple(self._recent), mean)  # (the steps themselves: never changed in place)
        return self._velocity_cache[1].copy()

    def _coasting(self, stamp: float | None, scale: float) -> np.ndarray:
        """The motion model for a frame of a gap nothing measured: the camera's motion where the SLAM left, its
        speed halved every `gap_half_life_s` since (a long gap slows to a stop), at the gates' rate; a slower
        stream (`scale` > 1: a car) keeps its speed."""
        half_life = self.params.gap_half_life_s
        if scale > 1.0 or stamp is None or self._gap_start is None or not math.isfinite(half_life) or half_life <= 0:
            return self._velocity()
        velocity = self._velocity_at_slam_last
        keep = 0.5 ** (max(0.0, stamp - self._gap_start) / half_life)
        slowed = np.eye(4)
        slowed[:3, :3] = rotation_exp(keep * rotation_log(velocity[:3, :3]))
        slowed[:3, 3] = keep * velocity[:3, 3]
        return slowed

    def _remember_slam(self, slam_pose: np.ndarray | None, stamp: float | None, frame_id: int | None = None) -> None:
        """After this frame's pose is decided: the SLAM's pose as the next step's start, and, where it had one,
        as the anchor a return after a gap is measured from."""
        self._slam_prev = None if slam_pose is None else slam_pose.copy()
        if slam_pose is not None:
            self._slam_last, self._out_at_slam_last = slam_pose.copy(), self._pose.copy()
            self.slam_last_frame = None if frame_id is None else int(frame_id)
            self._bridged = 0
        else:
            self._bridged += 1
        if stamp is not None:
            self._stamp = float(stamp)

    def _arbitrate(self, frame_id: int, slam_pose: np.ndarray, slam_step: np.ndarray, check_step: np.ndarray,
                   fitness: float, scale: float, judge: Judge | None, slam_weak: bool) -> np.ndarray:
        """Both estimates of this step are at hand: the SLAM's, unless they disagree and the evidence says
        otherwise."""
        p, r = self.params, self.report
        difference = step_difference(slam_step, check_step)
        if difference[0] <= p.translation_m * scale and difference[1] <= p.rotation_deg * scale:
            return slam_step
        if scale > 1.0 and self._continues(slam_step, scale) and not self._continues(check_step, scale):
            # two witnesses against one: the SLAM's step continues the camera's recent motion and the
            # registration's breaks it (KITTI 00 at 10 Hz: three registrations 1-3 deg off, on a slow car in a
            # street, turned a 1.3 m trajectory into 6.9 m)
            r.outvoted += 1
            return slam_step
        if slam_weak:  # the SLAM's own word: it barely tracked this frame
            r.slam_weak += 1
            r.overruled += 1
            self._note(frame_id)
            r.note_judgement(frame_id, "semmap", difference, None, fitness)
            return check_step
        verdict = self._judge(slam_pose, check_step, judge)
        if self._weigh(verdict):
            r.overruled += 1
            self._note(frame_id)
            r.note_judgement(frame_id, "semmap", difference, verdict, fitness)
            return check_step
        r.kept += 1
        r.note_judgement(frame_id, "slam", difference, verdict, fitness)
        return slam_step

    def _weigh(self, verdict: Verdict | None, walker_prior: bool = True) -> bool:
        """Add a verdict to the evidence of the recent disagreements (faded by `evidence_memory`, each verdict
        clipped to `evidence_clip`): does it now favour semmap's estimate by `min_t`? Why a running sum: a SLAM that
        people drag is dragged for a while, a few millimetres a frame, and each frame pair alone is within the
        noise as often as not (Bonn crowd: semmap's registration won 50 % of single judgements); the sum of a few
        consecutive ones is not. The sum in the SLAM's favour is held at one clipped verdict: a SLAM right about
        many small steps is not thereby right about a jump (Bonn crowd: a 26 cm jump was kept against t = 26 after
        eight verdicts for the SLAM). With a walker in view one strong verdict then decides, else two in a row.
        `walker_prior`: whether a walker in view lowers the bar (`_threshold`)."""
        a = self.params.arbiter
        self._verdict = verdict
        if verdict is None or verdict.matches < a.min_matches:
            return self.evidence >= self._threshold(walker_prior) and verdict is not None
        def clipped(t: float) -> float:
            return max(-a.evidence_clip, min(a.evidence_clip, t))

        # (a SLAM's record counts as one strong verdict at most: it was right about earlier steps, not about this one)
        self.evidence = max(-a.evidence_clip,
                            a.evidence_memory * self.evidence + clipped(verdict.t) + clipped(verdict.t_long))
        return self.evidence >= self._threshold(walker_prior)

    def _threshold(self, walker_prior: bool = True) -> float:
        a = self.params.arbiter
        return a.min_t - a.walker_prior if self._walker and walker_prior else a.min_t

    def _judge(self, slam_pose: np.ndarray, check_step: np.ndarray, judge: Judge | None) -> Verdict | None:
        """The static scene's verdict on the two motions over the window: the SLAM's from its pose at the window's
        start to this one, semmap's its own steps over the window then this registration; and the same over the
        long window, where the history reaches back that far (its `t_long`). None without a judge or without the
        SLAM's pose at the window's start (it was lost there: nothing to compare)."""
        a = self.params.arbiter
        verdicts = [self._judge_over(a.window_frames, slam_pose, check_step, judge)]
        if a.long_window_frames > a.window_frames:
            verdicts.append(self._judge_over(a.long_window_frames, slam_pose, check_step, judge))
        short = verdicts[0]
        long = verdicts[-1] if len(verdicts) > 1 else None
        if short is None:
            return long
        if long is not None and long.matches >= a.min_matches:
            return dataclasses.replace(short, t_long=long.t)
        return short

    def _judge_over(self, steps: int, slam_pose: np.ndarray, check_step: np.ndarray,
                    judge: Judge | None) -> Verdict | None:
        if judge is None or len(self._slam_window) < steps or self._slam_window[-steps] is None:
            return None
        slam_motion = np.linalg.inv(self._slam_window[-steps]) @ slam_pose
        semmap_motion = np.eye(4)
        for step in list(self._semmap_window)[len(self._semmap_window) - (steps - 1):]:
            semmap_motion = semmap_motion @ step
        return judge(slam_motion, semmap_motion @ check_step, steps)

    def _continues(self, step: np.ndarray, scale: float) -> bool:
        """Does `step` continue the camera's recent motion (within the gates, scaled to the frame interval)?"""
        if self.report.steps <= 1:
            return False
        p = self.params
        dt, dr = step_difference(step, self._velocity())
        return dt <= p.translation_m * scale and dr <= p.rotation_deg * scale

    def _without_witness(self, frame_id: int, slam_pose: np.ndarray, slam_step: np.ndarray, stamp: float | None,
                         scale: float, judge: Judge | None) -> np.ndarray:
        """No registration to witness the step: the SLAM's step stands if it continues the camera's recent motion
        (constant velocity) within the gates, scaled to the frame interval. If it breaks it, the static scene
        judges the SLAM's motion against the motion model's, as against a registration; only where the evidence
        favours the motion model does it carry this frame, and not for longer than `max_coast_s` in a row (a
        camera that changed its speed for good, a car braking, would otherwise be held at its old speed)."""
        p, r = self.params, self.report
        dt, dr = step_difference(slam_step, self._velocity())
        length = max(float(np.linalg.norm(slam_step[:3, 3])), float(np.linalg.norm(self._velocity()[:3, 3])))
        first = r.steps <= 1  # no motion known yet (the identity is no witness of a camera at rest)
        share = scale > 1.0 and dt <= p.jump_share * length  # (a slower stream: a car's metre-long steps)
        if first or (dt <= p.translation_m * scale or share) and dr <= p.rotation_deg * scale:
            r.unchecked += 1
            self._coast_since = None
            return slam_step
        if stamp is not None and self._coast_since is not None and stamp - self._coast_since >= p.max_coast_s:
            r.coast_limit += 1
            self._coast_since = None
            self._recent.clear()  # (the camera changed its speed for good: its old motion is no model any more)
            return slam_step
        difference = step_difference(slam_step, self._velocity())
        # (a fast turn: the SLAM's to make.) A walker lowers the bar for the motion model only on a slower stream
        # (`scale` > 1: a car at 10 Hz, whose motion is smooth enough for its recent motion to witness a step); a
        # hand-held camera's recent motion measures nothing: with the walker's bar it carried 17 frames of a turn in
        # Bonn crowd, 3 cm a frame off. (Without it on the car, the street along KITTI 00 ended 3.19 m, not 1.26.)
        if not self._weigh(self._judge(slam_pose, self._velocity(), judge), walker_prior=scale > 1.0):
            r.kept += 1
            r.note_judgement(frame_id, "slam", difference, self._verdict, 0.0)
            return slam_step
        if self._coast_since is None and stamp is not None:
            self._coast_since = float(self._stamp if self._stamp is not None else stamp)
        r.implausible += 1
        self._note(frame_id)
        r.note_judgement(frame_id, "motion", difference, self._verdict, 0.0)
        return self._velocity()

    def break_chain(self) -> None:
        """The SLAM's next pose is in a new frame (a restarted SLAM, a new map): its first step says nothing."""
        self._slam_prev = self._slam_last = self._out_at_slam_last = self.slam_last_frame = None
        self.anchor_frame = self._slam_at_anchor = self._out_at_anchor = None
        self._slam_window.clear()
        self._semmap_window.clear()

    def state(self) -> dict:
        r = self.report
        return {"pose": _flat(self._pose), "slam_prev": _flat(self._slam_prev),
                "recent": [_flat(step) for step in self._recent],
                "slam_last": _flat(self._slam_last), "out_at_slam_last": _flat(self._out_at_slam_last),
                "counters": r.counters(),
                "dynamic_seen": self._dynamic_seen, "stamp": self._stamp, "coast_since": self._coast_since,
                "frames": list(r.overruled_frames), "agreement": self.agreement.state()}

    def restore(self, state: dict) -> None:
        self._pose = _unflat(state.get("pose"), (4, 4))
        self._slam_prev = _unflat(state.get("slam_prev"), (4, 4))
        self._slam_last = _unflat(state.get("slam_last"), (4, 4))
        self._out_at_slam_last = _unflat(state.get("out_at_slam_last"), (4, 4))
        self._recent.clear()
        self._recent.extend(_unflat(step, (4, 4)) for step in state.get("recent", []))
        if not self._recent and state.get("last_step") is not None:  # (a state saved before the mean was kept)
            self._recent.append(_unflat(state["last_step"], (4, 4)))
        r = self.report
        r.set_counters(state.get("counters"))
        self._dynamic_seen = state.get("dynamic_seen")
        self._stamp, self._coast_since = state.get("stamp"), state.get("coast_since")
        r.overruled_frames = [int(f) for f in state.get("frames", [])]
        self.agreement.restore(state.get("agreement"))
        self._slam_window.clear()  # (the images of the window are gone too: the next judgements start afresh)
        self._semmap_window.clear()


def _flat(a: np.ndarray | None) -> list[float] | None:
    return None if a is None else np.asarray(a, dtype=np.float64).reshape(-1).tolist()


def _unflat(values: list[float] | None, shape: tuple[int, ...]) -> np.ndarray | None:
    return None if values is None else np.asarray(values, float).reshape(shape)
