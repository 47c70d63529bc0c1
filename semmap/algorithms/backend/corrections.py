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

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from semmap.algorithms.backend.pose_graph import GrowingRows
from semmap.core.config import CorrectionsParams

if TYPE_CHECKING:
    from semmap.algorithms.backend.pose_graph import PoseGraph


def frames_riding_on(ids: np.ndarray, nodes: np.ndarray, moved: list[int]) -> np.ndarray:
    """Rows of `ids` (every frame, ascending) that ride on the `moved` nodes: from each node up to the next
    node (frames before the first node ride on it too). Vectorised: a loop closure can move thousands."""
    if not moved or not len(nodes):
        return np.zeros(0, np.int64)
    moved_arr = np.asarray(moved, dtype=np.int64)
    j = np.searchsorted(nodes, moved_arr)
    start = np.where(j == 0, 0, np.searchsorted(ids, moved_arr))
    after = np.minimum(j + 1, len(nodes) - 1)
    end = np.where(j + 1 >= len(nodes), len(ids), np.searchsorted(ids, nodes[after]))
    lengths = np.maximum(end - start, 0)
    offsets = np.cumsum(lengths) - lengths
    return np.arange(int(lengths.sum()), dtype=np.int64) - np.repeat(offsets, lengths) + np.repeat(start, lengths)


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
    """Remembers what was sent and turns the graph's current estimate into the next delta.

    Cost per message: the frames that can have moved (those riding on a node iSAM2 moved, the new ones and the
    refresh), not the whole trajectory; memory: the pose last sent per frame (128 bytes a frame, 14 MB an hour
    at 30 fps) and per landmark.
    """

    def __init__(self, params: CorrectionsParams | None = None) -> None:
        self.params = params or CorrectionsParams()
        self._n = 0  # frames sent so far, the newest of them, and the pose last sent for each
        self._last_id = -1
        self._sent = GrowingRows((4, 4), 0.0)
        self._landmarks: dict[int, np.ndarray] = {}
        self._cursor = 0  # where the rolling refresh goes on
        self.counters = {"messages": 0, "full": 0, "poses_sent": 0, "poses_changed": 0, "poses_checked": 0}

    def next(self, graph: PoseGraph) -> CorrectionDelta:
        """The delta after the graph's latest update (consumes the graph's moved nodes)."""
        ids, stamps = graph.frame_table()
        candidates = frames_riding_on(ids, np.asarray(graph.node_ids(), np.int64), graph.take_moved_nodes())
        lids, lpos = graph.landmark_positions()
        return self._delta(ids, stamps, candidates, graph.corrected_rows, lids, lpos)

    def delta(
        self, ids: np.ndarray, stamps: np.ndarray, poses: np.ndarray, lids: np.ndarray, lpos: np.ndarray
    ) -> CorrectionDelta:
        """The delta from what was sent before to this estimate (every frame's pose, ascending ids)."""
        return self._delta(ids, stamps, np.arange(len(ids)), lambda rows: poses[rows], lids, lpos)

    def _delta(
        self,
        ids: np.ndarray,
        stamps: np.ndarray,
        candidates: np.ndarray,
        poses_of: Callable[[np.ndarray], np.ndarray],
        lids: np.ndarray,
        lpos: np.ndarray,
    ) -> CorrectionDelta:
        p = self.params
        n_old, n = self._n, len(ids)
        self.counters["messages"] += 1
        # frames only ever come after the ones sent (in order): otherwise start over with everything
        full = n_old == 0 or n < n_old or int(ids[n_old - 1]) != self._last_id
        if full:
            self.counters["full"] += 1
            self._landmarks = {}
            send = np.arange(n)
            poses = poses_of(send)
            self._sent = GrowingRows((4, 4), 0.0)
            for row in poses:
                self._sent.insert(self._sent.n, row)
        else:
            old = np.unique(candidates[candidates < n_old])
            refresh = np.zeros(0, np.int64)
            if p.refresh_frames:
                start = self._cursor % n_old
                refresh = (start + np.arange(min(p.refresh_frames, n_old))) % n_old
                self._cursor = start + len(refresh)
            check = np.union1d(old, refresh)
            current = poses_of(check)
            changed = moved(self._sent.rows[check], current, p.tolerance_m, p.tolerance_deg)
            self.counters["poses_checked"] += len(check)
            self.counters["poses_changed"] += int(changed[np.isin(check, old)].sum())
            keep = changed | np.isin(check, refresh)
            new = np.arange(n_old, n)
            new_poses = poses_of(new)
            for row in new_poses:
                self._sent.insert(self._sent.n, row)
            self._sent.rows[check[keep]] = current[keep]
            send = np.concatenate([check[keep], new])
            poses = np.concatenate([current[keep], new_poses])
        self._n, self._last_id = n, int(ids[n - 1]) if n else -1
        self.counters["poses_sent"] += len(send)
        lpos = np.asarray(lpos, np.float64).reshape(-1, 3)
        keep_lm = np.array(
            [
                full
                or int(i) not in self._landmarks
                or float(np.linalg.norm(self._landmarks[int(i)] - x)) > p.tolerance_m
                for i, x in zip(lids, lpos, strict=True)
            ],
            dtype=bool,
        )
        for i, x in zip(lids[keep_lm], lpos[keep_lm], strict=True):
            self._landmarks[int(i)] = x.copy()
        return CorrectionDelta(full, ids[send], stamps[send], poses, lids[keep_lm], lpos[keep_lm], n)
