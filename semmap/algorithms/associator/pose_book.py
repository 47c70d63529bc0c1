"""The associator's pose book: the best known camera-to-world pose per frame (corrected by the backend where it
has answered, odometry moved by the newest correction otherwise). Shared by the associator service and the
in-process driver (semmap/runtime/pipeline/inprocess.py), and by the prior-map session that re-expresses it."""

from __future__ import annotations

import bisect
from typing import Any

import numpy as np

from semmap.core.geometry import carry_correction
from semmap.core.messages import CorrectedPoses

POSES_KEPT = 300  # recent frames' poses saved with the map (see PoseBook.to_state)


class PoseBook:
    """Best known camera-to-world pose per frame: corrected by the backend where possible.

    The backend sends deltas (the poses that moved more than its tolerance, see algorithms/backend/corrections.py):
    a pose the book already has and the message does not carry stays the same array, so a view's `refresh`
    sees it unchanged and refinement re-estimates only the landmarks whose observing poses moved.
    """

    def __init__(self) -> None:
        self.odometry: dict[int, np.ndarray] = {}
        self.corrected: dict[int, np.ndarray] = {}
        self._corrected_ids: list[int] = []  # sorted keys of `corrected`
        self._seq = 0
        # relocalised against a prior map: odometry frame -> prior frame, and the first frame the backend
        # answers in the prior frame (earlier corrections are still in the odometry's)
        self.alignment: np.ndarray | None = None
        self.aligned_from = 0

    def align(self, transform: np.ndarray, from_frame: int) -> None:
        """From now on every pose is in the prior map's frame (semmap/algorithms/associator/prior_map.py)."""
        self.alignment, self.aligned_from = np.asarray(transform, np.float64).copy(), int(from_frame)
        self.corrected = {f: self.alignment @ p for f, p in self.corrected.items()}

    def set_corrected(self, msg: CorrectedPoses) -> None:
        """Apply a corrected-poses message: a full one replaces the book's corrections, a delta updates them
        (a delta older than the last one applied, e.g. a resent one, is ignored). A message sent before the
        relocalisation is brought into the prior map's frame."""
        if not msg.full and msg.seq <= self._seq:
            return
        self._seq = msg.seq
        if msg.full:
            self._corrected_ids = []
        new = [int(f) for f in msg.frame_ids if msg.full or int(f) not in self.corrected]
        changed = msg.apply_to(self.corrected)
        if self.alignment is not None and msg.frame_id < self.aligned_from:  # sent before the alignment
            for f in changed:
                self.corrected[f] = self.alignment @ self.corrected[f]
        if new and (not self._corrected_ids or new[0] > self._corrected_ids[-1]):
            self._corrected_ids.extend(new)  # the usual case: new frames come after the known ones
        else:
            for f in new:
                bisect.insort(self._corrected_ids, f)

    def to_state(self, recent: int = POSES_KEPT) -> dict[str, Any]:
        """What a restarted associator needs to place views as before the crash (replaying its journal, then
        until the backend's next correction): the odometry and corrected poses of the last `recent` frames
        (measurements still waiting for a pose are recent) and the newest corrected frame with its odometry,
        the anchor that moves later odometry onto the optimised estimate."""
        frames = sorted(self.odometry)[-recent:]
        anchor = next((k for k in reversed(self._corrected_ids) if k in self.odometry), None)
        if anchor is not None and anchor not in frames:
            frames.append(anchor)
        return {
            "odometry": {f: self.odometry[f].tobytes() for f in frames},
            "corrected": {f: self.corrected[f].tobytes() for f in frames if f in self.corrected},
            "alignment": None if self.alignment is None else self.alignment.tobytes(),
            "aligned_from": self.aligned_from,
            "seq": self._seq,  # the newest correction applied: an older delta resent later is still ignored
        }

    @classmethod
    def from_state(cls, state: dict[str, Any] | None) -> PoseBook:
        book = cls()
        if not state:
            return book

        def pose(raw: bytes) -> np.ndarray:
            return np.frombuffer(raw, np.float64).reshape(4, 4).copy()

        book.odometry = {int(f): pose(b) for f, b in state["odometry"].items()}
        book.corrected = {int(f): pose(b) for f, b in state["corrected"].items()}
        book._corrected_ids = sorted(book.corrected)
        book._seq = int(state.get("seq", 0))
        if state.get("alignment") is not None:
            book.alignment, book.aligned_from = pose(state["alignment"]), int(state["aligned_from"])
        return book

    def __call__(self, frame_id: int) -> np.ndarray | None:
        pose = self.corrected.get(frame_id)
        if pose is not None:
            return pose
        odom = self.odometry.get(frame_id)
        if odom is None:
            return None
        i = bisect.bisect_left(self._corrected_ids, frame_id) - 1
        while i >= 0:  # the newest corrected frame before this one that we also have odometry for
            k = self._corrected_ids[i]
            if k in self.odometry:
                return carry_correction(self.corrected[k], self.odometry[k], odom)
            i -= 1
        return odom if self.alignment is None else self.alignment @ odom
