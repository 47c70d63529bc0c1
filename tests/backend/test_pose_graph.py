"""PoseGraph on known synthetic graphs: drift correction, no harm to good odometry, robustness, merges,
relative-pose constraints, interpolation of non-node frames and late / out-of-order inputs."""

from __future__ import annotations

import copy
import math

import gtsam
import msgspec
import numpy as np
import pytest
from backend_sim import (
    FPS,
    TIGHT_SIGMAS,
    Scene,
    drifting,
    max_position_error,
    observe,
    optimized,
    run_graph,
    square_path,
)
from gtsam.symbol_shorthand import X

from semmap.algorithms.backend.pose_graph import BackendParams, PoseGraph, PoseGraphError
from semmap.algorithms.evaluation import ate_rmse
from semmap.core.geometry import interpolate_pose
from semmap.core.messages import Observation, Observations, OdometryPose

UP = np.array([0.0, 0.0, 1.0])


def square_scene(seed: int, every: int = 1, n: int = 100) -> Scene:
    rng = np.random.default_rng(seed)
    gt = square_path(n)
    landmarks = np.column_stack([rng.uniform(0.8, 3.2, 6), rng.uniform(0.8, 3.2, 6), rng.uniform(0.3, 1.3, 6)])
    scene = Scene(gt, drifting(gt, seed, UP), landmarks)
    observe(scene, rng, (0.03, 0.03), every=every)
    return scene


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_drift_on_a_square_is_corrected_and_landmarks_recovered(seed: int, kernel: str) -> None:
    scene = square_scene(seed)
    graph, _ = run_graph(scene, BackendParams(robust_kernel=kernel))
    ate_odometry = ate_rmse(scene.stamped_gt, scene.stamped_odometry)
    ate_optimized = ate_rmse(scene.stamped_gt, optimized(graph))
    assert ate_odometry > 0.05  # the drift is real
    # measured 0.082/0.068/0.066 -> huber 0.012/0.017/0.010 m, cauchy (the default; it gives up a little
    # efficiency on purely Gaussian noise like this for heavy tails) 0.013/0.0169/0.010 m
    assert ate_optimized < ate_odometry / (4.0 if kernel == "huber" else 3.8)
    ids, positions = graph.landmark_positions()
    assert ids.tolist() == list(range(6))
    # anchored at the first (true) pose: no alignment needed
    assert np.max(np.linalg.norm(positions - scene.landmarks[ids], axis=1)) < 0.05


def test_perfect_odometry_with_tight_sigmas_is_not_moved() -> None:
    gt = square_path(100)
    rng = np.random.default_rng(0)
    landmarks = np.column_stack([rng.uniform(0.8, 3.2, 6), rng.uniform(0.8, 3.2, 6), rng.uniform(0.3, 1.3, 6)])
    exact = Scene(gt, [p.copy() for p in gt], landmarks, sigmas=TIGHT_SIGMAS)
    observe(exact, rng, (1e-9, 1e-9))  # exact observations: a consistent graph must stay where it is
    graph, _ = run_graph(exact)
    assert max_position_error(gt, [p for _, p in optimized(graph)]) < 0.001
    noisy = Scene(gt, [p.copy() for p in gt], landmarks, sigmas=TIGHT_SIGMAS)
    observe(noisy, rng, (0.03, 0.06))  # 3-6 cm centroid noise against 0.2 mm / 0.01 deg per frame
    graph, _ = run_graph(noisy)
    assert ate_rmse(noisy.stamped_gt, optimized(graph)) < 0.002  # measured 0.3-1.1 mm
    assert max_position_error(gt, [p for _, p in optimized(graph)]) < 0.01


def test_one_wrong_association_two_metres_off_does_not_wreck_the_trajectory() -> None:
    scene = square_scene(0, every=6)
    clean = ate_rmse(scene.stamped_gt, optimized(run_graph(scene)[0]))
    bad = copy.deepcopy(scene)
    first = bad.observations[60][0]
    wrong = np.array(first.point_camera) + np.array([2.0, 0.0, 0.0])
    bad.observations[60].append(Observation(first.landmark_id, "thing", tuple(wrong.tolist()), first.sigma, 0.1))
    huber = ate_rmse(scene.stamped_gt, optimized(run_graph(bad, BackendParams(robust_kernel="huber"))[0]))
    cauchy = ate_rmse(scene.stamped_gt, optimized(run_graph(bad, BackendParams(robust_kernel="cauchy"))[0]))
    plain = ate_rmse(scene.stamped_gt, optimized(run_graph(bad, BackendParams(robust_kernel="none"))[0]))
    assert huber < clean * 1.15 + 0.001 and cauchy < clean * 1.15 + 0.001  # measured 17.6 / 19.1 vs 17.0 mm
    assert plain > 1.5 * huber  # without a kernel the same outlier costs more (measured 41.4 mm)


