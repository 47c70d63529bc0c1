"""Which dynamic objects are seen to move: what opens the repair's scope.

A person box is not evidence that a SLAM is wrong. A person who sits still at a desk (TUM fr1_rpy) is part of
the static scene for a SLAM; a false `person` box on a chair (the 0.25 person threshold gives a few per minute)
is too. Checking the SLAM's steps there only gives semmap's own registration the chance to be the one that is
wrong (fast rotation, motion blur, a flat desk). What corrupts a SLAM is an object that moves while it tracks
features on it. So the scope opens on motion, the paper's test for a landmark candidate applied to the dynamic
objects: each tracked object's centroid is put in the world by the camera poses the repair settled on, and an
object whose centroids over the last `window_s` scatter by more than `min_spread_m` (median absolute deviation
from their median, as the associator's MAD test) moves. An object the associator already saw moving (a chair
pushed: `reason == "moving"`) moves by definition.

What a box's centre can say is limited, and the test keeps to it (TUM fr1_rpy: a seated person whose box, seen
through a fast-turning camera, enters from the top and widens as the shoulders come into view):
- held boxes (`DynamicBox.held`: the tracker's prediction for a frame that did not detect the object, grown by
  how far it may have walked) are not measurements: left out;
- a box whose width changed by more than `max_width_change` since the object's previous view shows another part
  of the object: left out;
- a box cut by the image's left or right edge is placed by its inner edge, the one the object draws (a walker
  entering or leaving the view), and compared only with views placed the same way;
- a box cut by the top or bottom edge keeps its horizontal centre and its depth; its vertical centre (along the
  camera's y axis) does not count;
- the spread must exceed the threshold for `persist_views` views in a row (an object that moves keeps moving;
  one odd depth or box does not).
Pure: boxes and poses in, track ids out.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from semmap.core.messages import DynamicBox

EDGE_PX = 4.0  # a box this close to an edge of the image is cut by it
# (stamp, world point, the camera's y axis where the box is cut at the top or bottom, how the point was placed)
View = tuple[float, np.ndarray, "np.ndarray | None", str]


@dataclass(frozen=True)
class MotionParams:
    """When a tracked dynamic object counts as moving (the `odometry.motion_*` settings)."""

    window_s: float = 1.0  # centroids of the last second
    min_spread_m: float = 0.10  # MAD of the centroids beyond this: moving (a walker covers ~1 m a second)
    min_displacement_m: float = 0.30  # ... or the newest third of them this far from the oldest third
    min_views: int = 5  # the paper's tracklet length: fewer views say nothing yet
    persist_views: int = 3  # ... for this many views in a row
    max_width_change: float = 0.2  # a box whose width changed more than this share shows another part of the object


class MovingObjects:
    """Per frame: `observe(stamp, boxes, camera_to_world, fx, fy, cx, cy, width, height)` after its pose is known,
    `moving(boxes)` before the next one is decided (one frame late: the scope's hold keeps it open far longer)."""

    def __init__(self, params: MotionParams | None = None) -> None:
        self.params = params or MotionParams()
        self._views: dict[int, deque[View]] = {}  # track id -> its views of the last `window_s`
        self._width: dict[int, float] = {}  # track id -> width of its last detected box (px)
        self._above: dict[int, int] = {}  # track id -> views in a row whose spread exceeded the threshold
        self._moving: set[int] = set()
        self._still: set[int] = set()  # seen long enough to tell, and not moving
        self.seen_moving: set[int] = set()  # every track id ever found moving (the run's report)

    def moving(self, boxes: list[DynamicBox]) -> bool:
        """Whether any of these boxes belongs to an object seen moving."""
        return any(b.reason == "moving" or b.track_id in self._moving for b in boxes)

    def undecided(self, boxes: list[DynamicBox]) -> bool:
        """Whether any of these boxes belongs to an object not yet seen long enough to tell whether it moves (a
        person who just came into view): its first views are checked too, since a SLAM that tracks a walker goes
        wrong from the first frames (Bonn crowd: people in view from frame 0, seen moving from frame 22: those 22
        unchecked steps cost the whole run 5 cm)."""
        return any(b.track_id not in self._still and not self.moving([b]) for b in boxes)

    def observe(self, stamp: float, boxes: list[DynamicBox], camera_to_world: np.ndarray, fx: float, fy: float,
                cx: float, cy: float, width: int, height: int) -> None:
        p = self.params
        alive = set()
        for b in boxes:
            alive.add(b.track_id)
            if b.held:
                continue
            x0, y0, x1, y1 = b.box
            z = 0.5 * (b.depth_min_m + b.depth_max_m)
            previous_width = self._width.get(b.track_id)
            self._width[b.track_id] = x1 - x0
            left, right = x0 <= EDGE_PX, x1 >= width - EDGE_PX
            if z <= 0.0 or (left and right) or (previous_width is not None and abs(
                    (x1 - x0) - previous_width) > p.max_width_change * previous_width):
                continue
            u = x1 if left else (x0 if right else 0.5 * (x0 + x1))
            v = 0.5 * (y0 + y1)
            camera = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z])
            point = camera_to_world[:3, :3] @ camera + camera_to_world[:3, 3]
            cut = y0 <= EDGE_PX or y1 >= height - EDGE_PX  # (its vertical centre is the visible part's)
            placed = "left" if left else ("right" if right else "centre")
            views = self._views.setdefault(b.track_id, deque())
            views.append((float(stamp), point, camera_to_world[:3, 1].copy() if cut else None, placed))
            while views and stamp - views[0][0] > p.window_s:
                views.popleft()
            alike = deque(view for view in views if view[3] == placed)
            above = len(alike) >= p.min_views and (spread(alike) > p.min_spread_m
                                                   or displacement(alike) > p.min_displacement_m)
            self._above[b.track_id] = self._above.get(b.track_id, 0) + 1 if above else 0
            if self._above[b.track_id] >= p.persist_views:
                self._moving.add(b.track_id)
                self.seen_moving.add(b.track_id)
                self._still.discard(b.track_id)
            elif len(alike) >= p.min_views and alike[-1][0] - alike[0][0] >= 0.5 * p.window_s and not above:
                self._still.add(b.track_id)
        for gone in set(self._views) - alive:  # (a track's boxes come every frame while it lives, held or not)
            del self._views[gone]
        for table in (self._width, self._above):
            for gone in set(table) - alive:
                del table[gone]
        self._moving &= alive
        self._still &= alive

    def state(self) -> dict:
        return {"moving": sorted(self._moving), "still": sorted(self._still), "seen": sorted(self.seen_moving)}

    def restore(self, state: dict) -> None:
        """The views are not kept (a restart sees objects anew); which ones were moving is."""
        self._views.clear()
        self._width.clear()
        self._above.clear()
        self._moving = {int(t) for t in state.get("moving", [])}
        self._still = {int(t) for t in state.get("still", [])}
        self.seen_moving = {int(t) for t in state.get("seen", [])}


def displacement(views: deque[View]) -> float:
    """How far the median of the newest third of the centroids lies from that of the oldest third: a walker
    who started walking moves it long before the spread of the whole window grows (without the camera-y component
    where the newest view is cut at the top or bottom)."""
    points = np.array([view[1] for view in views])
    k = max(1, len(points) // 3)
    moved = np.median(points[-k:], axis=0) - np.median(points[:k], axis=0)
    vertical = views[-1][2]
    if vertical is not None:
        moved -= (moved @ vertical) * vertical
    return float(np.linalg.norm(moved))


def spread(views: deque[View]) -> float:
    """Median distance of the centroids from their (per-axis) median, robust to a few wrong depths or boxes; a
    view whose vertical centre says nothing (cut at the top or bottom) counts without its camera-y component."""
    points = np.array([view[1] for view in views])
    residuals = points - np.median(points, axis=0)
    for i, (_, _, vertical, _) in enumerate(views):
        if vertical is not None:
            residuals[i] -= (residuals[i] @ vertical) * vertical
    return float(np.median(np.linalg.norm(residuals, axis=1)))
