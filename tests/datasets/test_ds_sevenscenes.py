"""7-Scenes reader on the real redkitchen frames, plus the invalid-depth and corrupt-file paths."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from semmap.datasets import DatasetError
from semmap.datasets.sevenscenes import SevenScenesDataset


@pytest.fixture(scope="module")
def kitchen(kitchen_dir: Path) -> SevenScenesDataset:
    return SevenScenesDataset(kitchen_dir)


@pytest.mark.needs_data
def test_frame_zero(kitchen: SevenScenesDataset) -> None:
    assert len(kitchen) == 1000
    assert kitchen.rate_hz == 30.0 and kitchen.has_groundtruth
    frame = kitchen[0]
    assert frame.index == 0 and frame.stamp == 0.0
    assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth.shape == (480, 640) and frame.depth.dtype == np.uint16
    assert frame.depth_scale == 0.001
    k = frame.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (585.0, 585.0, 320.0, 240.0, 640, 480)
    valid = frame.depth[frame.depth > 0] * frame.depth_scale
    assert 0.3 < float(np.median(valid)) < 5.0  # a kitchen seen from ~1-3 m
    assert not np.any(frame.depth == 65535)
    assert frame.instances == []


@pytest.mark.needs_data
def test_poses_are_rigid_and_stamps_regular(kitchen: SevenScenesDataset, kitchen_dir: Path) -> None:
    for i in (0, 1, 500, 999):
        frame = kitchen[i]
        assert frame.stamp == pytest.approx(i / 30.0)
        pose = frame.gt_pose
        assert pose is not None and pose.shape == (4, 4)
        np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-9)
        assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0, abs=1e-9)
        raw = np.loadtxt(kitchen_dir / f"frame-{i:06d}.pose.txt")
        np.testing.assert_allclose(pose[:3, 3], raw[:3, 3])  # translation untouched
        np.testing.assert_allclose(pose[:3, :3], raw[:3, :3], atol=2e-3)  # rotation only re-orthonormalised
    gt = kitchen.groundtruth()
    assert len(gt) == 1000
    np.testing.assert_allclose([s for s, _ in gt[:3]], [0.0, 1 / 30, 2 / 30])
    path = np.array([p[:3, 3] for _, p in gt])
    assert 5.0 < np.linalg.norm(np.diff(path, axis=0), axis=1).sum() < 10.0  # README: 7.4 m


def _copy_frames(src: Path, dst: Path, count: int) -> None:
    dst.mkdir()
    shutil.copy(src / "camera-intrinsics.txt", dst)
    for i in range(count):
        for suffix in ("color.jpg", "depth.png", "pose.txt"):
            shutil.copy(src / f"frame-{i:06d}.{suffix}", dst)


@pytest.mark.needs_data
def test_corrupt_and_missing_files_raise_dataset_error(kitchen_dir: Path, tmp_path: Path) -> None:
    root = tmp_path / "seq"
    _copy_frames(kitchen_dir, root, 5)
    (root / "frame-000001.color.jpg").write_bytes(b"\xff\xd8\xff\xe0 definitely not a jpeg")
    (root / "frame-000002.depth.png").unlink()
    jpeg = (root / "frame-000003.color.jpg").read_bytes()
    (root / "frame-000003.color.jpg").write_bytes(jpeg[: len(jpeg) // 2])  # libjpeg would only warn
    png = (root / "frame-000004.depth.png").read_bytes()
    (root / "frame-000004.depth.png").write_bytes(png[: len(png) // 2])
    ds = SevenScenesDataset(root)
    assert len(ds) == 5
    assert ds[0].rgb.shape == (480, 640, 3)
    with pytest.raises(DatasetError, match="frame-000001.color.jpg"):
        ds[1]
    with pytest.raises(DatasetError, match="depth image missing"):
        ds[2]
    with pytest.raises(DatasetError, match="truncated JPEG"):
        ds[3]
    with pytest.raises(DatasetError, match="cannot decode depth image"):
        ds[4]
    with pytest.raises(IndexError):
        ds[5]


@pytest.mark.needs_data
def test_unreadable_pose_costs_its_frame_not_the_ground_truth(kitchen_dir: Path, tmp_path: Path) -> None:
    root = tmp_path / "seq"
    _copy_frames(kitchen_dir, root, 5)
    (root / "frame-000002.pose.txt").write_text("nan " * 16)
    ds = SevenScenesDataset(root)
    with pytest.raises(DatasetError, match="frame-000002.pose.txt"):
        ds[2]
    assert [round(t * 30) for t, _ in ds.groundtruth()] == [0, 1, 3, 4]
    assert [i for i, _ in ds.groundtruth_skipped] == [2]
    assert "frame-000002.pose.txt" in ds.groundtruth_skipped[0][1]


def test_invalid_depth_marker_and_defaults(tmp_path: Path) -> None:
    """65535 is 7-Scenes' 'no reading': it must come out as 0. No intrinsics file: the published K."""
    rgb = np.full((48, 64, 3), 128, np.uint8)
    depth = np.full((48, 64), 1500, np.uint16)
    depth[:5] = 65535
    for n in (7, 8):  # frame numbers need not start at 0: stamps follow the number
        assert cv2.imwrite(str(tmp_path / f"frame-{n:06d}.color.jpg"), rgb)
        assert cv2.imwrite(str(tmp_path / f"frame-{n:06d}.depth.png"), depth)
    ds = SevenScenesDataset(tmp_path)
    frame = ds[0]
    assert frame.stamp == pytest.approx(7 / 30)
    assert np.all(frame.depth[:5] == 0) and np.all(frame.depth[5:] == 1500)
    assert (frame.intrinsics.fx, frame.intrinsics.cx, frame.intrinsics.width) == (585.0, 320.0, 64)
    assert frame.gt_pose is None and not ds.has_groundtruth and ds.groundtruth() == []


