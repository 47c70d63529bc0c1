"""The repair of an external SLAM's steps (semmap/algorithms/odometry/repair.py): pure, on made-up motion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from semmap.algorithms.odometry.arbiter import Verdict
from semmap.algorithms.odometry.repair import RepairParams, SlamRepair, step_difference


def favours_semmap(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
                   from_frame: int | None = None) -> Verdict:
    """The static scene's verdict where semmap's registration is right (a person drags the SLAM)."""
    return Verdict(10.0, 200, 3.0, 0.8)


def favours_slam(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
                 from_frame: int | None = None) -> Verdict:
    """... and where the SLAM is (motion blur fooled the registration)."""
    return Verdict(-10.0, 200, 0.8, 3.0)


def weak(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int, from_frame: int | None = None) -> Verdict:
    """Too few static matches to say anything."""
    return Verdict(0.0, 5, float("nan"), float("nan"))


def _pose(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = (x, y, 0.0)
    return T


def _truth(n: int = 120) -> list[np.ndarray]:
    """A camera moving 2 mm a frame and turning 0.1 deg a frame."""
    return [_pose(0.002 * i, 0.0005 * i, 0.1 * i) for i in range(n)]


def _steps(poses: list[np.ndarray]) -> list[np.ndarray]:
    return [np.linalg.inv(a) @ b for a, b in zip(poses, poses[1:], strict=False)]


def _noisy(step: np.ndarray, rng: np.random.Generator, sigma_m: float = 0.0005) -> np.ndarray:
    out = step.copy()
    out[:3, 3] += rng.normal(0.0, sigma_m, 3)
    return out


def _run(repair: SlamRepair, slam: list[np.ndarray | None], checks: list[np.ndarray | None],
         fitness: list[float] | None = None, judge=favours_semmap,  # noqa: ANN001
         same_map: bool | None = None) -> list[np.ndarray]:
    out = [repair.update(0, slam[0], None)]
    for i in range(1, len(slam)):
        out.append(repair.update(i, slam[i], checks[i - 1], 1.0 if fitness is None else fitness[i - 1],
                                 judge=judge, same_map=same_map))
    return out


def _error(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    return max(float(np.linalg.norm(p[:3, 3] - q[:3, 3])) for p, q in zip(a, b, strict=True))


def test_agreeing_steps_are_the_slams_own():
    """Where semmap's registration agrees within the gate, the output is the SLAM's trajectory, untouched."""
    truth = _truth()
    rng = np.random.default_rng(0)
    checks = [_noisy(s, rng) for s in _steps(truth)]
    repair = SlamRepair(RepairParams(translation_m=0.005, rotation_deg=0.5))
    out = _run(repair, truth, checks)
    assert _error(out, truth) < 1e-9
    assert repair.report.overruled == 0 and repair.report.steps == len(truth) - 1


def test_wrong_steps_are_overruled_where_they_happened():
    """A SLAM dragged by a person for a few frames (3 cm a frame sideways), where the static scene favours semmap's
    registration: those steps are replaced, the trajectory ends within millimetres of the truth, and the report
    names the frames and the evidence of each."""
    truth = _truth()
    dragged = set(range(40, 46))
    slam, offset = [], np.eye(4)
    for i, pose in enumerate(truth):
        if i in dragged:
            offset = offset @ _pose(0.03)
        slam.append(offset @ pose)
    rng = np.random.default_rng(1)
    checks = [_noisy(s, rng) for s in _steps(truth)]
    repair = SlamRepair(RepairParams(translation_m=0.005, rotation_deg=0.5))
    out = _run(repair, slam, checks)
    assert _error(slam, truth) > 0.15  # the SLAM alone: 18 cm off
    assert _error(out, truth) < 0.01
    assert set(repair.report.overruled_frames) == dragged
    assert repair.report.spans() == [(40, 45)]
    judged = repair.report.judged
    assert [j["frame"] for j in judged] == sorted(dragged) and {j["winner"] for j in judged} == {"semmap"}
    assert judged[0]["t"] == 10.0 and judged[0]["matches"] == 200 and judged[0]["differ_mm"] > 20


def test_where_the_evidence_is_weak_or_contrary_the_slam_keeps_its_step():
    """The same disagreement while an object whose motion is not known yet is in view (a person who just came
    into view), but the static scene does not favour semmap's registration (too few matches, or the SLAM's motion
    explains them better: a fast turn that blurred the frames): the SLAM keeps every step. Without any judge at
    all (no images), the same."""
    truth = _truth()
    rng = np.random.default_rng(1)
    wrong_checks = [_pose(0.03) @ _noisy(s, rng) for s in _steps(truth)]
    for judge in (weak, favours_slam, None):
        repair = SlamRepair()
        out = [repair.update(0, truth[0], None)]
        for i in range(1, len(truth)):
            out.append(repair.update(i, truth[i], wrong_checks[i - 1], 1.0, moving_in_view=False, undecided=True,
                                     judge=judge))
        assert _error(out, truth) < 1e-9, judge
        assert repair.report.overruled == 0 and repair.report.kept == len(truth) - 1


def test_a_walker_in_view_is_evidence_too_but_a_contrary_scene_still_keeps_the_slams_step():
    """An object seen moving is itself evidence that a SLAM tracking it may be dragged: with a walker in view,
    semmap's registration wins a disagreement unless the static scene favours the SLAM's motion (a fast turn
    whose blur fooled the registration: the SLAM keeps its step)."""
    truth = _truth()
    rng = np.random.default_rng(1)
    wrong_checks = [_pose(0.03) @ _noisy(s, rng) for s in _steps(truth)]
    repair = SlamRepair()
    _run(repair, truth, wrong_checks, judge=weak)
    assert repair.report.overruled == len(truth) - 1 - 2  # (the first two steps have no window yet)
    repair = SlamRepair()
    out = _run(repair, truth, wrong_checks, judge=favours_slam)
    assert repair.report.overruled == 0 and _error(out, truth) < 1e-9


def test_the_evidence_of_a_few_consecutive_judgements_adds_up():
    """Each judgement alone favours semmap by 2 standard errors (below `min_t` 3): the fading sum of consecutive
    ones passes it from the second on, so a SLAM dragged for a while is repaired although no single frame pair
    shows it; a contrary judgement pulls the sum back."""
    truth = _truth(30)
    slam = [p @ _pose(0.01 * i) for i, p in enumerate(truth)]  # dragged 1 cm a frame
    checks = _steps(truth)
    verdicts = [2.0] * 20 + [-10.0] * 9

    def judge(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int) -> Verdict:
        return Verdict(verdicts[min(repair.report.steps - 1, len(verdicts) - 1)], 200, 1.0, 1.0)

    repair = SlamRepair()
    repair.update(0, slam[0], None)
    for i in range(1, len(slam)):  # (a person who came into view: no walker's evidence to add to the scene's)
        repair.update(i, slam[i], checks[i - 1], 1.0, moving_in_view=False, undecided=True, judge=judge)
    judged = [j for j in repair.report.judged if "t" in j]  # (the first frames: no window to judge over yet)
    winners = [j["winner"] for j in judged]
    assert winners[0] == "slam" and set(winners[1:17]) == {"semmap"}
    assert winners[-1] == "slam"


def test_a_long_record_of_verdicts_for_the_slam_does_not_keep_its_jump():
    """Twenty strong verdicts for the SLAM's steps, then it jumps 26 cm and the scene says so twice (t = 26): its
    record counts as one strong verdict, so the second verdict overrules the jump (with no walker in view)."""
    truth = _truth(30)
    slam = [p @ _pose(0.01 * i) for i, p in enumerate(truth)]  # 1 cm off the registration a frame ...
    for i in range(23, 30):
        slam[i] = slam[i] @ _pose(0.26)  # ... then a jump
    checks = _steps(truth)
    verdicts = [-26.0] * 21 + [26.0] * 8

    def judge(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
              from_frame: int | None = None) -> Verdict:
        return Verdict(verdicts[min(repair.report.steps - 1, len(verdicts) - 1)], 200, 1.0, 1.0)

    repair = SlamRepair()
    repair.update(0, slam[0], None)
    winners = []
    for i in range(1, len(slam)):
        repair.update(i, slam[i], checks[i - 1], 1.0, moving_in_view=False, undecided=True, judge=judge)
        winners.append(repair.last_winner)
    assert set(winners[2:21]) == {"slam"} and winners[21] == "slam" and winners[22] == "semmap"
    assert repair.evidence > 0


def test_lost_slam_is_carried_by_the_registration_then_by_constant_velocity():
    truth = _truth(60)
    slam: list[np.ndarray | None] = list(truth)
    for i in range(20, 30):
        slam[i] = None  # lost: ten frames without a pose
    # when it comes back in a new map (ORB-SLAM3 LOST), its first pose after the loss says nothing about the step
    shift = _pose(5.0, 2.0, 30.0)
    slam = [p if p is None or i < 30 else shift @ p for i, p in enumerate(slam)]
    checks: list[np.ndarray | None] = _steps(truth)
    for registered in (True, False):
        repair = SlamRepair()
        out = [repair.update(0, slam[0], None)]
        for i in range(1, len(slam)):
            if i == 20:
                repair.break_chain()  # (the front end says so: a new map)
            out.append(repair.update(i, slam[i], checks[i - 1] if registered else None, 1.0))
            assert repair.bridged == (slam[i] is None)
        assert repair.report.slam_missing == 11  # ten lost frames and the first one back
        # with registrations, their steps; without any, the mean of the last steps (the motion model)
        assert _error(out, truth) < (1e-6 if registered else 0.002)


def test_a_slam_back_in_the_same_map_continues_from_its_own_motion_over_the_gap():
    """ORB-SLAM3 RECENTLY_LOST, or a trajectory file without poses for a few frames: the frames in between were
    carried by a stand-in (here a registration 5 mm off per frame), but when the SLAM is back in the same map its
    motion over the whole gap places the next pose, so the stand-in's error does not stay in the trajectory."""
    truth = _truth(60)
    slam: list[np.ndarray | None] = [None if 20 <= i < 30 else p for i, p in enumerate(truth)]
    checks = [_pose(0.005) @ s for s in _steps(truth)]
    repair = SlamRepair()
    out = _run(repair, slam, checks, judge=favours_slam)
    assert repair.report.gaps_rejoined == 1 and repair.report.slam_missing == 10
    assert _error(out[30:], truth[30:]) < 1e-9  # back on the SLAM exactly
    assert _error(out[20:30], truth[20:30]) > 0.02  # (the stand-in drifted meanwhile)


