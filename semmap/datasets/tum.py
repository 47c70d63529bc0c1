"""TUM RGB-D reader: rgb.txt / depth.txt / groundtruth.txt lists, associated by nearest stamp.

The TUM streams are not synchronised, so frames are the rgb images that have a depth image within
`max_difference` seconds, matched greedily by smallest time difference exactly like TUM's associate.py;
ground truth (100 Hz mocap) is matched to each rgb stamp the same way. A frame without a ground-truth sample
that close (mocap has gaps: Bonn "crowd" has 67 ms at frame 160) gets a pose interpolated in SE(3) between the
samples either side of it when they are at most `gt_max_gap_s` apart (slerp on rotation, linear on
translation); only a frame in a longer gap gets None.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

from semmap.core.geometry import interpolate_pose

from .base import Dataset, DatasetError, FrameData, Intrinsics
from .calibration import CameraSource
from .images import image_size, read_depth_file, read_rgb_file
from .trajectory_io import read_tum

# Published TUM calibrations (fx, fy, cx, cy) of the colour camera; depth is registered to it.
TUM_INTRINSICS: dict[str, tuple[float, float, float, float]] = {
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
    "default": (525.0, 525.0, 319.5, 239.5),  # the "ROS default" TUM recommends when in doubt
}
DEPTH_FACTOR = 5000.0  # TUM depth PNG units per metre
_FREIBURG_RE = re.compile(r"(?:freiburg|fr)([123])(?![0-9])", re.IGNORECASE)


def is_tum_dir(path: Path) -> bool:
    return path.is_dir() and (path / "rgb.txt").is_file() and (path / "depth.txt").is_file()


def read_file_list(path: Path) -> list[tuple[float, list[str]]]:
    """(stamp, remaining fields) of every data line of a TUM list file, sorted by stamp."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"cannot read TUM list {path}: {exc}") from exc
    entries: list[tuple[float, list[str]]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        try:
            entries.append((float(fields[0]), fields[1:]))
        except ValueError as exc:
            raise DatasetError(f"{path}:{number}: bad timestamp {fields[0]!r}") from exc
    entries.sort(key=lambda e: e[0])
    return entries


def associate(
    first: Sequence[float], second: Sequence[float], max_difference: float = 0.02, offset: float = 0.0
) -> list[tuple[int, int]]:
    """Index pairs (i, j) with |first[i] - (second[j] + offset)| < max_difference, one-to-one.

    Same result as TUM's associate.py (all candidate pairs, closest first, each stamp used once) but
    only pairs inside the window are generated, so long sequences stay fast. Returned sorted by i.
    """
    a = np.asarray(first, dtype=float)
    b = np.asarray(second, dtype=float) + offset
    order = np.argsort(b, kind="stable")
    b_sorted = b[order]
    lo = np.searchsorted(b_sorted, a - max_difference, side="left")
    hi = np.searchsorted(b_sorted, a + max_difference, side="right")
    candidates: list[tuple[float, int, int]] = []
    for i in range(len(a)):
        for k in range(lo[i], hi[i]):
            diff = abs(a[i] - b_sorted[k])
            if diff < max_difference:
                candidates.append((diff, i, int(order[k])))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    matches: list[tuple[int, int]] = []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            matches.append((i, j))
    matches.sort()
    return matches


def _intrinsics_override(root: Path) -> tuple[tuple[float, float, float, float], float | None] | None:
    """(fx, fy, cx, cy) and an optional depth factor from camera.yaml or intrinsics.txt, if present.

    camera.yaml: fx/fy/cx/cy (+ depth_factor) at top level or under `camera:`/`intrinsics:`, or ORB-SLAM
    style `Camera.fx` keys (its `%YAML:1.0` header is skipped). intrinsics.txt: "fx fy cx cy" or a 3x3 K.
    """
    yaml_path = root / "camera.yaml"
    if yaml_path.is_file():
        try:
            text = "\n".join(ln for ln in yaml_path.read_text().splitlines() if not ln.startswith("%YAML"))
            data = yaml.safe_load(text) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise DatasetError(f"cannot parse {yaml_path}: {exc}") from exc
        if not isinstance(data, dict):
            raise DatasetError(f"{yaml_path} must hold a mapping with fx, fy, cx, cy")
        for key in ("camera", "intrinsics", "Camera"):
            if isinstance(data.get(key), dict):
                data = {**data, **data[key]}
        flat = {str(k).removeprefix("Camera."): v for k, v in data.items()}
        try:
            fx, fy, cx, cy = (float(flat[k]) for k in ("fx", "fy", "cx", "cy"))
            factor = flat.get("depth_factor", flat.get("DepthMapFactor"))
            return (fx, fy, cx, cy), (float(factor) if factor is not None else None)
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetError(f"{yaml_path} needs numeric fx, fy, cx, cy: {exc}") from exc
    txt_path = root / "intrinsics.txt"
    if txt_path.is_file():
        try:
            numbers = np.array(txt_path.read_text().replace(",", " ").split(), dtype=float)
        except (OSError, ValueError) as exc:
            raise DatasetError(f"cannot parse {txt_path}: {exc}") from exc
        if numbers.size == 4:
            return (float(numbers[0]), float(numbers[1]), float(numbers[2]), float(numbers[3])), None
        if numbers.size == 9:
            k = numbers.reshape(3, 3)
            return (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])), None
        raise DatasetError(f"{txt_path} must hold 'fx fy cx cy' or a 3x3 K, got {numbers.size} numbers")
    return None


