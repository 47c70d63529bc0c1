"""Per-frame cost that does not grow with the trajectory: the incrementally read estimate equals iSAM2's whole
estimate, the corrected-poses deltas keep a consumer's copy within tolerance with bounded messages."""

from __future__ import annotations

import math

import numpy as np
from backend_sim import Scene, drifting, observe, square_path

from semmap.algorithms.associator.pose_book import PoseBook
from semmap.algorithms.backend.corrections import CorrectionPublisher, CorrectionsParams, frames_riding_on, moved
from semmap.algorithms.backend.pose_graph import BackendParams, PoseGraph
from semmap.core.messages import CorrectedPoses


def _scene(n: int, seed: int = 0, laps: int = 1) -> Scene:
    rng = np.random.default_rng(seed)
    gt = square_path(n) * laps
    landmarks = np.column_stack([rng.uniform(0.8, 3.2, 6), rng.uniform(0.8, 3.2, 6), rng.uniform(0.3, 1.3, 6)])
    scene = Scene(gt, drifting(gt, seed, np.array([0.0, 0.0, 1.0])), landmarks)
    observe(scene, rng, (0.03, 0.03))
    return scene


def _whole_estimate(graph: PoseGraph) -> np.ndarray:
    """Every node's pose from iSAM2's whole estimate (what the graph avoids computing every frame)."""
    values = graph._isam.calculateEstimate()
    from gtsam.symbol_shorthand import X

    return np.stack([values.atPose3(X(f)).matrix() for f in graph.node_ids()])


def _max_pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    dt = float(np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1).max())
    cos = (np.einsum("nij,nij->n", a[:, :3, :3], b[:, :3, :3]) - 1.0) / 2.0
    return dt, float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())


def test_incremental_estimate_matches_the_whole_estimate_and_reads_few_nodes() -> None:
    scene = _scene(100, laps=2)  # the second lap revisits every landmark: loop closures through landmarks
    graph = PoseGraph(BackendParams())
    reads_per_frame = []
    for i, pose in enumerate(scene.odometry):
        graph.add_odometry(i, i / 30.0, pose, *scene.sigmas, keyframe=i % 3 == 0)
        if i in scene.observations:
            graph.add_observations(i, scene.observations[i])
        before = graph.counters["estimates_read"]
        graph.update()
        reads_per_frame.append(graph.counters["estimates_read"] - before)
        if i % 25 == 24:
            dt, dr = _max_pose_error(graph._est.rows, _whole_estimate(graph))
            assert dt < 1e-4 and dr < 0.01, (i, dt, dr)
    _, _, poses = graph.corrected_poses()
    assert len(poses) == len(scene.odometry)
    # on a straight stretch without revisits only the newest nodes move
    assert np.median(reads_per_frame) < 0.25 * graph.num_nodes


def test_deltas_keep_a_consumer_within_tolerance_with_bounded_messages() -> None:
    scene = _scene(120, seed=1, laps=2)
    graph = PoseGraph(BackendParams())
    params = CorrectionsParams(tolerance_m=0.001, tolerance_deg=0.05, refresh_frames=8)
    publisher = CorrectionPublisher(params)
    late = PoseBook()  # joins after 100 frames: the rolling refresh must give it every frame
    book = PoseBook()
    sizes = []
    for i, pose in enumerate(scene.odometry):
        graph.add_odometry(i, i / 30.0, pose, *scene.sigmas)
        book.odometry[i] = late.odometry[i] = pose
        if i in scene.observations:
            graph.add_observations(i, scene.observations[i])
        graph.update()
        delta = publisher.next(graph)
        message = CorrectedPoses.decode(
            CorrectedPoses("r", i + 1, i, *delta.arrays(), full=delta.full, num_frames=delta.num_frames).encode()
        )
        assert message.full == (i == 0)
        book.set_corrected(message)
        if i >= 100:
            late.set_corrected(message)
        sizes.append(len(message.frame_ids))
        ids, _, truth = graph.corrected_poses()
        mine = np.stack([book.corrected[int(f)] for f in ids])
        dt, dr = _max_pose_error(mine, truth)
        assert dt <= params.tolerance_m + 1e-9 and dr <= params.tolerance_deg + 1e-6, (i, dt, dr)
    n = len(scene.odometry)
    assert sorted(late.corrected) == list(range(n))  # caught up through the refresh alone
    # a delta carries the new frame, the refresh and what moved: far fewer than the trajectory
    assert np.median(sizes[50:]) < 0.25 * n
    assert publisher.counters["full"] == 1


def test_an_out_of_order_frame_starts_over_with_a_full_message() -> None:
    publisher = CorrectionPublisher(CorrectionsParams(refresh_frames=0))
    eye = np.eye(4)[None]
    d1 = publisher.delta(
        np.array([0, 2]), np.array([0.0, 0.1]), np.repeat(eye, 2, 0), np.zeros(0, np.int64), np.zeros((0, 3))
    )
    d2 = publisher.delta(np.array([0, 2, 3]), np.zeros(3), np.repeat(eye, 3, 0), np.array([5]), np.ones((1, 3)))
    assert d1.full and not d2.full and d2.frame_ids.tolist() == [3] and d2.landmark_ids.tolist() == [5]
    d3 = publisher.delta(np.array([0, 1, 2, 3]), np.zeros(4), np.repeat(eye, 4, 0), np.array([5]), np.ones((1, 3)))
    assert d3.full and d3.frame_ids.tolist() == [0, 1, 2, 3] and d3.landmark_ids.tolist() == [5]


def test_moved_measures_translation_and_rotation() -> None:
    a = np.repeat(np.eye(4)[None], 3, 0)
    b = a.copy()
    b[1, 0, 3] = 0.002
    c, s = math.cos(math.radians(0.1)), math.sin(math.radians(0.1))
    b[2, :2, :2] = [[c, -s], [s, c]]
    assert moved(a, b, 0.001, 0.05).tolist() == [False, True, True]
    assert moved(a, b, 0.01, 0.5).tolist() == [False, False, False]


def test_frames_riding_on_moved_nodes_matches_the_per_node_ranges() -> None:
    """The vectorised lookup gives each moved node's frames, from it up to the next node (the first node also
    carries the frames before it), as a loop over the nodes would."""
    rng = np.random.default_rng(3)
    ids = np.sort(rng.choice(5000, 1200, replace=False)).astype(np.int64)
    nodes = np.sort(rng.choice(ids[3:], 150, replace=False))
    moved = sorted(int(n) for n in rng.choice(nodes, 40, replace=False)) + [int(nodes[0]), int(nodes[-1])]
    moved = sorted(set(moved))
    expected = []
    for node in moved:
        j = int(np.searchsorted(nodes, node))
        start = 0 if j == 0 else int(np.searchsorted(ids, node))
        end = len(ids) if j + 1 >= len(nodes) else int(np.searchsorted(ids, nodes[j + 1]))
        expected.extend(range(start, end))
    assert frames_riding_on(ids, nodes, moved).tolist() == expected
    assert frames_riding_on(ids, nodes, []).size == 0