def _dragged_then_relocalised() -> tuple[list[np.ndarray], list[np.ndarray | None], list[np.ndarray]]:
    """A walker drags the SLAM 8 mm a frame (frames 20-25), it loses track (26-28) and relocalises in its map (29
    on: its poses true again); the registrations are right."""
    truth = _truth(60)
    slam: list[np.ndarray | None] = [p if i < 20 or i >= 29 else None if i >= 26 else _pose(0.008 * (i - 19)) @ p
                                     for i, p in enumerate(truth)]
    return truth, slam, _steps(truth)


def test_a_slam_relocalised_after_a_drag_rejoins_from_where_it_was_last_believed():
    """Its motion over the gap contains the drag's undoing (5 cm back in one step); its motion from the last frame
    whose step the output took (19) does not. The static scene between that frame and the newest decides."""
    truth, slam, checks = _dragged_then_relocalised()

    def scene(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
              from_frame: int | None = None) -> Verdict:
        if from_frame is None:
            return favours_semmap(slam_motion, semmap_motion, steps)
        assert from_frame == 19
        true = np.linalg.inv(truth[from_frame]) @ truth[29]
        closer = step_difference(semmap_motion, true)[0] < step_difference(slam_motion, true)[0]
        return Verdict(10.0 if closer else -10.0, 200, 1.0, 1.0)

    repair = SlamRepair()
    out = _run(repair, slam, checks, judge=scene)
    assert repair.report.overruled == 6 and repair.report.gaps_rejoined == 1
    assert repair.report.rejoined_from_anchor == 1 and repair.anchor_frame == 59
    assert _error(out[29:], truth[29:]) < 1e-6
    # without evidence (too few static matches between the two frames) its motion over the gap stands
    weak_anchor = SlamRepair()
    out = _run(weak_anchor, slam, checks,
               judge=lambda a, b, steps, from_frame=None: weak(a, b, steps) if from_frame else favours_semmap(a, b, 1))
    assert weak_anchor.report.rejoined_from_anchor == 0 and weak_anchor.report.gaps_rejoined == 1
    assert _error(out[29:], truth[29:]) == pytest.approx(0.048, abs=0.002)


