"""Real time at 3x the dataset rate with a detector slower than the input: queues stay bounded, frames are dropped
oldest-first and counted in stats.json, every frame still gets through the pipeline, the run ends when the stream
does (however many frames were dropped near its end), memory stays flat."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parents[2]
RSS_CEILING_MB = 1500  # every service, whatever the load


def _soak(semmap_run, out: Path, data: Path, frames: int, loops: int, *extra: str) -> dict:  # noqa: ANN001
    result = semmap_run([str(data), "--out", str(out), "--realtime", "--odometry", "gt", "--set", "run.speed=3",
                         "--set", f"run.loops={loops}", "--max-frames", str(frames), "--no-viz", *extra],
                        timeout=1800)  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads((out / "stats.json").read_text())


def _check(stats: dict, frames: int, overloaded: bool = True) -> None:
    assert stats["frames"]["published"] == frames
    assert stats["frames"]["processed"] == frames, "every frame gets an answer, skipped or not"
    detectors = [s for s in stats["services"].values() if s["service"] == "detector"]
    dropped = sum(s["counters"].get("frames_dropped", 0) for s in detectors)
    assert stats["frames"]["dropped"] == dropped
    if overloaded:
        assert dropped > 0, "every frame of a 90 Hz stream must overload a CPU detector"
    # (frames the planned cadence skips, `detector.every_n_frames` auto, are answered as `stride`; so are those
    # the queue passed over that the cadence would have skipped anyway: a drop is a detection real time cost)
    stride = sum(s["counters"].get("frames_stride", 0) for s in detectors)
    assert stats["frames"]["detected"] + dropped + stride == frames
    # the odometry keeps only its newest frames too: a frame it dropped has no pose, and the backend gives it up
    # (counted), the last frames of the stream included, instead of waiting for it
    backend = [s["counters"] for s in stats["services"].values() if s["service"] == "backend"]
    assert sum(c["frames"] + c.get("frames_without_odometry", 0) for c in backend) == frames
    for name, service in stats["services"].items():
        assert service["peak_rss_mb"] < RSS_CEILING_MB, name


@pytest.mark.needs_data
@pytest.mark.needs_model
def test_overload_drops_and_counts_frames(tmp_path: Path, data_root: Path, semmap_run) -> None:  # noqa: ANN001
    stats = _soak(semmap_run, tmp_path, data_root / "7scenes-redkitchen", 300, 1, "--set", "detector.every_n_frames=1")
    _check(stats, 300)
    # real time with the default `detector.precision: auto` takes this machine's measured choice
    from semmap.runtime.models.detector_choice import resolve_setup

    setup = resolve_setup("auto", 0, "auto", realtime=True)
    assert f"model {setup.label()} ({setup.origin}, auto" in (tmp_path / "logs" / "detector.log").read_text()


@pytest.mark.slow
@pytest.mark.needs_data
@pytest.mark.needs_model
def test_soak_memory_stays_flat(tmp_path: Path, data_root: Path, semmap_run) -> None:  # noqa: ANN001
    """Three passes over 7-Scenes at 3x speed (~35 s of 90 Hz input each): no service grows."""
    stats = _soak(semmap_run, tmp_path, data_root / "7scenes-redkitchen", 3000, 3)  # (the planned cadence)
    _check(stats, 3000, overloaded=False)
    for name, service in stats["services"].items():
        assert service["rss_late_mb"] - service["rss_early_mb"] < 60, (name, service)
