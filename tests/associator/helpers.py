"""Small analytic scenes for the associator tests: spheres in front of a wall, seen by a pinhole camera.

Why analytic: the unit tests need exact, fast depth images with known objects (a few ms per frame at
160x120), independent of the synthetic dataset renderer that the end-to-end tests use.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from semmap.algorithms.associator.candidate import View
from semmap.core.geometry import look_at  # noqa: F401 - tests import it from here
from semmap.core.messages import DepthPatch, Detection, Intrinsics, Measurement

K_SMALL = Intrinsics(140.0, 140.0, 79.5, 59.5, 160, 120)




@dataclass
class Sphere:
    centre: tuple[float, float, float]
    radius: float
    class_name: str = "cup"


# five objects on a table, seen by an orbiting camera (the analytic closed-loop scenes)
TABLE_SPHERES = [
    Sphere((0.35, 0.0, 0.8), 0.06, "cup"),
    Sphere((-0.3, 0.2, 0.75), 0.07, "bowl"),
    Sphere((0.0, -0.35, 0.85), 0.05, "bottle"),
    Sphere((-0.1, 0.4, 0.9), 0.06, "sports ball"),
    Sphere((0.1, 0.05, 1.0), 0.05, "apple"),
]


def orbit_pose(
    t: float,
    radius: float = 1.2,
    height: float = 1.2,
    period: float = 12.0,
    target: tuple[float, float, float] = (0.0, 0.0, 0.8),
) -> np.ndarray:
    a = 2 * np.pi * t / period - np.pi / 2
    return look_at(np.array([radius * np.cos(a), radius * np.sin(a), height]), np.array(target))


def render(
    pose: np.ndarray,
    spheres: list[Sphere],
    k: Intrinsics = K_SMALL,
    wall_m: float = 3.0,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(depth in mm as uint16, instance index image with -1 = background) of spheres in front of a wall that
    stands `wall_m` beyond the image centre's line of sight (a plane facing the camera)."""
    u, v = np.meshgrid(np.arange(k.width, dtype=float), np.arange(k.height, dtype=float))
    dirs = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)  # z = 1
    z = np.full(u.shape, wall_m)
    label = np.full(u.shape, -1)
    inv = np.linalg.inv(pose)
    for i, s in enumerate(spheres):
        c = inv[:3, :3] @ np.asarray(s.centre) + inv[:3, 3]
        # |t d - c|^2 = r^2 with d = dirs (z component 1): t is the z-depth.
        a = np.einsum("hwk,hwk->hw", dirs, dirs)
        b = -2.0 * dirs @ c
        cc = float(c @ c - s.radius**2)
        disc = b * b - 4 * a * cc
        hit = disc >= 0
        t = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0.0))) / (2 * a), np.inf)
        closer = hit & (t > 0.05) & (t < z)
        z = np.where(closer, t, z)
        label = np.where(closer, i, label)
    if noise_m > 0:
        z = z + (rng or np.random.default_rng(0)).normal(0.0, noise_m, z.shape) * z**2
    return np.rint(z * 1000.0).astype(np.uint16), label


def detections(
    pose: np.ndarray,
    spheres: list[Sphere],
    k: Intrinsics = K_SMALL,
    stride: int = 1,
    min_pixels: int = 12,
    **kw,
) -> list[Detection]:
    """Perfect boxes (the visible pixels' bounds) with depth patches, one per visible sphere."""
    depth, label = render(pose, spheres, k, **kw)
    out = []
    for i, s in enumerate(spheres):
        rows, cols = np.nonzero(label == i)
        if len(rows) < min_pixels:
            continue
        box = (float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1))
        d = float(np.median(depth[label == i])) / 1000.0
        out.append(Detection(box, s.class_name, 0.9, d, DepthPatch.from_depth(depth, box, stride)))
    return out


def measurement(frame_id: int, stamp: float, det: Detection, k: Intrinsics = K_SMALL) -> Measurement:
    return Measurement(frame_id, stamp, det, k, 0.001)


def box_measurement(
    depth_fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
    box: tuple[float, float, float, float],
    k: Intrinsics = K_SMALL,
    stride: int = 1,
    cls: str = "cup",
) -> Measurement:
    """A measurement whose depth image (metres) is depth_fn(u, v) over the whole image."""
    u, v = np.meshgrid(np.arange(k.width, dtype=float), np.arange(k.height, dtype=float))
    depth = np.rint(np.asarray(depth_fn(u, v), dtype=float) * 1000.0).astype(np.uint16)
    return Measurement(0, 0.0, Detection(box, cls, 0.9, 1.0, DepthPatch.from_depth(depth, box, stride)), k, 0.001)


def patch_measurement(
    patch: DepthPatch, box: tuple[float, float, float, float], k: Intrinsics = K_SMALL
) -> Measurement:
    return Measurement(0, 0.0, Detection(box, "cup", 0.9, 1.0, patch), k, 0.001)


def fake_view(
    frame_id: int,
    stamp: float,
    world: np.ndarray,
    size: float = 0.3,
    track_id: int = 0,
    alternatives: list[tuple[np.ndarray, float]] | None = None,
    truncated: bool = False,
    pose: np.ndarray | None = None,
    depth: float = 1.5,
) -> View:
    """A view whose chosen surface is a small cloud centred on `world` (identity pose unless given);
    `alternatives` adds (world centre, score) surfaces after it; the first surface scores 0.8."""
    pose = np.eye(4) if pose is None else pose
    inv = np.linalg.inv(pose)
    centres = [np.asarray(world, float)] + [np.asarray(c, float) for c, _ in alternatives or []]
    scores = [0.8] + [s for _, s in alternatives or []]
    offs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * size / 4
    pts = [((c + offs) @ inv[:3, :3].T + inv[:3, 3]).astype(np.float32) for c in centres]
    cams = np.array([inv[:3, :3] @ c + inv[:3, 3] for c in centres])
    return View(
        frame_id,
        stamp,
        track_id,
        pts,
        cams,
        np.full(len(centres), depth),
        np.array(scores),
        np.array([0.0, 0.0, 1.0]),
        size / depth,
        pose.copy(),
        truncated,
    )
