"""Every setting is validated before any process starts: `semmap run` with a bad value exits 2 at
once, naming the key; a service started by hand checks the same; `semmap config show` prints what a run uses."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from semmap.core.config import load_config

PROJECT = Path(__file__).resolve().parents[2]

# bad values of each kind: one that would raise a raw TypeError deep in the tracker, a confidence that detects
# nothing, a word for a bool, a fraction for a count, a list split into characters or of the wrong kind, a model
# file that is not there
BAD = [
    ("tracker.sigma_iou=banana", "tracker.sigma_iou"),
    ("detector.confidence=7", "detector.confidence"),
    ("loop_closure.enabled=maybe", "loop_closure.enabled"),
    ("tracker.min_length=1.5", "tracker.min_length"),
    ("detector.classes=[1, 2]", "detector.classes"),
    ("odometry.frame_offset=1,2", "odometry.frame_offset"),
    ("detector.model=/no/such/model.onnx", "detector.model"),
    ("associator.gate_u=-3", "associator.gate_u"),
    ("detector.kind=yolo", "detector.kind"),  # not a registered back end
    ("odometry.mode=lidar", "odometry.mode"),  # not a registered front end
]


@pytest.mark.parametrize(("override", "key"), BAD)
def test_a_bad_setting_fails_semmap_run_at_once_naming_the_key(
    tmp_path: Path, semmap_run, override: str, key: str
) -> None:  # noqa: ANN001
    out = tmp_path / "out"
    t0 = time.monotonic()
    result = semmap_run(["synthetic:frames=5", "--out", str(out), "--set", override], timeout=60)
    wall = time.monotonic() - t0
    print(f"semmap run --set {override}: exit {result.returncode} in {wall:.2f} s")
    assert result.returncode == 2, result.stderr
    assert f"error: {key}: expected" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr and result.stderr.count("error:") == 1, result.stderr
    assert not out.exists()  # refused before anything: no output directory, no process
    assert wall < 10  # ~1 s on an idle machine (the whole CLI start); loose for a loaded one


def test_a_bad_config_file_fails_semmap_run_naming_every_key(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    user = tmp_path / "my.yaml"
    user.write_text("tracker:\n  sigma_iou: banana\ndetector:\n  classes: cup,chair\n  confidence: 7\n")
    result = semmap_run(["synthetic:frames=5", "--out", str(tmp_path / "out"), "--config", str(user)], timeout=60)
    assert result.returncode == 2
    assert "tracker.sigma_iou: expected a number" in result.stderr
    assert "detector.confidence: expected a number <= 1" in result.stderr
    assert "detector.classes" not in result.stderr  # `a,b` is a list of two


def test_a_service_started_by_hand_validates_the_same(tmp_path: Path) -> None:
    """What `python -m semmap.services.X` (or compose) does with a bad value: the same check, exit 2."""
    result = subprocess.run(
        [sys.executable, "-m", "semmap.services.tracker", "--set", "tracker.sigma_iou=banana"],
        cwd=PROJECT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "tracker.sigma_iou: expected a number, got 'banana'" in result.stderr, result.stderr


def _config_show(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "semmap.cli", "config", "show", *args],
        cwd=PROJECT,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_config_show_prints_the_effective_configuration(tmp_path: Path) -> None:
    user = tmp_path / "my.yaml"
    user.write_text("run:\n  mode: realtime\n")
    overrides = ["detector.classes=cup,chair", "tracker.sigma_iou=0.3"]
    result = _config_show("--config", str(user), *(f"--set={item}" for item in overrides))
    assert result.returncode == 0, result.stderr
    text = result.stdout
    assert "\ntracker:" in text and "  sigma_iou: 0.3" in text and "  classes: [cup, chair]" in text
    assert "  mode: realtime" in text and "  confidence: 0.4" in text and "# paper" in text
    shown = tmp_path / "shown.yaml"
    shown.write_text(text)  # what it prints is a config file that gives the same settings
    assert load_config(shown) == load_config(user, overrides)
    result = _config_show("--set", "detector.confidence=7")
    assert result.returncode == 2 and "detector.confidence: expected a number <= 1" in result.stderr
    assert result.stdout == ""


def test_an_external_run_posed_by_semmap_refuses_a_slam_check_and_needs_a_vocabulary(
        tmp_path: Path, semmap_run, monkeypatch) -> None:  # noqa: ANN001
    """`semmap run external --odometry orbslam3` poses the camera's frames itself: asked to check the SLAM's poses
    too it says to choose one; without an ORB vocabulary (none set, none in the model directory) it says how to
    make one. Both before any process starts."""
    both = semmap_run(["external", "--odometry", "orbslam3", "--check-slam", "--out", str(tmp_path / "a")], timeout=60)
    assert both.returncode == 2 and "choose one" in both.stderr
    empty = tmp_path / "models"
    empty.mkdir()
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(empty))
    bare = semmap_run(["external", "--odometry", "orbslam3", "--out", str(tmp_path / "b")], timeout=60)
    assert bare.returncode == 2 and "semmap models vocabulary" in bare.stderr, bare.stderr
    assert not (tmp_path / "b" / "stats.json").exists()


def test_real_time_chooses_the_cheaper_front_end_settings_a_user_left_at_auto() -> None:
    """Real time registers half-size images and extracts fewer ORB features; lockstep registers full images; what a
    user set is kept."""
    from semmap.cli.run import realtime_front_end

    assert realtime_front_end(load_config(None, []), True) == [
        "odometry.registration_resolution=half", "odometry.orbslam3_features=800"]
    assert realtime_front_end(load_config(None, []), False) == ["odometry.registration_resolution=full"]
    chosen = load_config(None, ["odometry.registration_resolution=full", "odometry.orbslam3_features=1200"])
    assert realtime_front_end(chosen, True) == []