def _declared_size(yaml_path: Path) -> tuple[int, int] | None:
    """(width, height) where camera.yaml states them (`width`/`height`, `Camera.width`/`Camera.height`,
    `image_width`/`image_height`), else None."""
    try:
        text = "\n".join(ln for ln in yaml_path.read_text().splitlines() if not ln.startswith("%YAML"))
        data = yaml.safe_load(text) or {}
    except (OSError, yaml.YAMLError):
        return None
    if not isinstance(data, dict):
        return None
    for key in ("camera", "intrinsics", "Camera"):
        if isinstance(data.get(key), dict):
            data = {**data, **data[key]}
    flat = {str(k).removeprefix("Camera.").removeprefix("Camera1."): v for k, v in data.items()}
    for w_key, h_key in (("width", "height"), ("image_width", "image_height")):
        try:
            return int(flat[w_key]), int(flat[h_key])
        except (KeyError, TypeError, ValueError):
            continue
    return None


def tum_camera_name(root: Path) -> str:
    """'fr1' / 'fr2' / 'fr3' from the folder name (rgbd_dataset_freiburg2_desk -> fr2), else 'default'."""
    match = _FREIBURG_RE.search(root.resolve().name)
    return f"fr{match.group(1)}" if match else "default"


def interpolate_missing(stamps: Sequence[float], poses: list[np.ndarray | None],
                        gt: list[tuple[float, np.ndarray]], max_gap_s: float) -> int:
    """Fill `poses[i] is None` in place from the ground-truth samples either side of `stamps[i]` when those are
    at most `max_gap_s` apart; returns how many were filled (the rest have no pose within reach)."""
    if not gt:
        return 0
    gt_stamps = np.array([t for t, _ in gt])
    filled = 0
    for i, pose in enumerate(poses):
        if pose is not None:
            continue
        k = int(np.searchsorted(gt_stamps, stamps[i]))
        if k == 0 or k >= len(gt):  # before the first or after the last sample: no neighbour on one side
            continue
        t0, t1 = gt_stamps[k - 1], gt_stamps[k]
        if t1 - t0 > max_gap_s or t1 <= t0:
            continue
        poses[i] = interpolate_pose(gt[k - 1][1], gt[k][1], float((stamps[i] - t0) / (t1 - t0)))
        filled += 1
    return filled