def test_an_anchor_too_far_back_to_judge_from_leaves_the_rejoin_to_the_gaps_start():
    """A drag over seconds: between the anchor (19) and the SLAM's return (29) the scene says nothing (too few static
    matches), but from the gap's start (25, the SLAM's last pose, where the output was held on the truth) it tells
    the motion from the anchor (true) from the motion over the gap (the drag's undoing: 5 cm off)."""
    truth, slam, checks = _dragged_then_relocalised()
    asked: list[int | None] = []

    def scene(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
              from_frame: int | None = None) -> Verdict:
        if from_frame is None:
            return favours_semmap(slam_motion, semmap_motion, steps)
        asked.append(from_frame)
        if from_frame == 19:
            return weak(slam_motion, semmap_motion, steps)
        true = np.linalg.inv(truth[from_frame]) @ truth[29]
        closer = step_difference(semmap_motion, true)[0] < step_difference(slam_motion, true)[0]
        return Verdict(10.0 if closer else -10.0, 200, 1.0, 1.0)

    repair = SlamRepair()
    out = _run(repair, slam, checks, judge=scene)
    assert asked == [19, 25] and repair.report.rejoined_from_anchor == 1
    assert _error(out[29:], truth[29:]) < 1e-6
    # where the anchor's scene speaks for the motion over the gap, the gap's start is not asked
    asked.clear()
    decided = SlamRepair()
    _run(decided, slam, checks,
         judge=lambda a, b, steps, from_frame=None: (asked.append(from_frame), favours_slam(a, b, 0))[1]
         if from_frame else favours_semmap(a, b, 1))
    assert asked == [19] and decided.report.rejoined_from_anchor == 0


