"""The camera a run uses is stated and checked against the frames before the first one: real
7-Scenes and Bonn frames pass; a TUM folder with a wrong camera.yaml (depth factor 5x off, depth factor 1,
another camera's intrinsics, a principal point outside the image) is warned about or refused, naming the file
and the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from semmap.datasets import open_dataset
from semmap.datasets.calibration import CalibrationError, check_dataset_camera

BONN_INTRINSICS = "fx: 542.8\nfy: 542.6\ncx: 315.6\ncy: 237.8\n"



def _tum_copy(bonn: Path, dest: Path, camera_yaml: str | None, frames: int = 60) -> Path:
    """A TUM folder of Bonn's first frames (images linked, lists cut) with its own camera.yaml."""
    dest.mkdir()
    for sub in ("rgb", "depth"):
        (dest / sub).symlink_to(bonn / sub)
    for name in ("rgb.txt", "depth.txt"):
        lines = (bonn / name).read_text().splitlines()
        (dest / name).write_text("\n".join(lines[: frames + 2]) + "\n")
    if camera_yaml is not None:
        (dest / "camera.yaml").write_text(camera_yaml)
    return dest


@pytest.mark.needs_data
def test_real_recordings_pass_and_name_their_camera(kitchen_dir: Path, bonn_dir: Path) -> None:
    line, warnings = check_dataset_camera(open_dataset(kitchen_dir))
    assert warnings == []
    assert "camera-intrinsics.txt" in line and "fx 585 fy 585 cx 320 cy 240, 640x480" in line
    assert "depth 1000 units per metre" in line
    line, warnings = check_dataset_camera(open_dataset(bonn_dir))
    assert warnings == []
    assert "intrinsics.txt" in line and "640x480" in line and "depth 5000 units per metre" in line


@pytest.mark.needs_data
def test_a_right_camera_yaml_passes(bonn_dir: Path, tmp_path: Path) -> None:
    root = _tum_copy(bonn_dir, tmp_path / "tum", BONN_INTRINSICS + "depth_factor: 5000\n")
    line, warnings = check_dataset_camera(open_dataset(root))
    assert warnings == [] and str(root / "camera.yaml") in line


@pytest.mark.needs_data
def test_depth_factor_5x_off_is_warned_with_the_factor_that_fits(bonn_dir: Path, tmp_path: Path) -> None:
    root = _tum_copy(bonn_dir, tmp_path / "tum", BONN_INTRINSICS + "depth_factor: 1000\n")
    _, warnings = check_dataset_camera(open_dataset(root))
    assert len(warnings) == 1, warnings
    assert f"{root / 'camera.yaml'}, key depth_factor" in warnings[0]
    assert "depth_factor 5000 would give" in warnings[0]


@pytest.mark.needs_data
def test_depth_factor_1_is_refused(bonn_dir: Path, tmp_path: Path) -> None:
    root = _tum_copy(bonn_dir, tmp_path / "tum", BONN_INTRINSICS + "depth_factor: 1\n")
    with pytest.raises(CalibrationError, match=r"camera\.yaml, key depth_factor: depth factor 1 units per metre"):
        check_dataset_camera(open_dataset(root))


@pytest.mark.needs_data
@pytest.mark.parametrize(("camera", "match"), [
    ("fx: 1085.6\nfy: 1085.2\ncx: 631.2\ncy: 475.5\n", r"implies images of about 1262x951, but the frames are 640x480"),
    ("fx: 542.8\nfy: 542.6\ncx: 700\ncy: 237.8\n", r"principal point \(cx, cy = 700, 237.8\) lies outside"),
    (BONN_INTRINSICS + "width: 1280\nheight: 960\n", r"calibration is for 1280x960 images"),
])
def test_another_cameras_intrinsics_are_refused(bonn_dir: Path, tmp_path: Path, camera: str, match: str) -> None:
    root = _tum_copy(bonn_dir, tmp_path / "tum", camera)
    with pytest.raises(CalibrationError, match=match) as info:
        check_dataset_camera(open_dataset(root))
    assert str(root / "camera.yaml") in str(info.value)


@pytest.mark.needs_data
def test_semmap_run_refuses_before_anything_starts(bonn_dir: Path, tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    root = _tum_copy(bonn_dir, tmp_path / "tum", BONN_INTRINSICS + "depth_factor: 1\n")
    out = tmp_path / "out"
    result = semmap_run([str(root), "--out", str(out), "--odometry", "rgbd", "--no-viz"], timeout=60)
    assert result.returncode == 2, result.stderr
    assert "key depth_factor" in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert not out.exists()
    root2 = _tum_copy(bonn_dir, tmp_path / "tum2", BONN_INTRINSICS + "depth_factor: 1000\n")
    result = semmap_run([str(root2), "--out", str(out), "--odometry", "rgbd", "--no-viz", "--max-frames", "1",
                         "--set", "run.min_free_mb=1e12"], timeout=60)  # refused later (disk), after the warning
    assert "warning:" in result.stderr and "depth_factor 5000 would give" in result.stderr, result.stderr
