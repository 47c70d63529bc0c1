"""KITTI stereo: SGBM depth on the real sequence-06 pair, and the odometry-layout reader around it."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from semmap.datasets import DatasetError
from semmap.datasets.images import read_rgb
from semmap.datasets.kitti import (
    KittiDataset,
    depth_to_u16,
    read_calib,
    stereo_baseline,
    stereo_depth,
)

CALIB_04_12 = """P0: 7.070912e+02 0.0 6.018873e+02 0.0 0.0 7.070912e+02 1.831104e+02 0.0 0.0 0.0 1.0 0.0
P1: 7.070912e+02 0.0 6.018873e+02 -3.798145e+02 0.0 7.070912e+02 1.831104e+02 0.0 0.0 0.0 1.0 0.0
P2: 7.070912e+02 0.0 6.018873e+02 4.688783e+01 0.0 7.070912e+02 1.831104e+02 1.178601e-01 0.0 0.0 1.0 6.203223e-03
P3: 7.070912e+02 0.0 6.018873e+02 -3.334597e+02 0.0 7.070912e+02 1.831104e+02 1.930130e+00 0.0 0.0 1.0 3.318498e-03
"""


@pytest.fixture(scope="module")
def kitti06(data_root: Path) -> Path:
    path = data_root / "images" / "kitti06"
    if not (path / "kitti06-12-R-color.png").is_file():
        pytest.skip(f"no images/kitti06 stereo pair in {data_root}")
    return path


@pytest.fixture(scope="module")
def real_depth(kitti06: Path) -> tuple[np.ndarray, float, float]:
    calib = read_calib(kitti06 / "calib.txt")
    fx, baseline = float(calib["P2"][0, 0]), stereo_baseline(calib["P2"], calib["P3"])
    left, right = read_rgb(kitti06 / "kitti06-12-color.png"), read_rgb(kitti06 / "kitti06-12-R-color.png")
    return stereo_depth(left, right, fx, baseline), fx, baseline


def test_calibration_and_baseline(tmp_path: Path) -> None:
    (tmp_path / "calib.txt").write_text(CALIB_04_12)
    calib = read_calib(tmp_path / "calib.txt")
    assert set(calib) == {"P0", "P1", "P2", "P3"}
    assert stereo_baseline(calib["P2"], calib["P3"]) == pytest.approx((46.88783 + 333.4597) / 707.0912)
    assert stereo_baseline(calib["P0"], calib["P1"]) == pytest.approx(0.537, abs=0.002)  # grey pair
    (tmp_path / "calib.txt").write_text(CALIB_04_12.split("P2")[0])
    with pytest.raises(DatasetError, match="no P2"):
        read_calib(tmp_path / "calib.txt")


def test_stereo_depth_on_shifted_texture() -> None:
    """A random texture shifted by 20 px: depth must be fx * B / 20 nearly everywhere it is valid."""
    rng = np.random.default_rng(1)
    texture = cv2.resize(rng.integers(0, 255, (60, 160), dtype=np.uint8), (640, 240), interpolation=cv2.INTER_NEAREST)
    texture = cv2.GaussianBlur(texture, (3, 3), 0)
    left = np.repeat(texture[:, :-20, None], 3, axis=2)
    right = np.repeat(texture[:, 20:, None], 3, axis=2)  # a point at x in the left image is at x - 20 in the right
    depth = stereo_depth(left, right, 700.0, 0.5)
    valid = depth > 0
    assert valid.mean() > 0.6
    assert float(np.median(depth[valid])) == pytest.approx(700 * 0.5 / 20, rel=0.02)
    with pytest.raises(ValueError):
        stereo_depth(left, right[:, :-1], 700.0, 0.5)


def test_depth_to_u16_marks_unrepresentable_invalid() -> None:
    depth = np.array([0.0, 1.2345, 65.535, 70.0, -1.0, np.inf, np.nan], np.float32)
    np.testing.assert_array_equal(depth_to_u16(depth, 0.001), [0, 1234, 65535, 0, 0, 0, 0])
    assert depth_to_u16(np.array([70.0]), 0.01)[0] == 7000


@pytest.mark.needs_data
def test_real_pair_depth_is_plausible(real_depth: tuple[np.ndarray, float, float]) -> None:
    depth, fx, baseline = real_depth
    assert depth.shape == (370, 1226) and depth.dtype == np.float32
    assert baseline == pytest.approx(0.538, abs=0.001)
    valid = depth > 0
    assert valid.mean() > 0.6  # measured ~0.73 (the left 128 columns can never match)
    assert 5.0 < float(np.median(depth[valid])) < 40.0
    assert depth[valid].min() >= fx * baseline / 128 - 1e-3  # nothing closer than the largest disparity allows
    h, w = depth.shape
    bottom, top = depth[int(0.8 * h) :, w // 4 : 3 * w // 4], depth[: int(0.3 * h), w // 4 : 3 * w // 4]
    assert np.median(bottom[bottom > 0]) < 12.0  # the road just ahead of the car
    assert np.median(bottom[bottom > 0]) < 0.5 * np.median(top[top > 0])


def _standard_layout(kitti06: Path, root: Path) -> Path:
    (root / "image_2").mkdir(parents=True)
    (root / "image_3").mkdir()
    shutil.copy(kitti06 / "kitti06-12-color.png", root / "image_2" / "000000.png")
    shutil.copy(kitti06 / "kitti06-12-R-color.png", root / "image_3" / "000000.png")
    shutil.copy(kitti06 / "calib.txt", root / "calib.txt")
    return root


@pytest.mark.needs_data
def test_reader_on_standard_layout(kitti06: Path, tmp_path: Path, real_depth: tuple[np.ndarray, float, float]) -> None:
    root = _standard_layout(kitti06, tmp_path / "sequences" / "06")
    ds = KittiDataset(root)
    assert len(ds) == 1 and ds.rate_hz == 10.0 and not ds.has_groundtruth
    frame = ds[0]
    assert frame.stamp == 0.0 and frame.gt_pose is None
    assert frame.rgb.shape == (370, 1226, 3) and frame.rgb.dtype == np.uint8
    np.testing.assert_array_equal(frame.rgb, read_rgb(kitti06 / "kitti06-12-color.png"))
    assert frame.depth.dtype == np.uint16 and frame.depth_scale == 0.001
    k = frame.intrinsics
    assert (k.fx, k.cx, k.cy, k.width, k.height) == (707.0912, 601.8873, 183.1104, 1226, 370)
    expected = depth_to_u16(real_depth[0], 0.001)
    np.testing.assert_array_equal(frame.depth, expected)

    # times.txt and the odometry benchmark's poses/<seq>.txt next to sequences/
    (root / "times.txt").write_text("1.036\n1.140\n")
    (tmp_path / "poses").mkdir()
    (tmp_path / "poses" / "06.txt").write_text("1 0 0 5 0 1 0 0 0 0 1 2\n")
    ds = KittiDataset(root)
    assert ds[0].stamp == pytest.approx(1.036) and ds.has_groundtruth
    pose = ds[0].gt_pose
    assert pose is not None
    # camera 2 sits ~6 cm left of camera 0 (KITTI poses are camera 0's)
    np.testing.assert_allclose(pose[:3, 3], [5 - 46.88783 / 707.0912, 0.0, 2.0], atol=0.01)
    assert len(ds.groundtruth()) == 1


def test_bad_kitti_folders(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="calib.txt and image_2"):
        KittiDataset(tmp_path)
    (tmp_path / "image_2").mkdir()
    (tmp_path / "calib.txt").write_text(CALIB_04_12)
    with pytest.raises(DatasetError, match="image_3"):
        KittiDataset(tmp_path)
    (tmp_path / "image_3").mkdir()
    with pytest.raises(DatasetError, match="no NNNNNN.png"):
        KittiDataset(tmp_path)
    image = np.zeros((40, 64, 3), np.uint8)
    assert cv2.imwrite(str(tmp_path / "image_2" / "000000.png"), image)
    ds = KittiDataset(tmp_path)
    with pytest.raises(DatasetError, match="colour image missing"):
        ds[0]
