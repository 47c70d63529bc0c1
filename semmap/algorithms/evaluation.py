"""Trajectory accuracy of a run: ATE RMSE of odometry and optimised poses against ground truth, via evo.

Why evo: it is what the SLAM literature (and the paper) reports; matching its numbers needs its association
(nearest stamp within 10 ms), its SE(3) Umeyama alignment without scale and its translation APE.
Only `evo.core` is imported: `evo.tools` writes `~/.evo/settings.json` at import time, `evo.core` does not.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from semmap.core.outputs import SLAM_REFINED_TRAJECTORY, SLAM_TRAJECTORY
from semmap.datasets.base import DatasetError
from semmap.datasets.trajectory_io import read_tum

GROUNDTRUTH = "groundtruth.tum"
ODOMETRY = "trajectory_odometry.tum"
OPTIMIZED = "trajectory_optimized.tum"
RESULT = "eval.json"
MAX_STAMP_DIFF_S = 0.01

StampedPoses = Sequence[tuple[float, np.ndarray]]


class EvaluationError(ValueError):
    """Trajectories that cannot be evaluated: missing, empty, unreadable or without matching stamps."""


def _trajectory(poses: StampedPoses, name: str):  # -> evo PoseTrajectory3D
    from evo.core.trajectory import PoseTrajectory3D

    if len(poses) == 0:
        raise EvaluationError(f"{name} trajectory is empty")
    stamps = np.array([float(t) for t, _ in poses], dtype=np.float64)
    mats = [np.asarray(p, dtype=np.float64) for _, p in poses]
    if any(m.shape != (4, 4) or not np.all(np.isfinite(m)) for m in mats):
        raise EvaluationError(f"{name} trajectory holds a pose that is not a finite 4x4")
    order = np.argsort(stamps, kind="stable")
    return PoseTrajectory3D(poses_se3=[mats[i] for i in order], timestamps=stamps[order])


def ate_details(ref: StampedPoses, est: StampedPoses, max_diff: float = MAX_STAMP_DIFF_S) -> tuple[float, int]:
    """(ATE RMSE in metres, matched poses) of `est` against `ref` after SE(3) alignment (no scale)."""
    from evo import EvoException
    from evo.core import metrics, sync

    reference, estimate = _trajectory(ref, "reference"), _trajectory(est, "estimated")
    try:
        reference, estimate = sync.associate_trajectories(reference, estimate, max_diff=max_diff)
    except EvoException as exc:
        raise EvaluationError(f"trajectories cannot be associated (stamps {max_diff} s apart at most): "
                              f"{exc}") from None
    matched = estimate.num_poses
    if matched < 3:
        raise EvaluationError(f"only {matched} poses match in time: at least 3 are needed for an SE(3) alignment")
    try:
        estimate.align(reference, correct_scale=False)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((reference, estimate))
        rmse = float(ape.get_statistic(metrics.StatisticsType.rmse))
    except (EvoException, np.linalg.LinAlgError) as exc:
        raise EvaluationError(f"ATE computation failed: {exc}") from None
    if not math.isfinite(rmse):
        raise EvaluationError("ATE is not finite")
    return rmse, matched


def ate_rmse(ref: StampedPoses, est: StampedPoses, max_diff: float = MAX_STAMP_DIFF_S) -> float:
    """ATE RMSE (m) of `est` against `ref`, lists of (stamp s, 4x4 camera-to-world)."""
    return ate_details(ref, est, max_diff)[0]


def _read(path: Path) -> list[tuple[float, np.ndarray]]:
    if not path.is_file():
        raise EvaluationError(f"missing trajectory file {path}")
    try:
        poses = read_tum(path)
    except DatasetError as exc:
        raise EvaluationError(str(exc)) from None
    if not poses:
        raise EvaluationError(f"trajectory file {path} holds no poses")
    return poses


def write_json_atomic(path: Path, data: dict) -> None:
    """Write JSON via a temporary file and a rename: a reader never sees half a file."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def evaluate_run(out_dir: Path, groundtruth: Path | None = None) -> dict:
    """Evaluate a run's output folder and write `eval.json`; returns its contents.

    `groundtruth`: a TUM trajectory to score against instead of the run's own `groundtruth.tum` (a run whose data
    had none beside it: an external SLAM's, a bag's). Stamps are associated as evo associates them (nearest within
    10 ms), so the figures equal `evo_ape tum GT EST -a`. `poses` is the number of optimised poses matched.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise EvaluationError(f"run directory {out_dir} does not exist")
    gt = _read(Path(groundtruth) if groundtruth is not None else out_dir / GROUNDTRUTH)
    odometry = _read(out_dir / ODOMETRY)
    optimized = _read(out_dir / OPTIMIZED)
    ate_odometry, _ = ate_details(gt, odometry)
    ate_optimized, matched = ate_details(gt, optimized)
    # below a millimetre the odometry is exact (e.g. `--odometry gt`): a percentage of it means nothing
    improvement = 100.0 * (ate_odometry - ate_optimized) / ate_odometry if ate_odometry >= 1e-3 else None
    result = {"ate_odometry_m": ate_odometry, "ate_optimized_m": ate_optimized,
              "improvement_pct": improvement, "poses": matched,
              "groundtruth": str(groundtruth) if groundtruth is not None else GROUNDTRUTH}
    # the SLAM alone, to hold semmap's repair against: as it tracked, and as it saved itself at its end (ORB-SLAM3)
    for key, name in (("ate_slam_m", SLAM_TRAJECTORY), ("ate_slam_refined_m", SLAM_REFINED_TRAJECTORY)):
        if (out_dir / name).is_file():
            result[key] = ate_details(gt, _read(out_dir / name))[0]
    write_json_atomic(out_dir / RESULT, result)
    return result