def test_where_the_scene_cannot_say_the_cameras_motion_over_the_gap_tells_a_drag_from_its_undoing():
    """A walker drags the SLAM 5 cm a frame (30 cm), it loses track for 3 frames and relocalises in its map (as
    ORB-SLAM3 says, back from RECENTLY_LOST); the static scene
    has too few matches to judge the rejoin from either frame. Its motion over the gap (the 30 cm undone in one
    second's frames) breaks the camera's motion; its motion from the anchor continues it: that one is taken. A
    drag of 5 cm (the test above) is within the motion model's gates for both: the SLAM's motion over the gap."""
    truth = _truth(60)
    slam: list[np.ndarray | None] = [p if i < 20 or i >= 29 else None if i >= 26 else _pose(0.05 * (i - 19)) @ p
                                     for i, p in enumerate(truth)]
    repair = SlamRepair()
    out = _run(repair, slam, _steps(truth),
               judge=lambda a, b, steps, from_frame=None: weak(a, b, steps) if from_frame else favours_semmap(a, b, 1),
               same_map=True)
    assert repair.report.rejoined_from_anchor == 1 and repair.report.rejoin_by_motion == 1
    assert _error(out[29:], truth[29:]) < 0.01
    assert [j["rejoin_from"] for j in repair.report.judged if "rejoin_from" in j] == [25]


def test_behind_the_video_only_checked_steps_move_the_anchor_a_relocalised_slam_rejoins_from():
    """Real time, the front end behind: the dragged steps go unchecked (`unchecked`, no judge) but one, at frame 23,
    which a check over frames 20-23 overrules (`CheckedSlam._measure_over`). So the output no longer follows the
    SLAM, and when the SLAM relocalises (29) its motion over the gap would undo a drag the output partly did not
    take. The unchecked steps left the anchor at 19, where the two last agreed, and the rejoin is judged there even
    though nothing else is judged while behind (`judge_rejoin`): back on the truth. Had the unchecked steps moved
    the anchor, the output would keep the drag's undoing."""
    truth, slam, _ = _dragged_then_relocalised()

    def scene(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
              from_frame: int | None = None) -> Verdict:
        true = np.linalg.inv(truth[from_frame if from_frame is not None else 20]) @ truth[29 if from_frame else 23]
        closer = step_difference(semmap_motion, true)[0] < step_difference(slam_motion, true)[0]
        return Verdict(10.0 if closer else -10.0, 200, 1.0, 1.0)

    def run(anchor_stays: bool) -> tuple[SlamRepair, list[np.ndarray]]:
        repair = SlamRepair()
        out = [repair.update(0, slam[0], None)]
        for i in range(1, len(slam)):
            behind = 20 <= i <= 29 and i != 23
            check = None
            if i == 23:  # (the motion over 20-23 measured, as the step from frame 22's output: see `_measure_over`)
                check = np.linalg.inv(out[22]) @ out[20] @ np.linalg.inv(truth[20]) @ truth[23]
            elif not behind:
                check = np.linalg.inv(truth[i - 1]) @ truth[i]
            out.append(repair.update(i, slam[i], check, fitted_to_scene=i == 23, judge=None if behind else scene,
                                     unchecked=behind and anchor_stays, judge_rejoin=scene))
        return repair, out

    repair, out = run(anchor_stays=True)
    assert repair.report.overruled == 1 and repair.report.gaps_rejoined == 1
    assert repair.report.rejoined_from_anchor == 1
    assert _error(out[29:], truth[29:]) < 1e-6
    moved, out = run(anchor_stays=False)
    assert moved.report.rejoined_from_anchor == 0
    assert _error(out[29:], truth[29:]) > 0.01