def test_not_a_sevenscenes_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no frame-NNNNNN.color.png/.jpg"):
        SevenScenesDataset(tmp_path)
    (tmp_path / "camera-intrinsics.txt").write_text("1 2 3\n")
    assert cv2.imwrite(str(tmp_path / "frame-000000.color.jpg"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(DatasetError, match="expected 9 numbers"):
        SevenScenesDataset(tmp_path)


@pytest.mark.needs_data
def test_frames_travel_as_their_files(kitchen_dir: Path, tmp_path: Path) -> None:
    """The player sends a JPEG colour file and a 16-bit PNG depth file as stored (no decode and re-encode per
    frame); a receiver decodes the same pixels the reader gives, the "no reading" marker as 0."""
    from semmap.core.messages import Frame
    from semmap.runtime.pipeline.stages import frame_message

    root = tmp_path / "seq"
    _copy_frames(kitchen_dir, root, 2)
    depth_path = root / "frame-000001.depth.png"
    depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
    depth[:8, :8] = 65535  # 7-Scenes' "no reading"
    cv2.imwrite(str(depth_path), depth)
    data = SevenScenesDataset(root)[1]
    wire = frame_message("r", data).encode()
    assert len(wire) < 200_000  # ~690 KB with the depth raw
    frame = Frame.decode(wire)
    assert frame.rgb_jpeg == (root / "frame-000001.color.jpg").read_bytes()
    assert bytes(frame.depth_raw) == depth_path.read_bytes()
    np.testing.assert_array_equal(frame.rgb(), data.rgb)
    np.testing.assert_array_equal(frame.depth(), data.depth)
    assert np.all(frame.depth()[:8, :8] == 0) and not np.any(frame.depth() == 65535)


@pytest.mark.needs_data
def test_damaged_files_are_caught_where_they_are_read(kitchen_dir: Path, tmp_path: Path) -> None:
    """Frames stay encoded until needed, yet a damaged file is still the reader's DatasetError (the player counts
    and announces it), not a surprise in some service: a PNG's chunk CRCs and a JPEG's markers are checked."""
    from semmap.datasets.images import jpeg_size, png16_size

    root = tmp_path / "seq"
    _copy_frames(kitchen_dir, root, 3)
    png = bytearray((root / "frame-000001.depth.png").read_bytes())
    assert png16_size(bytes(png)) == (640, 480)
    png[len(png) // 2] ^= 0xFF  # one flipped byte inside the image data
    (root / "frame-000001.depth.png").write_bytes(bytes(png))
    jpeg = (root / "frame-000002.color.jpg").read_bytes()
    assert jpeg_size(jpeg) == (640, 480)
    assert jpeg_size(jpeg[:2] + jpeg[2:][::-1]) is None and png16_size(jpeg) is None
    (root / "frame-000002.color.jpg").write_bytes(jpeg[:300] + jpeg[-2:])  # headers cut off mid-way
    ds = SevenScenesDataset(root)
    assert ds[0].rgb_file is not None and ds[0].rgb_file.fmt == "jpeg" and ds[0].depth_file.fmt == "png16"
    with pytest.raises(DatasetError, match="frame-000001.depth.png"):
        ds[1]
    with pytest.raises(DatasetError, match="frame-000002.color.jpg"):
        ds[2]
