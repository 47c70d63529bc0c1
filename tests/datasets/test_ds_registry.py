"""open_dataset: layout auto-detection, forced readers, options, and the error for anything else."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from semmap.datasets import (
    DatasetError,
    available_formats,
    detect_format,
    find_data_root,
    open_dataset,
)
from semmap.datasets.kitti import KittiDataset
from semmap.datasets.sevenscenes import SevenScenesDataset
from semmap.datasets.tum import TumDataset


def _tiny_tum(root: Path) -> Path:
    root.mkdir()
    assert cv2.imwrite(str(root / "c.png"), np.zeros((24, 32, 3), np.uint8))
    assert cv2.imwrite(str(root / "d.png"), np.zeros((24, 32), np.uint16))
    (root / "rgb.txt").write_text("1.00 c.png\n")
    (root / "depth.txt").write_text("1.01 d.png\n")
    return root


def _tiny_kitti(root: Path) -> Path:
    (root / "image_2").mkdir(parents=True)
    (root / "image_3").mkdir()
    for side in ("image_2", "image_3"):
        assert cv2.imwrite(str(root / side / "000000.png"), np.zeros((24, 64, 3), np.uint8))
    p2 = "700 0 32 0 0 700 12 0 0 0 1 0"
    p3 = "700 0 32 -378 0 700 12 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p2}\nP1: {p3}\nP2: {p2}\nP3: {p3}\n")
    return root


def _tiny_sevenscenes(root: Path) -> Path:
    root.mkdir()
    assert cv2.imwrite(str(root / "frame-000000.color.jpg"), np.zeros((24, 32, 3), np.uint8))
    assert cv2.imwrite(str(root / "frame-000000.depth.png"), np.zeros((24, 32), np.uint16))
    (root / "camera-intrinsics.txt").write_text("585 0 16\n0 585 12\n0 0 1\n")
    return root


def test_detects_each_layout(tmp_path: Path) -> None:
    tum, kitti, seven = _tiny_tum(tmp_path / "tum"), _tiny_kitti(tmp_path / "kitti"), _tiny_sevenscenes(tmp_path / "7s")
    assert (detect_format(tum), detect_format(kitti), detect_format(seven)) == ("tum", "kitti", "7scenes")
    assert isinstance(open_dataset(str(tum)), TumDataset)
    assert isinstance(open_dataset(kitti), KittiDataset)
    assert isinstance(open_dataset(seven), SevenScenesDataset)
    assert isinstance(open_dataset(f"tum:{tum}"), TumDataset)  # forced reader
    ds = open_dataset(kitti, depth_scale=0.01)  # keyword options reach the reader
    assert ds[0].depth_scale == 0.01
    assert set(available_formats()) >= {"synthetic", "7scenes", "tum", "kitti"}


def test_unknown_layout_lists_supported_ones(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("not a dataset")
    with pytest.raises(DatasetError) as info:
        open_dataset(str(tmp_path))
    message = str(info.value)
    assert "matches no known layout" in message
    for layout in ("synthetic", "7-Scenes", "TUM RGB-D", "KITTI"):
        assert layout in message
    with pytest.raises(DatasetError, match="does not exist"):
        open_dataset(str(tmp_path / "nope"))
    with pytest.raises(DatasetError, match="does not exist"):
        open_dataset(f"kitti:{tmp_path / 'nope'}")
    with pytest.raises(DatasetError, match="not a KITTI odometry folder"):
        open_dataset(f"kitti:{tmp_path}")  # forcing the wrong reader fails in that reader, clearly
    with pytest.raises(DatasetError, match="bad options"):
        open_dataset(_tiny_tum(tmp_path / "tum"), no_such_option=1)
    assert issubclass(DatasetError, ValueError)


def test_synthetic_specs() -> None:
    ds = open_dataset("synthetic:frames=5,seed=3,depth_noise=0")
    assert type(ds).__name__ == "SyntheticDataset"
    assert len(ds) == 5 and ds.config.seed == 3 and ds.config.depth_noise == 0.0  # type: ignore[attr-defined]
    ds = open_dataset("synthetic:frames=4", seed=9, size="320x240")
    assert ds.config.seed == 9 and ds.intrinsics.width == 320  # type: ignore[attr-defined]
    assert len(open_dataset("synthetic")) == 300
    with pytest.raises(DatasetError, match="unknown option 'colour'.*valid options: size, frames, seed"):
        open_dataset("synthetic:colour=red")
    with pytest.raises(DatasetError, match="expected key=value"):
        open_dataset("synthetic:frames")
    with pytest.raises(DatasetError, match="bad value for frames"):
        open_dataset("synthetic:frames=many")


def test_find_data_root(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("SEMMAP_DATA", str(tmp_path))
    assert find_data_root() == tmp_path
    monkeypatch.setenv("SEMMAP_DATA", str(tmp_path / "missing"))
    assert find_data_root() is None
    monkeypatch.delenv("SEMMAP_DATA")
    default = Path(__file__).resolve().parents[2].parent / "shared" / "data"
    assert find_data_root() == (default if default.is_dir() else None)


@pytest.mark.needs_data
def test_real_folders_by_path_and_by_name(data_root: Path) -> None:
    if not (data_root / "7scenes-redkitchen").is_dir():
        pytest.skip("no 7scenes-redkitchen/")
    assert detect_format(data_root / "7scenes-redkitchen") == "7scenes"
    ds = open_dataset(str(data_root / "7scenes-redkitchen"))
    assert isinstance(ds, SevenScenesDataset) and len(ds) == 1000
    assert len(open_dataset("7scenes-redkitchen")) == 1000  # a bare name resolves under the data root
    assert detect_format(data_root / "images" / "kitti06") is None  # not the standard layout