def test_landmarks_enter_the_graph_only_after_enough_observations() -> None:
    graph = PoseGraph(BackendParams(min_observations_per_landmark=3))
    obs = Observation(7, "cup", (0.0, 0.0, 2.0), 0.03, 0.1)
    for i in range(3):
        graph.add_odometry(i, i / FPS, np.eye(4), 0.003, 0.005, keyframe=False)
        graph.add_observations(i, [obs])
        graph.update()
        ids, positions = graph.landmark_positions()
        assert len(ids) == (1 if i == 2 else 0)
    assert ids.tolist() == [7] and np.allclose(positions[0], [0.0, 0.0, 2.0], atol=1e-6)
    assert graph.num_nodes == 3  # the waiting observations made their frames nodes once the landmark counted


def test_landmark_constraints_can_be_switched_off() -> None:
    """`backend.landmark_constraints: false` (the ablation): observations are counted, the graph is odometry."""
    graph = PoseGraph(BackendParams(min_observations_per_landmark=1, landmark_constraints=False))
    graph.add_odometry(0, 0.0, np.eye(4), 0.003, 0.005)
    graph.add_observations(0, [Observation(1, "cup", (0.0, 0.0, 2.0), 0.03, 0.1)])
    graph.update()
    assert graph.counters["observations_ignored"] == 1 and graph.num_landmarks == 0


def test_degenerate_observations_are_dropped() -> None:
    graph = PoseGraph(BackendParams(min_observations_per_landmark=1))
    graph.add_odometry(0, 0.0, np.eye(4), 0.003, 0.005)
    graph.add_observations(0, [Observation(1, "cup", (0.0, 0.0, 0.0), 0.03, 0.1)])
    graph.update()
    assert graph.counters["observations_dropped"] == 1 and graph.num_landmarks == 0


def test_merged_duplicates_close_the_loop() -> None:
    """After the revisit the associator made new copies of every landmark; merging them is a loop closure."""
    scene = square_scene(3)
    ideal = ate_rmse(scene.stamped_gt, optimized(run_graph(scene)[0]))

    def relabel(frame: int, obs: list[Observation]) -> list[Observation]:
        return [msgspec.structs.replace(o, landmark_id=o.landmark_id + 100) for o in obs] if frame >= 50 else obs

    duplicated = copy.deepcopy(scene)
    duplicated.observations = {f: relabel(f, o) for f, o in scene.observations.items()}
    split, _ = run_graph(duplicated)
    assert graph_ids(split) == list(range(6)) + list(range(100, 106))

    merged = PoseGraph()
    for i, pose in enumerate(duplicated.odometry):
        merged.add_odometry(i, i / FPS, pose, *duplicated.sigmas)
        merged.add_observations(i, duplicated.observations.get(i, []))
        if i == 80:
            for j in range(6):
                merged.merge_landmarks(100 + j, j)
        merged.update()
    assert graph_ids(merged) == list(range(6))
    assert merged.resolve_landmark(103) == 3
    ate_split = ate_rmse(scene.stamped_gt, optimized(split))
    ate_merged = ate_rmse(scene.stamped_gt, optimized(merged))
    assert ate_merged < 0.75 * ate_split  # measured 10.1 vs 16.5 mm
    assert abs(ate_merged - ideal) < 0.001  # as good as if the duplicates had never been made
    _, positions = merged.landmark_positions()
    assert np.max(np.linalg.norm(positions - scene.landmarks, axis=1)) < 0.05


def graph_ids(graph: PoseGraph) -> list[int]:
    return graph.landmark_positions()[0].tolist()


