"""`semmap run` as a user runs it: separate processes over Zenoh, outputs, determinism, failures, Ctrl-C."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from semmap.datasets.trajectory_io import read_tum
from tests.pipeline.test_first_hour import check_summary

PROJECT = Path(__file__).resolve().parents[2]


def _assert_outputs(out: Path, frames: int, groundtruth: bool = True) -> dict:
    stats = json.loads((out / "stats.json").read_text())
    assert stats["outcome"] == "completed"
    assert stats["frames"]["published"] == frames and stats["frames"]["processed"] == frames
    assert len(read_tum(out / "trajectory_odometry.tum")) == frames
    assert len(read_tum(out / "trajectory_optimized.tum")) == frames
    assert (out / "groundtruth.tum").is_file() == groundtruth
    body = json.loads((out / "map.json").read_text())
    assert body["schema"] == "semmap.map/2"
    for lm in body["landmarks"]:
        assert set(lm) == {"id", "class", "centroid", "radius", "extent", "observations", "first_seen", "last_seen",
                           "status"}
    assert (out / "run.rrd").stat().st_size > 1000
    for name in ("player", "odometry", "detector", "tracker", "associator", "backend", "viz"):
        assert stats["services"][name]["state"] == "finished", name
    return body


def test_synthetic_run_writes_every_output(tmp_path: Path, semmap_run) -> None:
    result = semmap_run(["synthetic:frames=90", "--out", str(tmp_path), "--odometry", "gt+drift"])
    assert result.returncode == 0, result.stderr[-3000:]
    body = _assert_outputs(tmp_path, 90)
    assert len(body["landmarks"]) >= 5
    assert "bus: tcp/127.0.0.1:" in result.stderr
    summary = check_summary(result.stdout, tmp_path)  # what `./dev.sh demo` ends with
    assert summary["ate"] is not None and "90 processed of 90 published" in summary["frames"]
    _assert_recording(tmp_path / "run.rrd", body)


def _rerun(*args: str) -> subprocess.CompletedProcess:
    rerun = Path(sys.executable).with_name("rerun")
    return subprocess.run([str(rerun), *args], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "CI": "true"})


def _assert_recording(rrd: Path, body: dict) -> None:
    """The recording loads and holds landmark boxes, centre spheres, labels `class #id`, trajectories, timings."""
    assert _rerun("rrd", "verify", str(rrd)).returncode == 0
    summary = _rerun("rrd", "print", str(rrd)).stdout
    for entity, archetype in [("/world/landmarks/tile_", "Boxes3D:half_sizes"),
                              ("/world/landmarks/tile_", "Ellipsoids3D:half_sizes"),
                              ("/world/landmarks/tile_", "Points3D:"),
                              ("/world/trajectory/odometry", "LineStrips3D:strips"),
                              ("/world/trajectory/optimized", "LineStrips3D:strips"),
                              ("/world/camera/image ", "EncodedImage:blob"),
                              ("/world/camera/image/detections", "Boxes2D:"),
                              ("/world/camera/image/tracks", "Boxes2D:"),
                              ("/timings/detector/detect_ms", "Scalars:")]:
        assert any(entity in line and archetype in line for line in summary.splitlines()), entity
    table = _rerun("rrd", "print", "-vvv", str(rrd)).stdout  # wide cells are cut: look for any landmark's label
    assert any(f"{lm['class']} #{lm['id']}" in table for lm in body["landmarks"])


@pytest.mark.needs_data
def test_7scenes_run_through_separate_processes(tmp_path: Path, data_root: Path, semmap_run) -> None:
    result = semmap_run([str(data_root / "7scenes-redkitchen"), "--out", str(tmp_path), "--odometry", "gt+drift",
                         "--lockstep", "--max-frames", "60"], timeout=400)
    assert result.returncode == 0, result.stderr[-3000:]
    _assert_outputs(tmp_path, 60)
    stats = json.loads((tmp_path / "stats.json").read_text())
    # every frame detected (lockstep, every_n_frames 1): one detection per 1/30 s of video
    assert abs(stats["detection_interval_ms"]["max"] - 1000 / 30) < 1.0
    gt = read_tum(tmp_path / "groundtruth.tum")
    assert [round(t, 6) for t, _ in gt[:3]] == [0.0, round(1 / 30, 6), round(2 / 30, 6)]


def test_replay_is_deterministic(tmp_path: Path, semmap_run) -> None:
    outputs = []
    for name in ("a", "b"):
        out = tmp_path / name
        result = semmap_run(["synthetic:frames=40", "--out", str(out), "--odometry", "gt+drift", "--seed", "3",
                             "--no-viz"])
        assert result.returncode == 0, result.stderr[-3000:]
        outputs.append(out)
    for name in ("map.json", "trajectory_odometry.tum", "trajectory_optimized.tum"):
        assert (outputs[0] / name).read_text() == (outputs[1] / name).read_text(), name


def test_a_failing_service_fails_the_run_with_its_reason(tmp_path: Path, semmap_run) -> None:
    # a fault only the service itself finds (a missing model or trajectory file is refused before the run now):
    # a model file that is there but is no ONNX model
    broken = tmp_path / "broken-model.onnx"
    broken.write_bytes(b"not an onnx model")
    result = semmap_run(["synthetic:frames=10", "--out", str(tmp_path / "out"), "--no-viz", "--set",
                         "detector.kind=onnx", "--set", f"detector.model={broken}"], timeout=120)
    assert result.returncode == 1
    err = result.stderr
    assert "error: detector" in err and ("failed" in err or "exited with code" in err), err[-2000:]
    assert "broken-model.onnx" in err


def test_bad_arguments_are_clear_errors(tmp_path: Path, semmap_run) -> None:
    result = semmap_run([str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")], timeout=60)
    assert result.returncode == 2 and "does not exist" in result.stderr
    result = semmap_run(["synthetic", "--set", "tracker.sigma=1"], timeout=60)
    assert result.returncode == 2 and "unknown setting 'tracker.sigma'" in result.stderr


def test_ctrl_c_stops_every_service_and_keeps_outputs(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "semmap.cli", "run", "synthetic:frames=2000", "--out",
                             str(tmp_path), "--quiet", "--no-viz"], cwd=PROJECT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "CI": "true"})
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (tmp_path / "logs" / "player.log").is_file():
        time.sleep(0.2)
    time.sleep(12)  # let some frames through
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["outcome"] == "interrupted"
    assert 0 < stats["frames"]["published"] < 2000
    assert len(read_tum(tmp_path / "trajectory_odometry.tum")) > 0
    assert (tmp_path / "map.json").is_file()
    for service in stats["services"].values():
        assert service["state"] in ("stopped", "finished")


@pytest.mark.slow
@pytest.mark.needs_data
@pytest.mark.needs_model
def test_full_7scenes_sequence(kitchen_drift_run: Path) -> None:
    _assert_outputs(kitchen_drift_run, 1000)  # the run is shared with tests/pipeline/test_closed_loop.py