class TumDataset(Dataset):
    """One TUM RGB-D sequence folder; depth in 1/5000 m units (scale 0.0002)."""

    name = "tum"
    rate_hz = 30.0

    def __init__(self, root: str | Path, max_difference: float = 0.02, gt_max_gap_s: float = 0.1) -> None:
        self.root = Path(root)
        if not is_tum_dir(self.root):
            raise DatasetError(f"not a TUM RGB-D folder (needs rgb.txt and depth.txt): {self.root}")
        self.name = f"tum/{self.root.name}"
        self.max_difference = float(max_difference)
        self.gt_max_gap_s = float(gt_max_gap_s)
        if not self.gt_max_gap_s >= 0:
            raise DatasetError(f"gt_max_gap_s must be >= 0, got {gt_max_gap_s}")
        rgb_list = read_file_list(self.root / "rgb.txt")
        depth_list = read_file_list(self.root / "depth.txt")
        if not rgb_list:
            raise DatasetError(f"{self.root / 'rgb.txt'} lists no images")
        for path, entries in (("rgb.txt", rgb_list), ("depth.txt", depth_list)):
            if any(not fields for _, fields in entries):
                raise DatasetError(f"{self.root / path}: every line needs 'stamp filename'")
        pairs = associate([s for s, _ in rgb_list], [s for s, _ in depth_list], self.max_difference)
        if not pairs:
            raise DatasetError(
                f"no rgb/depth pairs within {self.max_difference} s in {self.root} (check the timestamps)"
            )
        self._stamps = [rgb_list[i][0] for i, _ in pairs]
        self._rgb_files = [rgb_list[i][1][0] for i, _ in pairs]
        self._depth_files = [depth_list[j][1][0] for _, j in pairs]

        self._poses: list[np.ndarray | None] = [None] * len(pairs)
        gt_path = self.root / "groundtruth.txt"
        self._reference: list[tuple[float, np.ndarray]] = []
        if gt_path.is_file():
            gt = read_tum(gt_path)
            lo, hi = self._stamps[0] - 0.1, self._stamps[-1] + 0.1
            self._reference = [(t, pose) for t, pose in gt if lo <= t <= hi]
            for i, j in associate(self._stamps, [s for s, _ in gt], self.max_difference):
                self._poses[i] = gt[j][1]
            self.interpolated = interpolate_missing(self._stamps, self._poses, gt, self.gt_max_gap_s)
        else:
            self.interpolated = 0

        override = _intrinsics_override(self.root)
        if override is not None:
            (fx, fy, cx, cy), factor = override
            self.camera_name = "file"
        else:
            self.camera_name = tum_camera_name(self.root)
            fx, fy, cx, cy = TUM_INTRINSICS[self.camera_name]
            factor = None
        self._depth_factor_given = factor is not None
        self.depth_scale = 1.0 / (factor or DEPTH_FACTOR)
        width, height = image_size(self.root / self._rgb_files[0])
        self.intrinsics = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)

    def camera_source(self) -> CameraSource:
        """Which file gave the intrinsics and the depth factor (camera.yaml, intrinsics.txt, or the built-in
        Freiburg calibration and TUM's 5000 units per metre)."""
        yaml_path, txt_path = self.root / "camera.yaml", self.root / "intrinsics.txt"
        if yaml_path.is_file():
            where, keys, size = str(yaml_path), "cx, cy", _declared_size(yaml_path)
        elif txt_path.is_file():
            where, keys, size = str(txt_path), "its cx, cy", None
        else:
            where = f"built-in default (TUM {self.camera_name} calibration, from the folder name)"
            keys, size = "cx, cy", None
        if self._depth_factor_given:
            depth_from, depth_key = f"{yaml_path}, key depth_factor", "depth_factor"
        else:
            depth_from = f"built-in TUM depth factor {DEPTH_FACTOR:g} (no depth_factor in {yaml_path.name})"
            depth_key = f"depth_factor (in {yaml_path})"
        return CameraSource(intrinsics_from=where, depth_from=depth_from, intrinsics_keys=keys, depth_key=depth_key,
                            declared_size=size, check_depth=True)

    def __len__(self) -> int:
        return len(self._stamps)

    def stamps(self) -> list[float]:
        return list(self._stamps)

    def __getitem__(self, index: int) -> FrameData:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range 0..{len(self) - 1}")
        index %= len(self)
        rgb = read_rgb_file(self.root / self._rgb_files[index])  # kept encoded until needed (and sent so)
        depth = read_depth_file(self.root / self._depth_files[index])
        if depth.size != rgb.size:
            raise DatasetError(
                f"depth {self._depth_files[index]} {depth.size[::-1]} and colour {rgb.size[::-1]} sizes differ"
            )
        pose = self._poses[index]
        return FrameData(
            index=index,
            stamp=self._stamps[index],
            rgb=rgb,
            depth=depth,
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            gt_pose=None if pose is None else pose.copy(),
        )

    @property
    def has_groundtruth(self) -> bool:
        return any(p is not None for p in self._poses)

    def groundtruth(self) -> list[tuple[float, np.ndarray]]:
        return [(s, p.copy()) for s, p in zip(self._stamps, self._poses, strict=True) if p is not None]

    def reference_trajectory(self) -> list[tuple[float, np.ndarray]]:
        return [(t, p.copy()) for t, p in self._reference] if self._reference else self.groundtruth()

    def files(self, index: int) -> tuple[str, str]:
        """(rgb, depth) file names of a frame, relative to the folder (for checking the association)."""
        return self._rgb_files[index], self._depth_files[index]
