"""Synthetic scenes for the backend tests: ground-truth paths, drifting odometry, landmark observations.

Drift comes from the odometry service's own `DriftingOdometry` (the handbook's model), so the tests exercise
the same odometry the pipeline produces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from semmap.algorithms.backend.pose_graph import BackendParams, PoseGraph
from semmap.algorithms.odometry.frontends import DriftingOdometry, OdometryInput
from semmap.core.geometry import look_at
from semmap.core.messages import Observation
from semmap.datasets import find_data_root
from semmap.datasets.trajectory_io import orthonormalize_pose

FPS = 30.0
TIGHT_SIGMAS = (0.0002, math.radians(0.01))  # the `gt` front end's declared per-frame covariance
DRIFT = {"translation_sigma_m": 0.003, "yaw_sigma_deg": 0.3, "yaw_bias_deg": 0.05}
DRIFT_SIGMAS = (0.003, math.radians(math.hypot(0.3, 0.05)))  # what DriftingOdometry declares


def shared_data(name: str) -> Path:
    """A folder of the shared real data ($SEMMAP_DATA or ../shared/data); a path that does not exist if absent."""
    root = find_data_root()
    return (root if root is not None else Path("/nonexistent/semmap-shared-data")) / name




def square_path(n: int = 100, side: float = 4.0) -> list[np.ndarray]:
    """n poses on a closed square (z up), each looking at the square's centre from 1.2 m height."""
    perimeter = 4 * side
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], float)
    centre = np.array([side / 2, side / 2, 0.8])
    poses = []
    for i in range(n):
        s = perimeter * i / n
        k = min(int(s // side), 3)
        xy = corners[k] + (corners[k + 1] - corners[k]) * (s - k * side) / side
        poses.append(look_at(np.array([xy[0], xy[1], 1.2]), centre))
    return poses


def drifting(gt: list[np.ndarray], seed: int, up: np.ndarray | None = None) -> list[np.ndarray]:
    odo = DriftingOdometry(seed, DRIFT["translation_sigma_m"], DRIFT["yaw_sigma_deg"], DRIFT["yaw_bias_deg"], up=up)
    return [odo.estimate(OdometryInput(i, i / FPS, pose)) for i, pose in enumerate(gt)]


def visible(pose: np.ndarray, point: np.ndarray, max_range: float) -> np.ndarray | None:
    """The point in the camera frame when it is in a 640x480 f=585 view within `max_range`, else None."""
    p = pose[:3, :3].T @ (point - pose[:3, 3])
    if p[2] < 0.3 or np.linalg.norm(p) > max_range:
        return None
    if abs(p[0] / p[2]) > 320 / 585 or abs(p[1] / p[2]) > 240 / 585:
        return None
    return p


@dataclass
class Scene:
    gt: list[np.ndarray]
    odometry: list[np.ndarray]
    landmarks: np.ndarray  # (M, 3) world
    observations: dict[int, list[Observation]] = field(default_factory=dict)
    sigmas: tuple[float, float] = DRIFT_SIGMAS

    @property
    def stamped_gt(self) -> list[tuple[float, np.ndarray]]:
        return [(i / FPS, p) for i, p in enumerate(self.gt)]

    @property
    def stamped_odometry(self) -> list[tuple[float, np.ndarray]]:
        return [(i / FPS, p) for i, p in enumerate(self.odometry)]


def observe(scene: Scene, rng: np.random.Generator, sigma: tuple[float, float] = (0.03, 0.03), every: int = 1,
            max_range: float = 8.0, view_bias: tuple[float, float] = (0.0, 0.0)) -> None:
    """Fill `scene.observations`: every `every`-th frame, each visible landmark with isotropic noise.

    `sigma` is a (low, high) range: each landmark draws its own noise level, which its messages declare.
    `view_bias` (low, high): each landmark's centroid also moves by up to that much, smoothly with the viewing
    direction and undeclared (B_j @ unit ray, B_j a random 3x3 per landmark scaled into that range): the visible
    surface's centroid does that on real data (handbook: 3-14 cm).
    """
    levels = rng.uniform(sigma[0], sigma[1], len(scene.landmarks))
    biases = [rng.uniform(*view_bias) * np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in scene.landmarks]
    for i in range(0, len(scene.gt), every):
        seen = []
        for j, point in enumerate(scene.landmarks):
            p = visible(scene.gt[i], point, max_range)
            if p is not None:
                ray_world = scene.gt[i][:3, :3] @ (p / np.linalg.norm(p))
                shift = scene.gt[i][:3, :3].T @ (biases[j] @ ray_world)
                noisy = p + shift + rng.normal(0.0, levels[j], 3)
                seen.append(Observation(j, "thing", (float(noisy[0]), float(noisy[1]), float(noisy[2])),
                                        float(levels[j]), 0.1))
        if seen:
            scene.observations[i] = seen


def run_graph(scene: Scene, params: BackendParams | None = None, keyframe_every: int = 1,
              graph: PoseGraph | None = None) -> tuple[PoseGraph, list[float]]:
    """Feed the scene frame by frame as the service would (odometry, observations, one update); update times."""
    graph = graph or PoseGraph(params or BackendParams())
    times = []
    for i, pose in enumerate(scene.odometry):
        graph.add_odometry(i, i / FPS, pose, *scene.sigmas, keyframe=i % keyframe_every == 0)
        if i in scene.observations:
            graph.add_observations(i, scene.observations[i])
        graph.update()
        times.append(graph.last_update_ms)
    return graph, times


def optimized(graph: PoseGraph) -> list[tuple[float, np.ndarray]]:
    _, stamps, poses = graph.corrected_poses()
    return list(zip(stamps.tolist(), poses, strict=True))


def max_position_error(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    return float(max(np.linalg.norm(x[:3, 3] - y[:3, 3]) for x, y in zip(a, b, strict=True)))


def load_7scenes_gt(root: Path, n: int = 1000) -> list[np.ndarray]:
    return [orthonormalize_pose(np.loadtxt(root / f"frame-{i:06d}.pose.txt")) for i in range(n)]


def landmarks_in_view(gt: list[np.ndarray], count: int, rng: np.random.Generator,
                      depth: tuple[float, float] = (1.0, 3.0)) -> np.ndarray:
    """`count` points where the cameras look: each on a random pixel ray of one of `count` evenly spaced frames."""
    points = []
    for i in np.linspace(0, len(gt) - 1, count).astype(int):
        ray = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), 1.0])
        p = ray / np.linalg.norm(ray) * rng.uniform(*depth)
        points.append(gt[i][:3, :3] @ p + gt[i][:3, 3])
    return np.array(points)