def test_merge_bookkeeping() -> None:
    graph = PoseGraph(BackendParams(min_observations_per_landmark=2))
    graph.add_odometry(0, 0.0, np.eye(4), 0.003, 0.005)
    seen = [Observation(1, "cup", (0.0, 0.0, 2.0), 0.03, 0.1)]
    graph.add_observations(0, seen * 2)  # landmark 1 active
    graph.add_observations(0, [Observation(2, "cup", (0.1, 0.0, 2.0), 0.03, 0.1)])  # 2 waits (1 of 2)
    graph.merge_landmarks(1, 2)  # the survivor adopts the absorbed variable and takes its waiting observation
    graph.update()
    assert graph_ids(graph) == [2]
    graph.add_observations(0, [Observation(3, "cup", (0.0, 0.0, 3.0), 0.03, 0.1)])
    graph.add_observations(0, [Observation(4, "cup", (0.0, 0.0, 3.0), 0.03, 0.1)])
    graph.merge_landmarks(4, 3)  # two waiting ones pool their counts: 2 >= 2, so 3 becomes a variable
    graph.merge_landmarks(3, 3)  # no-op
    graph.update()
    assert graph_ids(graph) == [2, 3]
    graph.merge_landmarks(3, 2)  # both in the graph: joined by a zero BetweenFactorPoint3
    graph.add_observations(0, [Observation(4, "cup", (0.0, 0.0, 2.5), 0.03, 0.1)])  # 4 -> 3 -> 2
    graph.update()
    ids, positions = graph.landmark_positions()
    assert ids.tolist() == [2] and graph.resolve_landmark(4) == 2
    assert abs(positions[0][2] - 2.5) < 0.2 and graph.counters["merges"] == 3


def test_relative_pose_constraint_closes_a_loop() -> None:
    scene = square_scene(0)
    scene.observations = {}
    graph, _ = run_graph(scene)
    end_error = np.linalg.norm(graph.corrected_pose(99)[:3, 3] - scene.gt[99][:3, 3])
    T_ab = np.linalg.inv(scene.gt[0]) @ scene.gt[99]  # e.g. ICP of the last view against the first
    graph.add_relative_pose_constraint(0, 99, T_ab, 0.01, math.radians(0.5))
    graph.update()
    closed_error = np.linalg.norm(graph.corrected_pose(99)[:3, 3] - scene.gt[99][:3, 3])
    assert end_error > 0.1 and closed_error < end_error / 5  # measured 0.29 -> 0.028 m
    closed_ate = ate_rmse(scene.stamped_gt, optimized(graph))
    assert closed_ate < ate_rmse(scene.stamped_gt, scene.stamped_odometry) / 3  # measured 0.082 -> 0.021 m
    # a grossly wrong constraint (robust by default) must not drag the trajectory away
    wrong = np.linalg.inv(scene.gt[10]) @ scene.gt[90]
    wrong[:3, 3] += [1.0, 0.0, 0.0]
    graph.add_relative_pose_constraint(10, 90, wrong, 0.01, math.radians(0.5))
    graph.update()
    assert ate_rmse(scene.stamped_gt, optimized(graph)) < 1.5 * closed_ate
    with pytest.raises(PoseGraphError):
        graph.add_relative_pose_constraint(0, 1000, T_ab, 0.01, 0.01)
    with pytest.raises(PoseGraphError):
        graph.add_relative_pose_constraint(0, 1, T_ab, 0.0, 0.01)


def test_non_node_frames_are_interpolated_from_the_previous_node() -> None:
    scene = square_scene(2, every=3)
    graph, _ = run_graph(scene, keyframe_every=5)
    ids, stamps, poses = graph.corrected_poses()
    assert ids.tolist() == list(range(100)) and np.allclose(stamps, np.arange(100) / FPS)
    expected_nodes = {i for i in range(100) if i % 5 == 0 or i % 3 == 0}
    assert graph.num_nodes == len(expected_nodes)
    for f in (1, 2, 7, 98):  # neither keyframes nor observed
        assert f not in expected_nodes
        prev = max(n for n in expected_nodes if n < f)
        want = graph.corrected_pose(prev) @ np.linalg.inv(scene.odometry[prev]) @ scene.odometry[f]
        assert np.allclose(poses[f], want, atol=1e-9) and np.allclose(graph.corrected_pose(f), want, atol=1e-9)
    assert ate_rmse(scene.stamped_gt, optimized(graph)) < ate_rmse(scene.stamped_gt, scene.stamped_odometry) / 3