def test_without_a_trustworthy_witness_a_jump_breaks_the_recent_motion():
    """Low-fitness registrations witness nothing; a SLAM step that jumps away from the camera's recent motion is
    refused where the static scene favours the motion model (counted as implausible), one that continues it stands
    (counted as unchecked). Where the scene favours the SLAM's jump (a fast turn), it stands too."""
    truth = _truth(40)
    slam = list(truth)
    slam[20:] = [_pose(0.2) @ p for p in truth[20:]]  # a 20 cm jump at frame 20
    checks = _steps(truth)
    fitness = [0.01] * len(checks)  # nothing registered well
    repair = SlamRepair(RepairParams(min_fitness=0.15))
    out = _run(repair, slam, checks, fitness)
    assert repair.report.implausible == 1 and repair.report.unchecked == len(truth) - 2
    assert _error(out, truth) < 0.01
    repair = SlamRepair(RepairParams(min_fitness=0.15))
    out = _run(repair, slam, checks, fitness, judge=favours_slam)
    assert repair.report.implausible == 0 and repair.report.kept >= 1
    assert _error(out, slam) < 1e-9


def test_untrusted_registrations_never_overrule():
    """A registration step that is itself implausible (a 1 m jump between two frames) does not overrule."""
    truth = _truth(30)
    checks = _steps(truth)
    checks[10] = _pose(1.0) @ checks[10]
    repair = SlamRepair()
    out = _run(repair, truth, checks)
    assert _error(out, truth) < 1e-9 and repair.report.overruled == 0


def test_state_restores_the_same_continuation():
    truth = _truth(80)
    slam = [(_pose(0.01 * (i >= 30)) @ p) for i, p in enumerate(truth)]
    checks = _steps(truth)
    whole = SlamRepair()
    expected = _run(whole, slam, checks)
    first = SlamRepair()
    _run(first, slam[:50], checks[:49])
    second = SlamRepair()
    second.restore(first.state())
    rest = [second.update(i, slam[i], checks[i - 1], judge=favours_semmap) for i in range(50, 80)]
    assert _error(rest, expected[50:]) < 1e-12
    assert second.report.counters() == whole.report.counters()
    assert first.state()["counters"] == first.report.counters()  # saved by name, not by position


def test_a_state_saved_with_positional_counters_still_restores():
    """Older journalled states held the counters as a list (6 long before `coast_limit`, then 8)."""
    repair = SlamRepair()
    state = repair.state()
    state["counters"] = [12, 3, 1, 2, 0, 4]
    repair.restore(state)
    counters = repair.report.counters()
    assert (counters["repair_steps"], counters["repair_overruled"], counters["repair_static"]) == (12, 3, 4)
    assert counters["repair_coast_limit"] == counters["repair_outvoted"] == 0


def test_step_difference():
    a, b = _pose(0.01), _pose(0.01, yaw_deg=2.0)
    dt, dr = step_difference(a, b)
    assert abs(dt) < 1e-12 and abs(dr - 2.0) < 1e-9


def test_static_scenes_keep_the_slams_steps():
    """With scope `moving` (the default) a step is checked only while an object is seen moving and for `hold_s`
    after: on a static scene a SLAM is better than frame-to-frame registration, so a noisy or even wrong
    registration changes nothing there; once a walker appears, the check is back."""
    truth = _truth(200)
    # registration 1 cm off on every step (beyond the 5 mm gate; within what a camera's motion may change, so it
    # is trusted: a registration breaking the recent motion by more witnesses nothing, see the car test)
    wrong_checks = [_pose(0.01) @ s for s in _steps(truth)]
    stamps = [i / 30 for i in range(len(truth))]
    repair = SlamRepair()
    out = [repair.update(0, truth[0], None, stamp=0.0, moving_in_view=False)]
    for i in range(1, 200):
        walker = 50 <= i < 55
        out.append(repair.update(i, truth[i], wrong_checks[i - 1], 1.0, moving_in_view=walker, stamp=stamps[i],
                                 judge=favours_semmap))
    r = repair.report
    # frames 50-54 hold a person, then 2 s (60 frames) of hold: 65 checked steps (the SLAM's steps continue the
    # recent motion and the wrong check's do not: the SLAM outvotes it, see the next test)
    assert r.overruled + r.outvoted == 65 and r.static == 199 - 65
    assert _error(out[:50], truth[:50]) < 1e-9
    always = SlamRepair(RepairParams(scope="always"))
    _run(always, truth, wrong_checks)
    # (the first two steps have no window of earlier frames to judge over: the SLAM keeps them)
    assert always.report.overruled == 197 and always.report.kept == 2


