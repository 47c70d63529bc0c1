"""A saved run's keyframe clouds with their optimised poses: what a session started from its map registers its
own keyframes to (semmap/algorithms/backend/loop_closure.py, `LoopCloser.set_prior`).

They come from the run directory beside the map: the backend's journal (backend.sqlite) holds every keyframe's
cloud as it registered it, trajectory_optimized.tum the poses in the map's frame, joined by time stamp. A map
without them (a merged map, a copied map.sqlite) still relocalises by its objects; the run says so.
"""

from __future__ import annotations

import sqlite3
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

from semmap.algorithms.backend.loop_closure import KeyframeCloud, decode_keyframe
from semmap.core.journal import read_extras
from semmap.datasets import DatasetError
from semmap.datasets.trajectory_io import read_tum

STAMP_TOLERANCE_S = 5e-6  # (the TUM file keeps microseconds)


@dataclass
class PriorKeyframes:
    keyframes: list[tuple[KeyframeCloud, np.ndarray]] = field(default_factory=list)
    unreadable: int = 0  # journalled keyframes that could not be decoded (skipped)
    without_pose: int = 0  # keyframes whose stamp the optimised trajectory lacks (skipped)
    missing: str | None = None  # why there are none at all, when so


def load_prior_keyframes(map_db: Path, max_keyframes: int = 1000) -> PriorKeyframes:
    """The newest `max_keyframes` keyframes of the run whose map is `map_db` (its directory's backend.sqlite and
    trajectory_optimized.tum), streamed: a long run's journal is not held whole. Never raises for what is missing
    or damaged: it is reported in the result."""
    run_dir = Path(map_db) if Path(map_db).is_dir() else Path(map_db).parent  # (a run directory or its map)
    journal, trajectory = run_dir / "backend.sqlite", run_dir / "trajectory_optimized.tum"
    out = PriorKeyframes()
    for path in (journal, trajectory):
        if not path.is_file():
            out.missing = f"{path} not found"
            return out
    try:
        poses = read_tum(trajectory)
    except (DatasetError, OSError) as exc:
        out.missing = f"unreadable: {exc}"
        return out
    if not poses:
        out.missing = f"{trajectory} is empty"
        return out
    stamps = np.array([t for t, _ in poses])
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    kept: deque[tuple[KeyframeCloud, np.ndarray]] = deque(maxlen=max_keyframes)
    try:
        for _, body in read_extras(journal):
            try:
                cloud, _ = decode_keyframe(body)
            except (msgpack.UnpackException, ValueError, KeyError, TypeError):  # (a damaged row: the rest serve)
                out.unreadable += 1
                continue
            k = int(np.searchsorted(stamps, cloud.stamp - STAMP_TOLERANCE_S))
            if k >= len(stamps) or abs(stamps[k] - cloud.stamp) > STAMP_TOLERANCE_S:
                out.without_pose += 1
                continue
            kept.append((cloud, poses[int(order[k])][1]))
    except sqlite3.Error as exc:
        out.missing = f"unreadable: {exc}"
        return out
    out.keyframes = list(kept)
    return out
