"""Microsoft 7-Scenes reader: one folder of frame-NNNNNN.{color.png,depth.png,pose.txt} per sequence.

The official download (redkitchen.zip -> seq-01.zip -> seq-01/) holds `frame-NNNNNN.color.png`; converted copies
(like ../shared/data/7scenes-redkitchen) may hold `.color.jpg`: both are read. The files carry no timestamps;
the Kinect ran at 30 Hz, so frame n is stamped n/30 s.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .base import Dataset, DatasetError, FrameData, Intrinsics
from .calibration import CameraSource
from .images import image_size, read_depth_file, read_rgb_file
from .trajectory_io import orthonormalize_pose

_FRAME_RE = re.compile(r"^frame-(\d+)\.color\.(?:jpg|png)$")
# The published 7-Scenes calibration, used when a folder has no camera-intrinsics.txt (the original zips have none).
DEFAULT_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


def is_sevenscenes_dir(path: Path) -> bool:
    """A folder with frame-*.color.png (official) or .color.jpg files (camera-intrinsics.txt optional)."""
    return path.is_dir() and any(_FRAME_RE.match(p.name) for p in path.glob("frame-*.color.*"))


def sequence_folders(path: Path) -> list[Path]:
    """The seq-NN/ folders of an unpacked 7-Scenes scene (redkitchen/seq-01, ...): one of them is a dataset."""
    return sorted(p for p in path.glob("seq-*") if is_sevenscenes_dir(p)) if path.is_dir() else []


def _read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    try:
        values = np.array(path.read_text().split(), dtype=float)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"cannot read {shape[0]}x{shape[1]} matrix from {path}: {exc}") from exc
    if values.size != shape[0] * shape[1]:
        raise DatasetError(f"expected {shape[0] * shape[1]} numbers in {path}, got {values.size}")
    if not np.all(np.isfinite(values)):
        bad = int(np.sum(~np.isfinite(values)))
        raise DatasetError(f"{bad} of the {values.size} numbers in {path} are not finite (nan or inf)")
    return values.reshape(shape)


class SevenScenesDataset(Dataset):
    """Frames of one 7-Scenes sequence folder, sorted by frame number; depth in mm (scale 0.001)."""

    name = "7scenes"
    rate_hz = 30.0
    depth_scale = 0.001

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"7-Scenes folder not found: {self.root}")
        frames: list[tuple[int, str]] = []
        for path in self.root.iterdir():
            match = _FRAME_RE.match(path.name)
            if match:
                frames.append((int(match.group(1)), path.name))
        if not frames:
            seqs = sequence_folders(self.root)
            hint = f" (a scene folder: run one sequence, e.g. {seqs[0]})" if seqs else ""
            raise DatasetError(f"no frame-NNNNNN.color.png/.jpg files in {self.root}{hint}")
        frames.sort()
        self._numbers = [n for n, _ in frames]
        self._color_names = [name for _, name in frames]
        self.name = f"7scenes/{self.root.name}"

        k_path = self.root / "camera-intrinsics.txt"
        self._k_file = k_path if k_path.exists() else None
        k = _read_matrix(k_path, (3, 3)) if k_path.exists() else DEFAULT_K
        width, height = image_size(self.root / self._color_names[0])
        self.intrinsics = Intrinsics(
            fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]), width=width, height=height
        )
        self._gt_cache: list[tuple[float, np.ndarray]] | None = None
        # frames whose pose file is unreadable (NaN, truncated): left out of the ground truth, named here
        self.groundtruth_skipped: list[tuple[int, str]] = []

    def camera_source(self) -> CameraSource:
        """Where the intrinsics come from (camera-intrinsics.txt or the published default); depth is always mm."""
        where = str(self._k_file) if self._k_file else "built-in default (the published 7-Scenes calibration)"
        return CameraSource(intrinsics_from=where, depth_from="7-Scenes depth PNGs are millimetres",
                            intrinsics_keys="K[0,2], K[1,2]" if self._k_file else "cx, cy", check_depth=True)

    def __len__(self) -> int:
        return len(self._numbers)

    def _stem(self, index: int) -> str:
        return f"frame-{self._numbers[index]:06d}"

    def stamp(self, index: int) -> float:
        return self._numbers[index] / self.rate_hz

    def stamps(self) -> list[float]:
        return [n / self.rate_hz for n in self._numbers]

    def _pose(self, index: int) -> np.ndarray | None:
        path = self.root / f"{self._stem(index)}.pose.txt"
        if not path.exists():
            return None
        pose = _read_matrix(path, (4, 4))
        return orthonormalize_pose(pose)

    def __getitem__(self, index: int) -> FrameData:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range 0..{len(self) - 1}")
        index %= len(self)
        stem = self._stem(index)
        rgb = read_rgb_file(self.root / self._color_names[index])  # kept encoded until needed (and sent so)
        depth = read_depth_file(self.root / f"{stem}.depth.png")  # 65535 (no reading) reads as 0
        if depth.size != rgb.size:
            raise DatasetError(f"{stem}: depth {depth.size[::-1]} and colour {rgb.size[::-1]} sizes differ in "
                               f"{self.root}")
        return FrameData(
            index=index,
            stamp=self.stamp(index),
            rgb=rgb,
            depth=depth,
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            gt_pose=self._pose(index),
        )

    @property
    def has_groundtruth(self) -> bool:
        return (self.root / f"{self._stem(0)}.pose.txt").exists()

    def groundtruth(self) -> list[tuple[float, np.ndarray]]:
        if self._gt_cache is None:
            result, skipped = [], []
            for i in range(len(self)):
                try:  # one bad pose file costs its frame (the player skips it too), not the whole ground truth
                    pose = self._pose(i)
                except DatasetError as exc:
                    skipped.append((i, str(exc)))
                    continue
                if pose is not None:
                    result.append((self.stamp(i), pose))
            self._gt_cache, self.groundtruth_skipped = result, skipped
        return [(stamp, pose.copy()) for stamp, pose in self._gt_cache]