def test_a_registration_that_breaks_the_recent_motion_is_outvoted():
    """Two witnesses against one: where the SLAM's step continues the camera's recent motion and the registration's
    does not (KITTI 00, a slow car in a street at 10 Hz: three registrations 1-3 deg off turned 1.3 m into 6.9 m),
    the SLAM's step stands; where the SLAM breaks it (a person drags it), the registration still overrules."""
    speeds = [1.7] * 60
    truth, stamps = _car(60, speeds)
    checks: list[np.ndarray | None] = _steps(truth)
    checks[30] = checks[30] @ _pose(0.0, 0.1)  # the registration slid 10 cm sideways
    slam = list(truth)
    slam[45:] = [_pose(0.3) @ p for p in truth[45:]]  # the SLAM jumps 30 cm at frame 45
    repair = SlamRepair()
    out = [repair.update(0, slam[0], None, stamp=0.0)]
    for i in range(1, 60):
        out.append(repair.update(i, slam[i], checks[i - 1], 1.0, moving_in_view=True, stamp=stamps[i],
                                 judge=favours_semmap))
    assert repair.report.outvoted == 1 and repair.report.overruled == 1
    assert _error(out, truth) < 1e-6


def test_copy_is_the_slam_itself():
    """`odometry.repair: false`: the SLAM's steps untouched, only frames without a SLAM pose carried."""
    truth = _truth(40)
    slam: list[np.ndarray | None] = list(truth)
    slam[10] = None
    repair = SlamRepair()
    out = [repair.copy(i, p) for i, p in enumerate(slam)]
    assert _error(out[:10], truth[:10]) < 1e-12
    assert repair.report.slam_missing == 1 and repair.report.gaps_rejoined == 1 and repair.report.overruled == 0
    assert _error(out, truth) < 0.003 and _error(out[11:], truth[11:]) < 1e-9  # (back on the SLAM after the gap)


def _car(n: int, speeds: list[float]) -> tuple[list[np.ndarray], list[float]]:
    """A car at 10 Hz along x at the given speed (m/s) per frame, gently turning; poses and stamps."""
    poses, x = [np.eye(4)], 0.0
    for i in range(1, n):
        x += speeds[i] / 10.0
        poses.append(_pose(x, 0.0, 0.05 * i))
    return poses, [i / 10.0 for i in range(n)]


def test_a_car_at_10_hz_keeps_its_slams_steps():
    """Street scale: a SLAM on a car at 10 Hz (steps of 0.7 m, centimetres of jitter, braking from 7 to 3 m/s) is
    not replaced by a motion model that was built for a hand-held camera at 30 Hz, and a registration that slid
    along a featureless road ("stopped", but trusted by its fitness) does not overrule it: the output is the SLAM's
    own trajectory (KITTI 00's ORB estimate in the street world went from 0.42 m to 31 m before this)."""
    speeds = [7.0] * 40 + list(np.linspace(7.0, 3.0, 20)) + [3.0] * 40
    truth, stamps = _car(100, speeds)
    rng = np.random.default_rng(1)
    slam = [truth[0]] + [t @ _noisy(np.eye(4), rng, 0.01) for t in truth[1:]]  # 1 cm jitter per pose
    checks: list[np.ndarray | None] = [None] * 99
    checks[30] = np.eye(4)  # one registration says the car stood still
    repair = SlamRepair()
    out = [repair.update(0, slam[0], None, stamp=0.0)]
    for i in range(1, 100):
        out.append(repair.update(i, slam[i], checks[i - 1], 1.0, moving_in_view=True, stamp=stamps[i],
                                 judge=favours_semmap))
    assert _error(out, slam) < 1e-9
    assert repair.report.overruled == 0 and repair.report.implausible == 0


def test_a_step_fitted_to_the_scene_witnesses_at_a_cameras_rate_not_at_a_cars():
    """A step fitted to the static matches 6 cm off the true step (PnP on a far scene, frames far apart) overrules
    nothing on a car at 10 Hz, even where the scene's verdict favours it; on a hand-held camera at 30 Hz it
    witnesses (and there the scene decides)."""
    for rate, overruled in ((10.0, False), (30.0, True)):
        # (a car changing its speed by 0.6 m/s a frame: its SLAM's steps break the recent motion, so the scene judges)
        truth = _car(30, [2.0 + 0.6 * (i % 2) for i in range(30)])[0] if rate == 10.0 else _truth(30)
        checks = [_pose(0.06) @ s for s in _steps(truth)]
        repair = SlamRepair()
        repair.update(0, truth[0], None, stamp=0.0)
        for i in range(1, 30):
            repair.update(i, truth[i], checks[i - 1], 0.15, moving_in_view=True, stamp=i / rate,
                          judge=favours_semmap, fitted_to_scene=True)
        assert (repair.report.overruled > 0) == overruled, rate


