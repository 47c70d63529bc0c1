"""The tracker and the odometry front end journal every frame: SIGKILLed and restarted with --resume, each goes on
exactly where it was, so a restart is a non-event downstream (same track ids, same tracklets, same poses).

The odometry case also kills it in its worst window: the frame was journalled but its pose and progress died
with the process (modelled by feeding the last journalled frame again after the restart, as the player resends
a frame without progress). The restarted service must answer that frame, not ignore it as already handled
(which stalled lockstep until the run failed).

Real processes over a real Zenoh router; detections of an analytic scene and frames of the synthetic room.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path

import numpy as np

from semmap.core.keys import Keys
from semmap.core.messages import Detections, Message, OdometryPose, Tracks
from semmap.datasets.synthetic import SyntheticDataset
from semmap.runtime.transport.bus import Bus, BusConfig
from semmap.services.player.service import frame_message
from tests.associator.helpers import K_SMALL, Sphere, detections, orbit_pose
from tests.reliability.lockstep_feeder import LockstepFeeder, run_killed_and_resumed, start_service

RATE = 30.0
SCENE = [Sphere((-0.25, 0.0, 0.8), 0.05, "cup"), Sphere((0.25, 0.1, 0.8), 0.06, "bowl"),
         Sphere((0.0, 0.45, 0.7), 0.2, "chair")]


class _Outputs:
    """Every message a service publishes on `key`, by frame (a frame answered twice must be answered the same)."""

    def __init__(self, endpoint: str, robot: str, key: str, kind: type[Message]) -> None:
        self.bus = Bus(BusConfig(mode="client", connect=[endpoint], listen=[]), robot)
        self.by_frame: dict[int, list[Message]] = {}
        self.lock = threading.Lock()
        self.bus.subscribe(key, kind, self._on)

    def _on(self, message: Message) -> None:
        with self.lock:
            self.by_frame.setdefault(message.frame_id, []).append(message)

    def close(self) -> None:
        self.bus.close()


def _run(router, robot: str, service: str, frames: list, kill_after: int | None, out: Path,  # noqa: ANN001
         key: str, kind: type[Message], resend_last: bool = False) -> dict[int, list[Message]]:
    """Feed `frames` to a fresh `service` (killed after `kill_after` frames and resumed, if given)."""
    out.mkdir()
    keys = Keys(robot)
    feeder = LockstepFeeder(router.endpoint, robot, service, [keys.detections if service == "tracker"
                                                              else keys.frames])
    outputs = _Outputs(router.endpoint, robot, key, kind)
    # the odometry case continues a seeded drift (a service started by hand would otherwise take `auto`)
    extra = ("--set", "odometry.mode=gt+drift") if service == "odometry" else ()
    procs = []
    try:
        if kill_after is None:
            procs.append(start_service(service, router.endpoint, robot, out, *extra))
            feeder.feed(frames)
        elif not resend_last:
            run_killed_and_resumed(feeder, service, router.endpoint, robot, out, frames, kill_after, procs, *extra)
        else:
            procs.append(start_service(service, router.endpoint, robot, out, *extra))
            feeder.feed(frames[:kill_after])
            procs[-1].send_signal(signal.SIGKILL)
            procs[-1].wait(timeout=10)
            feeder.restart()
            procs.append(start_service(service, router.endpoint, robot, out, "--resume", *extra))
            feeder.feed(frames[kill_after - 1:])  # the last journalled frame again: its answer was "lost"
        feeder.finish(procs[-1], out / f"{service}.log", len(frames))
    finally:
        feeder.close()
        outputs.close()
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
    assert "resumed after frame" in (out / f"{service}.log").read_text() or kill_after is None
    return outputs.by_frame


def _tracker_frames(keys: Keys, robot: str) -> list:
    frames = []
    for f in range(120):
        t = f / RATE
        dets = detections(orbit_pose(t), SCENE)
        if 40 <= f < 44:  # the chair's tracklet pauses (within max_age): kept across the kill below
            dets = [d for d in dets if d.class_name != "chair"]
        frames.append((f, [(keys.detections, Detections(robot, f, t, K_SMALL, 0.001, dets))]))
    return frames


def _same(a: dict[int, list[Message]], b: dict[int, list[Message]]) -> None:
    assert sorted(a) == sorted(b)
    for f in a:
        bodies = {_content(m) for m in a[f] + b[f]}
        assert len(bodies) == 1, f"frame {f} answered differently"


def _content(m: Message) -> bytes:
    """The message without its clock fields (send times and timings differ between runs)."""
    d = m.to_dict()
    for volatile in ("sent_at", "frame_sent_at", "timing_ms"):
        d.pop(volatile, None)
    return repr(sorted(d.items())).encode()


def test_a_killed_tracker_continues_its_tracklets(tmp_path: Path, router) -> None:  # noqa: ANN001
    robot = "trackerjournal"
    keys = Keys(robot)
    frames = _tracker_frames(keys, robot)
    clean = _run(router, robot, "tracker", frames, None, tmp_path / "clean", keys.tracks, Tracks)
    assert any(c.first for m in clean.values() for c in m[0].candidates), "no candidate: the test proved nothing"
    # killed with three tracklets running (one of them mid-gap): the restarted tracker must continue them
    crashed = _run(router, robot, "tracker", frames, 42, tmp_path / "crashed", keys.tracks, Tracks)
    _same(clean, crashed)


def test_a_killed_odometry_answers_a_frame_it_journalled_and_continues_the_drift(
        tmp_path: Path, router) -> None:  # noqa: ANN001
    robot = "odometryjournal"
    keys = Keys(robot)
    room = SyntheticDataset(frames=60)
    frames = [(i, [(keys.frames, frame_message(robot, room[i]))]) for i in range(len(room))]
    clean = _run(router, robot, "odometry", frames, None, tmp_path / "clean", keys.odometry, OdometryPose)
    crashed = _run(router, robot, "odometry", frames, 30, tmp_path / "crashed", keys.odometry, OdometryPose,
                   resend_last=True)
    assert len(crashed[29]) >= 2, "frame 29 was not answered again after the restart"
    _same(clean, crashed)
    # gt+drift by default: a restart that re-seeded the random walk would show here
    drift = np.linalg.norm(clean[59][0].pose[:3, 3] - room[59].gt_pose[:3, 3])
    assert drift > 1e-4
