"""A seeded synthetic street along a given trajectory: `synthetic:trajectory=PATH`.

The camera follows the poses of a trajectory file (KITTI: 12 numbers a line, camera-to-world, z forward, frames
at `rate_hz`; TUM: `t x y z qx qy qz qw`, stamps from the file) through a street generated from the path:
parked cars, benches, bicycles, traffic lights, stop signs and potted plants on both sides (3-9 m off the path),
cars driving to and fro in the oncoming lane and people walking on the pavements (moving), a ground and
buildings as background (instance 0: not objects). Frames are ray cast by the room world's renderer
(SyntheticDataset.render), so the oracle instance boxes, depth, colour and noise are made the same way.

Objects are placed from the seed along the path in one pass over its arc length, each one only where no object
stands yet and clear of every pose of the path: the world is one static layout, so a revisited street shows
the same objects (same instance ids) again, and a street the path crosses later never runs through the
camera. Up is the mean of the cameras' -y axes; the scene is built z-up ("street frame") and every pose and
object ground truth is reported in the trajectory file's own frame.

Rendering cost does not grow with the trajectory: the static geometry lives in 20 m grid cells and a frame
ray casts only the cells (and moving objects) within the depth range of its camera.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .base import DatasetError
from .synthetic import (
    FrameScene,
    Mesh,
    SyntheticConfig,
    SyntheticDataset,
    _jitter,
    _Object,
    _Part,
    _person_parts,
    _rgb,
    _rotate_x,
    _yaw_matrix,
    box_mesh,
    config_from_options,
    cylinder_mesh,
    sphere_mesh,
)
from .trajectory_io import read_trajectory as read_trajectory_file

STATIC_CLASSES = ("car", "bench", "bicycle", "traffic light", "stop sign", "potted plant")
MOVING_CLASSES = ("car", "person")


@dataclass(frozen=True)
class StreetConfig:
    """Everything that shapes a street sequence; equal configs (and trajectory files) give identical frames.

    Defaults: a KITTI-like camera at half resolution (620x188, fx = fy = 359), 10 Hz for KITTI pose files,
    depth to 40 m, depth noise sigma = depth_noise * z^2 (0.3 m at 40 m)."""

    trajectory: str = ""
    format: str = "auto"  # auto | kitti | tum
    frames: int = 0  # 0: every pose of the file, else at most this many
    seed: int = 0
    width: int = 620
    height: int = 188
    fx: float = 359.0
    fy: float = 359.0
    cx: float | None = None
    cy: float | None = None
    rate_hz: float = 10.0  # KITTI pose files only (TUM files carry their stamps)
    camera_height: float = 1.65  # above the ground
    spacing: float = 4.0  # metres of path between object slots (one each side)
    fill: float = 0.8  # chance a slot gets an object
    car_every: float = 60.0  # metres of path per moving car
    person_every: float = 30.0  # metres of path per walking person
    max_depth: float = 40.0
    depth_noise: float = 0.0002
    min_visible_pixels: int = 60

    def __post_init__(self) -> None:
        if not self.trajectory:
            raise DatasetError("synthetic street: trajectory=PATH is needed")
        if self.format not in ("auto", "kitti", "tum"):
            raise DatasetError(f"synthetic street: format must be auto, kitti or tum, got {self.format!r}")
        if self.frames < 0 or self.width < 16 or self.height < 16 or self.fx <= 0 or self.fy <= 0:
            raise DatasetError(f"synthetic street: frames >= 0, size >= 16x16 and fx, fy > 0 needed, got {self}")
        if self.rate_hz <= 0 or self.depth_noise < 0 or self.max_depth <= 0 or self.spacing < 1.0:
            raise DatasetError("synthetic street: rate_hz, max_depth > 0, depth_noise >= 0, spacing >= 1 m needed")
        if not 0.0 <= self.fill <= 1.0 or self.car_every <= 0 or self.person_every <= 0:
            raise DatasetError("synthetic street: fill in [0, 1], car_every and person_every > 0 needed")

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> StreetConfig:
        return config_from_options(cls, options, "synthetic street", "620x188")


def read_trajectory(path: str | Path, fmt: str = "auto", rate_hz: float = 10.0) -> list[tuple[float, np.ndarray]]:
    """(stamp, 4x4 camera-to-world) from a KITTI pose file (stamps i / rate_hz) or a TUM file; DatasetError
    for a missing, empty or unreadable file."""
    try:
        poses = read_trajectory_file(path, fmt, rate_hz)
    except DatasetError as exc:
        raise DatasetError(f"synthetic street: {exc}") from exc
    if len(poses) < 2:
        raise DatasetError(f"synthetic street: {path} holds {len(poses)} poses; at least 2 are needed")
    stack = np.stack([p for _, p in poses])
    if not np.all(np.isfinite(stack)):
        raise DatasetError(f"synthetic street: {path} holds non-finite poses")
    return poses


# ----------------------------------------------------------------------------------------------------------
# Object models, in their own frame: standing on the origin, facing +x


def _car_parts(rng: np.random.Generator) -> list[_Part]:
    paint = _rgb(rng.uniform(0.1, 0.9, 3))
    dark, glass = (0.08, 0.08, 0.09), (0.2, 0.25, 0.3)
    parts = [
        _Part(box_mesh((0.0, 0.0, 0.65), (4.2, 1.78, 0.7)), paint, 0.3, 0.15),
        _Part(box_mesh((-0.2, 0.0, 1.25), (2.3, 1.6, 0.52)), glass, 0.2, 0.2),
    ]
    for x in (-1.35, 1.35):
        for y in (-0.8, 0.8):
            parts.append(_Part(box_mesh((x, y, 0.32), (0.64, 0.22, 0.64)), dark, 0.05, 0.2))
    return parts


def _bench_parts(rng: np.random.Generator) -> list[_Part]:
    wood = _jitter(rng, (0.5, 0.32, 0.18))
    metal = (0.2, 0.2, 0.22)
    parts = [
        _Part(box_mesh((0.0, 0.0, 0.45), (0.45, 1.6, 0.06)), wood, 0.05, 0.35),
        _Part(box_mesh((-0.2, 0.0, 0.72), (0.05, 1.6, 0.4)), wood, 0.05, 0.35),
    ]
    parts += [_Part(box_mesh((0.0, y, 0.21), (0.42, 0.06, 0.42)), metal, 0.05, 0.2) for y in (-0.7, 0.7)]
    return parts


def _bicycle_parts(rng: np.random.Generator) -> list[_Part]:
    frame = _rgb(rng.uniform(0.1, 0.9, 3))
    tyre = (0.05, 0.05, 0.05)
    parts = []
    for x in (-0.55, 0.55):
        v, f = cylinder_mesh((0.0, 0.0, -0.03), 0.34, 0.34, 0.06, segments=16)
        parts.append(_Part((_rotate_x(v, math.pi / 2) + np.array([x, 0.0, 0.34]), f), tyre, 0.05, 0.2))
    parts += [
        _Part(box_mesh((0.0, 0.0, 0.6), (1.0, 0.05, 0.06)), frame, 0.05, 0.2),
        _Part(box_mesh((-0.15, 0.0, 0.5), (0.06, 0.05, 0.4)), frame, 0.05, 0.2),
        _Part(box_mesh((-0.15, 0.0, 0.9), (0.25, 0.12, 0.06)), tyre, 0.05, 0.2),
        _Part(box_mesh((0.5, 0.0, 0.95), (0.06, 0.55, 0.04)), tyre, 0.05, 0.2),
    ]
    return parts


def _traffic_light_parts(rng: np.random.Generator) -> list[_Part]:
    grey = _jitter(rng, (0.35, 0.36, 0.38))
    return [
        _Part(cylinder_mesh((0.0, 0.0, 0.0), 0.08, 0.07, 3.0, segments=12), grey, 0.1, 0.2),
        _Part(box_mesh((0.0, 0.0, 3.4), (0.3, 0.35, 0.9)), (0.08, 0.08, 0.08), 0.05, 0.2),
        _Part(box_mesh((0.16, 0.0, 3.7), (0.03, 0.22, 0.22)), (0.9, 0.1, 0.1), 0.1, 0.1),
        _Part(box_mesh((0.16, 0.0, 3.1), (0.03, 0.22, 0.22)), (0.1, 0.85, 0.2), 0.1, 0.1),
    ]


def _stop_sign_parts(rng: np.random.Generator) -> list[_Part]:
    v, f = cylinder_mesh((0.0, 0.0, -0.015), 0.38, 0.38, 0.03, segments=8)
    plate = _rotate_x(v, math.pi / 2)[:, [1, 0, 2]] + np.array([0.0, 0.0, 2.1])  # face along +x
    return [
        _Part(cylinder_mesh((0.0, 0.0, 0.0), 0.04, 0.04, 2.1, segments=10), (0.6, 0.6, 0.62), 0.1, 0.2),
        _Part((plate, f), _jitter(rng, (0.8, 0.05, 0.05)), 0.05, 0.3),
    ]


def _potted_plant_parts(rng: np.random.Generator) -> list[_Part]:
    return [
        _Part(cylinder_mesh((0.0, 0.0, 0.0), 0.22, 0.3, 0.5, segments=16), _jitter(rng, (0.65, 0.35, 0.2)), 0.05, 0.3),
        _Part(sphere_mesh((0.0, 0.0, 0.95), 0.45), _jitter(rng, (0.15, 0.5, 0.15)), 0.04, 0.5),
    ]


_MODELS = {
    "car": _car_parts,
    "bench": _bench_parts,
    "bicycle": _bicycle_parts,
    "traffic light": _traffic_light_parts,
    "stop sign": _stop_sign_parts,
    "potted plant": _potted_plant_parts,
}
# (class, weight, lateral offset range in m, footprint radius in m: objects keep 2 radii plus 0.5 m apart)
_KINDS = (
    ("car", 0.4, (4.4, 4.8), 2.2),
    ("bench", 0.12, (6.0, 7.5), 0.9),
    ("bicycle", 0.12, (5.5, 7.5), 0.9),
    ("traffic light", 0.08, (5.0, 5.6), 0.4),
    ("stop sign", 0.08, (5.0, 5.6), 0.4),
    ("potted plant", 0.2, (5.5, 8.5), 0.5),
)
_CELL = 20.0  # metres: the static geometry's grid


def _transform(mesh: Mesh, yaw: float, at: np.ndarray) -> Mesh:
    v, f = mesh
    return (v @ _yaw_matrix(yaw).T + at).astype(float), f


class _Path:
    """The trajectory in the street frame, resampled by horizontal arc length: position, heading, ground."""

    def __init__(self, positions: np.ndarray, camera_height: float) -> None:
        xy = positions[:, :2]
        step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(step)])
        self.length = float(arc[-1])
        self.s = np.arange(0.0, self.length + 1e-9, 1.0)
        keep = np.concatenate([[True], step > 1e-6])
        arc_k, xy_k, z_k = arc[keep], xy[keep], positions[keep, 2]
        if len(arc_k) < 2:  # the camera never moves horizontally
            arc_k, xy_k, z_k = np.array([0.0, 1.0]), np.vstack([xy[0], xy[0] + [1.0, 0.0]]), z_k.repeat(2)[:2]
            self.s = np.array([0.0])
        self.xy = np.column_stack([np.interp(self.s, arc_k, xy_k[:, 0]), np.interp(self.s, arc_k, xy_k[:, 1])])
        self.ground = np.interp(self.s, arc_k, z_k) - camera_height
        ahead = np.interp(self.s + 2.0, arc_k, xy_k[:, 0]) - np.interp(self.s - 2.0, arc_k, xy_k[:, 0])
        side = np.interp(self.s + 2.0, arc_k, xy_k[:, 1]) - np.interp(self.s - 2.0, arc_k, xy_k[:, 1])
        self.heading = np.arctan2(side, ahead)
        self.tree = cKDTree(xy)  # every pose: what must stay clear
        self.sample_tree = cKDTree(self.xy)

    def at(self, s: float) -> tuple[np.ndarray, float, float]:
        """(xy, heading, ground height) at arc length s (clamped)."""
        s = float(np.clip(s, 0.0, self.s[-1]))
        i = min(int(s), len(self.s) - 2) if len(self.s) > 1 else 0
        if len(self.s) == 1:
            return self.xy[0], float(self.heading[0]), float(self.ground[0])
        w = s - i
        xy = self.xy[i] * (1.0 - w) + self.xy[i + 1] * w
        turn = (self.heading[i + 1] - self.heading[i] + math.pi) % (2 * math.pi) - math.pi
        return xy, float(self.heading[i] + w * turn), float(self.ground[i] * (1.0 - w) + self.ground[i + 1] * w)

    def ground_at(self, xy: np.ndarray) -> float:
        _, i = self.sample_tree.query(xy)
        return float(self.ground[int(i)])

    def clearance(self, xy: np.ndarray) -> float:
        d, _ = self.tree.query(xy)
        return float(d)


class StreetDataset(SyntheticDataset):
    """The street world: SyntheticDataset's renderer over a generated street along a trajectory file."""

    name = "synthetic-street"
    platform = "vehicle"

    def __init__(self, config: StreetConfig | None = None, threads: int = 0, **options: Any) -> None:
        if config is not None and options:
            raise DatasetError("synthetic street: pass either a StreetConfig or options, not both")
        self.street = config if config is not None else StreetConfig.from_options(options)
        c = self.street
        poses = read_trajectory(c.trajectory, c.format, c.rate_hz)
        if c.frames:
            poses = poses[: c.frames]
        if len(poses) < 2:
            raise DatasetError("synthetic street: at least 2 frames needed")
        self._stamps = [t for t, _ in poses]
        self._poses = [p for _, p in poses]
        span = self._stamps[-1] - self._stamps[0]
        self.rate_hz = (len(poses) - 1) / span if span > 0 else c.rate_hz
        # A SyntheticConfig for what the renderer reads from it (seed, size, noise, visibility threshold).
        self.config = SyntheticConfig(
            frames=len(poses), seed=c.seed, width=c.width, height=c.height, fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy,
            rate_hz=self.rate_hz, depth_noise=c.depth_noise, min_visible_pixels=c.min_visible_pixels,
        )  # fmt: skip
        self.threads = int(threads)
        self.name = f"synthetic-street/{Path(c.trajectory).stem}/seed{c.seed}"
        self.intrinsics = self.config.intrinsics()
        self._sky = (0.62, 0.75, 0.9)
        self._max_depth = c.max_depth

        # Street frame: z up (the mean camera -y axis), x along the first pose's heading.
        stack = np.stack(self._poses)
        up = -stack[:, :3, 1].mean(axis=0)
        up /= np.linalg.norm(up)
        forward = stack[0, :3, 2] - up * float(stack[0, :3, 2] @ up)
        if np.linalg.norm(forward) < 1e-6:
            forward = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
        forward /= np.linalg.norm(forward)
        self._to_street = np.eye(4)
        self._to_street[:3, :3] = np.stack([forward, np.cross(up, forward), up])
        positions = stack[:, :3, 3] @ self._to_street[:3, :3].T
        self._path = _Path(positions, c.camera_height)

        rng = np.random.default_rng([c.seed, 34])
        self._objects: list[_Object] = [_Object(0, "background", [])]
        self._anchor: dict[int, np.ndarray] = {}  # static objects: xy (for the grid)
        self._place_static(rng)
        background = self._background(rng)
        self._place_moving(rng)
        self._classes = {o.instance_id: o.class_name for o in self._objects}
        self._moving_ids = {o.instance_id for o in self._objects if o.moving}
        self._build_cells(background)

        self._prepare_rays(c.seed)
        self._cache_key: tuple[int, ...] | None = None
        self._cache: tuple[np.ndarray, ...] | None = None

    # ---- the layout

    def _place_static(self, rng: np.random.Generator) -> None:
        """One pass along the path, a slot every `spacing` m on each side; every draw is made whether or not the
        slot is used, so the layout of a stretch depends only on the seed and the path before it."""
        c, path = self.street, self._path
        weights = np.array([k[1] for k in _KINDS])
        weights /= weights.sum()
        taken: dict[tuple[int, int], list[tuple[np.ndarray, float]]] = {}

        def free(xy: np.ndarray, radius: float) -> bool:
            gx, gy = int(xy[0] // 5.0), int(xy[1] // 5.0)
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    for other, r in taken.get((gx + dx, gy + dy), []):
                        if np.linalg.norm(other - xy) < radius + r + 0.5:
                            return False
            return True

        for s in np.arange(c.spacing / 2, path.length, c.spacing):
            for side in (1.0, -1.0):
                use, kind_draw, lateral, along, jitter = (float(x) for x in rng.random(5))
                model_seed = int(rng.integers(2**31))
                if use >= c.fill:
                    continue
                name, _, (lo, hi), radius = _KINDS[int(np.searchsorted(np.cumsum(weights), kind_draw))]
                xy0, heading, _ = path.at(s + (along - 0.5) * 1.5)
                normal = np.array([-math.sin(heading), math.cos(heading)])
                xy = xy0 + normal * side * (lo + (hi - lo) * lateral)
                if path.clearance(xy) < min(lo, 4.4) - 0.3 or not free(xy, radius):
                    continue  # on a road the path takes (a crossing, a revisit in the other lane) or taken
                taken.setdefault((int(xy[0] // 5.0), int(xy[1] // 5.0)), []).append((xy, radius))
                yaw = heading + (jitter - 0.5) * 0.2
                if name in ("bench", "bicycle", "potted plant"):
                    yaw += (jitter - 0.5) * 0.6
                if name in ("stop sign", "traffic light") and side < 0:
                    yaw += math.pi  # facing the traffic on that side
                at = np.array([xy[0], xy[1], path.ground_at(xy)])
                parts = _MODELS[name](np.random.default_rng(model_seed))
                parts = [dataclasses.replace(p, mesh=_transform(p.mesh, yaw, at)) for p in parts]
                self._anchor[len(self._objects)] = xy
                self._objects.append(_Object(len(self._objects), name, parts))

    def _background(self, rng: np.random.Generator) -> list[tuple[np.ndarray, _Part]]:
        """Ground tiles round the path and building blocks behind the pavements, each with its xy for the grid."""
        path = self._path
        out: list[tuple[np.ndarray, _Part]] = []
        cells = {(int(x // 10.0), int(y // 10.0)) for x, y in path.xy}
        cells = {(gx + dx, gy + dy) for gx, gy in cells for dx in range(-5, 6) for dy in range(-5, 6)}
        for gx, gy in sorted(cells):
            centre = np.array([gx * 10.0 + 5.0, gy * 10.0 + 5.0])
            if path.clearance(centre) > 50.0:
                continue
            top = path.ground_at(centre)
            near = path.clearance(centre) < 7.0
            colour = (0.3, 0.3, 0.32) if near else (0.45, 0.42, 0.38)
            out.append((centre, _Part(box_mesh((*centre, top - 0.1), (10.02, 10.02, 0.2)), colour, 0.5, 0.3)))
        for s in np.arange(0.0, path.length, 14.0):
            for side in (1.0, -1.0):
                lateral, width, depth, height, tint = (rng.random() for _ in range(5))
                xy0, heading, ground = path.at(s)
                normal = np.array([-math.sin(heading), math.cos(heading)])
                front, deep, long = 11.0 + 3.0 * lateral, 8.0 + 8.0 * depth, 9.0 + 5.0 * width
                centre = xy0 + normal * side * (front + deep / 2)
                # The block must stay 5 m clear of every pose: test its footprint on a 1 m grid.
                a = np.linspace(-long / 2, long / 2, int(long) + 1)
                b = np.linspace(-deep / 2, deep / 2, int(deep) + 1)
                aa, bb = np.meshgrid(a, b)
                tangent = np.array([math.cos(heading), math.sin(heading)])
                pts = centre + aa.reshape(-1, 1) * tangent + bb.reshape(-1, 1) * normal
                if float(path.tree.query(pts)[0].min()) < 5.0:
                    continue
                colour = _rgb(np.array([0.75, 0.68, 0.6]) * (0.7 + 0.4 * tint))
                box = box_mesh((*centre, ground + (6.0 + 14.0 * height) / 2 - 0.2), (long, deep, 6.0 + 14.0 * height),
                               heading)  # fmt: skip
                out.append((centre, _Part(box, colour, 0.8, 0.3)))
        return out

    def _place_moving(self, rng: np.random.Generator) -> None:
        """Cars to and fro in the oncoming lane (2.4 m left of the path) over 60 m stretches and people to and
        fro on the pavements (9 m off the path) over 14 m stretches; they follow the path's bends."""
        c, path = self.street, self._path
        movers: list[tuple[str, float, float, float, float, float]] = []  # class, s0, band, lateral, speed, phase
        for s in np.arange(c.car_every / 2, path.length, c.car_every):
            phase, speed = rng.random(), rng.random()
            movers.append(("car", float(s) - 30.0, 60.0, 2.4, 5.0 + 5.0 * speed, phase))
        for s in np.arange(c.person_every / 2, path.length, c.person_every):
            side, phase, speed = rng.random(), rng.random(), rng.random()
            movers.append(("person", float(s) - 7.0, 14.0, 9.0 if side < 0.5 else -9.0, 1.0 + 0.6 * speed, phase))
        for name, s0, band, lateral, speed, phase in movers:
            parts = _car_parts(rng) if name == "car" else _person_parts(rng)

            def motion(
                t: float, s0: float = s0, band: float = band, lateral: float = lateral, speed: float = speed,
                phase: float = phase, oncoming: bool = name == "car",
            ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
                u = (t * speed / band + phase) % 2.0
                forward = u < 1.0
                s = s0 + band * (u if forward else 2.0 - u)
                xy, heading, ground = path.at(s)
                normal = np.array([-math.sin(heading), math.cos(heading)])
                xy = xy + normal * lateral
                if oncoming:  # oncoming traffic drives against the path's direction
                    forward = not forward
                return _yaw_matrix(heading if forward else heading + math.pi), np.array([xy[0], xy[1], ground])

            self._objects.append(_Object(len(self._objects), name, parts, motion))

    def _build_cells(self, background: list[tuple[np.ndarray, _Part]]) -> None:
        """Per 20 m cell: its static triangles with their tables (instance ids, not yet frame-local)."""
        cells: dict[tuple[int, int], list[tuple[int, _Part]]] = {}
        for xy, part in background:
            cells.setdefault((int(xy[0] // _CELL), int(xy[1] // _CELL)), []).append((0, part))
        for obj in self._objects[1:]:
            if obj.moving:
                continue
            xy = self._anchor[obj.instance_id]
            cell = cells.setdefault((int(xy[0] // _CELL), int(xy[1] // _CELL)), [])
            cell.extend((obj.instance_id, part) for part in obj.parts)
        self._cells = {key: self._tables(items) for key, items in cells.items()}
        self._moving_tables = {
            o.instance_id: self._tables([(o.instance_id, p) for p in o.parts]) for o in self._objects if o.moving
        }

    @staticmethod
    def _tables(items: list[tuple[int, _Part]]) -> tuple[np.ndarray, ...]:
        vertices, triangles, color, inv_size, contrast, label = [], [], [], [], [], []
        n = 0
        for instance_id, part in items:
            v, f = part.mesh
            vertices.append(v)
            triangles.append(f + n)
            n += len(v)
            color.append(np.tile(np.asarray(part.color, np.float32) * np.float32(255.0), (len(f), 1)))
            inv_size.append(np.full(len(f), 1.0 / part.texture_size, np.float32))
            contrast.append(np.full(len(f), part.texture_contrast, np.float32))
            label.append(np.full(len(f), instance_id, np.int64))
        return (np.vstack(vertices).astype(np.float32), np.vstack(triangles).astype(np.int64), np.vstack(color),
                np.concatenate(inv_size), np.concatenate(contrast), np.concatenate(label))  # fmt: skip

    # ---- geometry over time

    def stamp(self, index: int) -> float:
        return self._stamps[index]

    def stamps(self) -> list[float]:
        return list(self._stamps)

    def camera_pose(self, index: int) -> np.ndarray:
        return self._poses[index].copy()

    def _scene_pose(self, pose: np.ndarray) -> np.ndarray:
        return self._to_street @ pose

    def _class_of(self, instance_id: int) -> str:
        return self._classes[instance_id]

    def _frame_scene(self, index: int) -> FrameScene:
        pose = self._scene_pose(self.camera_pose(index))
        cx, cy = pose[0, 3], pose[1, 3]
        reach = self.street.max_depth + _CELL  # a cell's contents stick out of it by up to ~half a cell
        gx0, gx1 = int((cx - reach) // _CELL), int((cx + reach) // _CELL)
        gy0, gy1 = int((cy - reach) // _CELL), int((cy + reach) // _CELL)
        keys = tuple(
            (gx, gy) for gx in range(gx0, gx1 + 1) for gy in range(gy0, gy1 + 1)
            if (gx, gy) in self._cells
            and math.hypot((gx + 0.5) * _CELL - cx, (gy + 0.5) * _CELL - cy) <= reach + _CELL * 0.71
        )  # fmt: skip
        flat = tuple(v for key in keys for v in key)
        if flat != self._cache_key or self._cache is None:
            self._cache = self._concat([self._cells[key] for key in keys])
            self._cache_key = flat
        parts = [self._cache]
        moving: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        t = self.stamp(index)
        for obj in self._objects:
            if obj.motion is None:
                continue
            rotation, translation = obj.motion(t)
            if math.hypot(translation[0] - cx, translation[1] - cy) > self.street.max_depth + 5.0:
                continue
            v, f, col, inv, con, lab = self._moving_tables[obj.instance_id]
            placed = (v @ rotation.T.astype(np.float32) + translation.astype(np.float32)).astype(np.float32)
            parts.append((placed, f, col, inv, con, lab))
            moving[obj.instance_id] = (rotation, translation)
        v, f, col, inv, con, lab = self._concat(parts) if len(parts) > 1 else self._cache
        ids, local = np.unique(np.concatenate([[0], lab]), return_inverse=True)
        local = local[1:].astype(np.int32)
        to_local = {int(g): i for i, g in enumerate(ids)}
        return FrameScene(
            vertices=v, triangles=np.ascontiguousarray(f, dtype=np.uint32), tri_color=col, tri_label=local,
            tri_inv_size=inv, tri_contrast=con, n_obj=len(ids),
            moving={to_local[g]: pose_ for g, pose_ in moving.items() if g in to_local}, ids=ids.astype(np.int32),
        )  # fmt: skip

    @staticmethod
    def _concat(tables: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
        if not tables:  # nothing near: one degenerate triangle far below
            v = np.array([[0, 0, -1e4], [1, 0, -1e4], [0, 1, -1e4]], np.float32)
            return (v, np.array([[0, 1, 2]], np.int64), np.zeros((1, 3), np.float32), np.ones(1, np.float32),
                    np.zeros(1, np.float32), np.zeros(1, np.int64))  # fmt: skip
        offsets = np.cumsum([0] + [len(t[0]) for t in tables[:-1]])
        return (
            np.vstack([t[0] for t in tables]),
            np.vstack([t[1] + o for t, o in zip(tables, offsets, strict=True)]),
            np.vstack([t[2] for t in tables]),
            np.concatenate([t[3] for t in tables]),
            np.concatenate([t[4] for t in tables]),
            np.concatenate([t[5] for t in tables]),
        )

    def _world_vertices(self, obj: _Object, poses: dict[int, tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """The object's vertices in the trajectory file's frame."""
        vertices = self._object_vertices(obj, poses)
        return vertices @ self._to_street[:3, :3]  # street -> trajectory frame (the transpose's action)

