"""The arbiter (semmap/algorithms/odometry/arbiter.py) on a rendered static scene: pure, no data needed."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from semmap.algorithms.odometry.arbiter import ArbiterParams, StepArbiter
from semmap.core.messages import DynamicBox

W, H = 640, 480
K = np.array([[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]])
# a room corner: back wall at z = 3 m, floor at y = 1 m, left wall at x = -1.5 m, a box face at z = 1.6 m
PLANES = [(np.array([0.0, 0.0, 1.0]), 3.0), (np.array([0.0, 1.0, 0.0]), 1.0), (np.array([1.0, 0.0, 0.0]), -1.5)]


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(cv2.resize(rng.integers(0, 255, (64, 64), dtype=np.uint8).astype(np.float32),
                                       (512, 512), interpolation=cv2.INTER_NEAREST), (3, 3), 0)


TEXTURES = [_texture(i) for i in range(4)]


def _render(camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RGB and depth (mm) of the corner seen from a camera pose (ray casting, nearest surface)."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    R, t = camera_to_world[:3, :3], camera_to_world[:3, 3]
    world_rays = rays @ R.T
    best = np.full((H, W), np.inf)
    colour = np.zeros((H, W), np.float32)
    surfaces = [*PLANES, (np.array([0.0, 0.0, 1.0]), 1.6)]
    for k, (n, d) in enumerate(surfaces):
        denom = world_rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (d - t @ n) / denom
        p = t + s[..., None] * world_rays
        ok = (s > 0.1) & np.isfinite(s)
        if k == 3:  # the box: only its face, 0.6 m wide
            ok &= (np.abs(p[..., 0] - 0.4) < 0.3) & (np.abs(p[..., 1] - 0.2) < 0.3)
        closer = ok & (s < best)
        axes = [a for a in range(3) if abs(n[a]) < 0.5]
        tex = TEXTURES[k]
        p = np.where(ok[..., None], p, 0.0)
        iu = (np.mod(p[..., axes[0]] * 150.0, 512)).astype(int)
        iv = (np.mod(p[..., axes[1]] * 150.0, 512)).astype(int)
        colour = np.where(closer, tex[iv.clip(0, 511), iu.clip(0, 511)], colour)
        best = np.where(closer, s, best)
    depth = np.where(np.isfinite(best), best * 1000.0, 0).astype(np.uint16)  # (ray z is 1: s is the depth)
    rgb = np.repeat(colour.clip(0, 255).astype(np.uint8)[..., None], 3, axis=2)
    return rgb, depth


def _pose(x: float, yaw_deg: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = (x, 0.0, 0.0)
    return T


def _arbiter(poses: list[np.ndarray], boxes: list[DynamicBox] | None = None) -> StepArbiter:
    arbiter = StepArbiter(ArbiterParams(window_frames=len(poses) - 1))
    for i, pose in enumerate(poses):
        rgb, depth = _render(pose)
        arbiter.push(i, rgb, depth, 0.001, K, list(boxes or []))
    return arbiter


def test_the_true_motion_wins_over_a_dragged_one_that_fits_the_image_nearly_as_well():
    """3 cm sideways with the half degree of yaw that keeps the far wall where it was: nearly the same image
    motion, but not the same geometry (the box and the near walls). The static scene tells them apart: the
    dragged motion loses decisively whichever side proposes it."""
    truth = [_pose(0.0, 0.0), _pose(0.005, 0.3), _pose(0.010, 0.6), _pose(0.015, 0.9)]
    arbiter = _arbiter(truth)
    true_motion = np.linalg.inv(truth[0]) @ truth[-1]
    dragged = true_motion @ _pose(0.03, np.degrees(0.03 / 3.0))
    semmap_right = arbiter.judge(dragged, true_motion, 3)
    slam_right = arbiter.judge(true_motion, dragged, 3)
    params = ArbiterParams()
    assert semmap_right.matches >= params.min_matches
    assert semmap_right.t > params.min_t and semmap_right.favours_semmap(params)
    assert slam_right.t < -params.min_t and not slam_right.favours_semmap(params)
    assert semmap_right.semmap_px < semmap_right.slam_px


def test_two_motions_that_agree_give_no_evidence_either_way():
    truth = [_pose(0.0, 0.0), _pose(0.004, 0.2), _pose(0.008, 0.4), _pose(0.012, 0.6)]
    arbiter = _arbiter(truth)
    true_motion = np.linalg.inv(truth[0]) @ truth[-1]
    verdict = arbiter.judge(true_motion, true_motion.copy(), 3)
    assert verdict.t == 0.0 and verdict.slam_px == verdict.semmap_px


def test_a_dynamic_box_over_the_whole_view_leaves_no_evidence():
    """Where the dynamic objects cover the image, no static match is left: weak evidence (the SLAM keeps its
    step), never a verdict drawn from the objects themselves."""
    truth = [_pose(0.0, 0.0), _pose(0.005, 0.3)]
    everything = DynamicBox(1, "person", (0.0, 0.0, float(W), float(H)), 0.5, 4.0, "moving")
    arbiter = _arbiter(truth, [everything])
    motion = np.linalg.inv(truth[0]) @ truth[-1]
    verdict = arbiter.judge(motion @ _pose(0.05, 0.0), motion, 1)
    assert verdict.matches < ArbiterParams().min_matches and not verdict.favours_semmap(ArbiterParams())


def test_a_window_longer_than_the_frames_held_is_no_judgement():
    arbiter = _arbiter([_pose(0.0, 0.0), _pose(0.005, 0.3)])
    verdict = arbiter.judge(np.eye(4), np.eye(4), 3)
    assert verdict.matches == 0 and verdict.t == 0.0


def test_a_pinned_frame_is_judged_from_after_the_window_has_moved_on():
    """A SLAM back after a gap is judged from the last frame the output took its step, or from the gap's start
    (repair.py `_rejoin`): each stays held, one a role, however far the window has moved."""
    truth = [_pose(0.004 * i, 0.2 * i) for i in range(8)]
    arbiter = StepArbiter(ArbiterParams(window_frames=2))
    for i, pose in enumerate(truth):
        rgb, depth = _render(pose)
        arbiter.push(i, rgb, depth, 0.001, K, [])
        if i in (1, 2):
            arbiter.pin(i)
        if i in (0, 3):
            arbiter.pin(i, "gap")
    assert arbiter.frames_held == 3 and arbiter.holds(2) and not arbiter.holds(1)
    assert arbiter.holds(3) and not arbiter.holds(0)  # (the other role's frame, replaced in its own role only)
    true_motion = np.linalg.inv(truth[2]) @ truth[-1]
    dragged = true_motion @ _pose(0.03, np.degrees(0.03 / 3.0))
    verdict = arbiter.judge(dragged, true_motion, 0, from_frame=2)
    assert verdict.favours_semmap(ArbiterParams()) and verdict.semmap_px < verdict.slam_px
    assert arbiter.judge(dragged, true_motion, 0, from_frame=1).matches == 0  # (no longer held: no judgement)


def test_a_step_fitted_to_the_static_matches_recovers_the_motion_the_boxes_leave_visible():
    """Where people cover most of the view (a box over the left two thirds), the background's corners that are
    left still fix the step: the fitted step is within millimetres of the truth; a box over everything leaves
    nothing to fit."""
    truth = [_pose(0.0, 0.0), _pose(0.02, 0.5)]
    people = DynamicBox(1, "person", (0.0, 0.0, 420.0, float(H)), 0.5, 4.0, "moving")
    step, inliers = _arbiter(truth, [people]).sparse_step()
    assert step is not None and inliers >= ArbiterParams().sparse_min_inliers
    error = np.linalg.inv(np.linalg.inv(truth[0]) @ truth[1]) @ step
    assert np.linalg.norm(error[:3, 3]) < 0.003
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(error[:3, :3]).as_rotvec())) < 0.1
    everything = DynamicBox(1, "person", (0.0, 0.0, float(W), float(H)), 0.5, 4.0, "moving")
    assert _arbiter(truth, [everything]).sparse_step() == (None, 0)


def test_the_sparse_witness_alone_repairs_a_dragged_slam():
    """`repair_witness: sparse`: no dense registration, each checked step is the fit to the static ORB matches, and
    it still overrules a SLAM that something drags 2 cm a frame sideways."""
    from semmap.algorithms.odometry.base import OdometryInput
    from semmap.algorithms.odometry.checked import CheckedSlam
    from semmap.algorithms.odometry.repair import RepairParams

    check = CheckedSlam(RepairParams(scope="always", witness="sparse"), dynamic_mask="range")
    truth = [_pose(0.01 * i, 0.3 * i) for i in range(6)]
    pose = np.eye(4)
    for i, true_pose in enumerate(truth):
        dragged = true_pose.copy()
        dragged[:3, 3] += (0.02 * i, 0.0, 0.0)
        rgb, depth = _render(true_pose)
        frame = OdometryInput(i, i / 30.0, None, rgb, depth, 0.001, K, [])
        pose = check.pose(frame, dragged)
    counters = check.counters()
    assert counters["repair_sparse_steps"] == counters["repair_steps"] == 5  # (every step, none registered densely)
    # the first two steps, before the judged window (3 frames) is full, stay the SLAM's: 4 cm of its 10 cm drag
    assert counters["repair_overruled"] == 3
    assert np.linalg.norm(pose[:3, 3] - truth[-1][:3, 3]) < 0.045


def test_a_front_end_behind_the_video_has_every_nth_step_checked_over_the_frames_since():
    """Real time, the front end behind the video (frames queued): no step gets a check of its own, but every 3rd is
    checked over the 3 frames since the last, fitted to the static scene's matches with the people left out by
    their depth band (here a box over the whole view, its band nearer than any wall: by box nothing would be left).
    A SLAM that something drags 1 cm a frame sideways is pulled back at each such check; with
    `behind_check_every` 0 nothing is checked while behind and the output is the SLAM's."""
    from semmap.algorithms.odometry.base import OdometryInput
    from semmap.algorithms.odometry.checked import CheckedSlam
    from semmap.algorithms.odometry.repair import RepairParams

    truth = [_pose(0.005 * i, 0.2 * i) for i in range(11)]
    renders = [_render(pose) for pose in truth]
    near_person = DynamicBox(1, "person", (0.0, 0.0, float(W), float(H)), 0.3, 0.8, "moving")

    def run(every: int) -> tuple[np.ndarray, dict[str, int]]:
        check = CheckedSlam(RepairParams(scope="always", behind_check_every=every), dynamic_mask="range")
        for i, true_pose in enumerate(truth):
            dragged = true_pose.copy()
            dragged[:3, 3] += (0.01 * i, 0.0, 0.0)
            frame = OdometryInput(i, i / 30.0, None, *renders[i], 0.001, K, [near_person], behind=True)
            pose = check.pose(frame, dragged)
        return pose, check.counters()

    pose, counters = run(3)
    # frame 2 is too early (3 frames back are not held yet), frames 5 and 8 are checked and overruled
    assert counters["repair_checked_behind"] == 2 and counters["repair_overruled"] == 2
    assert counters["repair_skipped_behind"] == 11 - 2
    # the drag before the first check and after the last stays: 2 + 2 cm of the SLAM's 10
    assert np.linalg.norm(pose[:3, 3] - truth[-1][:3, 3]) < 0.05
    unchecked, counters = run(0)
    assert counters["repair_checked_behind"] == 0 and counters["repair_overruled"] == 0
    assert np.linalg.norm(unchecked[:3, 3] - truth[-1][:3, 3]) > 0.095
