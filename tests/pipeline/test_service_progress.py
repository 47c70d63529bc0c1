"""How often a service reports progress: every frame in lockstep (the player paces the stream by it), at most every
PROGRESS_PERIOD_S in real time (nothing waits on each frame there; the messages cost the detector CPU), the newest
frame done each time, and the stream's last frame at once."""

from __future__ import annotations

import argparse

import pytest

from semmap.core.messages import Control, Progress
from semmap.runtime.transport import service as service_module
from semmap.runtime.transport.service import PROGRESS_PERIOD_S, Service, common_arguments


class Sent:
    """Stands in for the progress publisher: keeps what would have gone on the bus."""

    def __init__(self) -> None:
        self.frames: list[int] = []

    def put(self, message: Progress) -> int:
        self.frames.append(message.frame_id)
        return 0


def _service(mode: str) -> tuple[Service, Sent]:
    parser = argparse.ArgumentParser()
    common_arguments(parser)
    svc = Service(parser.parse_args(["--mode", mode]))
    sent = Sent()
    svc._progress_pub = sent  # type: ignore[assignment]
    return svc, sent


def test_lockstep_reports_every_frame() -> None:
    svc, sent = _service("lockstep")
    for frame_id in range(50):
        svc.report_progress(frame_id)
    assert sent.frames == list(range(50))


def test_real_time_reports_the_newest_frame_at_most_every_period(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = [100.0]
    monkeypatch.setattr(service_module.time, "monotonic", lambda: clock[0])
    svc, sent = _service("realtime")
    for frame_id in range(30):  # one second of 30 Hz video, frames 1/30 s apart
        svc.report_progress(frame_id)
        svc._send_owed_progress()  # (what the service loop does on every turn)
        clock[0] += 1 / 30
    assert len(sent.frames) <= 1 / PROGRESS_PERIOD_S + 1
    assert sent.frames == sorted(sent.frames) and sent.frames[0] == 0
    gaps = [b - a for a, b in zip(sent.frames, sent.frames[1:], strict=False)]
    assert all(gap >= PROGRESS_PERIOD_S * 30 - 1e-9 for gap in gaps), gaps
    # the newest frame done goes out once the period has passed, even with no frame coming
    clock[0] += PROGRESS_PERIOD_S
    svc._send_owed_progress()
    assert sent.frames[-1] == 29
    svc._send_owed_progress()
    assert sent.frames.count(29) == 1


def test_real_time_reports_the_last_frame_at_once_and_what_it_owes_at_finish(
        monkeypatch: pytest.MonkeyPatch) -> None:
    clock = [100.0]
    monkeypatch.setattr(service_module.time, "monotonic", lambda: clock[0])
    for ends in (False, True):
        svc, sent = _service("realtime")
        svc.out_dir = None
        svc.publish_status = lambda message="": None  # type: ignore[method-assign]
        svc.report_progress(0)
        svc.report_progress(1)  # owed: the period has not passed
        assert sent.frames == [0]
        if ends:
            svc.end_of_stream = Control(svc.robot, "end_of_stream", 3, 4)
            svc.report_progress(3)  # the stream's last frame: at once (the run's end waits for it), and finished
            assert sent.frames == [0, 3] and svc.finished and svc._progress_owed is None
        else:
            svc.finish()  # (stopped early, or told the stream ended): the newest frame done goes out first
            assert sent.frames == [0, 1] and svc._progress_owed is None
