"""ATE evaluation (evo) and the `semmap eval` command."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from backend_sim import FPS, drifting, shared_data, square_path

from semmap.algorithms.evaluation import EvaluationError, ate_details, ate_rmse, evaluate_run
from semmap.cli.evaluate import register
from semmap.datasets.trajectory_io import read_tum, write_tum

TRAJECTORIES = shared_data("trajectories")
needs_data = pytest.mark.skipif(not (TRAJECTORIES / "fr2_desk_ORB.txt").is_file(),
                                reason=f"TUM trajectories not found under {TRAJECTORIES} (set SEMMAP_DATA)")


@pytest.mark.needs_data
@needs_data
def test_fr2_desk_orb_slam_matches_the_measured_figure() -> None:
    gt = read_tum(TRAJECTORIES / "fr2_desk_groundtruth.txt")
    est = read_tum(TRAJECTORIES / "fr2_desk_ORB.txt")
    rmse, matched = ate_details(gt, est)
    assert rmse == pytest.approx(0.0081, abs=0.0001)
    assert matched == 2174  # evo with max_diff 0.01 s (the README's 2225 is what max_diff 0.02 s matches)
    assert ate_rmse(gt, est) == rmse


def write_run(out: Path, optimized_offset: float = 0.0) -> tuple[list, list]:
    gt = square_path(100)
    odometry = drifting(gt, 0, np.array([0.0, 0.0, 1.0]))
    stamped_gt = [(i / FPS, p) for i, p in enumerate(gt)]
    optimized = []
    for i, p in enumerate(gt):
        q = p.copy()
        q[0, 3] += optimized_offset * (-1) ** i
        optimized.append((i / FPS, q))
    write_tum(out / "groundtruth.tum", stamped_gt)
    write_tum(out / "trajectory_odometry.tum", [(i / FPS, p) for i, p in enumerate(odometry)])
    write_tum(out / "trajectory_optimized.tum", optimized)
    return stamped_gt, [(i / FPS, p) for i, p in enumerate(odometry)]


def test_evaluate_run_writes_eval_json(tmp_path: Path) -> None:
    stamped_gt, odometry = write_run(tmp_path, optimized_offset=0.01)
    result = evaluate_run(tmp_path)
    assert set(result) == {"ate_odometry_m", "ate_optimized_m", "improvement_pct", "poses", "groundtruth"}
    assert result["groundtruth"] == "groundtruth.tum"
    assert result["poses"] == 100
    assert result["ate_odometry_m"] == pytest.approx(ate_rmse(stamped_gt, odometry), rel=1e-6)
    assert result["ate_odometry_m"] > 0.05
    assert result["ate_optimized_m"] == pytest.approx(0.01, abs=0.001)  # alternating +-1 cm
    expected = 100 * (result["ate_odometry_m"] - result["ate_optimized_m"]) / result["ate_odometry_m"]
    assert result["improvement_pct"] == pytest.approx(expected)
    assert json.loads((tmp_path / "eval.json").read_text()) == result
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "eval.json", "groundtruth.tum", "trajectory_odometry.tum", "trajectory_optimized.tum"]


def test_a_slams_own_trajectories_are_scored_beside_semmaps(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A checked SLAM's own poses (`trajectory_slam.tum`) and those it refined at its end
    (`trajectory_slam_refined.tum`, ORB-SLAM3's saved trajectory) are scored against the same ground truth: the
    SLAM alone as it tracked, and as it alone would save it."""
    stamped_gt, odometry = write_run(tmp_path)
    write_tum(tmp_path / "trajectory_slam.tum", odometry)
    refined = []
    for i, (t, p) in enumerate(stamped_gt):
        q = p.copy()
        q[1, 3] += 0.02 * (-1) ** i
        refined.append((t, q))
    write_tum(tmp_path / "trajectory_slam_refined.tum", refined)
    result = evaluate_run(tmp_path)
    assert result["ate_slam_m"] == pytest.approx(result["ate_odometry_m"])
    assert result["ate_slam_refined_m"] == pytest.approx(0.02, abs=0.001)  # alternating +-2 cm
    assert run_cli(["eval", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == (
        f"SLAM alone {result['ate_slam_m']:.4f} m (trajectory_slam.tum), refined at its end "
        f"{result['ate_slam_refined_m']:.4f} m (trajectory_slam_refined.tum)")


def test_evaluation_errors(tmp_path: Path) -> None:
    with pytest.raises(EvaluationError, match="does not exist"):
        evaluate_run(tmp_path / "nope")
    write_run(tmp_path)
    (tmp_path / "trajectory_optimized.tum").unlink()
    with pytest.raises(EvaluationError, match="missing trajectory file .*trajectory_optimized.tum"):
        evaluate_run(tmp_path)
    (tmp_path / "trajectory_optimized.tum").write_text("# timestamp tx ty tz qx qy qz qw\n")
    with pytest.raises(EvaluationError, match="holds no poses"):
        evaluate_run(tmp_path)
    (tmp_path / "trajectory_optimized.tum").write_text("0.0 1 2 3\n")
    with pytest.raises(EvaluationError, match="expected 8 values"):
        evaluate_run(tmp_path)
    late = [(100.0 + t, p) for t, p in read_tum(tmp_path / "groundtruth.tum")]
    write_tum(tmp_path / "trajectory_optimized.tum", late)
    with pytest.raises(EvaluationError, match="cannot be associated|poses match"):
        evaluate_run(tmp_path)
    assert not (tmp_path / "eval.json").exists()
    with pytest.raises(EvaluationError, match="empty"):
        ate_rmse([], [(0.0, np.eye(4))])
    with pytest.raises(EvaluationError, match="at least 3"):
        ate_rmse([(0.0, np.eye(4)), (1.0, np.eye(4))], [(0.0, np.eye(4)), (1.0, np.eye(4))])


def run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="semmap")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_eval_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_run(tmp_path, optimized_offset=0.01)
    assert run_cli(["eval", str(tmp_path)]) == 0
    out = capsys.readouterr().out.strip()
    result = json.loads((tmp_path / "eval.json").read_text())
    assert out == (f"ATE odometry {result['ate_odometry_m']:.4f} m, optimised {result['ate_optimized_m']:.4f} m, "
                   f"improvement {result['improvement_pct']:.1f} % over 100 poses")
    assert run_cli(["eval", str(tmp_path / "missing")]) == 2
    assert "error: run directory" in capsys.readouterr().err


def test_evo_writes_nothing_into_home(tmp_path: Path) -> None:
    """evo.tools creates ~/.evo at import; the evaluation must only use evo.core (checked in a fresh process)."""
    (tmp_path / "run").mkdir()
    write_run(tmp_path / "run")
    home = tmp_path / "home"
    home.mkdir()
    env = {**os.environ, "HOME": str(home)}
    code = "import sys; from semmap.algorithms.evaluation import evaluate_run; evaluate_run(sys.argv[1])"
    root = Path(__file__).resolve().parents[2]
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "run")], check=True, env=env, cwd=root, timeout=120)
    assert (tmp_path / "run" / "eval.json").is_file()
    assert list(home.iterdir()) == []


