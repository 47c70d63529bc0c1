"""The latency plot's samples are held back and sent as one column per stage (semmap.services.viz.service)."""

from __future__ import annotations

from semmap.services.viz.service import TimingColumns


def test_samples_wait_by_stage_in_arrival_order_and_are_taken_once() -> None:
    timings = TimingColumns()
    timings.add("timings/detector/detect_ms", 2, 101.5)
    timings.add("timings/tracker/proposal", 2, 1.25)
    timings.add("timings/detector/detect_ms", 4, 99.0)
    assert len(timings) == 3
    assert timings.take() == {"timings/detector/detect_ms": ([2, 4], [101.5, 99.0]),
                              "timings/tracker/proposal": ([2], [1.25])}
    assert len(timings) == 0 and timings.take() == {}