def test_late_observations_insert_nodes_and_match_in_order_processing() -> None:
    """Observations of non-keyframes that arrive after later odometry split an existing odometry factor."""
    scene = square_scene(0, every=3)
    in_order, _ = run_graph(scene, keyframe_every=10)
    late = PoseGraph()
    for i, pose in enumerate(scene.odometry):
        late.add_odometry(i, i / FPS, pose, *scene.sigmas, keyframe=i % 10 == 0)
        if i - 4 in scene.observations:  # the associator is four frames behind
            late.add_observations(i - 4, scene.observations[i - 4])
        late.update()
    for f in range(96, 100):
        late.add_observations(f, scene.observations.get(f, []))
    late.update()
    assert late.counters["factors_replaced"] > 0
    a, b = optimized(in_order), optimized(late)
    assert max_position_error([p for _, p in a], [p for _, p in b]) < 0.005  # measured 1.6 mm


def test_observations_before_their_odometry_wait_for_it() -> None:
    graph = PoseGraph(BackendParams(min_observations_per_landmark=1))
    graph.add_odometry(0, 0.0, np.eye(4), 0.003, 0.005)
    graph.add_observations(1, [Observation(5, "cup", (0.0, 0.0, 2.0), 0.03, 0.1)])
    graph.update()
    assert graph.num_landmarks == 0 and graph.counters["observations_waiting_for_odometry"] == 1
    pose = np.eye(4)
    pose[0, 3] = 1.0
    graph.add_odometry(1, 1 / FPS, pose, 0.003, 0.005, keyframe=False)
    graph.update()
    ids, positions = graph.landmark_positions()
    assert ids.tolist() == [5] and np.allclose(positions[0], [1.0, 0.0, 2.0], atol=1e-6)


def test_repeated_odometry_replaces_the_earlier_one() -> None:
    scene = square_scene(0, n=20)
    graph = PoseGraph()
    for i, pose in enumerate(scene.odometry):
        graph.add_odometry(i, i / FPS, pose, *scene.sigmas)
    graph.update()
    moved = [p.copy() for p in scene.odometry]
    for f in (5, 19):
        moved[f][:3, 3] += [0.2, -0.1, 0.05]
        graph.add_odometry(f, f / FPS, moved[f], *scene.sigmas)
    graph.update()
    _, _, poses = graph.corrected_poses()
    assert max_position_error(list(poses), moved) < 1e-6  # without landmarks the estimate is the odometry


def test_incremental_estimate_matches_a_batch_solve() -> None:
    """iSAM2 (relinearizeSkip 1, threshold 0.001) must end where Levenberg-Marquardt on all factors ends."""
    scene = square_scene(3, every=2)
    graph, _ = run_graph(scene)
    factors = graph._isam.getFactorsUnsafe()
    batch_graph = gtsam.NonlinearFactorGraph()
    for i in range(factors.size()):
        if factors.exists(i):
            batch_graph.add(factors.at(i))
    estimate = graph._isam.calculateEstimate()
    batch = gtsam.LevenbergMarquardtOptimizer(batch_graph, estimate).optimize()
    worst = max(np.linalg.norm(estimate.atPose3(X(f)).translation() - batch.atPose3(X(f)).translation())
                for f in range(100))
    assert worst < 0.002  # measured 0.3 mm


def test_message_helpers_apply_merges_before_observations() -> None:
    graph = PoseGraph(BackendParams(min_observations_per_landmark=1))
    graph.add_odometry_message(OdometryPose("r1", 0, 0.0, np.eye(4), True, 0.003, 0.005))
    graph.add_observations_message(Observations("r1", 0, 0.0, [Observation(1, "cup", (0.0, 0.0, 2.0), 0.03, 0.1)]))
    graph.add_observations_message(Observations("r1", 0, 0.0, [Observation(2, "cup", (0.0, 0.0, 2.0), 0.03, 0.1)],
                                                merges=[(1, 2)]))
    graph.update()
    assert graph_ids(graph) == [2]


