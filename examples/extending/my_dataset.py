"""A dataset layout (docs/EXTENDING.md): numbered colour and depth images beside a `camera.json`.

    python examples/extending/my_dataset.py         # registers it, writes a 3-frame recording, opens it by path

    my_recording/
      camera.json        {"fx": 525, "fy": 525, "cx": 319.5, "cy": 239.5, "depth_scale": 0.001, "rate_hz": 30}
      color/000000.jpg   colour, any size (all frames alike)
      depth/000000.png   16-bit depth registered to the colour image, `depth_scale` metres a unit, 0 = no reading
      poses.txt          optional ground truth: one KITTI line (12 numbers, camera-to-world 3x4) per frame

A reader is a `Dataset` (length, frames by index, optional ground truth) and a `detect(path)` that recognises the
layout, registered under a name: `semmap run my_recording/` then finds it, and `my-pairs:PATH` forces it.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from semmap.datasets import Dataset, DatasetError, FrameData, Intrinsics, open_dataset, register
from semmap.datasets.images import image_size, read_depth_file, read_rgb_file
from semmap.datasets.trajectory_io import read_kitti_poses

NAME = "my-pairs"


def is_my_pairs_dir(path: Path) -> bool:
    return (path / "camera.json").is_file() and (path / "color").is_dir() and (path / "depth").is_dir()


class PairsDataset(Dataset):
    name = NAME

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        try:
            camera = json.loads((self.root / "camera.json").read_text())
            fx, fy, cx, cy = (float(camera[k]) for k in ("fx", "fy", "cx", "cy"))
        except (OSError, ValueError, KeyError) as exc:  # DatasetError: the run names the file and stops
            raise DatasetError(f"{self.root / 'camera.json'}: {exc}") from exc
        self.depth_scale = float(camera.get("depth_scale", 0.001))
        self.rate_hz = float(camera.get("rate_hz", 30.0))
        self.stems = sorted(p.stem for p in (self.root / "color").glob("*.jpg"))
        if not self.stems:
            raise DatasetError(f"no color/*.jpg in {self.root}")
        width, height = image_size(self.root / "color" / f"{self.stems[0]}.jpg")
        self.intrinsics = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)
        poses = self.root / "poses.txt"
        self.poses = read_kitti_poses(poses) if poses.is_file() else None
        if self.poses is not None and len(self.poses) != len(self.stems):
            raise DatasetError(f"{poses}: {len(self.poses)} poses for {len(self.stems)} frames")

    def __len__(self) -> int:
        return len(self.stems)

    def __getitem__(self, index: int) -> FrameData:
        stem = self.stems[index]
        rgb = read_rgb_file(self.root / "color" / f"{stem}.jpg")  # kept encoded: sent as stored, decoded on use
        depth = read_depth_file(self.root / "depth" / f"{stem}.png")
        gt_pose = None if self.poses is None else self.poses[index]
        return FrameData(index, index / self.rate_hz, rgb, depth, self.depth_scale, self.intrinsics, gt_pose)

    @property
    def has_groundtruth(self) -> bool:
        return self.poses is not None

    def groundtruth(self) -> list[tuple[float, np.ndarray]]:
        return [] if self.poses is None else [(i / self.rate_hz, p.copy()) for i, p in enumerate(self.poses)]


def open_pairs(path: Path, **options: object) -> Dataset:
    return PairsDataset(path, **options)


register(NAME, open_pairs, "numbered pairs: camera.json, color/*.jpg, depth/*.png (+ poses.txt)", is_my_pairs_dir)


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "my_recording"
        (root / "color").mkdir(parents=True)
        (root / "depth").mkdir()
        (root / "camera.json").write_text(json.dumps({"fx": 100, "fy": 100, "cx": 80, "cy": 60}))
        lines = []
        for i in range(3):
            cv2.imwrite(str(root / "color" / f"{i:06d}.jpg"), np.full((120, 160, 3), 50 * i, np.uint8))
            cv2.imwrite(str(root / "depth" / f"{i:06d}.png"), np.full((120, 160), 1500, np.uint16))
            lines.append(f"1 0 0 {0.01 * i} 0 1 0 0 0 0 1 0")
        (root / "poses.txt").write_text("\n".join(lines) + "\n")
        dataset = open_dataset(root)  # found by its layout, as `semmap run my_recording/` finds it
        frame = dataset[2]
        print(dataset.name, len(dataset), frame.stamp, frame.rgb.shape, frame.depth[0, 0], frame.gt_pose[0, 3])
        assert isinstance(dataset, PairsDataset) and len(dataset) == 3 and dataset.has_groundtruth
        assert frame.depth[0, 0] == 1500 and frame.gt_pose[0, 3] == 0.02
    return 0


if __name__ == "__main__":
    sys.exit(main())
