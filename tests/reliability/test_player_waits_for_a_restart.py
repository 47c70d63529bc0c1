"""Lockstep's frame timeout measures a live pipeline: while a waited-for service is down (its statuses stopped,
as when `semmap run` restarts it after a crash), the clock is paused, so a restart that takes longer than the
timeout on a loaded machine does not fail the run; a live service that makes no progress still does.

A real player process over a real Zenoh router; the test plays the waited-for service (statuses and progress).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from semmap.core.keys import Keys
from semmap.core.messages import Frame, Progress, ServiceStatus
from semmap.runtime.transport.bus import Bus, BusConfig
from tests.reliability.lockstep_feeder import start_service

ROBOT = "playerdown"
TIMEOUT_S = 4


class _FakeService:
    """Sends statuses every 0.5 s while `alive`, and progress for each frame while `answering`."""

    def __init__(self, endpoint: str) -> None:
        self.bus = Bus(BusConfig(mode="client", connect=[endpoint], listen=[]), ROBOT)
        keys = Keys(ROBOT)
        self.status = self.bus.publisher(keys.status("fake", "fake"))
        self.progress = self.bus.publisher(keys.progress("fake"))
        self.alive = threading.Event()
        self.answering = threading.Event()
        self.stop = threading.Event()
        self.frames: list[int] = []
        self.bus.subscribe(keys.frames, Frame, self._on_frame)
        threading.Thread(target=self._beat, daemon=True).start()

    def _on_frame(self, frame: Frame) -> None:
        self.frames.append(frame.frame_id)
        if self.answering.is_set():
            self.progress.put(Progress(ROBOT, "fake", frame.frame_id))

    def _beat(self) -> None:
        while not self.stop.is_set():
            if self.alive.is_set():
                self.status.put(ServiceStatus(ROBOT, "fake", "fake", "running"))
            time.sleep(0.5)

    def close(self) -> None:
        self.stop.set()
        self.bus.close()


def test_a_down_service_pauses_the_frame_timeout_a_stuck_one_fails_it(tmp_path: Path, router) -> None:  # noqa: ANN001
    fake = _FakeService(router.endpoint)
    fake.alive.set()
    fake.answering.set()
    proc = start_service("player", router.endpoint, ROBOT, tmp_path, "--data", "synthetic:frames=40", "--wait-for",
                         "fake", "--set", f"run.frame_timeout_s={TIMEOUT_S}")
    log = tmp_path / "player.log"
    try:
        deadline = time.monotonic() + 60
        while len(fake.frames) < 5 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(fake.frames) >= 5, log.read_text()
        # "crash": no status, no progress for three times the frame timeout; then back, and answering again
        fake.answering.clear()
        fake.alive.clear()
        time.sleep(3 * TIMEOUT_S)
        assert proc.poll() is None, "the player failed the run while the service was down:\n" + log.read_text()
        assert "frame timeout paused" in log.read_text()
        fake.alive.set()
        fake.answering.set()
        stuck_at = len(fake.frames)
        while len(fake.frames) < stuck_at + 5 and time.monotonic() < deadline + 30:
            time.sleep(0.1)
        assert len(fake.frames) >= stuck_at + 5, "the run did not go on after the service came back"
        # alive but stuck: the timeout runs, and fails the run
        fake.answering.clear()
        time.sleep(TIMEOUT_S + 8)
        assert f"within {TIMEOUT_S} s" in log.read_text()
    finally:
        fake.close()
        if proc.poll() is None:
            proc.kill()
