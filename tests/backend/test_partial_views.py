"""Partly seen objects: a depth camera sees an object's near surface, whose centre lies in front of the object's
centre along the ray (a parked car seen from the street: by a third of its size on average, in the street world
along KITTI 00), and every view from that side shares the offset. The backend loosens the range of an observation
by the depth the view may not have seen (`observation_range_sigma_unseen_factor` x the associator's `depth_unseen`;
messages without it: `observation_range_sigma_size_factor` x size) and keeps its bearing, so those views locate the
object without pulling the trajectory towards it."""

from __future__ import annotations

import math

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from semmap.algorithms.backend import factors
from semmap.algorithms.backend.pose_graph import BackendParams, PoseGraph
from semmap.core.messages import Observation

CAR = 4.5  # size (m)
NEAR_SIDE = 0.33  # the visible surface's centre in front of the object's, along the ray, as a share of its size


def drive_past_parked_cars(params: BackendParams, bias: float = NEAR_SIDE, noise: float = 0.0,
                           active_window_nodes: int | None = None,
                           unseen: float | None = None) -> tuple[float, float]:
    """A 120 m straight drive at 10 Hz (exact odometry, declared as a good SLAM's: 7 mm, 0.07 deg a frame) past a
    row of parked cars on its right, each observed every 5 frames from its near side; `unseen`: the depth_unseen
    the observations carry (None: none). (max position error m, max rotation error deg) of the optimised
    trajectory."""
    rng = np.random.default_rng(0)
    if active_window_nodes is not None:
        params = params.model_copy(update={"active_window_nodes": active_window_nodes, "settle_batch_nodes": 4})
    graph = PoseGraph(params)
    poses = []
    cars = [np.array([4.0, 0.5, 12.0 + 7.0 * j]) for j in range(14)]
    for k in range(120):
        pose = np.eye(4)
        pose[2, 3] = float(k)  # camera looking along +z (x right, y down), 1 m a frame
        poses.append(pose)
        graph.add_odometry(k, k / 10.0, pose, 0.0073, math.radians(0.071), keyframe=k % 10 == 0)
        if k % 5 == 0:
            views = []
            for j, centre in enumerate(cars):
                p = centre - pose[:3, 3]
                if p[2] < 2.0 or np.linalg.norm(p) > 30.0 or abs(p[0] / p[2]) > 1.0:
                    continue
                near = p - bias * CAR * p / np.linalg.norm(p) + rng.normal(0.0, noise, 3)
                views.append(Observation(j, "car", tuple(near.tolist()), 0.05, CAR, unseen))
            graph.add_observations(k, views)
        graph.update()
    _, _, est = graph.corrected_poses()
    position = max(float(np.linalg.norm(e[:3, 3] - p[:3, 3])) for e, p in zip(est, poses, strict=True))
    rotation = max(math.degrees(math.acos(min(1.0, (np.trace(e[:3, :3].T @ p[:3, :3]) - 1.0) / 2.0)))
                   for e, p in zip(est, poses, strict=True))
    return position, rotation


OFF = {"observation_range_sigma_size_factor": 0.0, "observation_range_sigma_unseen_factor": 0.0}


def test_near_side_views_of_parked_cars_do_not_bend_a_straight_drive() -> None:
    isotropic = drive_past_parked_cars(BackendParams(**OFF))
    assert isotropic[0] > 0.5 and isotropic[1] > 0.4  # measured 0.61 m, 0.48 deg: the isotropic model bends it
    loosened = drive_past_parked_cars(BackendParams(observation_range_sigma_size_factor=1.0))  # range sigma: size
    assert loosened[0] < 0.3 and loosened[1] < 0.25, loosened  # measured 0.18 m, 0.14 deg
    bearings = drive_past_parked_cars(BackendParams(observation_range_sigma_size_factor=3.0))
    assert bearings[0] < 0.05 and bearings[1] < 0.05, bearings  # the bearings alone: 3 cm, 0.02 deg


def test_the_depth_not_seen_loosens_the_range() -> None:
    """A car's side: its range is loosened by the depth the view may not have seen (up to its footprint); an
    observation that says it saw all there is keeps the isotropic sigma; one from an older sender too."""
    params = BackendParams(observation_range_sigma_unseen_factor=1.0)
    loosened = drive_past_parked_cars(params, unseen=CAR - 0.3)
    assert loosened[0] < 0.3 and loosened[1] < 0.25, loosened
    graph = PoseGraph(params)
    chair = Observation(0, "chair", (0.0, 0.0, 3.0), 0.1, 1.3, 0.0)
    car = Observation(1, "car", (0.0, 0.0, 8.0), 0.1, 4.8, 4.2)
    old = Observation(2, "car", (0.0, 0.0, 8.0), 0.1, 4.8)  # an older sender: no depth_unseen
    assert graph._observation_range_sigma(chair, 0.1) == 0.1
    assert math.isclose(graph._observation_range_sigma(car, 0.1), math.hypot(0.1, 4.2))
    assert graph._observation_range_sigma(old, 0.1) == 0.1  # observation_range_sigma_size_factor: 0 by default
    assert math.isclose(PoseGraph(BackendParams())._observation_range_sigma(car, 0.1), math.hypot(0.1, 4.2))
    assert PoseGraph(BackendParams(**OFF))._observation_range_sigma(car, 0.1) == 0.1


def test_loosened_range_keeps_what_unbiased_views_say() -> None:
    """Centred views with 20 cm noise: the bearings still hold the trajectory as the isotropic model did."""
    isotropic = drive_past_parked_cars(BackendParams(**OFF), bias=0.0, noise=0.2)
    loosened = drive_past_parked_cars(BackendParams(observation_range_sigma_size_factor=1.0), bias=0.0, noise=0.2)
    assert loosened[0] < isotropic[0] + 0.02 and loosened[1] < isotropic[1] + 0.02, (loosened, isotropic)


def test_settled_near_side_views_keep_their_loose_range() -> None:
    """Settling folds observations into a landmark prior with their (anisotropic) information: the result stays
    close to the whole graph's."""
    whole = drive_past_parked_cars(BackendParams(observation_range_sigma_size_factor=1.0))
    settled = drive_past_parked_cars(BackendParams(observation_range_sigma_size_factor=1.0), active_window_nodes=6)
    assert settled[0] < whole[0] + 0.1 and settled[1] < whole[1] + 0.1, (settled, whole)


def test_range_sigma_loosens_the_range_alone() -> None:
    point = np.array([3.0, 0.0, 4.0])  # 5 m away
    ray = point / 5.0
    across = np.array([0.8, 0.0, -0.6])
    plain = factors.observation_factor(X(0), L(0), point, 0.1, "none", 1.0)
    loose = factors.observation_factor(X(0), L(0), point, 0.1, "none", 1.0, range_sigma=1.0)

    def error(factor: gtsam.NonlinearFactor, offset: np.ndarray) -> float:
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3())
        values.insert(L(0), point + offset)
        return float(factor.error(values))

    assert math.isclose(error(plain, 0.1 * ray), 0.5, rel_tol=1e-6)  # one sigma along the ray
    assert math.isclose(error(loose, 0.1 * ray), 0.005, rel_tol=1e-6)  # a tenth of a sigma
    assert math.isclose(error(loose, 0.01 * across), error(plain, 0.01 * across), rel_tol=1e-3)  # the bearing's
    info = factors.observation_information(ray, 0.1, 1.0)
    assert np.isclose(ray @ info @ ray, 1.0) and np.isclose(across @ info @ across, 100.0)
    assert np.allclose(factors.observation_information(ray, 0.1, 0.1), np.eye(3) / 0.01)
