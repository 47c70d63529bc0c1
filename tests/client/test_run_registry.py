"""A run records where it can be found (semmap.runtime.transport.run_registry); clients find it by out dir or robot, and
fail clearly when there is none or more than one."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from semmap.runtime.transport.run_registry import RunInfo, RunNotFound, find_run, live_runs, register, unregister

PROJECT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def runtime(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    return tmp_path / "xdg"


def _info(tmp_path: Path, robot: str, run_id: str, port: int, pid: int | None = None) -> RunInfo:
    out = tmp_path / run_id
    out.mkdir()
    return RunInfo(robot, run_id, f"tcp/127.0.0.1:{port}", str(out), os.getpid() if pid is None else pid)


def test_a_run_is_found_by_out_dir_and_by_robot_and_gone_when_it_ends(tmp_path: Path) -> None:
    a = _info(tmp_path, "robot1", "aaaa", 7447)
    register(a)
    assert find_run(run_dir=a.out_dir) == a
    assert find_run(robot="robot1") == a and find_run() == a
    with pytest.raises(RunNotFound, match="no running semmap for robot 'robot2'"):
        find_run(robot="robot2")
    unregister(a)
    assert live_runs() == []
    assert find_run(run_dir=a.out_dir) == a  # run.json stays in the out dir as a record


def test_several_runs_or_a_dead_one_are_refused_with_what_was_found(tmp_path: Path) -> None:
    register(_info(tmp_path, "robot1", "aaaa", 7447))
    register(_info(tmp_path, "robot1", "bbbb", 7448))
    with pytest.raises(RunNotFound, match="2 semmap runs for robot 'robot1'.*aaaa.*bbbb"):
        find_run(robot="robot1")
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = _info(tmp_path, "robot3", "cccc", 7449, pid=dead.pid)
    register(stale)
    assert [r.run_id for r in live_runs("robot3")] == []  # a crashed run's file is skipped
    with pytest.raises(RunNotFound, match="has ended"):
        find_run(run_dir=stale.out_dir)


def test_the_bridge_says_when_it_finds_no_run(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(PROJECT), "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    env.pop("SEMMAP_ZENOH_CONNECT", None)
    result = subprocess.run(
        [sys.executable, "-m", "semmap.cli", "ros2", "--robot", "nobody"],
        cwd=PROJECT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "no running semmap for robot 'nobody'" in result.stderr and "--run OUT_DIR" in result.stderr


def test_a_run_that_checks_the_slam_says_so(tmp_path: Path) -> None:
    """`semmap run external --check-slam` records it, so a client or bridge that finds the run sends its poses to
    the `slam` key without a flag of its own to keep in step (an older run file reads as unchecked)."""
    a = _info(tmp_path, "robot1", "cccc", 7449)
    checked = RunInfo(a.robot, a.run_id, a.endpoint, a.out_dir, a.pid, check_slam=True)
    register(checked)
    assert find_run(run_dir=a.out_dir).check_slam is True
    unregister(checked)
    register(a)
    assert find_run(robot="robot1").check_slam is False
    unregister(a)


def test_a_run_that_poses_the_frames_itself_says_so(tmp_path: Path) -> None:
    """`semmap run external --odometry orbslam3` records its front end, so a client or bridge that finds the run
    sends no poses of its own (they would be a second odometry)."""
    a = _info(tmp_path, "robot1", "dddd", 7450)
    own = RunInfo(a.robot, a.run_id, a.endpoint, a.out_dir, a.pid, front_end="orbslam3")
    register(own)
    found = find_run(run_dir=a.out_dir)
    assert found.front_end == "orbslam3" and found.check_slam is False
    unregister(own)
