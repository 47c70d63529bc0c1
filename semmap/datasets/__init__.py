"""Data sources behind one interface, picked from a spec string so configs and the CLI just name a path.

`open_dataset("path/to/folder")` recognises the folder's layout; `open_dataset("synthetic:frames=600,seed=3")`
builds the synthetic scene; `open_dataset("tum:path")` forces a reader. New readers join via `register`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from semmap.core import environment
from semmap.core.config import Config

from .base import Dataset, DatasetError, FrameData, InstanceBox, Intrinsics, ObjectTruth
from .kitti import is_kitti_dir
from .rosbag import is_rosbag
from .sevenscenes import is_sevenscenes_dir
from .tum import is_tum_dir

__all__ = [
    "Intrinsics",
    "Dataset",
    "DatasetError",
    "FrameData",
    "InstanceBox",
    "ObjectTruth",
    "available_formats",
    "detect_format",
    "find_data_root",
    "open_dataset",
    "platform_of",
    "reader_options",
    "register",
]


@dataclass(frozen=True)
class _Format:
    name: str
    layout: str  # one line for error messages
    opener: Callable[..., Dataset]  # (path or None, **options) -> Dataset
    detect: Callable[[Path], bool] | None  # None: not file based (synthetic)


_REGISTRY: dict[str, _Format] = {}


def register(
    name: str, opener: Callable[..., Dataset], layout: str, detect: Callable[[Path], bool] | None = None
) -> None:
    """Add a reader; `detect(path)` makes open_dataset pick it for matching folders (checked in order)."""
    _REGISTRY[name] = _Format(name, layout, opener, detect)


def available_formats() -> dict[str, str]:
    """{format name: layout description} of every registered reader."""
    return {f.name: f.layout for f in _REGISTRY.values()}


def _open_synthetic(path: Path | None = None, **options: Any) -> Dataset:
    if "trajectory" in options:  # the street world along a trajectory file
        from .street import StreetDataset

        return StreetDataset(**options)
    from .synthetic import SyntheticDataset  # imports open3d (~1 s): only when asked for

    return SyntheticDataset(**options)


def _open_sevenscenes(path: Path, **options: Any) -> Dataset:
    from .sevenscenes import SevenScenesDataset

    return SevenScenesDataset(path, **options)


def _open_tum(path: Path, **options: Any) -> Dataset:
    from .tum import TumDataset

    return TumDataset(path, **options)


def _open_kitti(path: Path, **options: Any) -> Dataset:
    from .kitti import KittiDataset

    return KittiDataset(path, **options)


def _open_rosbag(path: Path, **options: Any) -> Dataset:
    from .rosbag import RosbagDataset

    return RosbagDataset(path, **options)


register(
    "synthetic",
    _open_synthetic,
    "synthetic[:frames=N,seed=S,size=WxH,...]: the built-in ray-cast scene (a dining room); "
    "synthetic:trajectory=PATH[,seed=S,size=WxH,frames=N,...]: a generated street (parked and moving cars, people, "
    "bicycles, benches, traffic lights, stop signs, potted plants, buildings) along a KITTI or TUM trajectory file, "
    "KITTI-like 620x188 camera, depth to 40 m",
)
register(
    "7scenes",
    _open_sevenscenes,
    "7-Scenes: a folder with frame-NNNNNN.color.png (or .jpg)/.depth.png/.pose.txt (+ camera-intrinsics.txt)",
    is_sevenscenes_dir,
)
register("tum", _open_tum, "TUM RGB-D: a folder with rgb.txt, depth.txt (+ groundtruth.txt)", is_tum_dir)
register(
    "kitti", _open_kitti, "KITTI odometry: a folder with calib.txt, image_2/, image_3/ (+ times.txt)", is_kitti_dir
)
register(
    "rosbag",
    _open_rosbag,
    "ROS bag: a ROS 1 .bag, a rosbag2 folder (.db3 or .mcap + metadata.yaml) or a single .mcap file",
    is_rosbag,
)


def find_data_root() -> Path | None:
    """The shared real-data folder: $SEMMAP_DATA if set, else <project root>/../shared/data if it exists.

    None when the chosen folder does not exist (a set but wrong $SEMMAP_DATA does not fall back silently).
    """
    env = environment.read(environment.DATA)
    if env:
        path = Path(env).expanduser()
        return path if path.is_dir() else None
    candidate = Path(__file__).resolve().parents[2].parent / "shared" / "data"
    return candidate if candidate.is_dir() else None


def detect_format(path: str | Path) -> str | None:
    """Name of the first registered reader whose layout matches the folder, or None."""
    path = Path(path)
    for fmt in _REGISTRY.values():
        if fmt.detect is not None and fmt.detect(path):
            return fmt.name
    return None


def _parse_value(text: str) -> Any:
    lowered = text.strip().lower()
    if lowered in ("true", "yes", "on"):
        return True
    if lowered in ("false", "no", "off"):
        return False
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text.strip()


def _parse_options(text: str, spec: str) -> dict[str, Any]:
    options: dict[str, Any] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        if "=" not in item:
            raise DatasetError(f"bad option {item!r} in {spec!r}: expected key=value")
        key, value = item.split("=", 1)
        options[key.strip()] = _parse_value(value)
    return options


def _unsupported(spec: str, reason: str) -> DatasetError:
    layouts = "\n".join(f"  - {layout}" for layout in available_formats().values())
    return DatasetError(f"cannot open dataset {spec!r}: {reason}. Supported:\n{layouts}")


def _resolve(path: Path) -> Path:
    """The path as given, or relative to the shared data root (so "7scenes-redkitchen" works anywhere)."""
    if path.exists() or path.is_absolute():
        return path
    root = find_data_root()
    if root is not None and (root / path).exists():
        return root / path
    return path


def reader_options(spec: str | Path, config: Config) -> dict[str, Any]:
    """The keyword options a run's config gives the reader of `spec`: its `rosbag` section for a bag, the
    ground-truth gap to interpolate over (`run.gt_max_gap_s`) for the TUM layout, none else."""
    text = str(spec).strip()
    name, _, rest = text.partition(":")
    if name == "rosbag" and rest:
        return config.rosbag.model_dump()
    path = _resolve(Path(text).expanduser())
    if path.exists() and is_rosbag(path):
        return config.rosbag.model_dump()
    try:
        fmt = detect_format(text) if name not in _REGISTRY else name
    except (DatasetError, OSError):
        fmt = None
    return {"gt_max_gap_s": config.run.gt_max_gap_s} if fmt == "tum" else {}


def platform_of(spec: str | Path) -> str:
    """What carries the camera of `spec` ("handheld" or "vehicle", `Dataset.platform`), told without opening it
    (a street world renders a city first): the street world and KITTI folders are vehicles, the rest hand-held."""
    text = str(spec).strip()
    name, _, rest = text.partition(":")
    if name == "synthetic":
        return "vehicle" if "trajectory" in _parse_options(rest, text) else "handheld"
    try:
        fmt = name if (rest and name in _REGISTRY) else detect_format(text)
    except (DatasetError, OSError):
        fmt = None
    return "vehicle" if fmt == "kitti" else "handheld"


def open_dataset(spec: str | Path, **options: Any) -> Dataset:
    """Open a dataset from a spec: a folder path (format auto-detected), "synthetic[:k=v,...]",
    or "<format>:<path>" to force a reader (e.g. "kitti:/data/sequences/06"). Keyword options go to the
    reader (options in the spec string and keyword options merge; keywords win). Raises DatasetError.
    """
    text = str(spec).strip()
    name, _, rest = text.partition(":")
    if name in _REGISTRY and _REGISTRY[name].detect is None:  # not file based: the rest is options
        merged = {**_parse_options(rest, text), **options}
        try:
            return _REGISTRY[name].opener(None, **merged)
        except TypeError as exc:
            raise DatasetError(f"bad options for {name!r}: {exc}") from exc
    if rest and name in _REGISTRY:
        fmt: _Format | None = _REGISTRY[name]
        path = _resolve(Path(rest).expanduser())
        if not path.exists():
            raise _unsupported(text, f"{path} does not exist")
    else:
        path = _resolve(Path(text).expanduser())
        if not path.exists():
            raise _unsupported(text, f"{path} does not exist")
        detected = detect_format(path)
        fmt = _REGISTRY[detected] if detected else None
        if fmt is None:
            from .sevenscenes import sequence_folders

            seqs = sequence_folders(path)
            if seqs:
                raise _unsupported(text, f"{path} is a 7-Scenes scene: give one sequence folder, e.g. {seqs[0]}")
            raise _unsupported(text, f"{path} matches no known layout")
    try:
        return fmt.opener(path, **options)
    except TypeError as exc:
        raise DatasetError(f"bad options for {fmt.name!r} reader: {exc}") from exc
