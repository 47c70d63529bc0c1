"""Detector replicas share the frame stream: every frame detected once, the same detections as one replica."""

from __future__ import annotations

from pathlib import Path

from semmap.core.messages import Detections


def _detections(router, tmp_path: Path, replicas: int, semmap_run, read_stats, collector_factory,
                every_n: int = 1) -> dict:  # fmt: skip
    robot = f"replicas{every_n}"
    collector = collector_factory(router.endpoint, robot, "{root}/detections", Detections)
    try:
        out = tmp_path / f"r{replicas}-{every_n}"
        result = semmap_run(["synthetic:frames=40", "--out", str(out), "--robot", robot, "--only",
                             "detector,tracker", "--detectors", str(replicas), "--connect", router.endpoint,
                             "--zenoh-mode", "client", "--odometry", "gt",
                             "--set", f"detector.every_n_frames={every_n}"], timeout=240)  # fmt: skip
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
    # the run's cadence is the merged stream's, as the tracker sees it in frame order: every n-th frame
    cadence = stats["detection_interval_ms"]
    period = every_n * 1000 / 30
    assert abs(cadence["p50"] - period) < 1.0 and abs(cadence["max"] - period) < 1.0, cadence
    return per_frame


def test_two_replicas_detect_each_frame_once_and_agree_with_one(router, tmp_path: Path, semmap_run, read_stats,
                                                               collector_factory) -> None:
    one = _detections(router, tmp_path, 1, semmap_run, read_stats, collector_factory)
    two = _detections(router, tmp_path, 2, semmap_run, read_stats, collector_factory)
    assert sorted(one) == list(range(40)) == sorted(two)
    assert one == two
    assert sum(len(v) for v in one.values()) > 40


def test_two_replicas_take_turns_at_a_cadence(router, tmp_path: Path, semmap_run, read_stats,
                                              collector_factory) -> None:
    """Every 2nd frame with 2 replicas: the due frames go to both in turn (by id alone, frame_id % 2, replica 1
    would own only frames that are never due and detect nothing), and the rest are answered as skipped."""
    two = _detections(router, tmp_path, 2, semmap_run, read_stats, collector_factory, every_n=2)
    assert sorted(two) == list(range(40))
    assert [f for f, boxes in sorted(two.items()) if boxes] == list(range(0, 40, 2))
