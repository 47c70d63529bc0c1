"""Detector replicas share the frame stream: every frame detected once, the same detections as one replica."""

from __future__ import annotations

from pathlib import Path

from semmap.core.messages import Detections


def _detections(router, tmp_path: Path, replicas: int, semmap_run, read_stats, collector_factory) -> dict:
    collector = collector_factory(router.endpoint, "replicas", "{root}/detections", Detections)
    try:
        out = tmp_path / f"r{replicas}"
        result = semmap_run(["synthetic:frames=40", "--out", str(out), "--robot", "replicas", "--only",
                             "detector,tracker", "--detectors", str(replicas), "--connect", router.endpoint,
                             "--zenoh-mode", "client", "--odometry", "gt"], timeout=240)
        assert result.returncode == 0, result.stderr[-3000:]
        stats = read_stats(out)
    finally:
        collector.bus.close()
    per_frame: dict[int, list[tuple]] = {}
    for msg in collector.items:
        assert msg.frame_id not in per_frame, f"frame {msg.frame_id} detected twice"
        per_frame[msg.frame_id] = [(d.class_name, round(d.score, 4), tuple(round(v, 2) for v in d.box))
                                   for d in msg.detections]
    detectors = [v for v in stats["services"].values() if v["service"] == "detector"]
    assert len(detectors) == replicas
    if replicas > 1:
        assert all(v["counters"].get("frames_detected", 0) > 5 for v in detectors), "work was not shared"
    # the run's cadence is the merged stream's, as the tracker sees it in frame order: every frame, 1/30 s apart
    cadence = stats["detection_interval_ms"]
    assert abs(cadence["p50"] - 1000 / 30) < 1.0 and abs(cadence["max"] - 1000 / 30) < 1.0, cadence
    return per_frame


def test_two_replicas_detect_each_frame_once_and_agree_with_one(router, tmp_path: Path, semmap_run, read_stats,
                                                               collector_factory) -> None:
    one = _detections(router, tmp_path, 1, semmap_run, read_stats, collector_factory)
    two = _detections(router, tmp_path, 2, semmap_run, read_stats, collector_factory)
    assert sorted(one) == list(range(40)) == sorted(two)
    assert one == two
    assert sum(len(v) for v in one.values()) > 40
