"""What every odometry front end shares: its input per frame, its error, its interface."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from semmap.core.messages import DynamicBox


class OdometryError(ValueError):
    """The front end cannot produce a pose for this input (e.g. `gt` on data without ground truth)."""


@dataclass
class OdometryInput:
    frame_id: int
    stamp: float
    gt_pose: np.ndarray | None
    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    depth_scale: float = 0.001
    intrinsics: np.ndarray | None = None  # 3x3
    dynamic: list[DynamicBox] | None = None  # the frame's dynamic objects, for front ends that leave them out
    slam_pose: np.ndarray | None = None  # an external SLAM's own pose of this frame (the `external` front end)
    # real time: the front end is behind the video (frames queue up); a check of the SLAM's step waits for a frame
    # with time for it (every n-th is made: checked.py), the SLAM's own tracking does not (a SLAM that misses frames
    # loses track)
    behind: bool = False
    # real time: the tracker's dynamic objects that came since the previous frame, as (frame id, stamp, boxes),
    # oldest first: each is seen at its own frame's pose (motion.py), not at this one's. None: `dynamic` are this
    # frame's own (lockstep), seen with it
    dynamic_seen: list[tuple[int, float, list[DynamicBox]]] | None = None


class FrontEnd(ABC):
    """One pose per frame, in frame order. `sigmas` is the declared per-frame (translation m, rotation rad)."""

    needs_images = False
    uses_dynamic = False  # leaves out the depth of dynamic objects (the service then gets them for each frame)
    needs_slam = False  # checks an external SLAM's poses (the service then gets them on the `slam` key)
    sigmas: tuple[float, float] = (0.01, 0.005)

    @abstractmethod
    def estimate(self, frame: OdometryInput) -> np.ndarray: ...

    def state(self) -> dict:
        """What a restarted service needs to continue the same trajectory (plain data)."""
        return {}

    def restore(self, state: dict) -> None:  # noqa: B027 - stateless front ends have nothing to restore
        """Continue from `state()` output."""


def flat(a: np.ndarray | None) -> list[float] | None:
    return None if a is None else [float(v) for v in np.asarray(a).reshape(-1)]


def unflat(values: list[float] | None, shape: tuple[int, ...]) -> np.ndarray | None:
    return None if values is None else np.asarray(values, float).reshape(shape)
