"""The backend journals every frame it handled, and each keyframe's depth cloud and loop closure: SIGKILLed
after it closed loops and restarted with --resume, it rebuilds the same graph (the same closures, no ICP rerun)
and the same kept clouds, so later closures and the final trajectory are exactly those of a run without the
crash.

Real processes over a real Zenoh router; the inputs are the synthetic room (one loop round the table, so the
last quarter revisits the first) with drifting odometry, fed frame by frame as player and odometry would.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from semmap.bus import Bus, BusConfig
from semmap.datasets.synthetic import SyntheticDataset
from semmap.messages import Control, Frame, Observations, OdometryPose, Progress
from services.player.service import frame_message

PROJECT = Path(__file__).resolve().parents[2]
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


class _Feeder:
    """Publishes frames, odometry and (empty) observations; follows the backend's progress."""

    def __init__(self, endpoint: str) -> None:
        self.bus = Bus(BusConfig(mode="client", connect=[endpoint], listen=[]), ROBOT)
        self.frames = self.bus.publisher(self.bus.keys.frames)
        self.odometry = self.bus.publisher(self.bus.keys.odometry)
        self.observations = self.bus.publisher(self.bus.keys.observations)
        self.control = self.bus.publisher(self.bus.keys.control)
        self.done = -1
        self.changed = threading.Condition()
        self.bus.subscribe(self.bus.keys.progress("backend"), Progress, self._on_progress)

    def _on_progress(self, p: Progress) -> None:
        with self.changed:
            self.done = max(self.done, p.frame_id)
            self.changed.notify_all()

    def feed(self, inputs: list[tuple[Frame | None, OdometryPose]]) -> None:
        assert self.frames.wait_matching(30), "the backend did not come up"
        for frame, odo in inputs:
            for _ in range(15):  # resent after 2 s without progress, as lockstep playback does
                if frame is not None:
                    self.frames.put(frame)
                self.odometry.put(odo)
                self.observations.put(Observations(ROBOT, odo.frame_id, odo.stamp))
                with self.changed:
                    if self.changed.wait_for(lambda f=odo.frame_id: self.done >= f, timeout=2.0):
                        break
            else:
                raise AssertionError(f"no progress for frame {odo.frame_id} in 30 s")

    def close(self) -> None:
        self.bus.close()


def _backend(endpoint: str, out: Path, *extra: str) -> subprocess.Popen:
    log = open(out / "backend.log", "ab")  # noqa: SIM115 - closed with the process
    return subprocess.Popen([sys.executable, "-m", "services.backend", "--connect", endpoint, "--zenoh-mode",
                             "client", "--robot", ROBOT, "--out", str(out), "--mode", "lockstep", *SETTINGS,
                             *extra], cwd=PROJECT, stdout=log, stderr=subprocess.STDOUT,
                            env={**os.environ, "CI": "true"})


def _finish(feeder: _Feeder, proc: subprocess.Popen, out: Path) -> np.ndarray:
    feeder.control.put(Control(ROBOT, "end_of_stream", FRAMES - 1, FRAMES))
    deadline = time.monotonic() + 30
    while "finished (last frame" not in (out / "backend.log").read_text() and time.monotonic() < deadline:
        time.sleep(0.1)
    feeder.control.put(Control(ROBOT, "stop"))
    assert proc.wait(timeout=30) == 0, (out / "backend.log").read_text()[-3000:]
    return np.loadtxt(out / "trajectory_optimized.tum")


def _closures(log: str) -> list[int]:
    """Frames that closed a loop, from the backend's log lines."""
    return [int(line.split("loop closure: frame ")[1].split()[0]) for line in log.splitlines()
            if "loop closure: frame " in line]


def test_a_killed_backend_resumes_with_its_loop_closures(tmp_path: Path, router) -> None:  # noqa: ANN001
    endpoint = router.endpoint
    inputs = _inputs()
    clean, crashed = tmp_path / "clean", tmp_path / "crashed"
    clean.mkdir()
    crashed.mkdir()
    feeder = _Feeder(endpoint)
    procs = []
    try:
        procs.append(_backend(endpoint, clean))
        feeder.feed(inputs)
        reference = _finish(feeder, procs[-1], clean)

        feeder.done = -1
        procs.append(_backend(endpoint, crashed))
        feeder.feed(inputs[:KILL_AFTER])
        procs[-1].send_signal(signal.SIGKILL)
        procs[-1].wait(timeout=10)
        feeder.done = -1
        procs.append(_backend(endpoint, crashed, "--resume"))
        feeder.feed(inputs[KILL_AFTER:])
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
