"""TUM RGB-D reader on a TUM-layout folder built from real 7-Scenes frames, with jittered stamps."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from semmap.datasets import DatasetError
from semmap.datasets.trajectory_io import write_tum
from semmap.datasets.tum import TUM_INTRINSICS, TumDataset, associate

T0 = 1305031102.0
N_FRAMES = 12


@pytest.fixture(scope="module")
def tum_dir(kitchen_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """rgbd_dataset_freiburg1_kitchen/: rgb at ~30 Hz with jitter, depth offset by a few ms, mocap at 100 Hz.

    Frame 5's depth is 30 ms away (no partner within 0.02 s: the frame is dropped); frames 0-1 have no
    ground truth near them; depth.txt has one extra image that no rgb frame matches.
    """
    root = tmp_path_factory.mktemp("tum") / "rgbd_dataset_freiburg1_kitchen"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(4)
    rgb_lines = ["# color images", "# file: 'generated from 7-Scenes'", "# timestamp filename"]
    depth_lines = ["# depth maps", "# file: 'generated'", "# timestamp filename"]
    gt = []
    for i in range(N_FRAMES):
        stamp = T0 + i / 30 + rng.uniform(-0.003, 0.003)
        d_stamp = stamp + (0.03 if i == 5 else rng.uniform(-0.008, 0.008))
        shutil.copy(kitchen_dir / f"frame-{i:06d}.color.jpg", root / "rgb" / f"{stamp:.6f}.jpg")
        depth_mm = cv2.imread(str(kitchen_dir / f"frame-{i:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
        depth_tum = np.clip(depth_mm.astype(np.uint32) * 5, 0, 65535).astype(np.uint16)  # mm -> 1/5000 m
        assert cv2.imwrite(str(root / "depth" / f"{d_stamp:.6f}.png"), depth_tum)
        rgb_lines.append(f"{stamp:.6f} rgb/{stamp:.6f}.jpg")
        depth_lines.append(f"{d_stamp:.6f} depth/{d_stamp:.6f}.png")
        if i >= 2:
            gt.append((stamp + rng.uniform(-0.004, 0.004), np.loadtxt(kitchen_dir / f"frame-{i:06d}.pose.txt")))
    extra = T0 + 5.0
    assert cv2.imwrite(str(root / "depth" / "extra.png"), np.zeros((480, 640), np.uint16))
    depth_lines.append(f"{extra:.6f} depth/extra.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines[:3] + depth_lines[3:][::-1]) + "\n")  # any order
    write_tum(root / "groundtruth.txt", gt, header="ground truth trajectory\ntimestamp tx ty tz qx qy qz qw")
    return root


@pytest.mark.needs_data
def test_association_and_frames(tum_dir: Path, kitchen_dir: Path) -> None:
    ds = TumDataset(tum_dir)
    assert len(ds) == N_FRAMES - 1  # frame 5 dropped
    source = [i for i in range(N_FRAMES) if i != 5]
    assert ds.camera_name == "fr1"
    k = ds.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == TUM_INTRINSICS["fr1"] and (k.width, k.height) == (640, 480)
    assert ds.depth_scale == pytest.approx(1 / 5000)
    for index, i in enumerate(source):
        rgb_name, depth_name = ds.files(index)
        assert abs(float(Path(rgb_name).stem) - float(Path(depth_name).stem)) < 0.02
        assert abs(float(Path(rgb_name).stem) - (T0 + i / 30)) < 0.004
    frame = ds[source.index(7)]
    assert frame.stamp == pytest.approx(T0 + 7 / 30, abs=0.004)
    assert frame.rgb.shape == (480, 640, 3) and frame.depth.dtype == np.uint16
    expected = cv2.imread(str(kitchen_dir / "frame-000007.depth.png"), cv2.IMREAD_UNCHANGED) * 0.001
    got = frame.depth * frame.depth_scale
    both = (expected > 0) & (expected < 13.0)
    np.testing.assert_allclose(got[both], expected[both], atol=1e-6)
    raw_pose = np.loadtxt(kitchen_dir / "frame-000007.pose.txt")
    assert frame.gt_pose is not None
    np.testing.assert_allclose(frame.gt_pose[:3, 3], raw_pose[:3, 3], atol=1e-8)
    np.testing.assert_allclose(frame.gt_pose[:3, :3], raw_pose[:3, :3], atol=2e-3)  # 7-Scenes R not exactly SO(3)


@pytest.mark.needs_data
def test_groundtruth_association(tum_dir: Path) -> None:
    ds = TumDataset(tum_dir)
    assert ds.has_groundtruth
    assert ds[0].gt_pose is None and ds[1].gt_pose is None  # no mocap sample within 0.02 s
    gt = ds.groundtruth()
    assert len(gt) == len(ds) - 2
    assert [s for s, _ in gt] == [ds[i].stamp for i in range(2, len(ds))]
    strict = TumDataset(tum_dir, max_difference=0.004)  # depth jitters +-8 ms: a tighter window drops pairs
    assert 0 < len(strict) < len(ds)


@pytest.mark.needs_data
def test_intrinsics_by_folder_name_and_override(tum_dir: Path, tmp_path: Path) -> None:
    for folder, camera in (
        ("rgbd_dataset_freiburg2_desk", "fr2"),
        ("fr3_walking_xyz", "fr3"),
        ("my_recording", "default"),
    ):
        copy = tmp_path / folder
        shutil.copytree(tum_dir, copy)
        ds = TumDataset(copy)
        assert ds.camera_name == camera
        assert (ds.intrinsics.fx, ds.intrinsics.cy) == (TUM_INTRINSICS[camera][0], TUM_INTRINSICS[camera][3])

    override = tmp_path / "my_recording"
    (override / "intrinsics.txt").write_text("600 0 330\n0 601 250\n0 0 1\n")
    k = TumDataset(override).intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == (600, 601, 330, 250)
    (override / "camera.yaml").write_text("%YAML:1.0\nCamera.fx: 510.0\nCamera.fy: 511.0\nCamera.cx: 300.0\n"
                                          "Camera.cy: 200.0\nDepthMapFactor: 1000.0\n")  # fmt: skip
    ds = TumDataset(override)  # camera.yaml wins over intrinsics.txt
    assert (ds.intrinsics.fx, ds.intrinsics.cy, ds.depth_scale) == (510, 200, 0.001)
    (override / "camera.yaml").write_text("camera:\n  fx: 1\n  fy: 2\n  cx: 3\n")
    with pytest.raises(DatasetError, match="fx, fy, cx, cy"):
        TumDataset(override)


def test_associate_matches_tum_semantics() -> None:
    first = [0.0, 0.033, 0.066, 0.100, 0.500]
    second = [0.001, 0.030, 0.034, 0.090, 0.300]
    # 0.033 takes 0.034 (closest); 0.066 has nothing within 0.02; 0.1 -> 0.09; 0.5 unmatched; 0.03 unused
    assert associate(first, second, 0.02) == [(0, 0), (1, 2), (3, 3)]
    # one-to-one: two rgb stamps near one depth stamp, the closer wins
    assert associate([1.0, 1.012], [1.01], 0.02) == [(1, 0)]
    assert associate([1.0], [0.9], 0.02, offset=0.1) == [(0, 0)]
    assert associate([], [1.0]) == []


def test_bad_tum_folders(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="needs rgb.txt and depth.txt"):
        TumDataset(tmp_path)
    (tmp_path / "rgb.txt").write_text("# nothing\n1.0 rgb/1.png\n")
    (tmp_path / "depth.txt").write_text("5.0 depth/5.png\n")
    with pytest.raises(DatasetError, match="no rgb/depth pairs"):
        TumDataset(tmp_path)
    (tmp_path / "depth.txt").write_text("abc depth/5.png\n")
    with pytest.raises(DatasetError, match="bad timestamp"):
        TumDataset(tmp_path)
