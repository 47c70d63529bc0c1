"""KITTI odometry stereo reader: colour pair image_2/image_3 + calib.txt, depth from semi-global matching.

KITTI has no depth camera, so each frame's depth image is computed from the rectified colour pair
(OpenCV StereoSGBM) and handed on as uint16 millimetres like the RGB-D datasets; points beyond what
uint16 mm can hold (65.5 m) are marked invalid rather than clamped to a wrong depth.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from .base import Dataset, DatasetError, FrameData, Intrinsics
from .images import read_rgb
from .trajectory_io import read_kitti_poses, read_timestamps

_IMAGE_RE = re.compile(r"^(\d+)\.png$")


def is_kitti_dir(path: Path) -> bool:
    return path.is_dir() and (path / "calib.txt").is_file() and (path / "image_2").is_dir()


def read_calib(path: str | Path) -> dict[str, np.ndarray]:
    """KITTI calib.txt as {name: 3x4 projection} (P0..P3, Tr when present)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"cannot read KITTI calibration {path}: {exc}") from exc
    calib: dict[str, np.ndarray] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        if ":" not in line:
            continue
        key, values = line.split(":", 1)
        try:
            numbers = np.array(values.split(), dtype=float)
        except ValueError as exc:
            raise DatasetError(f"{path}:{number}: bad calibration numbers: {exc}") from exc
        if numbers.size == 12:
            calib[key.strip()] = numbers.reshape(3, 4)
    for key in ("P2", "P3"):
        if key not in calib:
            raise DatasetError(f"{path} has no {key} (the colour stereo projection matrices)")
    return calib


def stereo_baseline(p_left: np.ndarray, p_right: np.ndarray) -> float:
    """Baseline in metres of a rectified pair from its projections: (P_l[0,3] - P_r[0,3]) / fx (0.54 m on KITTI)."""
    return float((p_left[0, 3] - p_right[0, 3]) / p_left[0, 0])


