"""The associator journals its inputs between map saves: SIGKILLed and restarted with --resume, it goes on from
the last input it handled, and the final map is exactly that of a run without the crash.

Real processes over a real Zenoh router; the inputs are an analytic scene (three objects seen from an orbit)
tracked by the real IOU tracker in this process, published frame by frame as the tracker and odometry would.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np

from semmap.algorithms.tracker.iou_tracker import IouTracker
from semmap.core.keys import Keys
from semmap.core.messages import OdometryPose, Tracks
from tests.associator.helpers import K_SMALL, Sphere, detections, orbit_pose
from tests.reliability.lockstep_feeder import LockstepFeeder, run_killed_and_resumed, start_service

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


def _frames(inputs: list[tuple[OdometryPose, Tracks]], keys: Keys) -> list:
    return [(odo.frame_id, [(keys.odometry, odo), (keys.tracks, tracks)]) for odo, tracks in inputs]


def _finish(feeder: LockstepFeeder, proc: subprocess.Popen, out: Path) -> list[dict]:
    feeder.finish(proc, out / "associator.log", FRAMES)
    return json.loads((out / "map.json").read_text())["landmarks"]


def test_a_killed_associator_resumes_from_its_journal(tmp_path: Path, router) -> None:  # noqa: ANN001
    endpoint, keys = router.endpoint, Keys(ROBOT)
    frames = _frames(_inputs(), keys)
    clean, crashed = tmp_path / "clean", tmp_path / "crashed"
    clean.mkdir()
    crashed.mkdir()
    feeder = LockstepFeeder(endpoint, ROBOT, "associator", [keys.tracks, keys.odometry])
    procs = []
    try:
        procs.append(start_service("associator", endpoint, ROBOT, clean))
        feeder.feed(frames)
        reference = _finish(feeder, procs[-1], clean)
        assert {lm["class"] for lm in reference} == {"cup", "bowl", "chair"}

        run_killed_and_resumed(feeder, "associator", endpoint, ROBOT, crashed, frames, KILL_AFTER, procs)
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