def test_params_from_config() -> None:
    params = BackendParams(robust_kernel="cauchy", robust_k=2, min_observations_per_landmark=2)
    assert params.robust_k == 2.0 and isinstance(params.robust_k, float)
    assert BackendParams(**params.model_dump()) == params
    with pytest.raises(ValueError, match="robust_kernal"):
        BackendParams(robust_kernal="huber")
    with pytest.raises(ValueError, match="robust_kernel"):
        BackendParams(robust_kernel="tukey")
    with pytest.raises(ValueError):
        BackendParams(prior_sigma_translation_m=0.0)
    with pytest.raises(ValueError):
        BackendParams(min_observations_per_landmark=1.5)  # type: ignore[arg-type]
    with pytest.raises(PoseGraphError):
        PoseGraph().add_odometry(0, 0.0, np.full((4, 4), np.nan), 0.01, 0.01)


def test_before_any_update_the_odometry_is_returned() -> None:
    graph = PoseGraph()
    ids, stamps, poses = graph.corrected_poses()
    assert ids.shape == (0,) and poses.shape == (0, 4, 4)
    graph.add_odometry(3, 0.1, np.eye(4), 0.003, 0.005)
    ids, _, poses = graph.corrected_poses()
    assert ids.dtype == np.int64 and ids.tolist() == [3] and np.allclose(poses[0], np.eye(4))
    with pytest.raises(KeyError):
        graph.corrected_pose(4)


def _moved_object_graph(retire_at: int | None) -> tuple[PoseGraph, list[np.ndarray]]:
    """A camera moving 1 cm a frame along x with exact odometry (declared 1 cm / 0.5 deg per frame); a chair
    (landmark 7) seen from every frame, pushed 0.3 m sideways at frame 30; a cup (landmark 8) that stays. The
    associator retires the chair at `retire_at` (its Observations carry `retired`)."""
    graph = PoseGraph(BackendParams())
    poses = []
    chair, cup = np.array([0.5, 2.0, 0.0]), np.array([-0.3, 2.5, 0.4])
    for f in range(60):
        pose = np.eye(4)
        pose[0, 3] = 0.01 * f
        poses.append(pose)
        graph.add_odometry_message(OdometryPose("robot1", f, f / FPS, pose, True, 0.01, math.radians(0.5), "gt"))
        where = chair + (np.array([0.3, 0.0, 0.0]) if f >= 30 else 0.0)
        obs = []
        for lid, world in ((7, where), (8, cup)):
            if lid == 7 and retire_at is not None and f >= retire_at:
                continue  # the associator removed it: no more observations of it
            point = world - pose[:3, 3]  # camera axes = world axes here
            obs.append(Observation(lid, "chair" if lid == 7 else "cup", tuple(point), 0.02, 0.5))
        graph.add_observations_message(Observations("robot1", f, f / FPS, obs,
                                                    retired=[7] if f == retire_at else []))
        graph.update()
    return graph, poses


def test_a_retired_landmark_stops_pulling_the_trajectory() -> None:
    kept, truth = _moved_object_graph(None)
    retired, _ = _moved_object_graph(45)

    def worst(graph: PoseGraph) -> float:
        ids, _, poses = graph.corrected_poses()
        return max(float(np.linalg.norm(p[:3, 3] - truth[int(i)][:3, 3])) for i, p in zip(ids, poses, strict=True))

    # the moved chair bends the trajectory while its factors stay; retired, they are gone and the cup and the
    # exact odometry hold it (measured: 0.10 m vs 1e-11 m)
    assert worst(kept) > 0.05
    assert worst(retired) < 0.01
    assert retired.counters["landmarks_retired"] == 1 and retired.counters["factors_retired"] >= 40
    ids, _ = retired.landmark_positions()
    assert ids.tolist() == [8]  # no longer reported to the associator
    # later observations of a retired landmark (sent before the retirement reached the backend) are ignored
    retired.add_observations(59, [Observation(7, "chair", (0.5, 2.0, 0.0), 0.02, 0.5)])
    assert retired.counters["observations_retired"] == 1


