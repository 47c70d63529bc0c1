"""`semmap eval DIR`: ATE of a finished run's odometry and optimised trajectories (writes DIR/eval.json)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _pct(value: float | None) -> str:
    return "n/a (exact odometry)" if value is None else f"{value:.1f} %"


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "eval", help="ATE of a run's odometry and optimised trajectories against ground truth",
        description="Read DIR/groundtruth.tum (or --groundtruth FILE), DIR/trajectory_odometry.tum and "
                    "DIR/trajectory_optimized.tum, "
                    "compute the ATE RMSE (SE(3)-aligned, no scale) of both and write DIR/eval.json.")
    p.add_argument("dir", metavar="DIR", help="output directory of a run (semmap run --out DIR)")
    p.add_argument("--groundtruth", type=Path, default=None, metavar="FILE",
                   help="a TUM ground-truth trajectory to score against (a run whose data had none beside it); "
                   "stamps are associated as evo does (nearest within 10 ms)")
    p.set_defaults(func=run_eval)


def run_eval(args: argparse.Namespace) -> int:
    from semmap.algorithms.evaluation import EvaluationError, evaluate_run

    try:
        result = evaluate_run(Path(args.dir), args.groundtruth)
    except EvaluationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"ATE odometry {result['ate_odometry_m']:.4f} m, optimised {result['ate_optimized_m']:.4f} m, "
          f"improvement {_pct(result['improvement_pct'])} over {result['poses']} poses")
    if result.get("ate_slam_m") is not None:  # (a checked SLAM: what it gave alone, as tracked and as it saves it)
        refined = result.get("ate_slam_refined_m")
        print(f"SLAM alone {result['ate_slam_m']:.4f} m (trajectory_slam.tum)"
              + (f", refined at its end {refined:.4f} m (trajectory_slam_refined.tum)" if refined is not None else ""))
    return 0