def stereo_depth(
    left_rgb: np.ndarray,
    right_rgb: np.ndarray,
    fx: float,
    baseline: float,
    *,
    num_disparities: int = 128,
    block_size: int = 5,
) -> np.ndarray:
    """Metric depth (HxW float32, 0 = invalid) of the left image of a rectified pair, by OpenCV SGBM.

    KITTI-style settings: 128 disparities (closest valid depth fx*B/128, ~3 m on KITTI), 5 px blocks,
    3-way SGBM (about twice as fast as full SGBM at the same accuracy here), uniqueness and speckle
    filtering to drop unreliable matches. depth = fx * baseline / disparity; disparity <= 0 is invalid.
    """
    if left_rgb.shape != right_rgb.shape or left_rgb.ndim not in (2, 3):
        raise ValueError(f"stereo images must have the same HxW[x3] shape: {left_rgb.shape} vs {right_rgb.shape}")
    if fx <= 0 or baseline <= 0:
        raise ValueError(f"fx and baseline must be positive, got fx={fx}, baseline={baseline}")
    num_disparities = max(16, int(np.ceil(num_disparities / 16)) * 16)
    # OpenCV fails with a bogus huge allocation when the search range does not fit the image: shrink it.
    num_disparities = min(num_disparities, (left_rgb.shape[1] - block_size) // 16 * 16)
    if num_disparities < 16:
        raise ValueError(f"image {left_rgb.shape[1]} px wide is too narrow for stereo matching")
    left = cv2.cvtColor(left_rgb, cv2.COLOR_RGB2GRAY) if left_rgb.ndim == 3 else left_rgb
    right = cv2.cvtColor(right_rgb, cv2.COLOR_RGB2GRAY) if right_rgb.ndim == 3 else right_rgb
    matcher = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=num_disparities,
        blockSize=block_size,
        P1=8 * block_size * block_size,
        P2=32 * block_size * block_size,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        preFilterCap=63,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    disparity = matcher.compute(left, right).astype(np.float32) / 16.0  # SGBM returns fixed-point 1/16 px
    depth = np.zeros(disparity.shape, dtype=np.float32)
    valid = disparity > 0
    depth[valid] = np.float32(fx * baseline) / disparity[valid]
    return depth


def depth_to_u16(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """float metres -> uint16 units of depth_scale; non-finite, <= 0 or unrepresentable depths become 0."""
    units = np.rint(np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0) / depth_scale)
    units[(units < 0) | (units > 65535)] = 0
    return units.astype(np.uint16)


class KittiDataset(Dataset):
    """One KITTI odometry sequence folder (image_2, image_3, calib.txt, optional times.txt and poses).

    Frames are the left colour camera (camera 2). Ground truth, when a pose file is found, is converted
    from KITTI's camera-0 poses to camera 2 (it sits P2[0,3]/fx = 6 cm to the side of camera 0).
    """

    name = "kitti"
    platform = "vehicle"
    rate_hz = 10.0

    def __init__(
        self,
        root: str | Path,
        depth_scale: float = 0.001,
        num_disparities: int = 128,
        block_size: int = 5,
        poses: str | Path | None = None,
    ) -> None:
        self.root = Path(root)
        if not is_kitti_dir(self.root):
            raise DatasetError(f"not a KITTI odometry folder (needs calib.txt and image_2/): {self.root}")
        if (self.root / "image_3").is_dir() is False:
            raise DatasetError(f"KITTI folder has no image_3/ (right colour camera): {self.root}")
        self.name = f"kitti/{self.root.name}"
        self.depth_scale = float(depth_scale)
        self.num_disparities = int(num_disparities)
        self.block_size = int(block_size)
        numbers = sorted(int(m.group(1)) for p in (self.root / "image_2").iterdir() if (m := _IMAGE_RE.match(p.name)))
        if not numbers:
            raise DatasetError(f"no NNNNNN.png images in {self.root / 'image_2'}")
        self._names = [f"{n:06d}.png" for n in numbers]

        calib = read_calib(self.root / "calib.txt")
        p2, p3 = calib["P2"], calib["P3"]
        self.baseline = stereo_baseline(p2, p3)
        if self.baseline <= 0:
            raise DatasetError(f"non-positive stereo baseline {self.baseline} from P2/P3 in {self.root}")
        first = read_rgb(self.root / "image_2" / self._names[0])
        self.intrinsics = Intrinsics(
            fx=float(p2[0, 0]),
            fy=float(p2[1, 1]),
            cx=float(p2[0, 2]),
            cy=float(p2[1, 2]),
            width=int(first.shape[1]),
            height=int(first.shape[0]),
        )
        # camera 2 expressed in camera 0: P2 = K [I | t], a point X0 maps to X2 = X0 + t.
        t2 = np.linalg.solve(p2[:, :3], p2[:, 3])
        self._cam0_to_cam2 = np.eye(4)
        self._cam0_to_cam2[:3, 3] = -t2  # pose of camera 2 in camera-0 coordinates

        times_path = self.root / "times.txt"
        if times_path.is_file():
            times = read_timestamps(times_path)
            if len(times) < numbers[-1] + 1:
                raise DatasetError(f"{times_path} has {len(times)} stamps but images go up to {numbers[-1]}")
            self._stamps = [times[n] for n in numbers]
        else:
            self._stamps = [n / self.rate_hz for n in numbers]

        self._poses: list[np.ndarray] | None = None
        pose_path = Path(poses) if poses is not None else self._find_poses()
        if pose_path is not None:
            cam0 = read_kitti_poses(pose_path)
            if len(cam0) < numbers[-1] + 1:
                raise DatasetError(f"{pose_path} has {len(cam0)} poses but images go up to {numbers[-1]}")
            self._poses = [cam0[n] @ self._cam0_to_cam2 for n in numbers]

    def _find_poses(self) -> Path | None:
        for candidate in (self.root / "poses.txt", self.root.parent.parent / "poses" / f"{self.root.name}.txt"):
            if candidate.is_file():
                return candidate
        return None

    def stamps(self) -> list[float]:
        return list(self._stamps)

    def __len__(self) -> int:
        return len(self._names)

    def stereo_pair(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) RGB images of a frame."""
        left = read_rgb(self.root / "image_2" / self._names[index])
        right = read_rgb(self.root / "image_3" / self._names[index])
        if left.shape != right.shape:
            raise DatasetError(f"{self._names[index]}: left {left.shape} and right {right.shape} sizes differ")
        return left, right

    def __getitem__(self, index: int) -> FrameData:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range 0..{len(self) - 1}")
        index %= len(self)
        left, right = self.stereo_pair(index)
        depth_m = stereo_depth(
            left,
            right,
            self.intrinsics.fx,
            self.baseline,
            num_disparities=self.num_disparities,
            block_size=self.block_size,
        )
        return FrameData(
            index=index,
            stamp=self._stamps[index],
            rgb=left,
            depth=depth_to_u16(depth_m, self.depth_scale),
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            gt_pose=None if self._poses is None else self._poses[index].copy(),
        )

    @property
    def has_groundtruth(self) -> bool:
        return self._poses is not None

    def groundtruth(self) -> list[tuple[float, np.ndarray]]:
        if self._poses is None:
            return []
        return [(s, p.copy()) for s, p in zip(self._stamps, self._poses, strict=True)]