def test_bridged_frames_are_placed_between_measured_ones_and_left_out_of_the_measured_trajectory() -> None:
    """Frames the front end did not measure (the SLAM had lost track) get stand-in poses between their measured
    neighbours, which the map may use, but the trajectory lists only what was measured, as the SLAM's own does."""
    scene = square_scene(0, n=20)
    graph = PoseGraph()
    for i, pose in enumerate(scene.odometry):
        guess = pose.copy()
        if 8 <= i <= 10:
            guess[:3, 3] += [0.3, 0.0, 0.0]  # the motion model's guess, far off
        graph.add_odometry(i, i / FPS, guess, *scene.sigmas, bridged=8 <= i <= 10)
    graph.update()
    ids, _, poses = graph.corrected_poses()
    assert ids.tolist() == list(range(20))
    between = interpolate_pose(scene.odometry[7], scene.odometry[11], 0.5)  # placed by time, not the guess
    assert np.linalg.norm(poses[9][:3, 3] - between[:3, 3]) < 0.01
    ids, stamps, poses = graph.measured_poses()
    assert ids.tolist() == [i for i in range(20) if not 8 <= i <= 10] and len(stamps) == len(poses) == 17
    assert graph.num_unmeasured == 3
    graph.add_odometry(9, 9 / FPS, scene.odometry[9], *scene.sigmas)  # measured after all
    assert graph.num_unmeasured == 2 and 9 in graph.measured_poses()[0].tolist()


def test_a_slams_refinement_at_its_end_replaces_the_odometry_it_sent() -> None:
    """OdometryRefinement: the refined poses replace the odometry of the frames the graph holds as measured (a
    stand-in and a frame it never had are passed over), and the optimised trajectory follows them (no landmarks:
    it is the odometry)."""
    scene = square_scene(0, n=40)
    graph = PoseGraph()
    for i, pose in enumerate(scene.odometry):
        graph.add_odometry(i, i / FPS, pose, *scene.sigmas, keyframe=i % 5 == 0, bridged=i == 7)
        graph.update()
    assert max_position_error(list(graph.measured_poses()[2]), scene.odometry[:7] + scene.odometry[8:]) < 1e-6
    taken = graph.refine_odometry([*range(40), 99], [*scene.gt, np.eye(4)])
    for _ in range(3):
        graph.update()
    assert taken == 39 and graph.counters["odometry_refined"] == 39
    ids, _, poses = graph.measured_poses()
    assert 7 not in ids.tolist()
    assert max_position_error(list(poses), scene.gt[:7] + scene.gt[8:]) < 1e-6


def test_a_refinement_is_taken_unless_the_loop_closures_say_it_is_worse() -> None:
    """BackendStage.refine: semmap's loop closures judge a SLAM's refinement at its end against its odometry as
    tracked; it is taken unless they say it is worse (or there are too few of them), else the tracked odometry
    stays and the reason is given."""
    from semmap.core.messages import OdometryRefinement
    from semmap.runtime.pipeline.stages import REFINEMENT_MIN_CLOSURES, BackendStage

    scene = square_scene(0, n=40)

    def stage_with_closures(count: int) -> BackendStage:
        stage = BackendStage()
        for i, pose in enumerate(scene.odometry):
            stage.graph.add_odometry(i, i / FPS, pose, *scene.sigmas, keyframe=i % 5 == 0)
        for k in range(count):  # (true relative motions, as a good registration measures them)
            a, b = 5 * k, 5 * k + 15
            stage.graph.add_relative_pose_constraint(a, b, np.linalg.inv(scene.gt[a]) @ scene.gt[b], 0.01, 0.01)
        stage.graph.update()
        return stage

    ids = np.arange(1, 40)
    truth = OdometryRefinement("robot1", "orbslam3", ids, np.stack(scene.gt[1:]))
    worse = [p.copy() for p in scene.odometry[1:]]
    for p in worse[10:]:
        p[:3, 3] += (0.3, 0.0, 0.0)  # (a jump the closures across it do not show)
    stage = stage_with_closures(REFINEMENT_MIN_CLOSURES)
    taken, why = stage.refine(truth)
    assert taken == 39 and why == ""
    stage = stage_with_closures(REFINEMENT_MIN_CLOSURES)
    taken, why = stage.refine(OdometryRefinement("robot1", "orbslam3", ids, np.stack(worse)))
    assert taken == 0 and "say it is worse" in why and stage.graph.counters.get("odometry_refined", 0) == 0
    taken, why = stage_with_closures(REFINEMENT_MIN_CLOSURES - 1).refine(truth)
    assert taken == 0 and "at least 3 are needed" in why
    withheld = OdometryRefinement("robot1", "orbslam3", ids[:0], np.zeros((0, 4, 4)), "2 object(s) were seen moving")
    assert stage_with_closures(5).refine(withheld) == (0, "2 object(s) were seen moving")
