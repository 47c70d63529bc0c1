"""A user's first hour with their own data: the official 7-Scenes layout (`.color.png`), a TUM folder with its own
camera.yaml and a SLAM trajectory file (checked against the frames' clock), and the summary a run ends with."""

from __future__ import annotations

import json
import re
import shutil
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest

from semmap.datasets import DatasetError, open_dataset
from semmap.datasets.trajectory_io import read_tum, write_tum

T0 = 1311868164.0  # a TUM-like Unix time


def parse_summary(stdout: str) -> dict:
    """The end-of-run summary as data: landmarks per class, ATE pair, output paths, next commands."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("semmap run summary"))
    result: dict = {"classes": {}, "outputs": [], "next": [], "ate": None}
    section = None
    for line in lines[start + 1 :]:
        text = line.strip()
        if line.startswith("  landmarks"):
            result["landmarks"] = int(text.split()[1]) if text.split()[1].isdigit() else 0
            section = "classes"
        elif line.startswith("  ATE"):
            odo, opt = re.findall(r"([0-9.]+) m", text)[:2]
            result["ate"] = (float(odo), float(opt))
        elif line.startswith("  frames"):
            result["frames"] = text
        elif line.startswith("  outputs"):
            section = "outputs"
        elif line.startswith("  next"):
            section = "next"
        elif line.startswith("    ") and section == "classes":
            name, n = text.rsplit(None, 1)
            result["classes"][name] = int(n)
        elif line.startswith("    ") and section in ("outputs", "next"):
            result[section].append(text)
    return result


def check_summary(stdout: str, out: Path) -> dict:
    """The summary agrees with the files of the run folder it describes."""
    summary = parse_summary(stdout)
    body = json.loads((out / "map.json").read_text())
    assert summary["landmarks"] == len(body["landmarks"])
    assert summary["classes"] == dict(Counter(lm["class"] for lm in body["landmarks"]))
    assert any(line.startswith(str(out / "map.json")) for line in summary["outputs"])
    if (out / "run.rrd").is_file():
        assert any(line.startswith(str(out / "run.rrd")) for line in summary["outputs"])
        assert any(line.startswith(f"semmap view {out}") for line in summary["next"])
    assert any(line.startswith(f"semmap query {out}") for line in summary["next"])
    if (out / "groundtruth.tum").is_file():
        assert any(line.startswith(f"semmap eval {out}") for line in summary["next"])
        scored = json.loads((out / "eval.json").read_text())
        assert summary["ate"] == (round(scored["ate_odometry_m"], 3), round(scored["ate_optimized_m"], 3))
    return summary


def _official_copy(kitchen_dir: Path, dst: Path, frames: int) -> Path:
    """The layout of Microsoft's download (seq-01.zip): PNG colour, no camera-intrinsics.txt."""
    dst.mkdir(parents=True)
    for i in range(frames):
        rgb = cv2.imread(str(kitchen_dir / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_COLOR)
        assert cv2.imwrite(str(dst / f"frame-{i:06d}.color.png"), rgb)
        for suffix in ("depth.png", "pose.txt"):
            shutil.copy(kitchen_dir / f"frame-{i:06d}.{suffix}", dst)
    return dst


@pytest.mark.needs_data
@pytest.mark.needs_model
def test_official_7scenes_layout_runs_and_ends_with_the_summary(kitchen_dir: Path, tmp_path: Path, semmap_run) -> None:
    seq = _official_copy(kitchen_dir, tmp_path / "redkitchen" / "seq-01", 45)
    ds = open_dataset(seq)
    assert ds.name == "7scenes/seq-01" and len(ds) == 45 and ds[3].rgb.shape == (480, 640, 3)
    with pytest.raises(DatasetError, match="give one sequence folder, e.g. .*seq-01"):
        open_dataset(tmp_path / "redkitchen")  # the unpacked scene, one level up
    out = tmp_path / "out"
    result = semmap_run([str(seq), "--out", str(out), "--odometry", "gt+drift"], timeout=400)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = check_summary(result.stdout, out)
    assert summary["landmarks"] >= 1 and "chair" in summary["classes"]
    assert summary["ate"] is not None and summary["ate"][0] > 0
    assert "45 processed of 45 published" in summary["frames"]


def _tum_copy(kitchen_dir: Path, root: Path, frames: int) -> list[tuple[float, np.ndarray]]:
    """A TUM-layout folder (Unix stamps, depth in 1/5000 m) with the camera in camera.yaml; returns the poses."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines, poses = [], [], []
    for i in range(frames):
        stamp = T0 + i / 30
        shutil.copy(kitchen_dir / f"frame-{i:06d}.color.jpg", root / "rgb" / f"{stamp:.6f}.jpg")
        depth = cv2.imread(str(kitchen_dir / f"frame-{i:06d}.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.uint32)
        depth[depth == 65535] = 0
        assert cv2.imwrite(str(root / "depth" / f"{stamp:.6f}.png"), np.clip(depth * 5, 0, 65535).astype(np.uint16))
        rgb_lines.append(f"{stamp:.6f} rgb/{stamp:.6f}.jpg")
        depth_lines.append(f"{stamp:.6f} depth/{stamp:.6f}.png")
        poses.append((stamp, np.loadtxt(kitchen_dir / f"frame-{i:06d}.pose.txt")))
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    # the README's example camera.yaml: 7-Scenes' Kinect, TUM's depth unit
    (root / "camera.yaml").write_text("fx: 585.0\nfy: 585.0\ncx: 320.0\ncy: 240.0\ndepth_factor: 5000.0\n")
    return poses


@pytest.mark.needs_data
@pytest.mark.needs_model
def test_tum_folder_with_camera_yaml_and_a_slam_trajectory_runs(kitchen_dir: Path, tmp_path: Path, semmap_run) -> None:
    root = tmp_path / "my_camera"
    poses = _tum_copy(kitchen_dir, root, 40)
    ds = open_dataset(root)
    assert ds.camera_name == "file" and (ds.intrinsics.fx, ds.intrinsics.cy) == (585.0, 240.0)
    trajectory = tmp_path / "slam.tum"
    write_tum(trajectory, poses)
    out = tmp_path / "out"
    result = semmap_run([str(root), "--out", str(out), "--odometry", f"file:{trajectory}", "--no-viz"], timeout=400)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "40 of 40 frames matched a pose within 0.05 s" in result.stderr
    assert len(read_tum(out / "trajectory_odometry.tum")) == 40
    check_summary(result.stdout, out)


@pytest.mark.needs_data
def test_a_trajectory_on_another_clock_is_refused_and_time_offset_fixes_it(
    kitchen_dir: Path, tmp_path: Path, semmap_run
) -> None:
    root = tmp_path / "my_camera"
    poses = _tum_copy(kitchen_dir, root, 20)
    from_zero = tmp_path / "from_zero.tum"
    write_tum(from_zero, [(stamp - T0, pose) for stamp, pose in poses])  # a SLAM that counts from its start
    out = tmp_path / "out"
    refused = semmap_run(
        [str(root), "--out", str(out), "--odometry", f"file:{from_zero}", "--only", "odometry", "--no-viz"]
    )
    assert refused.returncode == 2
    assert "matches only 0 of 20 frames" in refused.stderr
    assert "its poses span 0.000 .. 0.633 s" in refused.stderr
    assert f"the frames span {T0:.3f} .. {T0 + 19 / 30:.3f} s" in refused.stderr
    assert f"--time-offset {T0:.3f}" in refused.stderr
    assert not (out / "stats.json").exists()  # refused before anything started

    fixed = semmap_run(
        [
            str(root),
            "--out",
            str(out),
            "--odometry",
            f"file:{from_zero}",
            "--time-offset",
            str(T0),
            "--only",
            "odometry",
            "--no-viz",
        ]
    )
    assert fixed.returncode == 0, fixed.stderr[-3000:]
    assert "20 of 20 frames matched" in fixed.stderr
    written = read_tum(out / "trajectory_odometry.tum")
    np.testing.assert_allclose(written[7][1][:3, 3], poses[7][1][:3, 3], atol=1e-6)