def test_eval_against_a_groundtruth_file_equals_evo_ape(tmp_path: Path, data_root: Path) -> None:
    """`semmap eval DIR --groundtruth FILE` for a run whose data had no ground truth beside it: the figure is what
    `evo_ape tum FILE EST -a` prints (same association of stamps: nearest within 10 ms against the raw file)."""
    import re
    import shutil

    gt_file = data_root / "bonn_crowd" / "groundtruth.txt"
    est = data_root / "orbslam3" / "bonn_crowd_orbslam3_run1.tum"
    if not gt_file.is_file() or not est.is_file():
        pytest.skip("bonn_crowd ground truth or the shared ORB-SLAM3 trajectory absent")
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(est, run / "trajectory_odometry.tum")
    shutil.copy(est, run / "trajectory_optimized.tum")
    cli = subprocess.run([sys.executable, "-m", "semmap.cli", "eval", str(run), "--groundtruth", str(gt_file)],
                         capture_output=True, text=True, timeout=120)
    assert cli.returncode == 0, cli.stderr
    ours = json.loads((run / "eval.json").read_text())
    home = tmp_path / "home"
    (home / ".evo").mkdir(parents=True)
    evo = subprocess.run([str(Path(sys.executable).parent / "evo_ape"), "tum", str(gt_file), str(est), "-a"],
                         capture_output=True, text=True, timeout=120, env={"HOME": str(home), "CI": "true"})
    assert evo.returncode == 0, evo.stderr
    rmse = float(re.search(r"rmse\s+([0-9.]+)", evo.stdout).group(1))
    assert ours["ate_optimized_m"] == pytest.approx(rmse, abs=1e-6)
    assert ours["groundtruth"] == str(gt_file)
    missing = subprocess.run([sys.executable, "-m", "semmap.cli", "eval", str(run), "--groundtruth",
                              str(tmp_path / "none.txt")], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "missing trajectory file" in missing.stderr
