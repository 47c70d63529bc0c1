"""The associator journals its inputs between map saves: SIGKILLed and restarted with --resume, it goes on from
the last input it handled, and the final map is exactly that of a run without the crash.

Real processes over a real Zenoh router; the inputs are an analytic scene (three objects seen from an orbit)
tracked by the real IOU tracker in this process, published frame by frame as the tracker and odometry would.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from semmap.bus import Bus, BusConfig
from semmap.messages import Control, OdometryPose, Progress, Tracks
from services.tracker.iou_tracker import IouTracker
from tests.associator.helpers import K_SMALL, Sphere, detections, orbit_pose

PROJECT = Path(__file__).resolve().parents[2]
ROBOT = "journal"
FRAMES = 150
KILL_AFTER = 80
RATE = 30.0
SCENE = [Sphere((-0.25, 0.0, 0.8), 0.05, "cup"), Sphere((0.25, 0.1, 0.8), 0.06, "bowl"),
         Sphere((0.0, 0.45, 0.7), 0.2, "chair")]


def _inputs() -> list[tuple[OdometryPose, Tracks]]:
    tracker = IouTracker()
    out = []
    for f in range(FRAMES):
        t = f / RATE
        pose = orbit_pose(t)
        result = tracker.update(f, t, detections(pose, SCENE), K_SMALL, 0.001)
        odo = OdometryPose(ROBOT, f, t, pose, keyframe=True, sigma_translation=0.01, sigma_rotation=0.01, source="gt")
        out.append((odo, Tracks(ROBOT, f, t, result.candidates, result.ended, result.boxes)))
    return out


class _Feeder:
    """The test's side of the bus: publishes odometry and tracks, follows the associator's progress."""

    def __init__(self, endpoint: str) -> None:
        self.bus = Bus(BusConfig(mode="client", connect=[endpoint], listen=[]), ROBOT)
        self.odometry = self.bus.publisher(self.bus.keys.odometry)
        self.tracks = self.bus.publisher(self.bus.keys.tracks)
        self.control = self.bus.publisher(self.bus.keys.control)
        self.done = -1
        self.changed = threading.Condition()
        self.bus.subscribe(self.bus.keys.progress("associator"), Progress, self._on_progress)

    def _on_progress(self, p: Progress) -> None:
        with self.changed:
            self.done = max(self.done, p.frame_id)
            self.changed.notify_all()

    def feed(self, inputs: list[tuple[OdometryPose, Tracks]]) -> None:
        """Frame by frame, each once the previous one is through, resent after 2 s without progress (as lockstep
        playback does: a restarted associator may not have subscribed yet when the router still lists the
        killed one's subscription)."""
        assert self.tracks.wait_matching(30), "the associator did not come up"
        for odo, tracks in inputs:
            for _ in range(15):
                self.odometry.put(odo)
                self.tracks.put(tracks)
                with self.changed:
                    if self.changed.wait_for(lambda f=odo.frame_id: self.done >= f, timeout=2.0):
                        break
            else:
                raise AssertionError(f"no progress for frame {odo.frame_id} in 30 s")

    def close(self) -> None:
        self.bus.close()


def _associator(endpoint: str, out: Path, *extra: str) -> subprocess.Popen:
    log = open(out / "associator.log", "ab")  # noqa: SIM115 - closed with the process
    return subprocess.Popen([sys.executable, "-m", "services.associator", "--connect", endpoint, "--zenoh-mode",
                             "client", "--robot", ROBOT, "--out", str(out), "--mode", "lockstep", *extra],
                            cwd=PROJECT, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "CI": "true"})


def _finish(feeder: _Feeder, proc: subprocess.Popen, out: Path) -> list[dict]:
    feeder.control.put(Control(ROBOT, "end_of_stream", FRAMES - 1, FRAMES))
    deadline = time.monotonic() + 30
    while "finished (last frame" not in (out / "associator.log").read_text() and time.monotonic() < deadline:
        time.sleep(0.1)
    feeder.control.put(Control(ROBOT, "stop"))
    assert proc.wait(timeout=30) == 0, (out / "associator.log").read_text()[-3000:]
    return json.loads((out / "map.json").read_text())["landmarks"]


def test_a_killed_associator_resumes_from_its_journal(tmp_path: Path, router) -> None:  # noqa: ANN001
    endpoint = router.endpoint
    inputs = _inputs()
    clean, crashed = tmp_path / "clean", tmp_path / "crashed"
    clean.mkdir()
    crashed.mkdir()
    feeder = _Feeder(endpoint)
    procs = []
    try:
        procs.append(_associator(endpoint, clean))
        feeder.feed(inputs)
        reference = _finish(feeder, procs[-1], clean)
        assert {lm["class"] for lm in reference} == {"cup", "bowl", "chair"}

        feeder.done = -1
        procs.append(_associator(endpoint, crashed))
        feeder.feed(inputs[:KILL_AFTER])
        procs[-1].send_signal(signal.SIGKILL)
        procs[-1].wait(timeout=10)
        feeder.done = -1
        procs.append(_associator(endpoint, crashed, "--resume"))
        feeder.feed(inputs[KILL_AFTER:])
        final = _finish(feeder, procs[-1], crashed)
    finally:
        feeder.close()
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
    log = (crashed / "associator.log").read_text()
    assert "replayed" in log, "the kill came right after a save: nothing to replay, the test proved nothing"
    assert [lm["id"] for lm in final] == [lm["id"] for lm in reference]
    for a, b in zip(final, reference, strict=True):
        assert a["class"] == b["class"] and a["observations"] == b["observations"]
        np.testing.assert_allclose(a["centroid"], b["centroid"], atol=1e-9)
        np.testing.assert_allclose(a["extent"], b["extent"], atol=1e-9)
