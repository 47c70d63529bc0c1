"""Settling (backend.active_window_nodes): iSAM2 keeps a window of live nodes, older ones keep their estimate and
their factors become priors on what stays; cost stays bounded, the result stays close to the whole graph's."""

from __future__ import annotations

import numpy as np
import pytest
from backend_sim import FPS, Scene, drifting, observe, optimized, run_graph, square_path

from semmap.algorithms.backend.factors import robust_weight
from semmap.algorithms.backend.pose_graph import BackendParams, PoseGraph
from semmap.algorithms.evaluation import ate_rmse
from semmap.core.messages import Observation

WINDOW, BATCH = 30, 10


def _scene(laps: int, seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    gt = square_path(80) * laps  # every lap revisits every landmark
    landmarks = np.column_stack([rng.uniform(0.8, 3.2, 6), rng.uniform(0.8, 3.2, 6), rng.uniform(0.3, 1.3, 6)])
    scene = Scene(gt, drifting(gt, seed, np.array([0.0, 0.0, 1.0])), landmarks)
    observe(scene, rng, (0.03, 0.03), every=3)
    return scene


def _settling(**extra) -> BackendParams:
    return BackendParams(active_window_nodes=WINDOW, settle_batch_nodes=BATCH, **extra)


def _live_nodes(graph: PoseGraph) -> int:
    return len(graph.node_ids()) - graph._n_settled


def test_settling_bounds_the_live_graph_and_keeps_the_trajectory() -> None:
    scene = _scene(laps=4)
    whole, _ = run_graph(scene, BackendParams(active_window_nodes=0), keyframe_every=5)
    graph = PoseGraph(_settling())
    live, settled_before = [], {}
    for i, pose in enumerate(scene.odometry):
        graph.add_odometry(i, i / FPS, pose, *scene.sigmas, keyframe=i % 5 == 0)
        if i in scene.observations:
            graph.add_observations(i, scene.observations[i])
        graph.update()
        live.append(_live_nodes(graph))
        if i == 200:  # settled nodes keep their estimate from then on
            settled_before = {f: graph.corrected_pose(f) for f in graph.node_ids()[: graph._n_settled]}
    assert graph.counters["settles"] >= 3 and graph.counters["observations_settled"] > 0
    assert max(live) < WINDOW + BATCH
    assert settled_before and all(np.allclose(graph.corrected_pose(f), T) for f, T in settled_before.items())
    # iSAM2 holds the window and the landmarks, not the trajectory
    assert graph._isam.calculateEstimate().size() == _live_nodes(graph) + graph.num_landmarks
    ate_whole = ate_rmse(scene.stamped_gt, optimized(whole))
    ate_settled = ate_rmse(scene.stamped_gt, optimized(graph))
    ate_odometry = ate_rmse(scene.stamped_gt, scene.stamped_odometry)
    assert ate_settled < 0.5 * ate_odometry, (ate_settled, ate_odometry)
    assert ate_settled < ate_whole + 0.03, (ate_settled, ate_whole)


def test_nothing_settles_below_the_window() -> None:
    """A graph smaller than window + batch is the whole graph: the results tables' runs are unchanged."""
    scene = _scene(laps=1)
    a, _ = run_graph(scene, BackendParams(active_window_nodes=0), keyframe_every=5)
    b, _ = run_graph(scene, BackendParams(active_window_nodes=500), keyframe_every=5)
    assert b.counters["settles"] == 0
    assert np.array_equal(a.corrected_poses()[2], b.corrected_poses()[2])


def test_late_messages_about_settled_frames_become_priors() -> None:
    scene = _scene(laps=3, seed=1)
    graph, _ = run_graph(scene, _settling(), keyframe_every=5)
    horizon = graph._settled_horizon
    assert horizon > 0
    old = next(f for f in sorted(scene.observations) if f < horizon - 20)
    before = graph.counters["observations_settled"]
    graph.add_observations(old, scene.observations[old])  # observations of an old frame, arriving late
    graph.add_odometry(old, old / FPS, scene.odometry[old], *scene.sigmas)  # its odometry again
    newest = len(scene.odometry) - 1
    graph.add_relative_pose_constraint(old, newest, np.linalg.inv(scene.gt[old]) @ scene.gt[newest], 0.01, 0.01)
    graph.update()
    assert graph.counters["observations_settled"] == before + len(scene.observations[old])
    assert graph._settled_horizon == horizon and old not in graph._isam_nodes[graph._n_settled :]
    assert np.all(np.isfinite(graph.corrected_poses()[2]))


def test_retiring_a_landmark_drops_its_settled_prior() -> None:
    scene = _scene(laps=3, seed=2)
    graph, _ = run_graph(scene, _settling(), keyframe_every=5)
    settled = sorted(graph._settled_points)
    assert settled
    landmark = settled[0]
    graph.retire_landmark(landmark)
    graph.update()
    assert landmark not in graph._settled_points
    factors = graph._isam.getFactorsUnsafe()
    from gtsam.symbol_shorthand import L

    sigmas = [factors.at(i).noiseModel().sigmas()[0] for i in range(factors.size())
              if factors.at(i) is not None and list(factors.at(i).keys()) == [L(landmark)]]
    assert sigmas == [pytest.approx(1.0)]  # only the loose retirement prior holds it
    graph.add_observations(len(scene.odometry) - 1, [Observation(landmark, "thing", (0.0, 0.0, 2.0), 0.03, 0.1)])
    assert graph.counters["observations_retired"] >= 1


@pytest.mark.parametrize(("kernel", "residual", "weight"), [
    ("none", 10.0, 1.0), ("huber", 1.0, 1.0), ("huber", 2.69, 0.5), ("cauchy", 1.345, 0.5),
])
def test_robust_weight(kernel: str, residual: float, weight: float) -> None:
    assert robust_weight(kernel, 1.345, residual) == pytest.approx(weight)


def test_settling_is_deterministic() -> None:
    """A replay (crash recovery, `semmap run` twice) settles at the same nodes and gives the same trajectory."""
    scene = _scene(laps=3, seed=3)
    a, _ = run_graph(scene, _settling(), keyframe_every=5)
    b, _ = run_graph(scene, _settling(), keyframe_every=5)
    assert a.counters["settles"] > 0 and a.counters == b.counters
    assert np.array_equal(a.corrected_poses()[2], b.corrected_poses()[2])