def test_the_motion_model_carries_no_longer_than_max_coast_s():
    """Without a witness, a SLAM step that breaks the recent motion is refused; but a camera that changed its
    speed for good is not held at its old speed for ever: after `max_coast_s` the SLAM's steps count again."""
    truth = [_pose(0.01 * i) for i in range(30)] + [_pose(0.29 + 0.05 * i) for i in range(1, 91)]  # 0.3 -> 1.5 m/s
    stamps = [i / 30.0 for i in range(len(truth))]
    repair = SlamRepair(RepairParams(max_coast_s=0.5))
    out = [repair.update(0, truth[0], None, stamp=0.0)]
    for i in range(1, len(truth)):
        out.append(repair.update(i, truth[i], None, 0.0, moving_in_view=True, stamp=stamps[i],
                                 judge=favours_semmap))
    r = repair.report
    assert 10 <= r.implausible <= 16 and r.coast_limit == 1  # refused for half a second, then followed
    steps = _steps(out)
    assert np.allclose(steps[-1], _steps(truth)[-1])  # following the SLAM's new speed at the end


def _rotated(step: np.ndarray, rng: np.random.Generator, sigma_deg: float) -> np.ndarray:
    out = step.copy()
    out[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, np.radians(sigma_deg), 3)).as_matrix() @ out[:3, :3]
    return out


def _measured_run(truth: list[np.ndarray], stamps: list[float], noise_m: float, noise_deg: float,
                  check_noise_m: float = 0.0) -> tuple[SlamRepair, list[tuple[float, float]], list[np.ndarray]]:
    """A SLAM whose steps are off the truth by the noise, checked against a registration off by `check_noise_m`."""
    fixed = (0.01, np.radians(0.5))
    rng = np.random.default_rng(3)
    steps = _steps(truth)
    slam = [truth[0]]
    for s in steps:
        slam.append(slam[-1] @ _rotated(_noisy(s, rng, noise_m), rng, noise_deg))
    checks = [_noisy(s, rng, check_noise_m) if check_noise_m else s for s in steps]
    repair = SlamRepair(measured_sigmas_after=50)
    declared = [repair.declared_sigmas(fixed)]
    repair.update(0, slam[0], None, stamp=0.0, moving_in_view=False)
    for i in range(1, len(truth)):
        repair.update(i, slam[i], checks[i - 1], 1.0, moving_in_view=False, stamp=stamps[i])
        declared.append(repair.declared_sigmas(fixed))
    return repair, declared, slam


def test_declared_sigmas_are_measured_from_the_slams_own_consistency():
    """A trajectory file comes without a covariance. `file:` declared a fixed 1 cm and 0.5 deg a frame for any,
    six times looser in rotation than KITTI 00's ORB estimate, so biased landmark factors bent a trajectory that
    had closed its own loops (1.30 m -> 42.99 m). Now the sigmas are measured. A car at 10 Hz (no registration
    witnesses its metre steps): from its steps' roughness, a SLAM with 1 mm and 0.02 deg of step noise (per axis)
    declares about that, one with 5 mm and 0.3 deg about that; before `measured_sigmas_after` samples, and with
    it 0, the fixed sigmas stand; never looser than them; a restart keeps the measured ones."""
    fixed = (0.01, np.radians(0.5))
    truth, stamps = _car(300, [7.0] * 300)
    for noise_m, noise_deg in ((0.001, 0.02), (0.005, 0.3), (0.03, 2.0)):
        repair, declared, slam = _measured_run(truth, stamps, noise_m, noise_deg)
        assert declared[40] == fixed
        if noise_m > fixed[0]:  # (worse than the fixed sigmas: those)
            assert declared[-1] == fixed and repair.agreement.sigmas()[0] > fixed[0]
            continue
        assert declared[60] != fixed
        sigma_t, sigma_r = declared[-1]
        assert 0.7 * noise_m < sigma_t < 1.4 * noise_m, sigma_t
        assert 0.7 * noise_deg < np.degrees(sigma_r) < 1.4 * noise_deg, np.degrees(sigma_r)
        assert len(repair.agreement.agreement[0]) == 0  # (no witnessed step: the car's are beyond max_step_m)
        again = SlamRepair(measured_sigmas_after=50)
        again.restore(repair.state())
        assert again.agreement.sigmas() == repair.agreement.sigmas() == declared[-1]
        off = SlamRepair(measured_sigmas_after=0)
        _run(off, slam, _steps(truth))
        assert off.declared_sigmas(fixed) == fixed


