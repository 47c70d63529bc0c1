"""The one interface every data source implements, so the player never cares where frames come from."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field

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


@dataclass
class FrameData:
    """One RGB-D frame as the rest of the system sees it.

    depth is uint16 with `depth_scale` metres per unit (7-Scenes and TUM: millimetres / 5000ths; 0 = invalid).
    gt_pose is the 4x4 camera-to-world ground truth, or None where the dataset has none.
    """

    index: int
    stamp: float
    rgb: np.ndarray  # HxWx3 uint8, RGB order
    depth: np.ndarray  # HxW uint16
    depth_scale: float
    intrinsics: Intrinsics  # (the one intrinsics type: semmap.core.messages)
    gt_pose: np.ndarray | None = None
    instances: list[InstanceBox] = field(default_factory=list)


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
