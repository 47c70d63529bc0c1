"""The one interface every data source implements, so the player never cares where frames come from."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from semmap.core.messages import Intrinsics


class DatasetError(ValueError):
    """A dataset that cannot be opened or read: a wrong layout, a missing or corrupt file, a bad option.

    A ValueError so callers that already catch bad input keep working; raised instead of cv2/numpy
    assertions so the user sees which file is at fault.
    """


@dataclass(frozen=True)
class InstanceBox:
    """A ground-truth object instance visible in a frame (synthetic data only): what an oracle detector sees."""

    instance_id: int
    class_name: str
    box: tuple[float, float, float, float]  # x1, y1, x2, y2 in pixels
    visible_pixels: int
    moving: bool = False


@dataclass(frozen=True)
class EncodedImage:
    """An image as its file holds it, decoded only when its pixels are asked for.

    Why: a JPEG colour image and a 16-bit PNG depth image can travel on the bus exactly as stored, so the player
    need not decode each frame and re-encode it for the wire (on 7-Scenes that was ~6.5 ms of a 2-core machine's
    CPU per frame, and the raw depth made every frame 690 KB instead of 130 KB for each subscriber).
    `fmt` says which: "jpeg" (colour), "png16" (single-channel 16-bit depth), "other" (decoded before sending).
    `decoder` turns `data` into the array, raising DatasetError (with the file's name) if it cannot."""

    data: bytes
    fmt: str
    size: tuple[int, int]  # (width, height) from the file's header
    decoder: Callable[[], np.ndarray]

    def decode(self) -> np.ndarray:
        return self.decoder()


class FrameData:
    """One RGB-D frame as the rest of the system sees it.

    depth is uint16 with `depth_scale` metres per unit (7-Scenes and TUM: millimetres / 5000ths; 0 = invalid).
    gt_pose is the 4x4 camera-to-world ground truth, or None where the dataset has none.
    `rgb` and `depth` may be given as arrays or as `EncodedImage`s (a file's bytes): those are decoded the first
    time `.rgb` / `.depth` is read, and `rgb_file` / `depth_file` keep the bytes for whoever can use them as they
    are (`semmap.runtime.pipeline.stages.frame_message`).
    """

    __slots__ = ("index", "stamp", "_rgb", "_depth", "rgb_file", "depth_file", "depth_scale", "intrinsics",
                 "gt_pose", "instances")

    def __init__(self, index: int, stamp: float, rgb: np.ndarray | EncodedImage, depth: np.ndarray | EncodedImage,
                 depth_scale: float, intrinsics: Intrinsics, gt_pose: np.ndarray | None = None,
                 instances: list[InstanceBox] | None = None) -> None:
        self.index = index
        self.stamp = stamp
        self.rgb_file = rgb if isinstance(rgb, EncodedImage) else None
        self.depth_file = depth if isinstance(depth, EncodedImage) else None
        self._rgb = None if self.rgb_file is not None else rgb
        self._depth = None if self.depth_file is not None else depth
        self.depth_scale = depth_scale
        self.intrinsics = intrinsics
        self.gt_pose = gt_pose
        self.instances = list(instances or [])

    @property
    def rgb(self) -> np.ndarray:
        """HxWx3 uint8, RGB order (decoded from the file on first use)."""
        if self._rgb is None:
            self._rgb = self.rgb_file.decode()
        return self._rgb

    @rgb.setter
    def rgb(self, value: np.ndarray) -> None:  # new pixels: the file's bytes no longer describe them
        self._rgb, self.rgb_file = value, None

    @property
    def depth(self) -> np.ndarray:
        """HxW uint16, 0 = invalid (decoded from the file on first use)."""
        if self._depth is None:
            self._depth = self.depth_file.decode()
        return self._depth

    @depth.setter
    def depth(self, value: np.ndarray) -> None:
        self._depth, self.depth_file = value, None


@dataclass(frozen=True)
class ObjectTruth:
    """Ground truth of one object in a synthetic scene (world frame, metres)."""

    instance_id: int
    class_name: str
    centroid: tuple[float, float, float]
    extent: tuple[float, float, float]
    moving: bool


class Dataset(ABC):
    """A finite, indexable sequence of RGB-D frames with a nominal rate."""

    name: str = "dataset"
    rate_hz: float = 30.0
    # what carries the camera: "handheld" (a person: turns a lot, moves little) or "vehicle" (a car: metres a
    # frame); the simulated drift of `gt+drift` follows it (odometry.drift_profile auto)
    platform: str = "handheld"

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def __getitem__(self, index: int) -> FrameData: ...

    @property
    def has_groundtruth(self) -> bool:
        return False

    def stamps(self) -> list[float]:
        """Every frame's stamp (s), in frame order; readers override this to avoid decoding images."""
        return [self[i].stamp for i in range(len(self))]

    def groundtruth(self) -> list[tuple[float, np.ndarray]]:
        """(stamp, 4x4 camera-to-world) for every frame that has ground truth; empty where there is none."""
        return []

    def objects(self) -> list[ObjectTruth]:
        """Ground-truth objects (synthetic scenes only)."""
        return []

    def reference_trajectory(self) -> list[tuple[float, np.ndarray]]:
        """The ground truth to score a run against, as the dataset's own file holds it (a TUM folder's 100 Hz
        mocap samples over the frames' time span), so `semmap eval` associates stamps as evo does against that
        file; where the frames carry the ground truth themselves (7-Scenes, synthetic), `groundtruth()`."""
        return self.groundtruth()

    def __iter__(self) -> Iterator[FrameData]:
        for i in range(len(self)):
            yield self[i]


class WindowDataset(Dataset):
    """Frames [start, start + count) of another dataset, renumbered from 0 (stamps and poses unchanged): a
    later session of the same recording (`run.start_frame`), e.g. 7-Scenes frames 500-999 as a second day."""

    def __init__(self, inner: Dataset, start: int, count: int | None = None) -> None:
        if not 0 <= start < len(inner):
            raise DatasetError(f"start frame {start} outside the dataset's {len(inner)} frames")
        self.inner, self.start = inner, start
        self.count = len(inner) - start if count is None else max(0, min(count, len(inner) - start))
        self.name = f"{inner.name}[{start}:{start + self.count}]"
        self.rate_hz = inner.rate_hz

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int) -> FrameData:
        if not 0 <= index < self.count:
            raise IndexError(index)
        data = self.inner[self.start + index]
        data.index = index
        return data

    @property
    def has_groundtruth(self) -> bool:
        return self.inner.has_groundtruth

    def groundtruth(self) -> list[tuple[float, np.ndarray]]:
        gt = self.inner.groundtruth()
        if len(gt) != len(self.inner):  # not one pose per frame: keep those within the window's stamps
            stamps = self.inner.stamps()  # (not the frames: one of them may be unreadable)
            lo, hi = stamps[self.start], stamps[self.start + self.count - 1]
            return [(t, p) for t, p in gt if lo <= t <= hi]
        return gt[self.start : self.start + self.count]

    def objects(self) -> list[ObjectTruth]:
        return self.inner.objects()
