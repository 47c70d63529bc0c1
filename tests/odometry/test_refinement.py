"""A SLAM's refinement at its end, taken into the odometry: its own steps only, the whole run or none of it."""

from __future__ import annotations

import numpy as np

from semmap.algorithms.odometry.refinement import OutputStep, refine_outputs


def _at(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[0, 3] = x
    return pose


def test_the_slams_own_steps_take_their_refined_motion_and_semmaps_keep_theirs():
    """Frames 0-3: the SLAM's steps 0->1 and 2->3, semmap's step 1->2 (it overruled the SLAM there). The refined
    trajectory moves 2 cm a frame where the tracked one moved 1 cm; the overruled step stays 5 cm."""
    outputs = [OutputStep(0, 0.0, _at(0.0), False), OutputStep(1, 0.1, _at(0.01), True),
               OutputStep(2, 0.2, _at(0.06), False), OutputStep(3, 0.3, _at(0.07, 1.0), True)]
    refined = [(0.0, _at(0.5)), (0.1, _at(0.52)), (0.2, _at(0.54)), (0.3, _at(0.56, 2.0))]
    result = refine_outputs(outputs, refined, moving_seen=0, overruled=0)
    assert not result.withheld and result.frame_ids == [1, 2, 3]
    x = [float(p[0, 3]) for p in result.poses]
    np.testing.assert_allclose(x, [0.02, 0.07, 0.09], atol=1e-9)  # (the first pose stays where the output put it)
    yaw = np.degrees(np.arctan2(result.poses[-1][1, 0], result.poses[-1][0, 0]))
    assert abs(yaw - 2.0) < 1e-9  # (its refined rotation, not the tracked 1 degree)


def test_a_step_whose_ends_it_did_not_save_keeps_the_output():
    outputs = [OutputStep(0, 0.0, _at(0.0), False), OutputStep(1, 0.1, _at(0.01), True),
               OutputStep(2, 0.2, _at(0.02), True)]
    refined = [(0.0, _at(0.0)), (0.2, _at(0.1))]  # (frame 1: it did not save one)
    result = refine_outputs(outputs, refined, moving_seen=0, overruled=0)
    np.testing.assert_allclose([p[0, 3] for p in result.poses], [0.01, 0.02], atol=1e-9)


def test_nothing_is_taken_where_people_dragged_the_slam_or_there_is_no_refinement():
    """Objects seen moving and steps overruled: none of it. Objects seen moving that made semmap overrule nothing
    (a false box flickering on a static scene), or steps overruled with nothing seen moving: it is taken."""
    outputs = [OutputStep(0, 0.0, _at(0.0), False), OutputStep(1, 0.1, _at(0.01), True)]
    refined = [(0.0, _at(0.0)), (0.1, _at(0.05))]
    dragged = refine_outputs(outputs, refined, moving_seen=2, overruled=30)
    assert dragged.frame_ids == [] and "2 object(s) were seen moving and semmap overruled 30" in dragged.withheld
    for moving, overruled in ((2, 0), (0, 3)):
        taken = refine_outputs(outputs, refined, moving_seen=moving, overruled=overruled)
        assert taken.frame_ids == [1] and taken.withheld == ""
    none = refine_outputs(outputs, [], moving_seen=0, overruled=0)
    assert none.frame_ids == [] and "saved no refinement" in none.withheld


def _stats(backend: dict, odometry: dict) -> dict:
    return {"services": {"backend": {"service": "backend", "counters": backend},
                         "odometry": {"service": "odometry", "counters": odometry}}}


def test_the_summary_says_what_became_of_the_refinement_and_counts_what_was_passed_over():
    """Every end of a refinement is said where a user reads the run: taken (with the frames the graph did not hold
    as measured), withheld, late, or sent to a backend that was not waiting for it (its odometry.mode differs)."""
    from semmap.runtime.summary import refinement_note

    sent = {"refinement_frames": 999}
    assert refinement_note(_stats({"odometry_refined_frames": 999}, sent)) == "taken into semmap's result (999 frames)"
    note = refinement_note(_stats({"odometry_refined_frames": 996, "odometry_refinement_passed_over": 3}, sent))
    assert "996 frames; 3 passed over" in note
    assert "not taken" in refinement_note(_stats({"odometry_refinement_withheld": 1}, sent))
    assert "in time" in refinement_note(_stats({"odometry_refinement_timeouts": 1}, sent))
    assert "not waiting" in refinement_note(_stats({}, sent))
    assert refinement_note(_stats({}, {})) == refinement_note({}) == ""
