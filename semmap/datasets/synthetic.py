"""A seeded synthetic RGB-D sequence with exact ground truth: a dining room, a circling camera, walking people.

Why: real datasets give camera ground truth but no object ground truth, so mapping accuracy, the
handling of moving objects and loop closure can only be measured on data where every object's
class, position and visibility is known. Frames are ray cast with Open3D's RaycastingScene (it works
headless, where Open3D's renderer does not); each frame's instance boxes come from the hit triangle
ids, so they are what a perfect detector would report.

World frame: z up, the room's floor at z = 0, the table centred on the origin. Camera frame: OpenCV
(x right, y down, z forward); poses are camera-to-world.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import open3d as o3d

from semmap.core.geometry import look_at

from .base import Dataset, DatasetError, FrameData, InstanceBox, Intrinsics, ObjectTruth

Mesh = tuple[np.ndarray, np.ndarray]  # (V x 3 float vertices, T x 3 int triangles)


C = TypeVar("C")  # a world's config dataclass (config_from_options)


@dataclass(frozen=True)
class SyntheticConfig:
    """Everything that shapes a synthetic sequence; equal configs give bit-identical frames.

    fx/fy/cx/cy default (None) to the 640x480 Kinect-like camera (525, 525, 319.5, 239.5) scaled to
    width x height. depth_noise is the Gaussian sigma in metres at 1 m range (it grows with z^2, like a
    structured-light sensor); 0 gives exact depth.
    """

    frames: int = 300
    seed: int = 0
    width: int = 640
    height: int = 480
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    rate_hz: float = 30.0
    room_size: tuple[float, float, float] = (6.0, 5.0, 2.8)
    camera_radius: float = 2.0
    camera_height: float = 1.4
    camera_wave: float = 0.08
    persons: int = 2
    depth_noise: float = 0.001
    min_visible_pixels: int = 150
    moved: int = 0  # this many small table-top objects (seeded choice) stand elsewhere on the table (at most 4)
    removed: int = 0  # this many more (seeded choice, none of the moved ones) are gone: a later day's scene

    def __post_init__(self) -> None:
        if self.frames < 1 or self.width < 16 or self.height < 16:
            raise DatasetError(f"synthetic: frames >= 1 and size >= 16x16 needed, got {self}")
        if not 0 <= self.persons <= 2:
            raise DatasetError(f"synthetic: persons must be 0, 1 or 2, got {self.persons}")
        if not (0 <= self.moved <= 4 and self.removed >= 0 and self.moved + self.removed <= 8):
            raise DatasetError(f"synthetic: moved must be 0-4 and moved + removed at most 8, got {self.moved}, "
                               f"{self.removed}")
        if self.rate_hz <= 0 or self.depth_noise < 0:
            raise DatasetError("synthetic: rate_hz must be > 0 and depth_noise >= 0")
        lx, ly, lz = self.room_size
        # The camera circle must stay inside the room and clear of the person pacing along the tv wall.
        if self.camera_radius < 1.8:  # inside that the camera would walk through the chairs and the walking person
            raise DatasetError(f"synthetic: camera_radius must be >= 1.8 m, got {self.camera_radius}")
        if min(lx, ly) / 2 - self.camera_radius < 0.25 or lx / 2 - 0.8 < self.camera_radius:
            raise DatasetError(
                f"synthetic: room {lx}x{ly} m too small for camera_radius {self.camera_radius} "
                f"(needs room >= {2 * self.camera_radius + 1.6:.1f} x {2 * self.camera_radius + 0.5:.1f} m)"
            )
        low, high = self.camera_height - self.camera_wave, self.camera_height + self.camera_wave
        if low < 0.5 or high > lz - 0.1:
            raise DatasetError(f"synthetic: camera height {self.camera_height} +- {self.camera_wave} outside the room")

    def intrinsics(self) -> Intrinsics:
        sx, sy = self.width / 640.0, self.height / 480.0
        return Intrinsics(
            fx=self.fx if self.fx is not None else 525.0 * sx,
            fy=self.fy if self.fy is not None else 525.0 * sy,
            cx=self.cx if self.cx is not None else (self.width - 1) / 2.0,
            cy=self.cy if self.cy is not None else (self.height - 1) / 2.0,
            width=self.width,
            height=self.height,
        )

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> SyntheticConfig:
        """Build from loose options (strings from a spec like `synthetic:frames=600,seed=3,size=320x240`)."""
        return config_from_options(cls, options, "synthetic", "640x480")


def config_from_options(cls: type[C], options: Mapping[str, Any], label: str, size_example: str) -> C:
    """A world's config dataclass from loose options (strings from `synthetic:frames=600,size=320x240`): `size`
    sets width and height; each other option is read as its field's default type (tuple `AxBxC`, str, bool, int,
    else float; None stays None). DatasetError names an unknown option or a bad value."""
    fields = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]  # (declared order, for the error)
    values: dict[str, Any] = {}
    for key, raw in options.items():
        if key == "size":
            try:
                width, height = (int(v) for v in str(raw).lower().split("x"))
            except ValueError as exc:
                raise DatasetError(f"{label}: size must look like {size_example}, got {raw!r}") from exc
            values["width"], values["height"] = width, height
            continue
        if key not in fields:
            names = ", ".join(["size", *fields])
            raise DatasetError(f"{label}: unknown option {key!r}; valid options: {names}")
        default = getattr(cls, key)
        try:
            if isinstance(default, tuple):
                parts = raw if isinstance(raw, list | tuple) else str(raw).lower().split("x")
                values[key] = tuple(float(v) for v in parts)
            elif isinstance(default, str):
                values[key] = str(raw)
            elif isinstance(default, bool):
                values[key] = raw if isinstance(raw, bool) else str(raw).lower() in ("1", "true", "yes")
            elif isinstance(default, int):
                values[key] = int(raw)
            else:  # floats and the optional intrinsics
                values[key] = None if raw is None else float(raw)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"{label}: bad value for {key}: {raw!r}") from exc
    return cls(**values)


# ----------------------------------------------------------------------------------------------------------
# Mesh primitives (numpy only; the scene stays a few thousand triangles so it rebuilds in ~1 ms)


def box_mesh(center: tuple[float, float, float], size: tuple[float, float, float], yaw: float = 0.0) -> Mesh:
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    vertices = corners * np.asarray(size, dtype=float)
    faces = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    return _rotate_z(vertices, yaw) + np.asarray(center, dtype=float), faces


def cylinder_mesh(
    base: tuple[float, float, float], radius_bottom: float, radius_top: float, height: float, segments: int = 24
) -> Mesh:
    """A capped (truncated-cone) cylinder along +z standing on `base`."""
    angles = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    bottom = np.column_stack([ring * radius_bottom, np.zeros(segments)])
    top = np.column_stack([ring * radius_top, np.full(segments, height)])
    vertices = np.vstack([bottom, top, [[0.0, 0.0, 0.0], [0.0, 0.0, height]]]) + np.asarray(base, dtype=float)
    i = np.arange(segments)
    j = (i + 1) % segments
    cb, ct = 2 * segments, 2 * segments + 1
    faces = np.vstack(
        [
            np.column_stack([i, j, j + segments]),
            np.column_stack([i, j + segments, i + segments]),
            np.column_stack([np.full(segments, cb), j, i]),
            np.column_stack([np.full(segments, ct), i + segments, j + segments]),
        ]
    )
    return vertices, faces


def sphere_mesh(center: tuple[float, float, float], radius: float, rings: int = 10, segments: int = 18) -> Mesh:
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    body = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    vertices = np.vstack([[[0.0, 0.0, 1.0]], body, [[0.0, 0.0, -1.0]]]) * radius + np.asarray(center, float)
    faces = []
    south = len(vertices) - 1
    for s in range(segments):
        n = (s + 1) % segments
        faces.append([0, 1 + s, 1 + n])
        last = 1 + (rings - 2) * segments
        faces.append([south, last + n, last + s])
        for r in range(rings - 2):
            a, b = 1 + r * segments + s, 1 + r * segments + n
            faces.extend([[a, a + segments, b], [b, a + segments, b + segments]])
    return vertices, np.asarray(faces)


def _rotate_z(vertices: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return vertices @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T


def _rotate_x(vertices: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return vertices @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]).T


# ----------------------------------------------------------------------------------------------------------
# Scene description


@dataclass
class _Part:
    """One coloured piece of geometry; several parts can make one object (a chair is seat + back + legs)."""

    mesh: Mesh
    color: tuple[float, float, float]
    texture_size: float  # metres per texture cell
    texture_contrast: float


@dataclass
class _Object:
    instance_id: int  # 0 = the room (not an object)
    class_name: str
    parts: list[_Part]
    motion: Callable[[float], tuple[np.ndarray, np.ndarray]] | None = None  # t -> (R 3x3, translation)

    @property
    def moving(self) -> bool:
        return self.motion is not None


def _rgb(values: Any) -> tuple[float, float, float]:
    r, g, b = (float(v) for v in values)
    return r, g, b


def _person_parts(rng: np.random.Generator) -> list[_Part]:
    """A person in its own frame: feet at the origin, facing +x, 0.48 m wide, 0.3 m deep, 1.72 m tall."""
    shirt = _rgb(rng.uniform(0.2, 0.8, 3))
    trousers = (0.15, 0.17, 0.3)
    skin = (0.85, 0.66, 0.52)
    return [
        _Part(box_mesh((0.0, 0.11, 0.425), (0.16, 0.16, 0.85)), trousers, 0.05, 0.3),
        _Part(box_mesh((0.0, -0.11, 0.425), (0.16, 0.16, 0.85)), trousers, 0.05, 0.3),
        _Part(box_mesh((0.0, 0.0, 1.175), (0.3, 0.48, 0.65)), shirt, 0.04, 0.35),
        _Part(sphere_mesh((0.0, 0.0, 1.61), 0.11), skin, 0.03, 0.15),
    ]


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


FREE_TABLE_SPOTS = ((-0.3, -0.35), (-0.7, 0.33), (0.72, -0.38), (0.25, 0.38))  # clear of every table-top object
MOVABLE = ("cup", "bottle", "bowl", "book")


def changed_objects(config: SyntheticConfig, objects: list[_Object]) -> tuple[list[int], list[int]]:
    """Instance ids of the moved and the removed objects (seeded by the scene's seed, not drawn from the scene's
    own generator: a scene without changes is the same scene as before)."""
    pool = [o.instance_id for o in objects if o.class_name in MOVABLE]
    order = [pool[int(i)] for i in np.random.default_rng([config.seed, 13]).permutation(len(pool))]
    return order[: config.moved], order[config.moved : config.moved + config.removed]


def _change(objects: list[_Object], config: SyntheticConfig) -> None:
    """Move `moved` objects to free spots on the table and take `removed` ones out of the room (far below the
    floor: never rendered, the instance ids of the others stay as they were)."""
    if not (config.moved or config.removed):
        return
    moved, removed = changed_objects(config, objects)
    for oid, spot in zip(moved, FREE_TABLE_SPOTS, strict=False):
        obj = objects[oid]
        centre = np.mean(np.concatenate([part.mesh[0] for part in obj.parts]), axis=0)
        shift = np.array([spot[0] - centre[0], spot[1] - centre[1], 0.0])
        obj.parts = [dataclasses.replace(part, mesh=(part.mesh[0] + shift, part.mesh[1])) for part in obj.parts]
    for oid in removed:
        obj = objects[oid]
        obj.parts = [dataclasses.replace(part, mesh=(part.mesh[0] + np.array([0.0, 0.0, -50.0]), part.mesh[1]))
                     for part in obj.parts]


def _build_scene(config: SyntheticConfig) -> list[_Object]:
    """Room, table, things on and around it, people; small placements and colours depend on the seed (drawn in a
    fixed order, piece by piece: the scene of a seed never changes)."""
    rng = np.random.default_rng([config.seed, 7])
    lx, ly, _ = config.room_size
    objects: list[_Object] = [_room(config.room_size)]

    def add(class_name: str, parts: list[_Part]) -> None:
        objects.append(_Object(len(objects), class_name, parts))

    _add_table_and_things_on_it(add, rng)
    _add_chairs(add, rng)
    _add_furniture_by_the_walls(add, rng, lx, ly)
    _change(objects, config)
    _add_persons(objects, config, rng)
    return objects


def _jitter(rng: np.random.Generator, color: tuple[float, float, float]) -> tuple[float, float, float]:
    """A seeded variation of a colour (each channel within 15 %)."""
    return _rgb(np.clip(np.asarray(color) * rng.uniform(0.85, 1.15, 3), 0.0, 1.0))


def _near(rng: np.random.Generator, x: float, y: float) -> tuple[float, float]:
    """A seeded placement within 3 cm of (x, y)."""
    return x + float(rng.uniform(-0.03, 0.03)), y + float(rng.uniform(-0.03, 0.03))


def _room(size: tuple[float, float, float]) -> _Object:
    """Floor, ceiling and four walls."""
    lx, ly, lz = size
    return _Object(
        0,
        "room",
        [
            # Slabs 0.1 m thick that overlap at the edges, so no ray escapes through a corner.
            _Part(box_mesh((0.0, 0.0, -0.05), (lx + 0.2, ly + 0.2, 0.1)), (0.55, 0.42, 0.3), 0.08, 0.35),  # floor
            _Part(box_mesh((0.0, 0.0, lz + 0.05), (lx + 0.2, ly + 0.2, 0.1)), (0.9, 0.9, 0.88), 0.4, 0.15),
            _Part(box_mesh((-lx / 2 - 0.05, 0.0, lz / 2), (0.1, ly + 0.2, lz + 0.2)), (0.78, 0.76, 0.7), 0.2, 0.25),
            _Part(box_mesh((lx / 2 + 0.05, 0.0, lz / 2), (0.1, ly + 0.2, lz + 0.2)), (0.72, 0.78, 0.76), 0.2, 0.25),
            _Part(box_mesh((0.0, -ly / 2 - 0.05, lz / 2), (lx + 0.2, 0.1, lz + 0.2)), (0.8, 0.74, 0.66), 0.2, 0.25),
            _Part(box_mesh((0.0, ly / 2 + 0.05, lz / 2), (lx + 0.2, 0.1, lz + 0.2)), (0.7, 0.74, 0.8), 0.2, 0.25),
        ],
    )


def _add_table_and_things_on_it(add: Callable[[str, list[_Part]], None], rng: np.random.Generator) -> None:
    """The dining table and the cups, bottles, bowl, laptop and book on it."""
    top = 0.77  # table-top height
    wood = _jitter(rng, (0.55, 0.34, 0.18))
    table = [_Part(box_mesh((0.0, 0.0, 0.745), (1.6, 0.9, 0.05)), wood, 0.05, 0.3)]
    table += [
        _Part(box_mesh((sx * 0.74, sy * 0.39, 0.36), (0.06, 0.06, 0.72)), wood, 0.05, 0.3)
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    add("dining table", table)

    for x, y in ((0.05, -0.25), (0.35, -0.08), (-0.15, 0.25)):
        color = _jitter(rng, [(0.92, 0.92, 0.9), (0.8, 0.15, 0.12), (0.15, 0.3, 0.75)][int(rng.integers(3))])
        add("cup", [_Part(cylinder_mesh((*_near(rng, x, y), top), 0.04, 0.045, 0.1), color, 0.02, 0.3)])
    for x, y in ((0.15, 0.15), (-0.65, -0.25)):
        glass = _jitter(rng, (0.12, 0.45, 0.18))
        bx, by = _near(rng, x, y)
        add(
            "bottle",
            [
                _Part(cylinder_mesh((bx, by, top), 0.035, 0.035, 0.2), glass, 0.02, 0.3),
                _Part(cylinder_mesh((bx, by, top + 0.2), 0.035, 0.014, 0.04), glass, 0.02, 0.3),
                _Part(cylinder_mesh((bx, by, top + 0.24), 0.014, 0.014, 0.05), glass, 0.02, 0.3),
            ],
        )
    bowl_at = _near(rng, 0.6, -0.2)
    add("bowl", [_Part(cylinder_mesh((*bowl_at, top), 0.05, 0.085, 0.07), _jitter(rng, (0.9, 0.82, 0.6)), 0.02, 0.3)])
    lx0, ly0 = _near(rng, -0.45, 0.1)
    grey = _jitter(rng, (0.32, 0.33, 0.36))
    add(
        "laptop",
        [
            _Part(box_mesh((lx0, ly0, top + 0.01), (0.33, 0.23, 0.02)), grey, 0.02, 0.3),
            _Part(box_mesh((lx0, ly0 + 0.12, top + 0.13), (0.33, 0.012, 0.22)), (0.12, 0.14, 0.2), 0.02, 0.4),
        ],
    )
    book_at = _near(rng, 0.55, 0.2)
    book_box = box_mesh((*book_at, top + 0.015), (0.21, 0.15, 0.03), float(rng.uniform(-0.5, 0.5)))
    add("book", [_Part(book_box, _jitter(rng, (0.7, 0.12, 0.12)), 0.02, 0.35)])


def _add_chairs(add: Callable[[str, list[_Part]], None], rng: np.random.Generator) -> None:
    """Four chairs round the table."""
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * 0.45, sy * 0.62
            color = _jitter(rng, (0.42, 0.26, 0.14))
            parts = [_Part(box_mesh((cx, cy, 0.46), (0.44, 0.44, 0.04)), color, 0.04, 0.3)]
            parts.append(_Part(box_mesh((cx, cy + sy * 0.2, 0.715), (0.44, 0.04, 0.47)), color, 0.04, 0.3))
            parts += [
                _Part(box_mesh((cx + ex * 0.2, cy + ey * 0.2, 0.22), (0.04, 0.04, 0.44)), color, 0.04, 0.3)
                for ex in (-1, 1)
                for ey in (-1, 1)
            ]
            add("chair", parts)


def _add_furniture_by_the_walls(add: Callable[[str, list[_Part]], None], rng: np.random.Generator, lx: float,
                                ly: float) -> None:
    """The tv, refrigerator, potted plant and clock."""
    add(
        "tv",
        [
            _Part(box_mesh((-lx / 2 + 0.025, 0.0, 1.35), (0.05, 1.1, 0.65)), (0.06, 0.06, 0.07), 0.03, 0.3),
            _Part(box_mesh((-lx / 2 + 0.055, 0.0, 1.36), (0.012, 1.0, 0.57)), _jitter(rng, (0.15, 0.25, 0.5)), 0.05,
                  0.6),
        ],
    )
    add(
        "refrigerator",
        [_Part(box_mesh((-lx / 2 + 0.4, ly / 2 - 0.4, 0.9), (0.7, 0.7, 1.8)), _jitter(rng, (0.88, 0.88, 0.9)), 0.1,
               0.2)],
    )
    px, py = lx / 2 - 0.5, ly / 2 - 0.5
    add(
        "potted plant",
        [
            _Part(cylinder_mesh((px, py, 0.0), 0.12, 0.16, 0.32), _jitter(rng, (0.7, 0.36, 0.2)), 0.04, 0.3),
            _Part(sphere_mesh((px, py, 0.62), 0.32), _jitter(rng, (0.2, 0.5, 0.18)), 0.03, 0.5),
        ],
    )
    face_v, face_f = cylinder_mesh((0.0, 0.0, 0.0), 0.16, 0.16, 0.04)
    face_v = _rotate_x(face_v, math.pi / 2) + np.array([0.9, ly / 2, 2.0])
    add("clock", [_Part((face_v, face_f), _jitter(rng, (0.95, 0.95, 0.9)), 0.03, 0.5)])


def _add_persons(objects: list[_Object], config: SyntheticConfig, rng: np.random.Generator) -> None:
    """The people who walk through the room (`config.persons`: 0, 1 or 2)."""
    lx, ly, _ = config.room_size
    if config.persons >= 1:
        # Walks round the table between the chairs and the camera's circle, keeping roughly to the far side
        # of the table from the camera (swinging +-30 degrees about it), so it crosses the view behind the
        # table and occludes objects there without blotting out the whole image.
        swing_phase = float(rng.uniform(0.0, 2 * math.pi))
        loop_period = (config.frames - 1) / config.rate_hz if config.frames > 1 else 1.0

        def place(t: float) -> np.ndarray:
            a = math.pi / 2 + 2 * math.pi * t / loop_period + 0.5 * math.sin(2 * math.pi * t / 7.0 + swing_phase)
            return np.array([1.3 * math.cos(a), 1.2 * math.sin(a), 0.0])

        def loop(t: float) -> tuple[np.ndarray, np.ndarray]:
            velocity = place(t + 0.01) - place(t - 0.01)
            return _yaw_matrix(math.atan2(velocity[1], velocity[0])), place(t)

        objects.append(_Object(len(objects), "person", _person_parts(rng), loop))
    if config.persons >= 2:
        # Walks to and fro along the wall behind the tv side, crossing in front of the tv.
        phase = float(rng.uniform(0.0, 2 * math.pi))
        period = 9.0
        x_line = -lx / 2 + 0.55

        def pace(t: float, phase: float = phase, period: float = period) -> tuple[np.ndarray, np.ndarray]:
            w = 2 * math.pi / period
            y = min(1.5, ly / 2 - 0.95) * math.sin(w * t + phase)  # stops short of the refrigerator
            heading = math.pi / 2 if math.cos(w * t + phase) >= 0 else -math.pi / 2
            return _yaw_matrix(heading), np.array([x_line, y, 0.0])

        objects.append(_Object(len(objects), "person", _person_parts(rng), pace))


# ----------------------------------------------------------------------------------------------------------
# The dataset


@dataclass
class FrameScene:
    """The geometry one frame is ray cast against: the triangles, their per-triangle tables and the objects.

    tri_label holds frame-local object indices 0..n_obj-1 (0 = background); `ids` maps them to instance ids
    (None: local index = instance id, as in the room). `moving` holds the (R, t) of the moving objects in view,
    keyed by local index (their texture lives in their mesh frame)."""

    vertices: np.ndarray  # (V, 3) float32, moving objects already placed
    triangles: np.ndarray  # (T, 3) uint32, C-contiguous: Open3D wraps it per cast without a copy
    tri_color: np.ndarray
    tri_label: np.ndarray
    tri_inv_size: np.ndarray
    tri_contrast: np.ndarray
    n_obj: int
    moving: dict[int, tuple[np.ndarray, np.ndarray]]
    ids: np.ndarray | None = None


@dataclass
class SyntheticRender:
    """A frame plus its HxW int32 instance-id image (0 = room / nothing), for tests and evaluation."""

    frame: FrameData
    labels: np.ndarray


class SyntheticDataset(Dataset):
    """The synthetic sequence; frames are rendered on demand (ray casting dominates: ~30 ms on one core)."""

    name = "synthetic"
    _MAGIC = np.float32(12582912.0)  # 1.5 * 2**23: adding it leaves round(x) in the low mantissa bits
    _HASH_WEIGHTS = np.array([73856093, 19349663, 83492791], np.int32)

    def __init__(self, config: SyntheticConfig | None = None, threads: int = 0, **options: Any) -> None:
        if config is not None and options:
            raise DatasetError("synthetic: pass either a SyntheticConfig or options, not both")
        self.config = config if config is not None else SyntheticConfig.from_options(options)
        self.threads = int(threads)  # ray-casting threads, 0 = Open3D's default (all cores)
        self.rate_hz = float(self.config.rate_hz)
        self.name = f"synthetic/seed{self.config.seed}"
        self.intrinsics = self.config.intrinsics()
        self._objects = _build_scene(self.config)
        self._classes = {o.instance_id: o.class_name for o in self._objects}
        self._moving_ids = {o.instance_id for o in self._objects if o.moving}

        # The whole scene is one triangle mesh, rebuilt per frame (only the moving objects' vertices change;
        # ~2.7k triangles build in well under 1 ms), so a ray's primitive id indexes these per-triangle tables.
        vertices: list[np.ndarray] = []
        triangles: list[np.ndarray] = []
        color: list[np.ndarray] = []
        inv_size: list[np.ndarray] = []
        contrast: list[np.ndarray] = []
        label: list[np.ndarray] = []
        self._moving_vertices: dict[int, slice] = {}  # rows of self._vertices per moving object (mesh frame)
        n_vertices = 0
        for obj in sorted(self._objects, key=lambda o: o.moving):
            first = n_vertices
            for part in obj.parts:
                v, f = part.mesh
                n_tri = len(f)
                vertices.append(v)
                triangles.append(f + n_vertices)
                n_vertices += len(v)
                color.append(np.tile(np.asarray(part.color, np.float32) * np.float32(255.0), (n_tri, 1)))
                inv_size.append(np.full(n_tri, 1.0 / part.texture_size, np.float32))
                contrast.append(np.full(n_tri, part.texture_contrast, np.float32))
                label.append(np.full(n_tri, obj.instance_id, np.int32))
            if obj.moving:
                self._moving_vertices[obj.instance_id] = slice(first, n_vertices)
        self._vertices = np.vstack(vertices).astype(np.float32)
        # numpy, not an Open3D tensor: an Open3D allocation still alive when the process ends makes Open3D's
        # leak check at exit end the process with status 1 (a service that stopped cleanly reported failure)
        self._triangles = np.ascontiguousarray(np.vstack(triangles), dtype=np.uint32)
        self._tri_color, self._tri_label = np.vstack(color), np.concatenate(label)
        self._tri_inv_size, self._tri_contrast = np.concatenate(inv_size), np.concatenate(contrast)
        self._prepare_rays(self.config.seed)

    # ---- geometry over time

    def stamp(self, index: int) -> float:
        return index / self.rate_hz

    def stamps(self) -> list[float]:
        return [self.stamp(i) for i in range(len(self))]

    def camera_pose(self, index: int) -> np.ndarray:
        """Camera-to-world at frame `index`: one loop round the table, the last frame back at the start pose."""
        c = self.config
        phi = 2 * math.pi * index / (c.frames - 1) if c.frames > 1 else 0.0
        theta = -math.pi / 2 + phi
        position = np.array(
            [c.camera_radius * math.cos(theta), c.camera_radius * math.sin(theta),
             c.camera_height + c.camera_wave * math.sin(3 * phi)]
        )  # fmt: skip
        target = np.array([0.25 * math.sin(2 * phi), 0.15 * math.sin(phi), 0.8 + 0.05 * math.sin(5 * phi)])
        return look_at(position, target)

    def object_poses(self, index: int) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """(R, t) of every moving object at frame `index`: its mesh frame (feet, facing +x) to world."""
        t = self.stamp(index)
        return {o.instance_id: o.motion(t) for o in self._objects if o.motion is not None}

    def _object_vertices(self, obj: _Object, poses: dict[int, tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        vertices = np.vstack([p.mesh[0] for p in obj.parts])
        if obj.instance_id in poses:
            rotation, translation = poses[obj.instance_id]
            vertices = vertices @ rotation.T + translation
        return vertices

    def _world_vertices(self, obj: _Object, poses: dict[int, tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """The object's vertices in the frame its ground truth is reported in (the room's own; a world built in
        another frame, the street, turns them)."""
        return self._object_vertices(obj, poses)

    def object_centroids(self, index: int) -> dict[int, np.ndarray]:
        """World AABB centre of every object at frame `index` (static ones never change)."""
        poses = self.object_poses(index)
        result = {}
        for obj in self._objects[1:]:
            vertices = self._world_vertices(obj, poses)
            result[obj.instance_id] = (vertices.min(0) + vertices.max(0)) / 2
        return result

    def objects(self) -> list[ObjectTruth]:
        """Every object; centroid/extent are its world AABB (at frame 0 for the moving ones)."""
        poses = self.object_poses(0)
        truths = []
        for obj in self._objects[1:]:
            vertices = self._world_vertices(obj, poses)
            lo, hi = vertices.min(0), vertices.max(0)
            centroid, extent = (lo + hi) / 2, hi - lo
            truths.append(
                ObjectTruth(
                    instance_id=obj.instance_id,
                    class_name=obj.class_name,
                    centroid=(float(centroid[0]), float(centroid[1]), float(centroid[2])),
                    extent=(float(extent[0]), float(extent[1]), float(extent[2])),
                    moving=obj.moving,
                )
            )
        return truths

    # ---- dataset interface

    def __len__(self) -> int:
        return self.config.frames

    @property
    def has_groundtruth(self) -> bool:
        return True

    def groundtruth(self) -> list[tuple[float, np.ndarray]]:
        return [(self.stamp(i), self.camera_pose(i)) for i in range(len(self))]

    def __getitem__(self, index: int) -> FrameData:
        return self.render(index).frame

    # Hooks the street world (semmap.datasets.street) overrides: the frame's geometry, the pose in the scene's
    # frame, the colour of rays that hit nothing (None: the room's floor colour, as ever) and the depth range.
    _sky: tuple[float, float, float] | None = None
    _max_depth: float | None = None

    def _frame_scene(self, index: int) -> FrameScene:
        vertices = self._vertices.copy()
        moving_poses = self.object_poses(index)
        for instance_id, rows in self._moving_vertices.items():
            rotation, translation = moving_poses[instance_id]
            vertices[rows] = vertices[rows] @ rotation.T.astype(np.float32) + translation.astype(np.float32)
        return FrameScene(
            vertices, self._triangles, self._tri_color, self._tri_label, self._tri_inv_size, self._tri_contrast,
            len(self._objects), {i: moving_poses[i] for i in self._moving_ids},
        )  # fmt: skip

    def _scene_pose(self, pose: np.ndarray) -> np.ndarray:
        return pose

    def _class_of(self, instance_id: int) -> str:
        return self._classes[instance_id]

    def _prepare_rays(self, seed: int) -> None:
        """What every frame's ray cast and shading reuse: the camera's ray directions, the seeded depth-noise bank,
        pixel rows and columns, the texture key and the light."""
        k = self.intrinsics
        u, v = np.meshgrid(np.arange(k.width, dtype=np.float32), np.arange(k.height, dtype=np.float32))
        # (N, 3) camera-frame ray directions with z = 1, so the ray parameter t_hit is the z-depth itself.
        self._dirs_cam = np.stack(
            [((u - np.float32(k.cx)) / np.float32(k.fx)).ravel(), ((v - np.float32(k.cy)) / np.float32(k.fy)).ravel(),
             np.ones(u.size, np.float32)], axis=1
        )  # fmt: skip
        self._inv_dir_norm = (1.0 / np.linalg.norm(self._dirs_cam, axis=1)).astype(np.float32)
        # Depth noise is drawn from one seeded bank at a per-frame offset: a fresh normal draw per frame
        # would cost more than the rest of the shading together.
        bank_rng = np.random.default_rng([seed, 11])
        self._noise_bank = bank_rng.standard_normal(2 * u.size + 7919, dtype=np.float32)
        self._rows = np.repeat(np.arange(k.height, dtype=np.int32), k.width)
        self._cols = np.tile(np.arange(k.width, dtype=np.int32), k.height)
        self._texture_key = np.int32((seed * 2654435761) & 0x7FFFFFFF)
        light = np.array([0.35, -0.25, 1.0])
        self._light = (light / np.linalg.norm(light)).astype(np.float32)  # direction towards a high, oblique light

    def render(self, index: int) -> SyntheticRender:
        """Ray cast frame `index`: RGB, depth (mm), exact pose, instance boxes and the instance-id image."""
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range 0..{len(self) - 1}")
        index %= len(self)
        k = self.intrinsics
        pose = self.camera_pose(index)
        fs = self._frame_scene(index)
        cast_pose = self._scene_pose(pose)
        origin = cast_pose[:3, 3].astype(np.float32)
        # rays = [origin, R d] for every pixel in one product: d's third component is 1, which adds the origin.
        to_rays = np.zeros((3, 6), np.float32)
        to_rays[:, 3:] = cast_pose[:3, :3].T
        to_rays[2, :3] = origin
        rays = self._dirs_cam @ to_rays
        dirs = rays[:, 3:]

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor.from_numpy(fs.vertices), o3d.core.Tensor.from_numpy(fs.triangles))
        hits = scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=self.threads)

        triangle = hits["primitive_ids"].numpy().astype(np.intp)  # one conversion instead of one per lookup
        depth = hits["t_hit"].numpy()
        normals = hits["primitive_normals"].numpy()
        missed = hits["geometry_ids"].numpy() == o3d.t.geometry.RaycastingScene.INVALID_ID
        any_missed = bool(missed.any())  # only with a degenerate room (the street: the sky)
        far = None  # beyond the depth range (the street's): shaded as ever, but no depth and no object
        if self._max_depth is not None:
            far = (depth > np.float32(self._max_depth)) & ~missed
            far = far if far.any() else None
        if any_missed:
            triangle = np.where(missed, 0, triangle)
            depth = np.where(missed, np.float32(0.0), depth)
            normals = np.where(missed[:, None], np.float32(0.0), normals)
        labels = np.take(fs.tri_label, triangle)
        if any_missed:
            labels[missed] = 0
        if far is not None:
            labels[far] = 0
        # (object, row) pixel counts: the per-object totals, and the rows each object covers for its box.
        n_obj = fs.n_obj
        row_counts = np.bincount(labels * np.int32(k.height) + self._rows, minlength=n_obj * k.height)
        row_counts = row_counts.reshape(n_obj, k.height)
        counts = row_counts.sum(axis=1)

        # Texture: hashed value noise in surface cells, in the mesh frame for moving objects.
        dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
        px, py, pz = dx * depth, dy * depth, dz * depth
        px += origin[0]
        py += origin[1]
        pz += origin[2]
        # The texture lives on the surface: the coordinate along a face's dominant normal axis is left out of
        # the hash, so an axis-aligned face lying on a texture-cell boundary does not flicker.
        nx, ny, nz = normals[:, 0], normals[:, 1], normals[:, 2]
        tx, ty, tz = np.abs(nx) < 0.7, np.abs(ny) < 0.7, np.abs(nz) < 0.7
        for i, (rotation, translation) in fs.moving.items():
            if counts[i] == 0:
                continue
            pixels = np.flatnonzero(labels == i)
            cos_t, sin_t = np.float32(rotation[0, 0]), np.float32(rotation[1, 0])
            ox, oy = px[pixels] - np.float32(translation[0]), py[pixels] - np.float32(translation[1])
            px[pixels] = cos_t * ox + sin_t * oy
            py[pixels] = cos_t * oy - sin_t * ox
            pz[pixels] -= np.float32(translation[2])
            lx = cos_t * nx[pixels] + sin_t * ny[pixels]
            ly = cos_t * ny[pixels] - sin_t * nx[pixels]
            tx[pixels], ty[pixels] = np.abs(lx) < 0.7, np.abs(ly) < 0.7
        scale = np.take(fs.tri_inv_size, triangle)
        key = ((px * scale + self._MAGIC).view(np.int32) * (tx * self._HASH_WEIGHTS[0])) ^ self._texture_key
        key ^= (py * scale + self._MAGIC).view(np.int32) * (ty * self._HASH_WEIGHTS[1])
        key ^= (pz * scale + self._MAGIC).view(np.int32) * (tz * self._HASH_WEIGHTS[2])
        key ^= key >> 13
        key *= np.int32(0x5BD1E995)
        key ^= key >> 15
        noise = (key & 255).astype(np.float32) * np.float32(1.0 / 255.0) - np.float32(0.5)

        # Lambertian shading: one high oblique light plus a weak headlight; normals turned to face the camera.
        n_dot_d = nx * dx
        n_dot_d += ny * dy
        n_dot_d += nz * dz
        n_dot_l = (nx * self._light[0] + ny * self._light[1] + nz * self._light[2]) * -np.sign(n_dot_d)
        shade = np.maximum(n_dot_l, 0.0) * np.float32(0.6) + np.abs(n_dot_d) * self._inv_dir_norm * np.float32(0.2)
        shade += np.float32(0.25)
        shade *= np.float32(1.0) + np.take(fs.tri_contrast, triangle) * noise
        np.minimum(shade, np.float32(1.0), out=shade)
        rgb = np.take(fs.tri_color, triangle, axis=0)
        rgb *= shade[:, None]
        rgb = rgb.astype(np.uint8)
        if any_missed and self._sky is not None:
            rgb[missed] = np.asarray(self._sky, np.float32) * np.float32(255.0)

        depth_mm = self._depth_mm(index, depth, missed if any_missed else None, far)
        instances = self._instances(labels, counts, row_counts, fs)
        if fs.ids is not None:
            labels = np.take(fs.ids, labels)
        labels_2d = labels.reshape(k.height, k.width)
        return SyntheticRender(
            frame=FrameData(
                index=index,
                stamp=self.stamp(index),
                rgb=rgb.reshape(k.height, k.width, 3),
                depth=depth_mm.reshape(k.height, k.width),
                depth_scale=0.001,
                intrinsics=k,
                gt_pose=pose,
                instances=instances,
            ),
            labels=labels_2d,
        )

    def _depth_mm(self, index: int, depth: np.ndarray, missed: np.ndarray | None,
                  far: np.ndarray | None) -> np.ndarray:
        """The ray lengths as a uint16 depth image in mm, with the sensor's noise (seeded per frame); rays that hit
        nothing (`missed`) or ended beyond the depth range (`far`) read 0, as a depth camera's holes do."""
        depth_mm = depth * np.float32(1000.0)
        if self.config.depth_noise > 0:
            start = (index * 7919 + 104729) % (len(self._noise_bank) - depth.size)
            noise_mm = self._noise_bank[start : start + depth.size] * depth
            noise_mm *= depth
            noise_mm *= np.float32(self.config.depth_noise * 1000.0)
            depth_mm += noise_mm
        depth_mm += np.float32(0.5)
        np.clip(depth_mm, 0.0, 65535.0, out=depth_mm)
        depth_mm = depth_mm.astype(np.uint16)
        if missed is not None:
            depth_mm[missed] = 0
        if far is not None:
            depth_mm[far] = 0
        return depth_mm

    def _instances(
        self, labels: np.ndarray, counts: np.ndarray, row_counts: np.ndarray, fs: FrameScene
    ) -> list[InstanceBox]:
        """Tight boxes of the objects with enough visible pixels; box = (x1, y1, x2, y2), x2/y2 exclusive."""
        k = self.intrinsics
        n_obj = fs.n_obj
        visible = [i for i in np.flatnonzero(counts >= self.config.min_visible_pixels) if i != 0]
        if not visible:
            return []
        # (object, row) and (object, column) occupancy from bincounts instead of one mask per object.
        rows = row_counts > 0
        cols = np.bincount(labels * np.int32(k.width) + self._cols, minlength=n_obj * k.width)
        cols = cols.reshape(n_obj, k.width) > 0
        boxes = []
        for i in visible:
            r, c = np.flatnonzero(rows[i]), np.flatnonzero(cols[i])
            instance_id = int(i) if fs.ids is None else int(fs.ids[i])
            boxes.append(
                InstanceBox(
                    instance_id=instance_id,
                    class_name=self._class_of(instance_id),
                    box=(float(c[0]), float(r[0]), float(c[-1] + 1), float(r[-1] + 1)),
                    visible_pixels=int(counts[i]),
                    moving=int(i) in fs.moving,
                )
            )
        return boxes
