"""The backend journals every frame it handled, and each keyframe's depth cloud and loop closure: SIGKILLed
after it closed loops and restarted with --resume, it rebuilds the same graph (the same closures, no ICP rerun)
and the same kept clouds, so later closures and the final trajectory are exactly those of a run without the
crash.

Real processes over a real Zenoh router; the inputs are the synthetic room (one loop round the table, so the
last quarter revisits the first) with drifting odometry, fed frame by frame as player and odometry would.
"""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import numpy as np

from semmap.core.keys import Keys
from semmap.core.messages import Frame, Observations, OdometryPose
from semmap.datasets.synthetic import SyntheticDataset
from semmap.services.player.service import frame_message
from tests.reliability.lockstep_feeder import LockstepFeeder, run_killed_and_resumed, start_service

ROBOT = "backendjournal"
FRAMES = 241  # 8 s; frame 240 is back at frame 0's pose
KILL_AFTER = 235  # frame 230 has closed a loop by then, frame 240 closes one after the restart
SETTINGS = ["--set", "loop_closure.min_gap_s=2.0"]


def _inputs() -> list[tuple[Frame, OdometryPose]]:
    """Frames (depth for the loop closer) and odometry with a yaw bias of 0.03 deg a frame (~0.2 m at the end)."""
    room = SyntheticDataset(frames=FRAMES)
    bias = np.eye(4)
    a = math.radians(0.03)
    bias[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    pose = room.camera_pose(0)
    out = []
    for i in range(FRAMES):
        if i:
            pose = bias @ pose @ (np.linalg.inv(room.camera_pose(i - 1)) @ room.camera_pose(i))
        frame = room[i] if i % 10 == 0 else None  # the backend only looks at every 10th frame's depth
        msg = frame_message(ROBOT, frame) if frame is not None else None
        out.append((msg, OdometryPose(ROBOT, i, room.stamp(i), pose.copy(), keyframe=True, sigma_translation=0.003,
                                      sigma_rotation=math.radians(0.3), source="gt+drift")))
    return out


def _frames(inputs: list[tuple[Frame | None, OdometryPose]], keys: Keys) -> list:
    """Each frame's messages: the frame (keyframes only), its odometry and its (empty) observations."""
    return [(odo.frame_id, ([(keys.frames, frame)] if frame is not None else [])
             + [(keys.odometry, odo), (keys.observations, Observations(ROBOT, odo.frame_id, odo.stamp))])
            for frame, odo in inputs]


def _finish(feeder: LockstepFeeder, proc: subprocess.Popen, out: Path) -> np.ndarray:
    feeder.finish(proc, out / "backend.log", FRAMES)
    return np.loadtxt(out / "trajectory_optimized.tum")


def _closures(log: str) -> list[int]:
    """Frames that closed a loop, from the backend's log lines."""
    return [int(line.split("loop closure: frame ")[1].split()[0]) for line in log.splitlines()
            if "loop closure: frame " in line]


def test_a_killed_backend_resumes_with_its_loop_closures(tmp_path: Path, router) -> None:  # noqa: ANN001
    endpoint, keys = router.endpoint, Keys(ROBOT)
    frames = _frames(_inputs(), keys)
    clean, crashed = tmp_path / "clean", tmp_path / "crashed"
    clean.mkdir()
    crashed.mkdir()
    feeder = LockstepFeeder(endpoint, ROBOT, "backend", [keys.frames, keys.odometry, keys.observations])
    procs = []
    try:
        procs.append(start_service("backend", endpoint, ROBOT, clean, *SETTINGS))
        feeder.feed(frames)
        reference = _finish(feeder, procs[-1], clean)

        run_killed_and_resumed(feeder, "backend", endpoint, ROBOT, crashed, frames, KILL_AFTER, procs, *SETTINGS)
        final = _finish(feeder, procs[-1], crashed)
    finally:
        feeder.close()
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
    closed = _closures((clean / "backend.log").read_text())
    assert any(f < KILL_AFTER for f in closed) and any(f > KILL_AFTER for f in closed), closed
    log = (crashed / "backend.log").read_text()
    assert "restored the pose graph" in log
    assert [f for f in _closures(log) if f > KILL_AFTER] == [f for f in closed if f > KILL_AFTER]
    np.testing.assert_array_equal(final, reference)
