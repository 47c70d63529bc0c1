"""What the backend sends on `poses/corrected`: deltas, not the whole trajectory (pure, no I/O).

Why: the whole trajectory every frame made the message, its encoding and every consumer's work grow with the run
(an hour at 30 fps: 108,000 poses, 14 MB a frame). Each message now carries
- the frames whose corrected pose moved more than `tolerance_m` / `tolerance_deg` from what was last sent for
  them (so a consumer's copy never strays further than that from the backend's estimate), new frames always;
- a rolling refresh of `refresh_frames` consecutive frames, cycling through the trajectory, so a consumer that
  joins late (a restarted viewer) has every pose after `num_frames / refresh_frames` messages, with a bounded
  message size (a periodic whole snapshot would again grow with the trajectory);
- the landmarks whose position moved more than `tolerance_m` (new ones always).
The first message (and any after frames arrived out of order) is `full`: every frame and landmark.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from semmap.config import check_field_types, params_from_section

if TYPE_CHECKING:
    from services.backend.pose_graph import PoseGraph


@dataclass
class CorrectionsParams:
    """The YAML `corrections:` section."""

    tolerance_m: float = 0.001
    tolerance_deg: float = 0.05
    refresh_frames: int = 32

    def __post_init__(self) -> None:
        check_field_types(self, "corrections")
        if self.tolerance_m < 0 or self.tolerance_deg < 0 or self.refresh_frames < 0:
            raise ValueError("corrections.tolerance_m, tolerance_deg and refresh_frames must be >= 0")

    @classmethod
    def from_config(cls, section: dict | None) -> CorrectionsParams:
        return params_from_section(cls, section, "corrections")


@dataclass
class CorrectionDelta:
    full: bool
    frame_ids: np.ndarray
    stamps: np.ndarray
    poses: np.ndarray
    landmark_ids: np.ndarray
    landmark_positions: np.ndarray
    num_frames: int

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(frame_ids, stamps, poses, landmark_ids, landmark_positions): CorrectedPoses' positional fields."""
        return self.frame_ids, self.stamps, self.poses, self.landmark_ids, self.landmark_positions


def moved(old: np.ndarray, new: np.ndarray, tolerance_m: float, tolerance_deg: float) -> np.ndarray:
    """Mask of the (N,4,4) pose pairs that differ by more than the tolerances (translation, rotation angle)."""
    far = np.linalg.norm(new[:, :3, 3] - old[:, :3, 3], axis=1) > tolerance_m
    cos = (np.einsum("nij,nij->n", new[:, :3, :3], old[:, :3, :3]) - 1.0) / 2.0
    return far | (cos < np.cos(np.radians(tolerance_deg)))


class CorrectionPublisher:
    """Remembers what was sent and turns the graph's current estimate into the next delta."""

    def __init__(self, params: CorrectionsParams | None = None) -> None:
        self.params = params or CorrectionsParams()
        self._ids = np.zeros(0, np.int64)  # frames sent so far (ascending) and the pose last sent for each
        self._poses = np.zeros((0, 4, 4))
        self._landmarks: dict[int, np.ndarray] = {}
        self._cursor = 0  # where the rolling refresh goes on
        self.counters = {"messages": 0, "full": 0, "poses_sent": 0, "poses_changed": 0}

    def next(self, graph: PoseGraph) -> CorrectionDelta:
        ids, stamps, poses = graph.corrected_poses()
        lids, lpos = graph.landmark_positions()
        return self.delta(ids, stamps, poses, lids, lpos)

    def delta(self, ids: np.ndarray, stamps: np.ndarray, poses: np.ndarray, lids: np.ndarray,
              lpos: np.ndarray) -> CorrectionDelta:
        """The delta from what was sent before to this estimate (every frame's pose, ascending ids)."""
        p = self.params
        n_old = len(self._ids)
        self.counters["messages"] += 1
        full = n_old == 0 or len(ids) < n_old or not np.array_equal(ids[:n_old], self._ids)
        if full:  # the first message, or a frame arrived out of order: start over with everything
            self.counters["full"] += 1
            send = np.ones(len(ids), bool)
            self._landmarks = {}
        else:
            send = np.zeros(len(ids), bool)
            send[n_old:] = True
            send[:n_old] = moved(self._poses, poses[:n_old], p.tolerance_m, p.tolerance_deg)
            self.counters["poses_changed"] += int(send[:n_old].sum())
            if p.refresh_frames and n_old:
                start = self._cursor % n_old
                rows = (start + np.arange(min(p.refresh_frames, n_old))) % n_old
                send[rows] = True
                self._cursor = start + len(rows)
        self._ids = ids.copy()
        if full:
            self._poses = poses.copy()
        else:
            self._poses = np.concatenate([self._poses, poses[n_old:]]) if len(ids) > n_old else self._poses
            self._poses[send] = poses[send]
        self.counters["poses_sent"] += int(send.sum())
        keep = np.array([full or int(i) not in self._landmarks
                         or float(np.linalg.norm(self._landmarks[int(i)] - x)) > p.tolerance_m
                         for i, x in zip(lids, lpos, strict=True)], dtype=bool)
        for i, x in zip(lids[keep], lpos[keep], strict=True):
            self._landmarks[int(i)] = x.copy()
        return CorrectionDelta(full, ids[send], stamps[send], poses[send], lids[keep],
                               np.asarray(lpos, np.float64).reshape(-1, 3)[keep], len(ids))