def test_declared_sigmas_take_the_registrations_disagreement_where_it_witnessed():
    """A hand-held camera at 30 Hz: semmap's registration witnesses its steps (on a static scene too, where the
    repair leaves them unchecked). The disagreement holds the registration's noise as well (here 3 mm against the
    SLAM's 1 mm): an upper bound, and the larger of the two measures is declared."""
    truth = _truth(300)
    stamps = [i / 30.0 for i in range(300)]
    repair, declared, _ = _measured_run(truth, stamps, 0.001, 0.02, check_noise_m=0.003)
    assert len(repair.agreement.agreement[0]) == 299 and repair.report.static == 299
    expected = np.hypot(0.001, 0.003)
    assert 0.7 * expected < declared[-1][0] < 1.4 * expected, declared[-1][0]
    # a step the repair overruled is semmap's, not the SLAM's: it declares the fixed sigmas (Bonn crowd: 85 % of
    # the steps), the next one of the SLAM's own the measured ones again
    fixed = (0.01, np.radians(0.5))
    step = _steps(truth)[-1]
    repair.update(300, truth[-1] @ step @ _pose(0.05), step, 1.0, moving_in_view=True, stamp=10.0, judge=favours_semmap)
    assert repair.report.overruled == 1 and repair.declared_sigmas(fixed) == fixed
    repair.update(301, truth[-1] @ step @ _pose(0.05) @ step, step, 1.0, moving_in_view=True, stamp=10.0 + 1 / 30,
                  judge=favours_semmap)
    assert repair.report.overruled == 1 and repair.declared_sigmas(fixed) != fixed


def test_a_walker_lowers_the_bar_for_a_registration_not_for_the_motion_model():
    """With a walker in view an undecided scene lets semmap's registration win (the walker itself is evidence
    that the SLAM may be dragged), but not a hand-held camera's motion model, which measures nothing: a SLAM step
    that breaks the recent motion stands unless the scene favours the motion model by `min_t`. (A car's, at 10 Hz,
    keeps the walker's bar: its motion is smooth.)"""
    def undecided(slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int) -> Verdict:
        return Verdict(0.5, 200, 1.0, 1.0)

    truth = _truth(40)
    slam = list(truth)
    slam[20:] = [_pose(0.2) @ p for p in truth[20:]]  # a jump (or a sudden turn the SLAM saw right)
    checks = _steps(truth)
    repair = SlamRepair(RepairParams(min_fitness=0.15))
    out = _run(repair, slam, checks, [0.01] * len(checks), judge=undecided)  # no registration to witness
    assert repair.report.implausible == 0 and repair.report.kept >= 1
    assert _error(out, slam) < 1e-9
    repair = SlamRepair(RepairParams(min_fitness=0.15))
    _run(repair, slam, checks, [0.01] * len(checks), judge=favours_semmap)
    assert repair.report.implausible == 1
    repair = SlamRepair()  # a registration that witnesses every step
    out = _run(repair, slam, checks, judge=undecided)
    assert repair.report.overruled == 1 and _error(out, truth) < 0.01


def _lost_for(rate_hz: float, speed_mps: float, lost: int, half_life_s: float = 0.25,
              back: bool = False) -> tuple[SlamRepair, list[np.ndarray], list[np.ndarray]]:
    """A camera at `speed_mps` along x whose SLAM has no pose for `lost` frames after 30, with nothing to witness
    the steps (the front end behind in real time); `back`: the SLAM returns for 10 frames (its map: not said)."""
    n = 30 + lost + (10 if back else 0)
    truth = [_pose(speed_mps * i / rate_hz) for i in range(n)]
    slam = [None if 30 <= i < 30 + lost else p for i, p in enumerate(truth)]
    repair = SlamRepair(RepairParams(gap_half_life_s=half_life_s))
    out = [repair.update(i, s, None, 0.0, moving_in_view=False, stamp=i / rate_hz) for i, s in enumerate(slam)]
    return repair, out, truth


def test_a_gap_nothing_measured_slows_to_a_stop_at_a_hand_held_cameras_rate_not_at_a_cars():
    """Nothing measured the frames of a gap: a hand-held camera's motion over seconds is no straight line, so
    the motion model slows to a stop; a car keeps going. A SLAM back in the same map still rejoins."""
    walk = 29 / 30.0  # where the hand-held camera was when its SLAM left (frame 29, at 1 m/s)
    _, out, _ = _lost_for(30.0, 1.0, 120)  # 4 s lost
    assert 0.1 < out[-1][0, 3] - walk < 0.6  # (at its old speed: 4 m on)
    _, straight, _ = _lost_for(30.0, 1.0, 120, half_life_s=float("inf"))
    assert straight[-1][0, 3] - walk == pytest.approx(4.0, abs=0.01)
    _, car, truth = _lost_for(10.0, 7.0, 10)  # a car at 10 Hz, 1 s lost: its speed kept
    assert _error(car, truth) < 1e-6
    repair, back, truth = _lost_for(30.0, 1.0, 15, back=True)  # half a second lost, the SLAM back
    assert repair.report.gaps_rejoined == 1 and _error(back[45:], truth[45:]) < 1e-9
